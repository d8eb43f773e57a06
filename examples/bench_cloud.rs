//! The point cloud of `nerflabel cloud` against a generated scene's exact
//! surfaces: per labelled object, the points around it (above its support)
//! and their distance to its true surface, for the sensor cloud and the
//! cloud completed by a fitted model. Objects without sensor depth (glass)
//! are the point: the sensor gives them almost nothing.
//!
//! Run: `cargo run --release --example bench_cloud -- SCENE_DIR --model MODEL`
//! (SCENE_DIR made by `nerflabel fixture ... [--realistic]`, MODEL by
//! `nerflabel fit SCENE_DIR --time 120 --model MODEL`).

use nerflabel::boxes::completed::completed_cloud;
use nerflabel::fixture::read_meta;
use nerflabel::nerf::model_file::Model;
use nerflabel::poses::{fuse_cloud, scene_bounds, BoundsOptions, CloudOptions, PointCloud};
use nerflabel::scan::{load, LoadOptions};
use std::path::PathBuf;
use std::time::Instant;

type Error = Box<dyn std::error::Error>;

fn main() -> Result<(), Error> {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let dir = PathBuf::from(args.first().ok_or("usage: bench_cloud SCENE_DIR --model MODEL")?);
    let model_path = args
        .iter()
        .position(|a| a == "--model")
        .and_then(|i| args.get(i + 1))
        .map(PathBuf::from)
        .ok_or("--model MODEL is required")?;
    let mut scan = load(&dir, &LoadOptions::default())?;
    let model = Model::from_bytes(&std::fs::read(&model_path)?, &model_path)?;
    // The model's refined poses, as `cloud` uses them.
    model.apply_fitted_poses(&mut scan);
    let options = CloudOptions {
        bounds: Some(scene_bounds(&scan, &BoundsOptions::default())?.aabb),
        ..CloudOptions::default()
    };
    let t = Instant::now();
    let sensor = fuse_cloud(&scan, &options)?;
    let sensor_s = t.elapsed().as_secs_f64();
    let t = Instant::now();
    let completed = completed_cloud(&scan, &model, &options, &|_| {})?;
    let completed_s = t.elapsed().as_secs_f64();
    println!(
        "{}: voxel {:.4} m; sensor cloud {} points in {sensor_s:.1} s, completed {} points in {completed_s:.1} s",
        dir.display(),
        completed.voxel_size,
        sensor.len(),
        completed.len()
    );
    println!(
        "{:<10} {:>8} {:>9} {:>10} {:>10} {:>10} {:>9}",
        "object", "no depth", "cloud", "points", "median m", "90 % m", "<= 1 cm"
    );
    let scene = read_meta(&dir)?.build_scene();
    for object in scene.labelled() {
        let bottom = object.center().z - 0.5 * object.size.z;
        for (name, cloud) in [("sensor", &sensor), ("model", &completed)] {
            let mut d = distances(
                cloud,
                |p| object.box_contains(p, 0.01) && p.z > bottom + 0.01,
                |p| object.surface_distance(p),
            );
            d.sort_by(f64::total_cmp);
            let q = |f: f64| d.get((f * d.len() as f64) as usize).copied().unwrap_or(f64::NAN);
            let within = d.iter().filter(|&&x| x <= 0.01).count() as f64 / d.len().max(1) as f64;
            println!(
                "{:<10} {:>8} {:>9} {:>10} {:>10.4} {:>10.4} {:>9.3}",
                object.label,
                object.no_sensor_depth,
                name,
                d.len(),
                q(0.5),
                q(0.9),
                within
            );
        }
    }
    Ok(())
}

/// Distances of the cloud's points that `keep` accepts.
fn distances(
    cloud: &PointCloud,
    keep: impl Fn(nalgebra::Vector3<f64>) -> bool,
    distance: impl Fn(nalgebra::Vector3<f64>) -> f64,
) -> Vec<f64> {
    cloud
        .positions
        .iter()
        .map(|p| nalgebra::Vector3::from(p.map(f64::from)))
        .filter(|p| keep(*p))
        .map(distance)
        .collect()
}
