//! The fused coloured point cloud of a scan (`nerflabel cloud`): every valid
//! depth pixel of every frame back-projected, coloured from its rgb frame,
//! kept inside the scene bounds and averaged per voxel.
//!
//! Frames are fused in parallel, each into its own voxel hash that is merged
//! into one per worker, so memory is bounded by the number of occupied voxels
//! times the worker count. Sums are integers (positions as 16-bit fixed-point
//! offsets inside the voxel), so the result does not depend on the order in
//! which workers merge; voxels are emitted sorted by their index.

use super::bounds::depth_intrinsics;
use super::{scene_bounds, BoundsOptions, DAabb, GeometryError};
use crate::scan::{DepthMap, Frame, Intrinsics, Scan};
use nalgebra::{Matrix3, Point3, Vector3};
use rayon::prelude::*;
use std::borrow::Cow;
use std::collections::HashMap;
use std::hash::{BuildHasherDefault, Hasher};
use std::io::Write;
use std::path::Path;

/// Most voxels along one axis; keeps f32 grid coordinates exact to 1/256 voxel.
pub const MAX_VOXELS_PER_AXIS: u64 = 1 << 16;
/// Fixed-point steps per voxel edge for the position sums.
const FIXED_ONE: f32 = 65_536.0;

/// How to fuse the cloud.
#[derive(Clone, Debug, PartialEq)]
pub struct CloudOptions {
    /// Voxel edge in metres; `None` derives it from the scene.
    pub voxel_size: Option<f64>,
    /// Without `voxel_size`: voxels along the longest scene edge.
    pub voxels_per_extent: u32,
    /// World box to keep points in; `None` computes the scene bounds.
    pub bounds: Option<DAabb>,
    /// Options for computing the scene bounds.
    pub bounds_options: BoundsOptions,
}

impl Default for CloudOptions {
    fn default() -> Self {
        CloudOptions {
            voxel_size: None,
            voxels_per_extent: 512,
            bounds: None,
            bounds_options: BoundsOptions::default(),
        }
    }
}

/// A coloured point cloud in world coordinates (metres).
#[derive(Clone, Debug, Default, PartialEq)]
pub struct PointCloud {
    /// Point positions, one per occupied voxel.
    pub positions: Vec<[f32; 3]>,
    /// Mean 8-bit RGB colour of each point.
    pub colors: Vec<[u8; 3]>,
    /// Voxel edge used, metres.
    pub voxel_size: f64,
    /// World box the points were kept in.
    pub bounds: DAabb,
    /// Back-projected depth points inside the box, before downsampling.
    pub fused_points: u64,
}

impl PointCloud {
    /// Number of points.
    pub fn len(&self) -> usize {
        self.positions.len()
    }

    /// Whether there are no points.
    pub fn is_empty(&self) -> bool {
        self.positions.is_empty()
    }
}

/// Running sums of one voxel.
#[derive(Clone, Copy, Debug, Default)]
struct Acc {
    count: u64,
    offset: [u64; 3],
    rgb: [u64; 3],
}

impl Acc {
    fn merge(&mut self, o: &Acc) {
        self.count += o.count;
        for i in 0..3 {
            self.offset[i] += o.offset[i];
            self.rgb[i] += o.rgb[i];
        }
    }
}

/// Hash of a packed voxel index: the splitmix64 finaliser (the keys are
/// ours, so no protection against crafted collisions is needed).
#[derive(Default)]
struct VoxelHasher(u64);

impl Hasher for VoxelHasher {
    fn write(&mut self, bytes: &[u8]) {
        for b in bytes {
            self.write_u64(self.0 ^ u64::from(*b));
        }
    }

    fn write_u64(&mut self, x: u64) {
        let mut z = x.wrapping_add(0x9E37_79B9_7F4A_7C15);
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        self.0 = z ^ (z >> 31);
    }

    fn finish(&self) -> u64 {
        self.0
    }
}

type VoxelMap = HashMap<u64, Acc, BuildHasherDefault<VoxelHasher>>;

/// The voxel grid over the kept box.
#[derive(Clone, Copy, Debug)]
struct Grid {
    min: Point3<f64>,
    voxel: f64,
    dims: [u64; 3],
}

/// Back-project, colour, crop and voxel-average all depth of `scan`.
pub fn fuse_cloud(scan: &Scan, options: &CloudOptions) -> Result<PointCloud, GeometryError> {
    // Check every frame up front so the parallel part cannot fail.
    for frame in &scan.frames {
        depth_intrinsics(frame)?;
    }
    fuse_depth_maps(scan, options, &sensor_depth)
}

/// A frame's own depth map and its intrinsics, where it has one.
fn sensor_depth(frame: &Frame) -> Option<(Cow<'_, DepthMap>, Intrinsics)> {
    match (&frame.depth, depth_intrinsics(frame)) {
        (Some(depth), Ok(Some(k))) => Some((Cow::Borrowed(depth), k)),
        _ => None,
    }
}

/// [`fuse_cloud`] of the depth maps `depth_of` gives for each frame (with
/// their intrinsics): the sensor's, or depth completed by a fitted model.
pub fn fuse_depth_maps<'s>(
    scan: &'s Scan,
    options: &CloudOptions,
    depth_of: &(dyn Fn(&'s Frame) -> Option<(Cow<'s, DepthMap>, Intrinsics)> + Sync),
) -> Result<PointCloud, GeometryError> {
    let bounds = match options.bounds {
        Some(b) => b,
        None => scene_bounds(scan, &options.bounds_options)?.aabb,
    };
    let grid = make_grid(&bounds, options)?;
    for frame in &scan.frames {
        if !super::bounds::is_finite(&frame.camera_to_world) {
            return Err(GeometryError::BadPose {
                frame: frame.name.clone(),
            });
        }
    }
    let merged = scan
        .frames
        .par_iter()
        .fold(VoxelMap::default, |acc, frame| {
            let voxels = match depth_of(frame) {
                Some((depth, k)) => frame_voxels(frame, &depth, &k, &grid),
                None => VoxelMap::default(),
            };
            merge(acc, voxels)
        })
        .reduce(VoxelMap::default, merge);
    let mut voxels: Vec<(u64, Acc)> = merged.into_iter().collect();
    voxels.sort_unstable_by_key(|(k, _)| *k);
    let mut cloud = PointCloud {
        voxel_size: grid.voxel,
        bounds,
        ..PointCloud::default()
    };
    cloud.positions.reserve(voxels.len());
    cloud.colors.reserve(voxels.len());
    for (key, acc) in voxels {
        let n = acc.count as f64;
        let index = Vector3::new((key >> 32) as f64, ((key >> 16) & 0xffff) as f64, (key & 0xffff) as f64);
        let frac =
            Vector3::new(acc.offset[0] as f64, acc.offset[1] as f64, acc.offset[2] as f64) / (n * f64::from(FIXED_ONE));
        let p = grid.min + (index + frac) * grid.voxel;
        cloud.positions.push(p.coords.cast::<f32>().into());
        cloud
            .colors
            .push(acc.rgb.map(|c| ((c + acc.count / 2) / acc.count).min(255) as u8));
        cloud.fused_points += acc.count;
    }
    Ok(cloud)
}

/// Union of two voxel maps, summing shared voxels into the larger map.
fn merge(a: VoxelMap, b: VoxelMap) -> VoxelMap {
    let (mut big, small) = if a.len() >= b.len() { (a, b) } else { (b, a) };
    for (k, v) in small {
        big.entry(k).or_default().merge(&v);
    }
    big
}

/// Voxel grid over `bounds` with the requested or derived voxel size.
fn make_grid(bounds: &DAabb, options: &CloudOptions) -> Result<Grid, GeometryError> {
    let extent = bounds.max_extent();
    let voxel = options
        .voxel_size
        .unwrap_or(extent / f64::from(options.voxels_per_extent.max(1)));
    let bad = |reason: String| GeometryError::BadVoxelSize { voxel, extent, reason };
    if !(bounds.is_valid() && extent > 0.0) {
        return Err(bad(format!("the scene box {bounds:?} is empty")));
    }
    if !(voxel.is_finite() && voxel > 0.0) {
        return Err(bad("it must be a positive finite number".into()));
    }
    let per_axis = (bounds.extent() / voxel).map(|n| n.ceil().max(1.0));
    if per_axis.max() > MAX_VOXELS_PER_AXIS as f64 {
        return Err(bad(format!(
            "it needs {} voxels along one axis, at most {MAX_VOXELS_PER_AXIS}",
            per_axis.max()
        )));
    }
    let dims = [per_axis.x as u64, per_axis.y as u64, per_axis.z as u64];
    Ok(Grid {
        min: bounds.min,
        voxel,
        dims,
    })
}

/// Voxel sums of the valid pixels of `depth` (with intrinsics `k`, seen
/// from `frame`'s pose and coloured from its rgb image) inside the grid.
fn frame_voxels(frame: &Frame, depth: &DepthMap, k: &Intrinsics, grid: &Grid) -> VoxelMap {
    let mut map = VoxelMap::default();
    let (w, h) = (depth.width as usize, depth.height as usize);
    let (rw, rh) = frame.size();
    if rw == 0 || rh == 0 || depth.metres.len() != w * h || !(k.fx > 0.0 && k.fy > 0.0) {
        return map;
    }
    // Camera point (x, y, 1) * z to grid coordinates: g = z * (A (x, y, 1)) + b.
    let a: Matrix3<f32> = (frame.camera_to_world.rotation.matrix() / grid.voxel).cast();
    let b: Vector3<f32> = ((frame.camera_center() - grid.min) / grid.voxel).cast();
    let dims = Vector3::new(grid.dims[0] as f32, grid.dims[1] as f32, grid.dims[2] as f32);
    // The rgb pixel on each depth pixel's ray (the nearest centre).
    let rgb_k = frame.intrinsics;
    let nearest =
        |t: f64, focal: f64, centre: f64, size: u32| ((t * focal + centre).round().max(0.0) as u32).min(size - 1);
    let rgb_col: Vec<u32> = (0..w)
        .map(|u| nearest((u as f64 - k.cx) / k.fx, rgb_k.fx, rgb_k.cx, rw))
        .collect();
    let xs: Vec<Vector3<f32>> = (0..w)
        .map(|u| a.column(0) * ((u as f64 - k.cx) / k.fx) as f32)
        .collect();
    // Neighbouring pixels mostly share a voxel: sum runs locally first.
    let mut run: Option<(u64, Acc)> = None;
    for (v, row) in depth.metres.chunks_exact(w).enumerate().take(h) {
        let rgb_row = nearest((v as f64 - k.cy) / k.fy, rgb_k.fy, rgb_k.cy, rh);
        let row_dir = a.column(1) * ((v as f64 - k.cy) / k.fy) as f32 + a.column(2);
        for (u, &z) in row.iter().enumerate() {
            if !(z > 0.0 && z.is_finite()) {
                continue;
            }
            let g = (xs[u] + row_dir) * z + b;
            // Also rejects NaN.
            if !(0..3).all(|i| g[i] >= 0.0 && g[i] < dims[i]) {
                continue;
            }
            // g >= 0, so truncation is floor (and avoids a libm call).
            let cell = g.map(|x| x as u32);
            let frac = (g - cell.map(|c| c as f32)).map(|f| (f * FIXED_ONE).min(FIXED_ONE - 1.0));
            let key = (u64::from(cell.x) << 32) | (u64::from(cell.y) << 16) | u64::from(cell.z);
            let px = frame.rgb.get_pixel(rgb_col[u], rgb_row).0;
            let acc = match &mut run {
                Some((k, acc)) if *k == key => acc,
                _ => {
                    if let Some((k, acc)) = run.take() {
                        map.entry(k).or_default().merge(&acc);
                    }
                    &mut run.insert((key, Acc::default())).1
                }
            };
            acc.count += 1;
            acc.offset[0] += frac.x as u64;
            acc.offset[1] += frac.y as u64;
            acc.offset[2] += frac.z as u64;
            for (sum, c) in acc.rgb.iter_mut().zip(px) {
                *sum += u64::from(c);
            }
        }
    }
    if let Some((k, acc)) = run {
        map.entry(k).or_default().merge(&acc);
    }
    map
}

/// Write `cloud` as binary little-endian PLY (x y z float, red green blue uchar).
pub fn write_ply(path: &Path, cloud: &PointCloud) -> Result<(), GeometryError> {
    crate::atomic::write_with(path, |w| {
        write!(
            w,
            "ply\nformat binary_little_endian 1.0\ncomment nerflabel fused point cloud, voxel size {} m\n\
             element vertex {}\nproperty float x\nproperty float y\nproperty float z\n\
             property uchar red\nproperty uchar green\nproperty uchar blue\nend_header\n",
            cloud.voxel_size,
            cloud.positions.len()
        )?;
        for (p, c) in cloud.positions.iter().zip(&cloud.colors) {
            let mut rec = [0u8; 15];
            for (i, x) in p.iter().enumerate() {
                rec[4 * i..4 * i + 4].copy_from_slice(&x.to_le_bytes());
            }
            rec[12..].copy_from_slice(c);
            w.write_all(&rec)?;
        }
        Ok(())
    })
    .map_err(|source| GeometryError::Io {
        path: path.to_path_buf(),
        source,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::poses::test_scene::Room;

    #[test]
    fn room_cloud_lies_on_the_walls_with_one_point_per_occupied_voxel() {
        let room = Room::default();
        let scan = room.scan();
        // A voxel size whose boundaries do not coincide with the walls, where
        // rounding would split one wall layer into two.
        let voxel = 0.0937;
        let cloud = fuse_cloud(
            &scan,
            &CloudOptions {
                voxel_size: Some(voxel),
                ..CloudOptions::default()
            },
        )
        .unwrap();
        assert_eq!(cloud.positions.len(), cloud.colors.len());
        assert_eq!(
            cloud.fused_points,
            24 * 64 * 48,
            "every pixel lies inside the padded bounds"
        );
        assert!(cloud.len() > 500, "{}", cloud.len());
        // Reference: distinct voxels of all pixels, back-projected in f64.
        let mut keys = std::collections::HashSet::new();
        for f in &scan.frames {
            let d = f.depth.as_ref().unwrap();
            for (i, z) in d.metres.iter().enumerate() {
                let (u, v) = ((i % 64) as f64, (i / 64) as f64);
                let p = f.camera_to_world * Point3::from(f.intrinsics.unproject(u, v) * *z as f64);
                let key: [i64; 3] = ((p - cloud.bounds.min) / voxel).map(|x| x.floor() as i64).into();
                keys.insert(key);
            }
        }
        let ratio = cloud.len() as f64 / keys.len() as f64;
        assert!(
            (ratio - 1.0).abs() < 0.005,
            "{} voxels, reference {}",
            cloud.len(),
            keys.len()
        );
        for p in &cloud.positions {
            let p = Vector3::new(p[0] as f64, p[1] as f64, p[2] as f64);
            // Distance to the nearest wall of the room: points are averages of
            // wall points, so only voxels on edges may leave the wall a little.
            let d = (p.abs() - room.half).abs().min();
            assert!(d < 0.05, "{p} is {d} m from every wall");
        }
    }

    #[test]
    fn fusion_is_deterministic_and_crops_to_the_bounds() {
        let scan = Room::default().scan();
        let box_ = DAabb::new(Point3::new(0.0, -2.0, -2.0), Point3::new(3.0, 2.0, 2.0));
        let opts = CloudOptions {
            bounds: Some(box_),
            voxels_per_extent: 64,
            ..CloudOptions::default()
        };
        let a = fuse_cloud(&scan, &opts).unwrap();
        let b = fuse_cloud(&scan, &opts).unwrap();
        assert_eq!(a, b);
        assert!(!a.is_empty());
        assert!(
            a.positions.iter().all(|p| p[0] >= 0.0),
            "points left of the box were kept"
        );
        assert!((a.voxel_size - 4.0 / 64.0).abs() < 1e-12);
    }

    #[test]
    fn absurd_voxel_sizes_are_errors() {
        let scan = Room::default().scan();
        for v in [0.0, -1.0, f64::NAN, 1e-9] {
            let err = fuse_cloud(
                &scan,
                &CloudOptions {
                    voxel_size: Some(v),
                    ..CloudOptions::default()
                },
            )
            .unwrap_err();
            assert!(matches!(err, GeometryError::BadVoxelSize { .. }), "{v}: {err}");
        }
    }
}
