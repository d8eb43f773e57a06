//! Sensor depth fused over every frame into a truncated signed distance
//! grid around each box (TSDF fusion). The fused source takes its sensor
//! depth from here rather than from one frame: many frames average the
//! noise of one and fill its holes, and the surface stays where the sensor
//! put it. The benchmarks also use it alone, as the TSDF baseline of the
//! NeRFing-it paper.

use super::parse::BoxSet;
use crate::poses::DAabb;
use crate::scan::Frame;
use nalgebra::{Point3, Rotation3, Vector3};
use rayon::prelude::*;

/// Truncation distance in voxels.
const TRUNCATION_VOXELS: f64 = 4.0;
/// Space fused around each box, in truncation distances.
const MARGIN_TRUNCATIONS: f64 = 2.0;
/// Voxels per block at most; a larger box gets coarser voxels.
const MAX_BLOCK_VOXELS: f64 = 32e6;

/// One axis-aligned TSDF block.
struct Block {
    origin: Point3<f64>,
    voxel: f64,
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
    fn sample(&self, p: &Point3<f64>) -> Option<f32> {
        let g = (p - self.origin) / self.voxel - Vector3::repeat(0.5);
        let base = g.map(f64::floor);
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
    fn interval(&self, origin: &Point3<f64>, dir: &Vector3<f64>) -> Option<(f64, f64)> {
        let hi = self.origin + Vector3::new(self.dims[0] as f64, self.dims[1] as f64, self.dims[2] as f64) * self.voxel;
        DAabb::new(self.origin, hi)
            .ray_interval(origin, dir)
            .filter(|(t0, t1)| t0 < t1)
    }
}

/// TSDF blocks around every box, fused from the frames' sensor depth.
pub struct BoxTsdf {
    blocks: Vec<Block>,
}

impl BoxTsdf {
    /// Fuse every frame's depth into a block of `voxel` metres around each box.
    pub fn fuse(frames: &[Frame], boxes: &BoxSet, voxel: f64) -> BoxTsdf {
        let blocks = boxes
            .boxes
            .iter()
            .map(|b| {
                let extent = b.world_half_extent();
                // Coarser voxels for a box too large to hold at this size.
                let reach = |voxel: f64| extent + Vector3::repeat(MARGIN_TRUNCATIONS * TRUNCATION_VOXELS * voxel);
                let count = |voxel: f64| (reach(voxel) * 2.0 / voxel).product();
                let mut voxel = voxel;
                while count(voxel) > MAX_BLOCK_VOXELS {
                    voxel *= 1.25;
                }
                let half = reach(voxel);
                let span = half * 2.0 / voxel;
                let dims = [span.x.ceil() as usize, span.y.ceil() as usize, span.z.ceil() as usize];
                let n = dims[0] * dims[1] * dims[2];
                let mut block = Block {
                    origin: b.center - half,
                    voxel,
                    dims,
                    tsdf: vec![0.0; n],
                    weight: vec![0.0; n],
                };
                integrate(&mut block, frames, TRUNCATION_VOXELS * voxel);
                block
            })
            .collect();
        BoxTsdf { blocks }
    }

    /// Depth (z, metres) of the first fused surface along the unit ray `dir`
    /// from `origin`, whose z grows by `z_per_t` per metre along it; 0 = none.
    pub fn depth_along(&self, origin: &Point3<f64>, dir: &Vector3<f64>, z_per_t: f64) -> f64 {
        self.first_crossing(origin, dir, f64::NEG_INFINITY, f64::INFINITY)
            .map_or(0.0, |t| t * z_per_t)
    }

    /// [`Self::depth_along`] searching only depths from `z_near` to `z_far`
    /// (from half a voxel before, so that a surface right at `z_near` is
    /// found): where only a surface near a known depth matters, the ray's
    /// way through the rest of the block is skipped.
    pub fn depth_between(
        &self,
        origin: &Point3<f64>,
        dir: &Vector3<f64>,
        z_per_t: f64,
        z_near: f64,
        z_far: f64,
    ) -> f64 {
        self.first_crossing(origin, dir, z_near / z_per_t, z_far / z_per_t)
            .map_or(0.0, |t| t * z_per_t)
    }

    /// Ray parameter of the first zero crossing (outside to inside) of the
    /// fused distance searched from `from` (less one search step) to `to`.
    fn first_crossing(&self, origin: &Point3<f64>, dir: &Vector3<f64>, from: f64, to: f64) -> Option<f64> {
        let mut best = f64::INFINITY;
        for block in &self.blocks {
            let Some((t0, t1)) = block.interval(origin, dir) else {
                continue;
            };
            let step = 0.5 * block.voxel;
            let (t0, t1) = (t0.max(from - step), t1.min(to));
            if t0 >= best {
                continue;
            }
            let truncation = TRUNCATION_VOXELS * block.voxel;
            let mut t = t0;
            let mut previous: Option<(f64, f32)> = None;
            while t <= t1.min(best) {
                let mut advance = step;
                match block.sample(&(origin + dir * t)) {
                    Some(v) => {
                        if let Some((tp, vp)) = previous {
                            if vp > 0.0 && v <= 0.0 {
                                best = best.min(tp + (t - tp) * (vp / (vp - v)) as f64);
                                break;
                            }
                        }
                        previous = Some((t, v));
                        // The surface is at least this far: skip most of the way.
                        advance = advance.max(0.8 * v as f64 * truncation);
                    }
                    None => previous = None,
                }
                t += advance;
            }
        }
        best.is_finite().then_some(best)
    }
}

/// A frame with depth, as the integration sees it.
struct View<'a> {
    world_to_cam: Rotation3<f64>,
    eye: Point3<f64>,
    /// Camera coordinates from one voxel of a row (along x) to the next.
    row_step: Vector3<f64>,
    frame: &'a Frame,
}

/// Running average of the truncated signed distance over every frame.
fn integrate(block: &mut Block, frames: &[Frame], truncation: f64) {
    let dims = block.dims;
    let voxel = block.voxel;
    let slab = dims[0] * dims[1];
    let origin = block.origin;
    let views: Vec<View> = frames
        .iter()
        .filter(|f| f.depth.is_some())
        .map(|frame| {
            let world_to_cam = frame.camera_to_world.rotation.transpose();
            View {
                world_to_cam,
                eye: Point3::from(frame.camera_to_world.translation.vector),
                row_step: world_to_cam * Vector3::x() * voxel,
                frame,
            }
        })
        .collect();
    block
        .tsdf
        .par_chunks_mut(slab)
        .zip(block.weight.par_chunks_mut(slab))
        .enumerate()
        .for_each_init(Vec::new, |row_starts, (k, (tsdf, weight))| {
            for j in 0..dims[1] {
                // Camera coordinates are affine along a row of voxels: each
                // view's start and step, instead of a rotation per voxel.
                let p0 = origin + Vector3::new(0.5, j as f64 + 0.5, k as f64 + 0.5) * voxel;
                row_starts.clear();
                row_starts.extend(views.iter().map(|view| view.world_to_cam * (p0 - view.eye)));
                for i in 0..dims[0] {
                    let n = j * dims[0] + i;
                    for (start, View { row_step, frame, .. }) in row_starts.iter().zip(&views) {
                        let c = start + row_step * i as f64;
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

#[cfg(test)]
mod tests {
    use super::*;
    use crate::boxes::parse::Box3;
    use crate::rng::Rng;
    use crate::scan::{DepthMap, Intrinsics};
    use nalgebra::{IsometryMatrix3, Matrix3, Translation3};

    /// A camera at `eye` looking straight down (OpenCV axes: x right, y down, z forward = -z world).
    fn looking_down(eye: Vector3<f64>) -> IsometryMatrix3<f64> {
        let r = Matrix3::from_diagonal(&Vector3::new(1.0, -1.0, -1.0));
        IsometryMatrix3::from_parts(Translation3::from(eye), Rotation3::from_matrix_unchecked(r))
    }

    /// An 80x60 frame with depth `metres` (row-major) seen from `pose`.
    fn view(i: u64, pose: IsometryMatrix3<f64>, metres: Vec<f32>) -> Frame {
        let k = Intrinsics {
            fx: 60.0,
            fy: 60.0,
            cx: 39.5,
            cy: 29.5,
        };
        let depth = DepthMap {
            width: 80,
            height: 60,
            metres,
        };
        Frame::new(i, format!("{i:06}"), image::RgbImage::new(80, 60), Some(depth), pose, k)
    }

    #[test]
    fn noisy_views_of_a_floor_fuse_to_the_floor() {
        let mut rng = Rng::new(1, 0);
        let sigma = 0.004;
        let frames: Vec<Frame> = (0..12)
            .map(|i| {
                let eye = Vector3::new(0.02 * (i % 4) as f64, 0.02 * (i / 4) as f64, 1.0);
                // Looking straight down at the floor z = 0: every pixel's z-depth is the height.
                let metres = (0..80 * 60).map(|_| (1.0 + sigma * rng.normal()) as f32).collect();
                view(i, looking_down(eye), metres)
            })
            .collect();
        let boxes = BoxSet::from_boxes(vec![Box3 {
            label: "patch".into(),
            instance_id: 1,
            center: Point3::new(0.0, 0.0, 0.02),
            size: Vector3::new(0.2, 0.2, 0.04),
            rotation: Rotation3::identity(),
        }]);
        let tsdf = BoxTsdf::fuse(&frames, &boxes, 0.004);
        let mut errors = Vec::new();
        for x in [-0.05, 0.0, 0.05] {
            for y in [-0.05, 0.0, 0.05] {
                let eye = Point3::new(x, y, 1.0);
                errors.push(tsdf.depth_along(&eye, &-Vector3::z(), 1.0) - 1.0);
            }
        }
        // Twelve frames of 4 mm noise average to about 1.2 mm.
        assert!(errors.iter().all(|e| e.abs() < 0.003), "{errors:?}");
        // Outside every block, and along a ray that never meets the floor, nothing.
        assert_eq!(tsdf.depth_along(&Point3::new(2.0, 0.0, 1.0), &-Vector3::z(), 1.0), 0.0);
        assert_eq!(tsdf.depth_along(&Point3::new(0.0, 0.0, 1.0), &Vector3::z(), 1.0), 0.0);
    }

    /// Oblique cameras over a depth map that varies across the image: every
    /// voxel's fused distance and weight are those of projecting its own
    /// centre into every frame (the rows step their camera coordinates).
    #[test]
    fn fused_voxels_match_projecting_each_voxel_centre_into_each_frame() {
        let mut rng = Rng::new(3, 0);
        let frames: Vec<Frame> = (0..6)
            .map(|i| {
                let eye = Vector3::new(0.1 * rng.normal(), 0.1 * rng.normal(), 0.6 + 0.1 * rng.f64());
                let tilt = Rotation3::from_euler_angles(0.3 * rng.normal(), 0.3 * rng.normal(), rng.f64() * 6.0);
                let down = looking_down(eye);
                let metres = (0..80 * 60)
                    .map(|n| (0.5 + 0.002 * (n % 80) as f64 + 0.003 * (n / 80) as f64) as f32)
                    .collect();
                view(
                    i,
                    IsometryMatrix3::from_parts(down.translation, tilt * down.rotation),
                    metres,
                )
            })
            .collect();
        let boxes = BoxSet::from_boxes(vec![Box3 {
            label: "block".into(),
            instance_id: 1,
            center: Point3::new(0.01, -0.02, 0.05),
            size: Vector3::new(0.12, 0.1, 0.08),
            rotation: Rotation3::identity(),
        }]);
        let fused = BoxTsdf::fuse(&frames, &boxes, 0.004);
        let block = &fused.blocks[0];
        let truncation = TRUNCATION_VOXELS * block.voxel;
        let mut observed = 0;
        for n in (0..block.tsdf.len()).step_by(7) {
            let [di, dj] = [block.dims[0], block.dims[1]];
            let (i, j, l) = (n % di, (n / di) % dj, n / (di * dj));
            let p = block.origin + Vector3::new(i as f64 + 0.5, j as f64 + 0.5, l as f64 + 0.5) * block.voxel;
            let (mut value, mut weight) = (0.0f32, 0.0f32);
            for f in &frames {
                let c = f.camera_to_world.inverse() * p;
                let k = &f.intrinsics;
                let (u, v) = (k.fx * c.x / c.z + k.cx, k.fy * c.y / c.z + k.cy);
                if c.z <= 1e-6 || !(u >= -0.5 && v >= -0.5 && u < 79.5 && v < 59.5) {
                    continue;
                }
                let z = f64::from(f.depth.as_ref().unwrap().get(u.round() as u32, v.round() as u32));
                if z - c.z < -truncation {
                    continue;
                }
                value = (value * weight + ((z - c.z) / truncation).min(1.0) as f32) / (weight + 1.0);
                weight += 1.0;
            }
            assert_eq!(block.weight[n], weight, "voxel {n}");
            assert!(
                (block.tsdf[n] - value).abs() < 1e-5,
                "voxel {n}: {} against {value}",
                block.tsdf[n]
            );
            observed += usize::from(weight > 0.0 && value.abs() < 1.0);
        }
        assert!(observed > 100, "only {observed} voxels near a surface");
    }

    /// A thin slab 5 cm above a floor, in one block: the first surface along
    /// a ray is the slab, the surface searched between two depths the one
    /// there, and none where there is none.
    #[test]
    fn a_search_between_depths_finds_the_surface_there_only() {
        let voxel = 0.005;
        let truncation = TRUNCATION_VOXELS * voxel;
        let dims = [20, 20, 40];
        let origin = Point3::new(-0.05, -0.05, -0.05);
        // Signed distance (outside positive) to the union of the floor z < 0
        // and the slab 0.05 < z < 0.06.
        let slab = |z: f64| (z - 0.06).max(0.05 - z);
        let sdf = |z: f64| z.min(slab(z));
        let mut tsdf = vec![0.0f32; dims[0] * dims[1] * dims[2]];
        for (n, v) in tsdf.iter_mut().enumerate() {
            let z = origin.z + ((n / (dims[0] * dims[1])) as f64 + 0.5) * voxel;
            *v = (sdf(z) / truncation).clamp(-1.0, 1.0) as f32;
        }
        let weight = vec![1.0f32; tsdf.len()];
        let fused = BoxTsdf {
            blocks: vec![Block {
                origin,
                voxel,
                dims,
                tsdf,
                weight,
            }],
        };
        // From 1 m above the floor, looking down: z along the ray is the distance.
        let (eye, down) = (Point3::new(0.0, 0.0, 1.0), -Vector3::z());
        let first = fused.depth_along(&eye, &down, 1.0);
        assert!((first - 0.94).abs() < 0.002, "slab top at 0.94 m, found {first}");
        let near_floor = fused.depth_between(&eye, &down, 1.0, 0.98, 1.02);
        assert!((near_floor - 1.0).abs() < 0.002, "floor at 1 m, found {near_floor}");
        let near_slab = fused.depth_between(&eye, &down, 1.0, 0.93, 0.95);
        // Its own samples, so not to the bit.
        assert!((near_slab - first).abs() < 0.001, "{near_slab} against {first}");
        assert_eq!(fused.depth_between(&eye, &down, 1.0, 0.6, 0.9), 0.0);
        // Unbounded, it is the first surface to the bit.
        let unbounded = fused.depth_between(&eye, &down, 1.0, f64::NEG_INFINITY, f64::INFINITY);
        assert_eq!(unbounded.to_bits(), first.to_bits());
    }
}
