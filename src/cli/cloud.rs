//! `nerflabel cloud`: fused coloured point cloud as binary PLY, completed
//! by the fitted model when there is one, with boxes drawn in on request.

use super::common::{check_model_scan, load_scan, model_path, progress_bar, read_model, work_dir};
use super::verbosity::say;
use super::CloudArgs;
use anyhow::Context;
use nerflabel::boxes::completed::completed_cloud;
use nerflabel::boxes::read_boxes;
use nerflabel::boxes::wireframe::wireframe_points;
use nerflabel::nerf::model_file::Model;
use nerflabel::outputs::{check_outputs, Output, ProtectedInputs};
use nerflabel::poses::{fuse_cloud, scene_bounds, write_ply, BoundsOptions, CloudOptions, DAabb};
use nerflabel::scan::Scan;

pub fn run(args: &CloudArgs) -> anyhow::Result<()> {
    let scan_dir = &args.scan.scan;
    let output = args
        .output
        .clone()
        .unwrap_or_else(|| work_dir(scan_dir).join("cloud.ply"));
    let outputs = [Output::file(&output, "the point cloud")];
    check_outputs(&outputs, None)?;
    let boxes = args.boxes.as_deref().map(read_boxes).transpose()?;
    let model_path = model_path(scan_dir, args.model.as_ref());
    let use_model = !args.sensor && (args.model.is_some() || model_path.is_file());
    let model = use_model.then(|| read_model(&model_path)).transpose()?.map(|(m, _)| m);
    let mut scan = load_scan(&args.scan)?;
    check_outputs(&outputs, Some(&ProtectedInputs::of(&scan)))?;
    let mut options = CloudOptions {
        voxel_size: args.voxel,
        ..CloudOptions::default()
    };
    let mut cloud = match &model {
        Some(model) => {
            check_model_scan(model, &model_path, &mut scan, args.force)?;
            options.bounds = Some(cloud_bounds(&scan, model)?);
            let bar = progress_bar(
                scan.frames.len() as u64,
                "rendering depth {bar:30} {pos}/{len} frames {elapsed}",
            );
            let cloud = completed_cloud(&scan, model, &options, &|done| bar.set_position(done as u64))
                .context("cannot fuse the point cloud")?;
            bar.finish_and_clear();
            cloud
        }
        None => fuse_cloud(&scan, &options).context("cannot fuse the point cloud")?,
    };
    let points = cloud.len();
    if let Some(boxes) = &boxes {
        for (p, c) in wireframe_points(boxes, 0.5 * cloud.voxel_size) {
            cloud.positions.push(p);
            cloud.colors.push(c);
        }
    }
    write_ply(&output, &cloud).with_context(|| format!("cannot write {}", output.display()))?;
    let source = match &model {
        Some(_) => format!("sensor depth completed by the model {}", model_path.display()),
        None => "sensor depth".to_string(),
    };
    let edges = match &boxes {
        Some(b) => format!(
            " and the edges of {} box(es) ({} points)",
            b.boxes.len(),
            cloud.len() - points
        ),
        None => String::new(),
    };
    say!(
        "wrote {points} points ({} m voxels, {source}){edges} to {}",
        cloud.voxel_size,
        output.display()
    );
    Ok(())
}

/// The box the cloud is kept in: the scene bounds of the sensor depth, or
/// the model's whole scene where the scan has too little depth for them.
fn cloud_bounds(scan: &Scan, model: &Model) -> anyhow::Result<DAabb> {
    if let Ok(bounds) = scene_bounds(scan, &BoundsOptions::default()) {
        return Ok(bounds.aabb);
    }
    let transform = model.scene_transform()?;
    let corners = (0..8).map(|i| {
        let unit = nalgebra::Point3::new((i & 1) as f64, ((i >> 1) & 1) as f64, ((i >> 2) & 1) as f64);
        transform.local_to_world_point(&unit)
    });
    DAabb::from_points(corners).context("the model's scene box is empty")
}
