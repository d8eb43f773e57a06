//! Scan frames turned into training and held-out views in local
//! coordinates, plus the depth rays that seed the occupancy grid.

use super::camera::{LocalCamera, View};
use super::occupancy::DepthRay;
use crate::poses::SceneTransform;
use crate::scan::Scan;
use rayon::prelude::*;

/// Views of a scan split into training and held-out sets.
pub struct Dataset {
    pub train: Vec<View>,
    pub holdout: Vec<View>,
    /// Scan frame index of each training view.
    pub train_frames: Vec<usize>,
    /// Scan frame index of each held-out view.
    pub holdout_frames: Vec<usize>,
    /// Mean colour of the training images, used behind empty rays.
    pub background: [f32; 3],
}

/// Whether frame `index` is held out when every `every`-th frame is (0 = none).
/// The held-out frames are the last of each group of `every`, so the first
/// frame of a scan always trains.
pub fn is_holdout(index: usize, every: usize) -> bool {
    every > 1 && (index + 1) % every == 0
}

/// The camera of a scan frame in local coordinates.
pub fn local_camera(frame: &crate::scan::Frame, transform: &SceneTransform) -> LocalCamera {
    let (w, h) = frame.size();
    LocalCamera::new(&transform.world_to_local_pose(&frame.camera_to_world), &frame.intrinsics, w, h)
}

/// Build the views of `scan` in the local frame of `transform`.
pub fn build(scan: &Scan, transform: &SceneTransform, holdout_every: usize) -> Dataset {
    let views: Vec<View> = scan
        .frames
        .par_iter()
        .map(|frame| {
            let depth = frame.depth.as_ref().map(|d| {
                let scale = transform.scale as f32;
                d.metres.iter().map(|&m| if m > 0.0 && m.is_finite() { m * scale } else { 0.0 }).collect()
            });
            View { camera: local_camera(frame, transform), rgb: frame.rgb.as_raw().clone(), depth }
        })
        .collect();
    let mut data = Dataset { train: Vec::new(), holdout: Vec::new(), train_frames: Vec::new(), holdout_frames: Vec::new(), background: [0.5; 3] };
    let single = views.len() < 2;
    for (i, view) in views.into_iter().enumerate() {
        // A one-frame scan trains on its only frame.
        if !single && is_holdout(i, holdout_every) {
            data.holdout.push(view);
            data.holdout_frames.push(i);
        } else {
            data.train.push(view);
            data.train_frames.push(i);
        }
    }
    data.background = mean_colour(&data.train);
    data
}

fn mean_colour(views: &[View]) -> [f32; 3] {
    let mut sum = [0.0f64; 3];
    let mut n = 0u64;
    for v in views {
        for px in v.rgb.chunks_exact(3).step_by(7) {
            for c in 0..3 {
                sum[c] += px[c] as f64;
            }
            n += 1;
        }
    }
    if n == 0 {
        return [0.5; 3];
    }
    sum.map(|s| (s / n as f64 / 255.0) as f32)
}

/// Depth rays of the training views (every `stride`-th pixel both ways).
pub fn depth_rays(views: &[View], stride: usize) -> Vec<DepthRay> {
    let stride = stride.max(1);
    views
        .par_iter()
        .flat_map_iter(|view| {
            let cam = view.camera;
            let width = cam.width as usize;
            let height = cam.height as usize;
            let depth = view.depth.as_deref();
            (0..height).step_by(stride).flat_map(move |y| {
                (0..width).step_by(stride).filter_map(move |x| {
                    let z = depth?[y * width + x];
                    if !(z > 0.0 && z.is_finite()) {
                        return None;
                    }
                    let (ray, t_per_z) = cam.ray(x as f32, y as f32);
                    Some(DepthRay { origin: ray.origin, dir: ray.dir, t_hit: z * t_per_z })
                })
            })
        })
        .collect()
}
