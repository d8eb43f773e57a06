//! Robust scene bounds from the scan's depth and camera positions.
//!
//! Rule (all thresholds are fractions of the scene's own size, so a scene
//! scaled by 0.01 or 100 gets the same bounds scaled by the same factor):
//! 1. Back-project a deterministic subsample of the depth pixels (every
//!    `stride`-th pixel of each frame, at most [`BoundsOptions::max_points`]
//!    in total) to world points.
//! 2. Per axis, sort the coordinates. The core is the 5th..95th percentile;
//!    its widest axis gives the scene size `W`. Each side then grows from the
//!    core towards the outer percentile (`low_percentile`, `high_percentile`,
//!    0.5 and 99.5 by default) but stops at the first gap between consecutive
//!    values wider than `W / 10` (flying pixels far behind the scene are
//!    separated from it by such a gap) and never reaches further than `W`
//!    beyond the core.
//! 3. Unite with every camera centre and pad each side by `padding` (5 %) of
//!    the longest edge.
//!
//! `Scan::bounds` (bbox.txt) overrides the result as given. A scan without any
//! usable depth falls back to the union of the camera frusta truncated at
//! `0..far`, where `far = far_factor x D` (2 x D by default) and `D` is the
//! diagonal of the camera centres' bounding box (the trajectory diameter, up
//! to a factor sqrt(3)); `far` is a z-depth, the frustum corners are the
//! image corners. With a single camera position there is no scale and the
//! fallback fails.

use super::{DAabb, GeometryError};
use crate::scan::{Frame, Scan};
use nalgebra::Point3;
use rayon::prelude::*;

/// Lower core percentile (the part of the cloud that is certainly scene).
const CORE_LOW: f64 = 5.0;
/// Upper core percentile.
const CORE_HIGH: f64 = 95.0;
/// A gap wider than this fraction of the core size ends a tail.
const GAP_FRACTION: f64 = 0.1;
/// A tail reaches at most this many core sizes beyond the core.
const MAX_REACH: f64 = 1.0;

/// How to compute the bounds.
#[derive(Clone, Debug, PartialEq)]
pub struct BoundsOptions {
    /// Most depth points to back-project (the pixel stride is derived from it).
    pub max_points: usize,
    /// Outermost lower percentile a side may reach, in percent.
    pub low_percentile: f64,
    /// Outermost upper percentile a side may reach, in percent.
    pub high_percentile: f64,
    /// Padding per side as a fraction of the longest edge.
    pub padding: f64,
    /// No-depth fallback: frustum range as a multiple of the trajectory diameter.
    pub far_factor: f64,
}

impl Default for BoundsOptions {
    fn default() -> Self {
        BoundsOptions {
            max_points: 2_000_000,
            low_percentile: 0.5,
            high_percentile: 99.5,
            padding: 0.05,
            far_factor: 2.0,
        }
    }
}

/// Where the bounds came from.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum BoundsSource {
    /// The scan's own `bbox.txt`.
    User,
    /// Robust percentiles of the back-projected depth, united with the cameras.
    Depth,
    /// No usable depth: union of the truncated camera frusta.
    CameraFrusta,
}

/// Figures about the depth points behind the bounds.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct PointStats {
    /// Frames that carry a depth map.
    pub frames_with_depth: usize,
    /// Depth pixels before subsampling.
    pub candidate_pixels: u64,
    /// Pixel stride of the subsample.
    pub stride: u64,
    /// Valid (positive, finite) points in the subsample.
    pub sampled: usize,
    /// Sampled points outside the robust point box (flying pixels, far walls).
    pub rejected: usize,
    /// Robust box of the points alone, before cameras and padding.
    pub point_box: Option<DAabb>,
    /// Smallest, median and largest sampled depth in metres (0 without depth).
    pub depth_min: f64,
    pub depth_median: f64,
    pub depth_max: f64,
}

/// Deterministic subsample of a scan's depth, back-projected to world points.
#[derive(Clone, Debug, Default)]
pub struct DepthSamples {
    /// World points, frame by frame in scan order.
    pub points: Vec<Point3<f64>>,
    /// Their depths in metres, same order.
    pub depths: Vec<f32>,
    /// Frames that carry a depth map.
    pub frames_with_depth: usize,
    /// Depth pixels before subsampling.
    pub candidate_pixels: u64,
    /// Pixel stride used.
    pub stride: u64,
}

/// The scene's world-frame bounds and what they were made from.
#[derive(Clone, Debug)]
pub struct SceneBounds {
    /// World-frame box, metres.
    pub aabb: DAabb,
    /// Where it came from.
    pub source: BoundsSource,
    /// Statistics of the depth points.
    pub stats: PointStats,
    /// Every sampled depth point (outliers included), for the normalisation.
    pub samples: Vec<Point3<f64>>,
    /// Camera centres, scan order.
    pub cameras: Vec<Point3<f64>>,
    /// Options the bounds were made with (the normalisation reuses them).
    pub options: BoundsOptions,
}

/// User bounds must hold at least 1 in this many sampled depth points
/// (a few flying pixels inside bounds placed away from the scene do not count).
const USER_BOUNDS_MIN_SHARE: usize = 1000;

/// Compute robust scene bounds for `scan`.
pub fn scene_bounds(scan: &Scan, options: &BoundsOptions) -> Result<SceneBounds, GeometryError> {
    if scan.frames.is_empty() {
        return Err(GeometryError::NoFrames);
    }
    let cameras = camera_centers(scan)?;
    let samples = sample_depth_points(scan, options.max_points)?;
    let point_box = robust_box(&samples.points, |p| *p, options.low_percentile, options.high_percentile);
    let mut stats = depth_stats(&samples);
    stats.point_box = point_box;
    if let Some(b) = point_box {
        stats.rejected = samples.points.par_iter().filter(|p| !b.contains(p)).count();
    }
    let (aabb, source) = if let Some(user) = scan.bounds {
        let b = DAabb::new(user.min, user.max);
        if !b.is_valid() || !(0..3).all(|a| b.min[a] < b.max[a]) {
            return Err(GeometryError::InvalidUserBounds {
                min: user.min.into(),
                max: user.max.into(),
            });
        }
        // Bounds holding (almost) none of the measured surface train nothing.
        let total = samples.points.len();
        let inside = samples.points.par_iter().filter(|p| b.contains(p)).count();
        if total > 0 && inside * USER_BOUNDS_MIN_SHARE < total {
            return Err(GeometryError::UserBoundsMissScene {
                min: user.min.into(),
                max: user.max.into(),
                inside,
                total,
            });
        }
        (b, BoundsSource::User)
    } else if let Some(b) = point_box {
        let b = cameras.iter().fold(b, |b, c| b.including(c));
        (pad_relative(&b, options.padding), BoundsSource::Depth)
    } else {
        (frusta_bounds(scan, &cameras, options)?, BoundsSource::CameraFrusta)
    };
    if !(aabb.max_extent().is_finite() && aabb.max_extent() > 0.0) {
        return Err(GeometryError::NoScale { cameras: cameras.len() });
    }
    Ok(SceneBounds {
        aabb,
        source,
        stats,
        samples: samples.points,
        cameras,
        options: options.clone(),
    })
}

/// Camera centres, failing on a non-finite pose.
pub(crate) fn camera_centers(scan: &Scan) -> Result<Vec<Point3<f64>>, GeometryError> {
    scan.frames
        .iter()
        .map(|f| {
            if is_finite(&f.camera_to_world) {
                Ok(f.camera_center())
            } else {
                Err(GeometryError::BadPose { frame: f.name.clone() })
            }
        })
        .collect()
}

/// Back-project every `stride`-th depth pixel of every frame, with the stride
/// chosen so that at most `max_points` pixels are visited.
pub fn sample_depth_points(scan: &Scan, max_points: usize) -> Result<DepthSamples, GeometryError> {
    let mut candidate_pixels: u64 = 0;
    let mut frames_with_depth = 0;
    for frame in &scan.frames {
        if let Some(d) = &frame.depth {
            frames_with_depth += 1;
            candidate_pixels = candidate_pixels.saturating_add(u64::from(d.width) * u64::from(d.height));
        }
    }
    let stride = candidate_pixels.div_ceil(max_points.max(1) as u64).max(1);
    let per_frame: Vec<(Vec<Point3<f64>>, Vec<f32>)> = scan
        .frames
        .par_iter()
        .enumerate()
        .map(|(i, f)| sample_frame(f, stride, splitmix64(i as u64) % stride))
        .collect::<Result<_, _>>()?;
    let total = per_frame.iter().map(|(p, _)| p.len()).sum();
    let mut out = DepthSamples {
        points: Vec::with_capacity(total),
        depths: Vec::with_capacity(total),
        frames_with_depth,
        candidate_pixels,
        stride,
    };
    for (p, d) in per_frame {
        out.points.extend(p);
        out.depths.extend(d);
    }
    Ok(out)
}

/// Sample one frame's depth from flat pixel index `phase` on, every `stride`.
fn sample_frame(frame: &Frame, stride: u64, phase: u64) -> Result<(Vec<Point3<f64>>, Vec<f32>), GeometryError> {
    let Some(depth) = &frame.depth else {
        return Ok((Vec::new(), Vec::new()));
    };
    let Some(k) = depth_intrinsics(frame)? else {
        return Ok((Vec::new(), Vec::new()));
    };
    if !is_finite(&frame.camera_to_world) {
        return Err(GeometryError::BadPose {
            frame: frame.name.clone(),
        });
    }
    let w = u64::from(depth.width);
    let mut points = Vec::new();
    let mut depths = Vec::new();
    let mut idx = phase;
    while let Some(&z) = usize::try_from(idx).ok().and_then(|i| depth.metres.get(i)) {
        if z > 0.0 && z.is_finite() {
            let (u, v) = ((idx % w) as f64, (idx / w) as f64);
            let p = frame.camera_to_world * Point3::from(k.unproject(u, v) * f64::from(z));
            if p.iter().all(|x| x.is_finite()) {
                points.push(p);
                depths.push(z);
            }
        }
        idx += stride;
    }
    Ok((points, depths))
}

/// Intrinsics for a frame's depth grid (rescaled if it differs from the rgb
/// grid); `None` for an empty depth map. Fails on a size mismatch.
pub(crate) fn depth_intrinsics(frame: &Frame) -> Result<Option<crate::scan::Intrinsics>, GeometryError> {
    let Some(depth) = &frame.depth else { return Ok(None) };
    let expected = u64::from(depth.width) * u64::from(depth.height);
    if depth.metres.len() as u64 != expected {
        return Err(GeometryError::BadDepthSize {
            frame: frame.name.clone(),
            width: depth.width,
            height: depth.height,
            found: depth.metres.len(),
        });
    }
    if expected == 0 {
        return Ok(None);
    }
    let rgb = frame.size();
    let grid = (depth.width, depth.height);
    let k = if rgb == grid || rgb.0 == 0 || rgb.1 == 0 {
        frame.intrinsics
    } else {
        frame.intrinsics.scaled(rgb, grid)
    };
    Ok(Some(k))
}

/// Robust per-axis box of `points` after `map` (see the module rule, step 2);
/// `None` without points.
pub(crate) fn robust_box<F>(points: &[Point3<f64>], map: F, low: f64, high: f64) -> Option<DAabb>
where
    F: Fn(&Point3<f64>) -> Point3<f64> + Sync,
{
    if points.is_empty() {
        return None;
    }
    let axes: Vec<Vec<f64>> = (0..3)
        .into_par_iter()
        .map(|a| {
            let mut v: Vec<f64> = points.iter().map(|p| map(p)[a]).collect();
            v.sort_unstable_by(f64::total_cmp);
            v
        })
        .collect();
    let n = points.len();
    let rank = |q: f64| ((q.clamp(0.0, 100.0) / 100.0) * (n - 1) as f64).round() as usize;
    let (outer_lo, outer_hi) = (rank(low.min(high)), rank(high.max(low)));
    let core_lo = rank(CORE_LOW).max(outer_lo);
    let core_hi = rank(CORE_HIGH).min(outer_hi).max(core_lo);
    let size = axes.iter().map(|v| v[core_hi] - v[core_lo]).fold(0.0, f64::max);
    let gap = GAP_FRACTION * size;
    let reach = MAX_REACH * size;
    let mut lo = Point3::origin();
    let mut hi = Point3::origin();
    for (a, v) in axes.iter().enumerate() {
        let mut j = core_hi;
        while j < outer_hi && v[j + 1] - v[j] <= gap {
            j += 1;
        }
        hi[a] = v[j].min(v[core_hi] + reach);
        let mut i = core_lo;
        while i > outer_lo && v[i] - v[i - 1] <= gap {
            i -= 1;
        }
        lo[a] = v[i].max(v[core_lo] - reach);
    }
    let b = DAabb::new(lo, hi);
    b.is_valid().then_some(b)
}

/// `b` padded on every side by `fraction` of its longest edge.
pub(crate) fn pad_relative(b: &DAabb, fraction: f64) -> DAabb {
    b.padded(fraction * b.max_extent())
}

/// Union of the frusta truncated at `far` (module rule), padded.
fn frusta_bounds(scan: &Scan, cameras: &[Point3<f64>], options: &BoundsOptions) -> Result<DAabb, GeometryError> {
    let no_scale = GeometryError::NoScale { cameras: cameras.len() };
    let Some(centres) = DAabb::from_points(cameras.iter().copied()) else {
        return Err(no_scale);
    };
    let far = options.far_factor * centres.extent().norm();
    if !(far.is_finite() && far > 0.0) {
        return Err(no_scale);
    }
    let mut b = centres;
    for f in &scan.frames {
        let (w, h) = f.size();
        let (w, h) = (f64::from(w), f64::from(h));
        for (u, v) in [(-0.5, -0.5), (w - 0.5, -0.5), (-0.5, h - 0.5), (w - 0.5, h - 0.5)] {
            let p = f.camera_to_world * Point3::from(f.intrinsics.unproject(u, v) * far);
            if p.iter().all(|x| x.is_finite()) {
                b = b.including(&p);
            }
        }
    }
    Ok(pad_relative(&b, options.padding))
}

/// Whether every element of a pose is finite.
pub(crate) fn is_finite(pose: &nalgebra::IsometryMatrix3<f64>) -> bool {
    pose.rotation
        .matrix()
        .iter()
        .chain(pose.translation.vector.iter())
        .all(|x| x.is_finite())
}

/// Depth minimum, median and maximum of the samples.
fn depth_stats(s: &DepthSamples) -> PointStats {
    let mut stats = PointStats {
        frames_with_depth: s.frames_with_depth,
        candidate_pixels: s.candidate_pixels,
        stride: s.stride,
        sampled: s.points.len(),
        ..PointStats::default()
    };
    if !s.depths.is_empty() {
        let mut d = s.depths.clone();
        let mid = d.len() / 2;
        let (below, median, above) = d.select_nth_unstable_by(mid, f32::total_cmp);
        stats.depth_median = f64::from(*median);
        stats.depth_min = f64::from(below.iter().copied().fold(*median, f32::min));
        stats.depth_max = f64::from(above.iter().copied().fold(*median, f32::max));
    }
    stats
}

/// Mix bits so consecutive frames start their stride at unrelated pixels.
fn splitmix64(x: u64) -> u64 {
    let mut z = x.wrapping_add(0x9E37_79B9_7F4A_7C15);
    z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
    z ^ (z >> 31)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::poses::test_scene::Room;
    use crate::scan::Bounds;
    use nalgebra::Vector3;

    fn room_box(room: &Room) -> DAabb {
        let (lo, hi) = room.local_box();
        DAabb::new(room.to_world(&lo), room.to_world(&hi))
    }

    #[test]
    fn clean_room_bounds_hug_the_walls() {
        let room = Room::default();
        let b = scene_bounds(&room.scan(), &BoundsOptions::default()).unwrap();
        assert_eq!(b.source, BoundsSource::Depth);
        let walls = room_box(&room);
        let pad = 0.05 * walls.max_extent();
        // Padding added on top of the exact walls, up to the discrete sampling.
        assert!(
            (b.aabb.min - (walls.min - Vector3::repeat(pad))).amax() < 0.02,
            "{:?}",
            b.aabb
        );
        assert!(
            (b.aabb.max - (walls.max + Vector3::repeat(pad))).amax() < 0.02,
            "{:?}",
            b.aabb
        );
        assert_eq!(b.stats.stride, 1);
        assert_eq!(b.stats.sampled, 24 * 64 * 48);
    }

    #[test]
    fn stride_caps_the_number_of_points() {
        let room = Room::default();
        let s = sample_depth_points(&room.scan(), 10_000).unwrap();
        assert_eq!(s.stride, (24u64 * 64 * 48).div_ceil(10_000));
        assert!(s.points.len() <= 10_000 && s.points.len() > 9_000, "{}", s.points.len());
        let again = sample_depth_points(&room.scan(), 10_000).unwrap();
        assert_eq!(s.points, again.points);
    }

    #[test]
    fn robust_box_cuts_a_far_cluster_beyond_the_gap() {
        // 97 % of values in [0, 1], 3 % at 1000: the outer percentile lands in
        // the far cluster but the gap rule stops at 1.
        let splat = |x: f64| Point3::new(x, x, x);
        let mut pts: Vec<Point3<f64>> = (0..970).map(|i| splat(i as f64 / 969.0)).collect();
        pts.extend((0..30).map(|i| splat(1000.0 + i as f64)));
        let b = robust_box(&pts, |p| *p, 0.5, 99.5).unwrap();
        assert!((b.max.x - 1.0).abs() < 1e-12 && b.min.x < 0.01, "{b:?}");
    }

    #[test]
    fn user_box_overrides_and_invalid_box_is_an_error() {
        let mut scan = Room::default().scan();
        let user = Bounds {
            min: nalgebra::Point3::new(-1.0, -1.0, -1.0),
            max: nalgebra::Point3::new(1.0, 2.0, 3.0),
        };
        scan.bounds = Some(user);
        let b = scene_bounds(&scan, &BoundsOptions::default()).unwrap();
        assert_eq!(b.source, BoundsSource::User);
        assert_eq!((b.aabb.min, b.aabb.max), (user.min, user.max));
        scan.bounds = Some(Bounds {
            min: nalgebra::Point3::new(1.0, 1.0, 1.0),
            max: nalgebra::Point3::new(2.0, 0.5, 2.0),
        });
        let err = scene_bounds(&scan, &BoundsOptions::default()).unwrap_err();
        assert!(matches!(err, GeometryError::InvalidUserBounds { .. }), "{err}");
    }

    #[test]
    fn bad_depth_size_names_the_frame() {
        let mut scan = Room::default().scan();
        if let Some(d) = scan.frames[3].depth.as_mut() {
            d.metres.pop();
        }
        let err = scene_bounds(&scan, &BoundsOptions::default()).unwrap_err();
        assert!(err.to_string().contains("frame 000003"), "{err}");
    }

    #[test]
    fn single_camera_without_depth_has_no_scale() {
        let room = Room {
            with_depth: false,
            frames: 1,
            ..Room::default()
        };
        let err = scene_bounds(&room.scan(), &BoundsOptions::default()).unwrap_err();
        assert!(matches!(err, GeometryError::NoScale { cameras: 1 }), "{err}");
    }
}
