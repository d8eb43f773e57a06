//! How far refined poses lie from a generated scan's exact ones
//! (`gt/pose`), beside the captured poses: the poses `fit` aligns to the
//! depth (computed here, without fitting) and, given a model, the poses
//! stored in it and those aligned once more to its final field. Per frame:
//! how far its depth points, placed in the world by the exact pose, land
//! from where they were measured when seen through the pose (what a label
//! drawn through it is off by, in pixels), and how far the camera centre is
//! from the exact one; medians and 95th percentiles.
//!
//! Run: `cargo run --release --example bench_poses -- SCAN_DIR [MODEL]`

use nalgebra::{IsometryMatrix3, Matrix3, Point3, Rotation3, Translation3};
use nerflabel::nerf::model_file::Model;
use nerflabel::poses::{refine_poses, trajectory_alignment, RefineOptions};
use nerflabel::scan::{load, LoadOptions, Scan};
use std::path::PathBuf;

type Error = Box<dyn std::error::Error>;

fn main() -> Result<(), Error> {
    let args: Vec<PathBuf> = std::env::args().skip(1).map(PathBuf::from).collect();
    let (scan_dir, model_path) = match args.as_slice() {
        [scan] => (scan, None),
        [scan, model] => (scan, Some(model)),
        _ => return Err("usage: bench_poses SCAN_DIR [MODEL]".into()),
    };
    let captured = load(scan_dir, &LoadOptions::default())?;
    let t = std::time::Instant::now();
    let refinement = refine_poses(&captured, &RefineOptions::default())?.ok_or("the scan has no depth to align to")?;
    let refine_s = t.elapsed().as_secs_f64();
    let mut aligned = captured.clone();
    aligned.set_poses(&refinement.camera_to_world);
    let exact: Vec<IsometryMatrix3<f64>> = captured
        .frames
        .iter()
        .map(|f| read_pose(&scan_dir.join("gt/pose").join(format!("{}.txt", f.name))))
        .collect::<Result<_, _>>()?;
    println!(
        "{} frames; aligned to the depth in {refine_s:.1} s: {} ({} frames refined)",
        exact.len(),
        refinement.verdict(),
        refinement.refined_count()
    );
    let mut compared = vec![("captured", captured.clone()), ("aligned to the depth", aligned)];
    if let Some(path) = model_path {
        let mut fitted = captured.clone();
        let model = Model::load(path)?;
        model.apply_fitted_poses(&mut fitted);
        compared.push(("stored in the model", fitted.clone()));
        let t = std::time::Instant::now();
        let again = align_again(&model, &fitted)?;
        println!("aligned again in {:.1} s", t.elapsed().as_secs_f64());
        let mut a = fitted.clone();
        a.set_poses(&again);
        compared.push(("stored, aligned to the final field", a));
    }
    let exact_scan = {
        let mut e = captured.clone();
        e.set_poses(&exact);
        e
    };
    println!(
        "| poses | reprojection px: median / p95 | camera position mm: median / p95 | reprojection px, trajectory moved onto the exact one: median / p95 |"
    );
    println!("|---|---|---|---|");
    let mut common = Vec::new();
    for (name, scan) in &compared {
        let poses = scan.poses();
        let (px, mm) = (reprojection(&poses, &exact_scan), camera_error(&poses, &exact));
        // What is left once the whole trajectory's common offset is gone:
        // the frames' disagreement among themselves.
        // Probes half a metre ahead: about where the cameras look.
        let onto = trajectory_alignment(&poses, &exact, 0.5);
        let n = poses.len().max(1) as f64;
        let shift: nalgebra::Vector3<f64> = poses
            .iter()
            .zip(&exact)
            .map(|(p, e)| p.translation.vector - e.translation.vector)
            .sum::<nalgebra::Vector3<f64>>()
            / n;
        let turn: nalgebra::Vector3<f64> = poses
            .iter()
            .zip(&exact)
            .map(|(p, e)| (p.rotation * e.rotation.inverse()).scaled_axis())
            .sum::<nalgebra::Vector3<f64>>()
            / n;
        common.push(format!(
            "{name}: mean centre shift {:.1} mm, mean turn {:.2} deg",
            shift.norm() * 1e3,
            turn.norm().to_degrees()
        ));
        let moved: Vec<_> = poses.iter().map(|p| onto * p).collect();
        let relative = reprojection(&moved, &exact_scan);
        println!(
            "| {name} | {:.2} / {:.2} | {:.1} / {:.1} | {:.2} / {:.2} |",
            quantile(&px, 0.5),
            quantile(&px, 0.95),
            quantile(&mm, 0.5),
            quantile(&mm, 0.95),
            quantile(&relative, 0.5),
            quantile(&relative, 0.95),
        );
    }
    println!(
        "common offset of each trajectory from the exact one: {}",
        common.join("; ")
    );
    Ok(())
}

/// The poses of `scan` aligned once more to the model's final field, as the
/// fit's last pass does (a second pass shows what is left to gain).
fn align_again(model: &Model, scan: &Scan) -> Result<Vec<IsometryMatrix3<f64>>, Error> {
    use nerflabel::nerf::train::photometric::{align_to_field, PhotometricOptions};
    let render = model.render_options(true);
    let maps = model
        .header
        .appearance
        .clone()
        .unwrap_or_else(|| vec![nerflabel::nerf::appearance::IDENTITY; scan.frames.len()]);
    let a = align_to_field(
        &model.field,
        &model.occupancy,
        &render,
        &model.scene_transform()?,
        &scan.frames,
        &maps,
        &model
            .header
            .vignetting
            .unwrap_or(nerflabel::nerf::appearance::NO_VIGNETTING),
        &(0..scan.frames.len()).collect::<Vec<_>>(),
        &PhotometricOptions::default(),
    );
    let kept = a.frames.iter().filter(|f| f.refined).count();
    println!(
        "aligned to the final field again: {kept} of {} frames kept",
        a.frames.len()
    );
    Ok(a.camera_to_world)
}

/// A pose file of the native layout: world-to-camera, 4x4, row by row.
fn read_pose(path: &std::path::Path) -> Result<IsometryMatrix3<f64>, Error> {
    let text = std::fs::read_to_string(path).map_err(|e| format!("{}: {e}", path.display()))?;
    let v: Vec<f64> = text.split_whitespace().map(str::parse).collect::<Result<_, _>>()?;
    if v.len() != 16 {
        return Err(format!("{}: expected 16 numbers", path.display()).into());
    }
    let r = Matrix3::new(v[0], v[1], v[2], v[4], v[5], v[6], v[8], v[9], v[10]);
    let world_to_camera = IsometryMatrix3::from_parts(Translation3::new(v[3], v[7], v[11]), Rotation3::from_matrix(&r));
    Ok(world_to_camera.inverse())
}

/// Camera position error per frame, mm.
fn camera_error(poses: &[IsometryMatrix3<f64>], exact: &[IsometryMatrix3<f64>]) -> Vec<f64> {
    poses
        .iter()
        .zip(exact)
        .map(|(p, e)| (p.translation.vector - e.translation.vector).norm() * 1000.0)
        .collect()
}

/// Per frame, the mean distance (pixels) between where its depth points,
/// placed in the world by the exact pose, appear through `poses` and where
/// they were measured: what a label drawn through the pose is off by.
fn reprojection(poses: &[IsometryMatrix3<f64>], exact: &Scan) -> Vec<f64> {
    poses
        .iter()
        .zip(&exact.frames)
        .filter_map(|(pose, f)| {
            let depth = f.depth.as_ref()?;
            let world_to_camera = pose.inverse();
            let (mut sum, mut count) = (0.0, 0usize);
            for v in (0..depth.height).step_by(8) {
                for u in (0..depth.width).step_by(8) {
                    let z = depth.get(u, v);
                    if z <= 0.0 {
                        continue;
                    }
                    let world = f.camera_to_world * Point3::from(f.intrinsics.unproject(u as f64, v as f64) * z as f64);
                    if let Some((x, y)) = f.intrinsics.project(&(world_to_camera * world)) {
                        sum += ((x - u as f64).powi(2) + (y - v as f64).powi(2)).sqrt();
                        count += 1;
                    }
                }
            }
            (count > 0).then(|| sum / count as f64)
        })
        .collect()
}

fn quantile(values: &[f64], q: f64) -> f64 {
    let mut v = values.to_vec();
    v.sort_by(f64::total_cmp);
    v.get(((v.len() as f64 - 1.0) * q).round() as usize)
        .copied()
        .unwrap_or(f64::NAN)
}
