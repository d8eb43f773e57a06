//! Ray cast of the product's TSDF (`nerflabel::boxes::tsdf`) into whole
//! frames, for the TSDF baseline of the benchmarks: sensor depth fused at
//! 5 mm (the NeRFing-it paper's Open3D baseline), labelled like sensor depth.

use nalgebra::Point3;
use nerflabel::boxes::tsdf::BoxTsdf;
use nerflabel::scan::{DepthMap, Frame};
use rayon::prelude::*;

/// Voxel edge of the paper's baseline, metres.
pub const VOXEL_M: f64 = 0.005;

/// `frame` with its depth replaced by the fused surface (on the colour grid).
pub fn raycast_frame(tsdf: &BoxTsdf, frame: &Frame) -> Frame {
    let (w, h) = frame.size();
    let rot = frame.camera_to_world.rotation;
    let origin = Point3::from(frame.camera_to_world.translation.vector);
    let metres: Vec<f32> = (0..(w * h) as usize)
        .into_par_iter()
        .map(|i| {
            let (x, y) = ((i % w as usize) as f64, (i / w as usize) as f64);
            let ray = rot * frame.intrinsics.unproject(x, y);
            let len = ray.norm();
            tsdf.depth_along(&origin, &(ray / len), 1.0 / len) as f32
        })
        .collect();
    let depth = DepthMap {
        width: w,
        height: h,
        metres,
    };
    Frame::new(
        frame.id,
        frame.name.clone(),
        frame.rgb.clone(),
        Some(depth),
        frame.camera_to_world,
        frame.intrinsics,
    )
}
