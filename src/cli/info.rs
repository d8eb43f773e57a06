//! `nerflabel info`: validate a scan and print its summary.

use super::common::load_scan;
use super::InfoArgs;
use anyhow::Context;
use nerflabel::poses::{estimate_pose_scale, refine_poses, scene_bounds, BoundsOptions, BoundsSource, RefineOptions};

pub fn run(args: &InfoArgs) -> anyhow::Result<()> {
    let scan = load_scan(&args.scan)?;
    let summary = nerflabel::scan::summarize(&scan);
    println!("{summary}");
    let bounds = scene_bounds(&scan, &BoundsOptions::default()).context("cannot compute the scene bounds")?;
    let source = match bounds.source {
        BoundsSource::User => "bbox.txt",
        BoundsSource::Depth => "depth percentiles + cameras",
        BoundsSource::CameraFrusta => "camera frusta (no depth)",
    };
    let (lo, hi) = (bounds.aabb.min, bounds.aabb.max);
    println!(
        "scene bounds:   [{:.3}, {:.3}, {:.3}] .. [{:.3}, {:.3}, {:.3}] m  ({source})",
        lo.x, lo.y, lo.z, hi.x, hi.y, hi.z
    );
    let e = bounds.aabb.extent();
    println!("scene size:     {:.3} x {:.3} x {:.3} m", e.x, e.y, e.z);
    let refinement =
        refine_poses(&scan, &RefineOptions::default()).context("cannot compare the poses with the depth")?;
    match estimate_pose_scale(&scan).context("cannot compare the camera motion with the depth")? {
        Some(e) => println!("pose scale:     {}", e.verdict()),
        None => println!("pose scale:     fewer than two frames have depth; the scale cannot be checked"),
    }
    match refinement {
        Some(r) => println!("poses vs depth: {}", r.verdict()),
        None => println!("poses vs depth: fewer than two frames have depth; the poses cannot be checked against it"),
    }
    Ok(())
}
