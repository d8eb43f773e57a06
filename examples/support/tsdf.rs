//! The TSDF-fusion baseline of the NeRFing-it paper, for the benchmarks
//! only (not part of the product): the scan's sensor depth fused into a
//! truncated signed distance grid (5 mm voxels, as the paper's Open3D
//! baseline) around each box, then ray cast into every frame to give a
//! dense depth map that is labelled like sensor depth.

use glam::{DMat3, DVec3};
use nerflabel::boxes::BoxSet;
use nerflabel::scan::{DepthMap, Frame, Scan};
use rayon::prelude::*;

/// Voxel edge, metres (the paper's baseline).
pub const VOXEL_M: f64 = 0.005;
/// Truncation distance in voxels.
const TRUNCATION_VOXELS: f64 = 4.0;
/// Space fused around each box, metres.
const MARGIN_M: f64 = 0.1;

/// One axis-aligned TSDF block.
struct Block {
    origin: DVec3,
    dims: [usize; 3],
    /// Signed distance / truncation, in [-1, 1]; weight 0 = never observed.
    tsdf: Vec<f32>,
    weight: Vec<f32>,
}

impl Block {
    fn index(&self, i: usize, j: usize, k: usize) -> usize {
        (k * self.dims[1] + j) * self.dims[0] + i
    }

    /// Trilinear TSDF at `p`; `None` where a corner was never observed.
    fn sample(&self, p: DVec3) -> Option<f32> {
        let g = (p - self.origin) / VOXEL_M - DVec3::splat(0.5);
        let base = g.floor();
        let f = g - base;
        let (i0, j0, k0) = (base.x as i64, base.y as i64, base.z as i64);
        if i0 < 0 || j0 < 0 || k0 < 0 {
            return None;
        }
        let (i0, j0, k0) = (i0 as usize, j0 as usize, k0 as usize);
        if i0 + 1 >= self.dims[0] || j0 + 1 >= self.dims[1] || k0 + 1 >= self.dims[2] {
            return None;
        }
        let mut value = 0.0;
        for c in 0..8 {
            let (di, dj, dk) = (c & 1, (c >> 1) & 1, (c >> 2) & 1);
            let n = self.index(i0 + di, j0 + dj, k0 + dk);
            if self.weight[n] == 0.0 {
                return None;
            }
            let w = (if di == 1 { f.x } else { 1.0 - f.x })
                * (if dj == 1 { f.y } else { 1.0 - f.y })
                * (if dk == 1 { f.z } else { 1.0 - f.z });
            value += w * self.tsdf[n] as f64;
        }
        Some(value as f32)
    }

    /// Ray parameters where the ray is inside the block.
    fn interval(&self, origin: DVec3, dir: DVec3) -> Option<(f64, f64)> {
        let hi = self.origin + DVec3::new(self.dims[0] as f64, self.dims[1] as f64, self.dims[2] as f64) * VOXEL_M;
        let (mut t0, mut t1) = (0.0f64, f64::INFINITY);
        for a in 0..3 {
            if dir[a].abs() < 1e-15 {
                if origin[a] < self.origin[a] || origin[a] > hi[a] {
                    return None;
                }
                continue;
            }
            let (ta, tb) = ((self.origin[a] - origin[a]) / dir[a], (hi[a] - origin[a]) / dir[a]);
            t0 = t0.max(ta.min(tb));
            t1 = t1.min(ta.max(tb));
        }
        (t0 < t1).then_some((t0, t1))
    }
}

/// TSDF blocks around every box, fused from the scan's sensor depth.
pub struct Tsdf {
    blocks: Vec<Block>,
}

impl Tsdf {
    /// Fuse every frame's depth into a block around each box.
    pub fn fuse(scan: &Scan, boxes: &BoxSet) -> Tsdf {
        let truncation = TRUNCATION_VOXELS * VOXEL_M;
        let blocks = boxes
            .boxes
            .iter()
            .map(|b| {
                let r = b.rotation;
                let extent = DMat3::from_cols(r.x_axis.abs(), r.y_axis.abs(), r.z_axis.abs()) * (b.size * 0.5);
                let lo = b.center - extent - DVec3::splat(MARGIN_M);
                let span = (extent + DVec3::splat(MARGIN_M)) * 2.0 / VOXEL_M;
                let dims = [span.x.ceil() as usize, span.y.ceil() as usize, span.z.ceil() as usize];
                let n = dims[0] * dims[1] * dims[2];
                let mut block = Block { origin: lo, dims, tsdf: vec![0.0; n], weight: vec![0.0; n] };
                integrate(&mut block, &scan.frames, truncation);
                block
            })
            .collect();
        Tsdf { blocks }
    }

    /// Depth (z, metres) of the first zero crossing along the pixel's ray, 0 = none.
    fn cast(&self, origin: DVec3, dir: DVec3, z_per_t: f64) -> f32 {
        let step = 0.5 * VOXEL_M;
        let mut best = f64::INFINITY;
        for block in &self.blocks {
            let Some((t0, t1)) = block.interval(origin, dir) else { continue };
            if t0 >= best {
                continue;
            }
            let mut t = t0;
            let mut previous: Option<(f64, f32)> = None;
            while t <= t1.min(best) {
                match block.sample(origin + dir * t) {
                    Some(v) => {
                        if let Some((tp, vp)) = previous {
                            if vp > 0.0 && v <= 0.0 {
                                best = best.min(tp + (t - tp) * (vp / (vp - v)) as f64);
                                break;
                            }
                        }
                        previous = Some((t, v));
                    }
                    None => previous = None,
                }
                t += step;
            }
        }
        if best.is_finite() {
            (best * z_per_t) as f32
        } else {
            0.0
        }
    }

    /// The frame with its depth replaced by the ray-cast TSDF (on the colour grid).
    pub fn raycast_frame(&self, frame: &Frame) -> Frame {
        let (w, h) = frame.size();
        let rot = DMat3::from_mat4(frame.camera_to_world);
        let origin = frame.camera_to_world.w_axis.truncate();
        let metres: Vec<f32> = (0..(w * h) as usize)
            .into_par_iter()
            .map(|i| {
                let (x, y) = ((i % w as usize) as f64, (i / w as usize) as f64);
                let ray = rot * frame.intrinsics.unproject(x, y);
                let len = ray.length();
                self.cast(origin, ray / len, 1.0 / len)
            })
            .collect();
        let depth = DepthMap { width: w, height: h, metres };
        Frame::new(frame.id, frame.name.clone(), frame.rgb.clone(), Some(depth), frame.camera_to_world, frame.intrinsics)
    }
}

/// Running weighted average of the truncated signed distance over every frame.
fn integrate(block: &mut Block, frames: &[Frame], truncation: f64) {
    let dims = block.dims;
    let slab = dims[0] * dims[1];
    let origin = block.origin;
    let views: Vec<(DMat3, DVec3, &Frame)> = frames
        .iter()
        .filter(|f| f.depth.is_some())
        .map(|f| {
            let rot = DMat3::from_mat4(f.camera_to_world).transpose();
            (rot, f.camera_to_world.w_axis.truncate(), f)
        })
        .collect();
    block.tsdf.par_chunks_mut(slab).zip(block.weight.par_chunks_mut(slab)).enumerate().for_each(|(k, (tsdf, weight))| {
        for j in 0..dims[1] {
            for i in 0..dims[0] {
                let p = origin + DVec3::new(i as f64 + 0.5, j as f64 + 0.5, k as f64 + 0.5) * VOXEL_M;
                let n = j * dims[0] + i;
                for (world_to_cam, eye, frame) in &views {
                    let c = *world_to_cam * (p - *eye);
                    if c.z <= 1e-6 {
                        continue;
                    }
                    let k = &frame.intrinsics;
                    let (u, v) = (k.fx * c.x / c.z + k.cx, k.fy * c.y / c.z + k.cy);
                    let (w, h) = frame.size();
                    if !(u >= -0.5 && v >= -0.5 && u < w as f64 - 0.5 && v < h as f64 - 0.5) {
                        continue;
                    }
                    let Some(depth) = &frame.depth else { continue };
                    let z = depth.get(u.round() as u32, v.round() as u32) as f64;
                    if z <= 0.0 {
                        continue;
                    }
                    let sdf = z - c.z;
                    if sdf < -truncation {
                        continue;
                    }
                    let value = (sdf / truncation).min(1.0) as f32;
                    tsdf[n] = (tsdf[n] * weight[n] + value) / (weight[n] + 1.0);
                    weight[n] += 1.0;
                }
            }
        }
    });
}
