//! Photometric alignment of frame pairs, reconciled over the whole
//! trajectory in one least-squares solve.
//!
//! Depth alone leaves frames free to slide along what they see: on a
//! SLAM-like tabletop scan, groups of frames settle on copies of the scene
//! 2 cm apart along the table and still agree with each other's depth to
//! 1.4 mm (each frame's nearest depth points are its own group's). Colour
//! pins that slide: a frame's depth carries its image into a partner frame,
//! where a coarse-to-fine Gauss-Newton finds the rigid move of the partner
//! that makes the two images agree (with a gain and offset for exposure);
//! every pair's move is then reconciled at once (a linearised pose graph).
//! Measured on such a scan: the normalised correlation of a pair across
//! the two groups is 0.41 through the depth-aligned poses, 0.80 through
//! the exact ones.

use super::refine::{gauss_newton_solve, median, MAD_TO_SIGMA, TUKEY_C};
use crate::scan::{colour_borders, ColourBorder, Frame, EDGE_RELATIVE_GAP};
use nalgebra::{DMatrix, DVector, IsometryMatrix3, Matrix6, Point3, Rotation3, Translation3, Vector3, Vector6};
use rayon::prelude::*;

/// How the pairs are aligned.
#[derive(Clone, Copy, Debug)]
pub struct PairwiseOptions {
    /// Partners per frame (the frames that see most of what it sees,
    /// spread over the trajectory).
    pub partners: usize,
    /// Image pyramid levels (each half the size of the one below).
    pub levels: usize,
    /// Gauss-Newton iterations per level.
    pub iterations: usize,
    /// Points (pixels with depth and an image gradient) per frame and level.
    pub points: usize,
    /// Rounds of (align pairs, reconcile).
    pub rounds: usize,
}

impl Default for PairwiseOptions {
    fn default() -> Self {
        PairwiseOptions {
            partners: 4,
            levels: 4,
            iterations: 6,
            points: 2500,
            rounds: 2,
        }
    }
}

/// A partner must see this share of a frame's depth points.
const MIN_OVERLAP: f64 = 0.3;
/// Fewest points left in a pair's last iteration for its move to count.
const MIN_POINTS: usize = 200;
/// Narrowest pyramid level, pixels.
const MIN_LEVEL_WIDTH: usize = 80;
/// Farthest a pair's move may shift its points, in pixels of the coarsest
/// pyramid level: Gauss-Newton there converges from a pixel or two away;
/// a move beyond a few of them fell into another minimum.
const REACH_COARSE_PX: f64 = 3.0;
/// Directions of a pair's move with less than this share of the best
/// constrained direction's information are left alone.
const WEAK_DIRECTION: f64 = 1e-3;

/// A grey image (luma, 0-255) at one pyramid level.
struct Gray {
    width: usize,
    height: usize,
    data: Vec<f32>,
}

impl Gray {
    /// The luma of `image`, its dead `border` lines repeating the nearest
    /// line that shows the scene (so they make no edge to align).
    fn from_rgb(image: &crate::scan::RgbImage, border: &ColourBorder) -> Gray {
        let (w, h) = image.dimensions();
        let (x0, y0, x1, y1) = border.kept_rect(w, h);
        let kept = x1 > x0 && y1 > y0;
        let mut data = Vec::with_capacity((w * h) as usize);
        for y in 0..h {
            for x in 0..w {
                let (sx, sy) = if kept {
                    (x.clamp(x0, x1 - 1), y.clamp(y0, y1 - 1))
                } else {
                    (x, y)
                };
                let p = image.get_pixel(sx, sy);
                data.push(0.299 * f32::from(p[0]) + 0.587 * f32::from(p[1]) + 0.114 * f32::from(p[2]));
            }
        }
        Gray {
            width: w as usize,
            height: h as usize,
            data,
        }
    }

    /// Half the size, each pixel the mean of the four below it.
    fn halved(&self) -> Gray {
        let (width, height) = ((self.width / 2).max(1), (self.height / 2).max(1));
        let mut data = Vec::with_capacity(width * height);
        for y in 0..height {
            for x in 0..width {
                let at = |dx: usize, dy: usize| {
                    let (sx, sy) = ((2 * x + dx).min(self.width - 1), (2 * y + dy).min(self.height - 1));
                    self.data[sy * self.width + sx]
                };
                data.push(0.25 * (at(0, 0) + at(1, 0) + at(0, 1) + at(1, 1)));
            }
        }
        Gray { width, height, data }
    }

    #[inline]
    fn at(&self, x: usize, y: usize) -> f32 {
        self.data[y * self.width + x]
    }

    /// Bilinear value and gradient at continuous pixel (x, y); `None` within
    /// a pixel of the border.
    fn sample(&self, x: f64, y: f64) -> Option<(f64, f64, f64)> {
        if !(x >= 1.0 && y >= 1.0 && x < (self.width - 2) as f64 && y < (self.height - 2) as f64) {
            return None;
        }
        let (x0, y0) = (x.floor() as usize, y.floor() as usize);
        let (fx, fy) = ((x - x0 as f64) as f32, (y - y0 as f64) as f32);
        let bilinear = |xx: usize, yy: usize| {
            (1.0 - fy) * ((1.0 - fx) * self.at(xx, yy) + fx * self.at(xx + 1, yy))
                + fy * ((1.0 - fx) * self.at(xx, yy + 1) + fx * self.at(xx + 1, yy + 1))
        };
        let value = bilinear(x0, y0);
        // Central differences of the bilinear surface, one pixel each way.
        let gx = 0.5 * (bilinear(x0 + 1, y0) - bilinear(x0 - 1, y0));
        let gy = 0.5 * (bilinear(x0, y0 + 1) - bilinear(x0, y0 - 1));
        Some((f64::from(value), f64::from(gx), f64::from(gy)))
    }
}

/// One frame ready for pairing: its image pyramid, intrinsics per level,
/// and per level the camera-frame points of pixels with depth and texture
/// with their grey value.
struct PairFrame {
    pyramid: Vec<Gray>,
    intrinsics: Vec<crate::scan::Intrinsics>,
    points: Vec<Vec<(Point3<f64>, f64)>>,
    /// Sparse camera-frame depth points, for choosing partners.
    overlap_probe: Vec<Point3<f64>>,
}

impl PairFrame {
    fn new(frame: &Frame, border: &ColourBorder, opts: &PairwiseOptions) -> PairFrame {
        let mut pyramid = vec![Gray::from_rgb(&frame.rgb, border)];
        let full = (frame.rgb.width(), frame.rgb.height());
        let mut intrinsics = vec![frame.intrinsics];
        for _ in 1..opts.levels {
            let coarsest = &pyramid[pyramid.len() - 1];
            // Coarser than this, the texture that pins a frame blurs away.
            if coarsest.width / 2 < MIN_LEVEL_WIDTH {
                break;
            }
            let next = coarsest.halved();
            intrinsics.push(frame.intrinsics.scaled(full, (next.width as u32, next.height as u32)));
            pyramid.push(next);
        }
        let points = pyramid
            .iter()
            .zip(&intrinsics)
            .map(|(gray, k)| textured_points(frame, gray, k, opts.points))
            .collect();
        let overlap_probe = textured_points(
            frame,
            &pyramid[pyramid.len() - 1],
            &intrinsics[intrinsics.len() - 1],
            200,
        )
        .into_iter()
        .map(|(p, _)| p)
        .collect();
        PairFrame {
            pyramid,
            intrinsics,
            points,
            overlap_probe,
        }
    }
}

/// Camera-frame points of the level's pixels that have depth away from a
/// depth edge and an image gradient above the level's median, at most
/// `wanted` of them on a regular stride.
fn textured_points(frame: &Frame, gray: &Gray, k: &crate::scan::Intrinsics, wanted: usize) -> Vec<(Point3<f64>, f64)> {
    let Some(depth) = &frame.depth else {
        return Vec::new();
    };
    let Ok(Some(depth_k)) = super::bounds::depth_intrinsics(frame) else {
        return Vec::new();
    };
    let reach = super::refine::stored_pixel_reach(frame, depth);
    let mut candidates = Vec::new();
    for y in 1..gray.height.saturating_sub(1) {
        for x in 1..gray.width.saturating_sub(1) {
            let gx = gray.at(x + 1, y) - gray.at(x - 1, y);
            let gy = gray.at(x, y + 1) - gray.at(x, y - 1);
            candidates.push((gx * gx + gy * gy, x, y));
        }
    }
    if candidates.is_empty() {
        return Vec::new();
    }
    let mut magnitudes: Vec<f32> = candidates.iter().map(|c| c.0).collect();
    let mid = magnitudes.len() / 2;
    let threshold = *magnitudes.select_nth_unstable_by(mid, f32::total_cmp).1;
    let textured: Vec<_> = candidates.into_iter().filter(|c| c.0 > threshold).collect();
    let stride = (textured.len() / wanted.max(1)).max(1);
    let mut out = Vec::new();
    for &(_, x, y) in textured.iter().step_by(stride) {
        // The level pixel's centre on the depth grid.
        let ray = k.unproject(x as f64, y as f64);
        let Some((u, v)) = depth_k.project(&Point3::from(ray)) else {
            continue;
        };
        let (u, v) = (u.round(), v.round());
        if u < 0.0 || v < 0.0 {
            continue;
        }
        let (u, v) = (u as u32, v as u32);
        let z = depth.get(u, v);
        if z > 0.0 && z.is_finite() && super::refine::away_from_edges(depth, u, v, z, reach) {
            out.push((Point3::from(ray * f64::from(z)), f64::from(gray.at(x, y))));
        }
    }
    out
}

/// The world-frame move of a camera about the pivot `c`: `Y -> R (Y - c) + c + t`.
#[derive(Clone, Copy, Debug)]
struct Move {
    rotation: Rotation3<f64>,
    translation: Vector3<f64>,
}

impl Move {
    fn identity() -> Move {
        Move {
            rotation: Rotation3::identity(),
            translation: Vector3::zeros(),
        }
    }

    /// This move followed by a small one (rotation vector, translation).
    fn then(self, omega: Vector3<f64>, t: Vector3<f64>) -> Move {
        let increment = Rotation3::new(omega);
        Move {
            rotation: increment * self.rotation,
            translation: increment * self.translation + t,
        }
    }

    fn isometry(&self, pivot: &Point3<f64>) -> IsometryMatrix3<f64> {
        Translation3::from(pivot.coords + self.translation)
            * IsometryMatrix3::from_parts(Translation3::identity(), self.rotation)
            * Translation3::from(-pivot.coords)
    }

    /// As a 6-vector (rotation vector times `lever`, translation): metres.
    fn twist(&self, lever: f64) -> Vector6<f64> {
        let w = self.rotation.scaled_axis() * lever;
        Vector6::new(
            w.x,
            w.y,
            w.z,
            self.translation.x,
            self.translation.y,
            self.translation.z,
        )
    }
}

/// What aligning partner `j` to frame `i` found.
struct PairMove {
    i: usize,
    j: usize,
    /// The move of `j` (relative to `i`), as a twist in metres.
    twist: Vector6<f64>,
    /// Its information (Gauss-Newton Hessian over the residual variance).
    information: Matrix6<f64>,
}

/// A point of frame `i` as partner `j` sees it.
struct Seen {
    world: Point3<f64>,
    camera: Point3<f64>,
    /// Grey value in `i`, then in `j` with its gradient.
    grey_i: f64,
    grey_j: f64,
    gradient: (f64, f64),
}

/// Align camera `j` to frame `i`'s depth and image: the move of `j` about
/// the pivot that makes `j`'s image agree with `i`'s where `i` measured
/// depth. `None` when too few points are seen or nothing constrains it.
fn align_pair(
    frames: &[PairFrame],
    (i, j): (usize, usize),
    poses: &[IsometryMatrix3<f64>],
    (depth_j, depth_k): (Option<&crate::scan::DepthMap>, Option<crate::scan::Intrinsics>),
    (pivot, lever): (&Point3<f64>, f64),
    iterations: usize,
) -> Option<PairMove> {
    let (a, b) = (&frames[i], &frames[j]);
    let mut moved = Move::identity();
    let mut last = None;
    // Reused over levels and iterations.
    let most = a.points.iter().map(Vec::len).max().unwrap_or(0);
    let (mut world, mut seen, mut residuals) = (
        Vec::with_capacity(most),
        Vec::with_capacity(most),
        Vec::with_capacity(most),
    );
    for level in (0..a.pyramid.len().min(b.pyramid.len())).rev() {
        // A level of a small image may hold too few textured pixels.
        if a.points[level].len() < MIN_POINTS && level > 0 {
            continue;
        }
        world.clear();
        world.extend(a.points[level].iter().map(|(p, g)| (poses[i] * p, *g)));
        let (image, k) = (&b.pyramid[level], &b.intrinsics[level]);
        let mut level_best = (f64::NEG_INFINITY, moved);
        for _ in 0..iterations {
            let to_camera = (moved.isometry(pivot) * poses[j]).inverse();
            seen.clear();
            for &(x, grey_i) in &world {
                let p = to_camera * x;
                let Some((u, v)) = k.project(&p) else { continue };
                let Some((grey_j, gx, gy)) = image.sample(u, v) else {
                    continue;
                };
                if !occluded_in(depth_j, depth_k, &p) {
                    seen.push(Seen {
                        world: x,
                        camera: p,
                        grey_i,
                        grey_j,
                        gradient: (gx, gy),
                    });
                }
            }
            if seen.len() < MIN_POINTS {
                return None;
            }
            // A step that made the images agree less is taken back.
            let grey_i: Vec<f64> = seen.iter().map(|s| s.grey_i).collect();
            let grey_j: Vec<f64> = seen.iter().map(|s| s.grey_j).collect();
            let agreement = correlation(&grey_i, &grey_j).unwrap_or(f64::NEG_INFINITY);
            if agreement < level_best.0 {
                moved = level_best.1;
                break;
            }
            level_best = (agreement, moved);
            // Exposure: j's values mapped onto i's by a gain and an offset.
            let n = seen.len() as f64;
            let mean_i = seen.iter().map(|s| s.grey_i).sum::<f64>() / n;
            let mean_j = seen.iter().map(|s| s.grey_j).sum::<f64>() / n;
            let (mut cov, mut var) = (0.0, 0.0);
            for s in &seen {
                cov += (s.grey_j - mean_j) * (s.grey_i - mean_i);
                var += (s.grey_j - mean_j).powi(2);
            }
            let gain = if var > 0.0 { (cov / var).clamp(0.5, 2.0) } else { 1.0 };
            residuals.clear();
            residuals.extend(seen.iter().map(|s| gain * (s.grey_j - mean_j) + mean_i - s.grey_i));
            let scale = MAD_TO_SIGMA * median(residuals.iter().map(|r| r.abs()).collect());
            if !(scale > 0.0) {
                return None;
            }
            let cutoff = TUKEY_C * scale;
            let to_world = to_camera.rotation.inverse();
            let mut hessian = Matrix6::<f64>::zeros();
            let mut gradient = Vector6::<f64>::zeros();
            for (s, &r) in seen.iter().zip(&residuals) {
                if r.abs() >= cutoff {
                    continue;
                }
                let u = 1.0 - (r / cutoff).powi(2);
                let weight = u * u;
                let (p, (gx, gy)) = (s.camera, s.gradient);
                let du = Vector3::new(k.fx / p.z, 0.0, -k.fx * p.x / (p.z * p.z));
                let dv = Vector3::new(0.0, k.fy / p.z, -k.fy * p.y / (p.z * p.z));
                // Image change per world-frame motion of the point.
                let dimage = to_world * (gain * (gx * du + gy * dv));
                // Moving the camera by (w, t) about the pivot moves the point,
                // as the camera sees it, by -(w x y) - t, y its offset from
                // the pivot: d/dw = -(y x dimage), rotations in metres at the
                // lever's length.
                let drot = -(s.world - pivot).cross(&dimage) / lever;
                let jacobian = Vector6::new(drot.x, drot.y, drot.z, -dimage.x, -dimage.y, -dimage.z);
                hessian += weight * jacobian * jacobian.transpose();
                gradient += weight * r * jacobian;
            }
            let delta = gauss_newton_solve(&hessian, &gradient, WEAK_DIRECTION)?;
            moved = moved.then(
                Vector3::new(delta[0], delta[1], delta[2]) / lever,
                Vector3::new(delta[3], delta[4], delta[5]),
            );
            last = Some(hessian / (scale * scale));
            // Converged: the step moves points by a hundredth of a millimetre.
            if delta.norm() < 1e-5 {
                break;
            }
        }
    }
    let information = last?;
    // Kept only when the images agree better and the move stays within what
    // the coarsest level can reach (a few of its pixels).
    let moved_j = moved.isometry(pivot) * poses[j];
    let (before, after) = (
        pair_correlation(frames, (i, j), (&poses[i], &poses[j]), (depth_j, depth_k))?,
        pair_correlation(frames, (i, j), (&poses[i], &moved_j), (depth_j, depth_k))?,
    );
    let reach_px = REACH_COARSE_PX * f64::from(1u32 << (a.pyramid.len() - 1).min(16));
    if !(after > before) || mean_shift_px(&a.points[0], &b.intrinsics[0], (&poses[i], &poses[j], &moved_j)) > reach_px {
        return None;
    }
    let twist = moved.twist(lever);
    twist.iter().all(|v| v.is_finite()).then_some(PairMove {
        i,
        j,
        twist,
        information,
    })
}

/// Whether camera-frame point `p` lies clearly behind what `depth` measured
/// at its pixel (something nearer hides it).
fn occluded_in(depth: Option<&crate::scan::DepthMap>, k: Option<crate::scan::Intrinsics>, p: &Point3<f64>) -> bool {
    let (Some(depth), Some(k)) = (depth, k) else {
        return false;
    };
    let Some((u, v)) = k.project(p) else {
        return true;
    };
    if u < 0.0 || v < 0.0 {
        return false;
    }
    let measured = f64::from(depth.get(u.round() as u32, v.round() as u32));
    measured > 0.0 && measured < p.z * (1.0 - f64::from(EDGE_RELATIVE_GAP))
}

/// Share of frame `i`'s probe points that camera `j` sees unhidden.
fn overlap(frames: &[PairFrame], scan_frames: &[Frame], poses: &[IsometryMatrix3<f64>], i: usize, j: usize) -> f64 {
    let probe = &frames[i].overlap_probe;
    if probe.is_empty() {
        return 0.0;
    }
    let to_j = poses[j].inverse() * poses[i];
    let depth_k = super::bounds::depth_intrinsics(&scan_frames[j]).ok().flatten();
    let k = &scan_frames[j].intrinsics;
    let (w, h) = (
        f64::from(scan_frames[j].rgb.width()),
        f64::from(scan_frames[j].rgb.height()),
    );
    let seen = probe
        .iter()
        .filter(|p| {
            let q = to_j * *p;
            k.project(&q)
                .is_some_and(|(u, v)| u >= 0.0 && v >= 0.0 && u < w && v < h)
                && !occluded_in(scan_frames[j].depth.as_ref(), depth_k, &q)
        })
        .count();
    seen as f64 / probe.len() as f64
}

/// Partners of every frame: the frames that see most of its depth, spread
/// over the trajectory (no two within `spacing` frames of each other).
fn choose_pairs(
    frames: &[PairFrame],
    scan_frames: &[Frame],
    poses: &[IsometryMatrix3<f64>],
    partners: usize,
) -> Vec<(usize, usize)> {
    let n = frames.len();
    let spacing = (n / (4 * partners.max(1))).max(1);
    (0..n)
        .into_par_iter()
        .flat_map_iter(|i| {
            let mut ranked: Vec<(f64, usize)> = (0..n)
                .filter(|&j| j != i)
                .map(|j| (overlap(frames, scan_frames, poses, i, j), j))
                .filter(|&(o, _)| o >= MIN_OVERLAP)
                .collect();
            ranked.sort_by(|a, b| b.0.total_cmp(&a.0).then(a.1.cmp(&b.1)));
            let mut picked: Vec<usize> = Vec::new();
            for (_, j) in ranked {
                if picked.len() == partners {
                    break;
                }
                if picked.iter().all(|&p| p.abs_diff(j) >= spacing) && j.abs_diff(i) >= spacing.min(2) {
                    picked.push(j);
                }
            }
            picked.into_iter().map(move |j| (i, j))
        })
        .collect()
}

/// Moves of every frame (twists about the pivot, metres) that best agree
/// with all pairs' relative moves; a faint pull towards no move keeps the
/// system solvable where pairs leave a frame or the whole free.
fn reconcile(pairs: &[PairMove], frames: usize) -> Option<Vec<Vector6<f64>>> {
    let size = 6 * frames;
    let mut a = DMatrix::<f64>::zeros(size, size);
    let mut b = DVector::<f64>::zeros(size);
    let mut largest = 0.0f64;
    for p in pairs {
        let h = p.information;
        let hd = h * p.twist;
        largest = largest.max(h.diagonal().max());
        for r in 0..6 {
            b[6 * p.j + r] += hd[r];
            b[6 * p.i + r] -= hd[r];
            for c in 0..6 {
                a[(6 * p.i + r, 6 * p.i + c)] += h[(r, c)];
                a[(6 * p.j + r, 6 * p.j + c)] += h[(r, c)];
                a[(6 * p.i + r, 6 * p.j + c)] -= h[(r, c)];
                a[(6 * p.j + r, 6 * p.i + c)] -= h[(r, c)];
            }
        }
    }
    if !(largest > 0.0) {
        return None;
    }
    for d in 0..size {
        a[(d, d)] += 1e-6 * largest;
    }
    let x = a.cholesky()?.solve(&b);
    x.iter()
        .all(|v| v.is_finite())
        .then(|| (0..frames).map(|f| x.fixed_rows::<6>(6 * f).into_owned()).collect())
}

/// Mean over pairs of the normalised correlation of the two images where
/// the first frame measured depth (finest level): how well the poses make
/// the frames' colours agree.
fn agreement(
    frames: &[PairFrame],
    scan_frames: &[Frame],
    pairs: &[(usize, usize)],
    poses: &[IsometryMatrix3<f64>],
) -> f64 {
    let scores: Vec<f64> = pairs
        .par_iter()
        .filter_map(|&(i, j)| {
            let depth_k = super::bounds::depth_intrinsics(&scan_frames[j]).ok().flatten();
            pair_correlation(
                frames,
                (i, j),
                (&poses[i], &poses[j]),
                (scan_frames[j].depth.as_ref(), depth_k),
            )
        })
        .collect();
    if scores.is_empty() {
        return f64::NAN;
    }
    scores.iter().sum::<f64>() / scores.len() as f64
}

/// Normalised correlation of frame `i`'s image with `j`'s where `i` measured
/// depth and `j` sees it unhidden (finest level), through the given poses.
fn pair_correlation(
    frames: &[PairFrame],
    (i, j): (usize, usize),
    (pose_i, pose_j): (&IsometryMatrix3<f64>, &IsometryMatrix3<f64>),
    (depth_j, depth_k): (Option<&crate::scan::DepthMap>, Option<crate::scan::Intrinsics>),
) -> Option<f64> {
    let to_j = pose_j.inverse() * pose_i;
    let (image, k) = (&frames[j].pyramid[0], &frames[j].intrinsics[0]);
    let (mut a, mut b) = (Vec::new(), Vec::new());
    for (p, grey) in &frames[i].points[0] {
        let q = to_j * p;
        let Some((u, v)) = k.project(&q) else { continue };
        let Some((value, _, _)) = image.sample(u, v) else {
            continue;
        };
        if !occluded_in(depth_j, depth_k, &q) {
            a.push(*grey);
            b.push(value);
        }
    }
    correlation(&a, &b)
}

/// Mean distance, in `k`'s pixels, between where camera-frame `points` of
/// the frame at `pose_i` appear through `pose_j` and through `moved_j`.
fn mean_shift_px(
    points: &[(Point3<f64>, f64)],
    k: &crate::scan::Intrinsics,
    (pose_i, pose_j, moved_j): (&IsometryMatrix3<f64>, &IsometryMatrix3<f64>, &IsometryMatrix3<f64>),
) -> f64 {
    let (to_j, to_moved) = (pose_j.inverse() * pose_i, moved_j.inverse() * pose_i);
    let shifts: Vec<f64> = points
        .iter()
        .filter_map(|(p, _)| {
            let (a, b) = (k.project(&(to_j * p))?, k.project(&(to_moved * p))?);
            Some(((a.0 - b.0).powi(2) + (a.1 - b.1).powi(2)).sqrt())
        })
        .collect();
    if shifts.is_empty() {
        return f64::INFINITY;
    }
    shifts.iter().sum::<f64>() / shifts.len() as f64
}

fn correlation(a: &[f64], b: &[f64]) -> Option<f64> {
    if a.len() < MIN_POINTS {
        return None;
    }
    let n = a.len() as f64;
    let (ma, mb) = (a.iter().sum::<f64>() / n, b.iter().sum::<f64>() / n);
    let (mut ab, mut aa, mut bb) = (0.0, 0.0, 0.0);
    for (x, y) in a.iter().zip(b) {
        ab += (x - ma) * (y - mb);
        aa += (x - ma).powi(2);
        bb += (y - mb).powi(2);
    }
    let r = ab / (aa * bb).sqrt();
    r.is_finite().then_some(r)
}

/// Poses moved so that the frames' images agree where their depth overlaps
/// (unchanged where no round makes them agree better); `None` when the
/// frames' depth holds too few textured points.
pub fn align_pairs(
    scan_frames: &[Frame],
    poses: &[IsometryMatrix3<f64>],
    opts: &PairwiseOptions,
) -> Option<Vec<IsometryMatrix3<f64>>> {
    let borders = colour_borders(scan_frames);
    let frames: Vec<PairFrame> = scan_frames
        .par_iter()
        .zip(&borders)
        .map(|(f, border)| PairFrame::new(f, border, opts))
        .collect();
    // Pivot and lever: the centre and spread of the frames' depth points.
    let world: Vec<Point3<f64>> = frames
        .iter()
        .zip(poses)
        .flat_map(|(f, pose)| f.overlap_probe.iter().map(move |p| pose * p))
        .collect();
    if world.len() < MIN_POINTS {
        return None;
    }
    let pivot = Point3::from(world.iter().map(|p| p.coords).sum::<Vector3<f64>>() / world.len() as f64);
    let lever = (world.iter().map(|p| (p - pivot).norm_squared()).sum::<f64>() / world.len() as f64).sqrt();
    if !(lever > 0.0) {
        return None;
    }
    let depth_ks: Vec<_> = scan_frames
        .iter()
        .map(|f| super::bounds::depth_intrinsics(f).ok().flatten())
        .collect();
    let mut current = poses.to_vec();
    for _ in 0..opts.rounds {
        let pairs = choose_pairs(&frames, scan_frames, &current, opts.partners);
        if pairs.is_empty() {
            break;
        }
        let before = agreement(&frames, scan_frames, &pairs, &current);
        let moves: Vec<PairMove> = pairs
            .par_iter()
            .filter_map(|&(i, j)| {
                align_pair(
                    &frames,
                    (i, j),
                    &current,
                    (scan_frames[j].depth.as_ref(), depth_ks[j]),
                    (&pivot, lever),
                    opts.iterations,
                )
            })
            .collect();
        let Some(twists) = reconcile(&moves, frames.len()) else {
            break;
        };
        let next: Vec<IsometryMatrix3<f64>> = current
            .iter()
            .zip(&twists)
            .map(|(pose, x)| {
                let m = Move::identity().then(Vector3::new(x[0], x[1], x[2]) / lever, Vector3::new(x[3], x[4], x[5]));
                m.isometry(&pivot) * pose
            })
            .collect();
        let after = agreement(&frames, scan_frames, &pairs, &next);
        if !(after > before) {
            break;
        }
        current = next;
    }
    Some(current)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::scan::{DepthMap, Intrinsics, RgbImage};
    use nalgebra::Matrix3;

    /// Grey level of a textured floor at (x, y): a few sinusoids of 4-20 cm
    /// wavelength, so no shift along it looks like another.
    fn floor_texture(x: f64, y: f64) -> f64 {
        let waves = [
            (31.0, 17.0, 0.3),
            (-12.0, 29.0, 1.1),
            (47.0, -8.0, 2.0),
            (9.0, 61.0, 0.7),
        ];
        let sum: f64 = waves.iter().map(|&(a, b, phase)| (a * x + b * y + phase).sin()).sum();
        128.0 + 28.0 * sum
    }

    /// Cameras 1 m above a textured floor, on a circle, looking down and
    /// inward; exact depth and colour.
    fn floor_frames(count: usize) -> Vec<Frame> {
        let (w, h) = (160u32, 120u32);
        let k = Intrinsics {
            fx: 120.0,
            fy: 120.0,
            cx: 79.5,
            cy: 59.5,
        };
        (0..count)
            .map(|i| {
                let angle = std::f64::consts::TAU * i as f64 / count as f64;
                let eye = Vector3::new(0.25 * angle.cos(), 0.25 * angle.sin(), 1.0);
                let forward = (-eye).normalize();
                let right = forward.cross(&Vector3::y()).normalize();
                let down = forward.cross(&right);
                let rotation = Rotation3::from_matrix_unchecked(Matrix3::from_columns(&[right, down, forward]));
                let mut rgb = RgbImage::new(w, h);
                let mut metres = vec![0.0f32; (w * h) as usize];
                for v in 0..h {
                    for u in 0..w {
                        let ray = k.unproject(f64::from(u), f64::from(v));
                        let d = rotation * ray;
                        let t = -eye.z / d.z;
                        let hit = eye + d * t;
                        metres[(v * w + u) as usize] = t as f32;
                        let g = floor_texture(hit.x, hit.y).round().clamp(0.0, 255.0) as u8;
                        rgb.put_pixel(u, v, image::Rgb([g, g, g]));
                    }
                }
                Frame::new(
                    i as u64,
                    format!("{i:06}"),
                    rgb,
                    Some(DepthMap {
                        width: w,
                        height: h,
                        metres,
                    }),
                    IsometryMatrix3::from_parts(Translation3::from(eye), rotation),
                    k,
                )
            })
            .collect()
    }

    /// Spread of the frames' offsets from the truth once their common
    /// offset is removed: what depth cannot see on a plane (metres, RMS).
    fn relative_slide(poses: &[IsometryMatrix3<f64>], truth: &[Frame]) -> f64 {
        let offsets: Vec<Vector3<f64>> = poses
            .iter()
            .zip(truth)
            .map(|(p, f)| p.translation.vector - f.camera_to_world.translation.vector)
            .collect();
        let mean = offsets.iter().sum::<Vector3<f64>>() / offsets.len() as f64;
        (offsets.iter().map(|o| (o - mean).norm_squared()).sum::<f64>() / offsets.len() as f64).sqrt()
    }

    /// Two halves of the trajectory slid 1.5 cm apart along the floor agree
    /// with each other's depth exactly; their images bring them together.
    #[test]
    fn frames_slid_along_a_textured_plane_are_brought_back_by_their_colour() {
        let frames = floor_frames(16);
        let slid: Vec<IsometryMatrix3<f64>> = frames
            .iter()
            .enumerate()
            .map(|(i, f)| {
                let sign = if i < 8 { 1.0 } else { -1.0 };
                Translation3::new(0.0075 * sign, -0.004 * sign, 0.0) * f.camera_to_world
            })
            .collect();
        let before = relative_slide(&slid, &frames);
        let aligned = align_pairs(&frames, &slid, &PairwiseOptions::default()).expect("the frames pair up");
        let after = relative_slide(&aligned, &frames);
        assert!(
            after < 0.1 * before,
            "relative slide {:.2} mm -> {:.2} mm",
            before * 1e3,
            after * 1e3
        );
    }

    /// Exact poses stay: the images already agree.
    #[test]
    fn exact_poses_are_not_moved() {
        let frames = floor_frames(12);
        let poses: Vec<_> = frames.iter().map(|f| f.camera_to_world).collect();
        let aligned = align_pairs(&frames, &poses, &PairwiseOptions::default()).unwrap_or(poses.clone());
        let moved = aligned
            .iter()
            .zip(&poses)
            .map(|(a, p)| (a.translation.vector - p.translation.vector).norm())
            .fold(0.0, f64::max);
        assert!(moved < 2e-4, "a camera moved {:.3} mm", moved * 1e3);
    }

    /// A padded dark last row and column would be the strongest edge of
    /// every frame, fixed in the image: the grey image repeats the last
    /// line that shows the scene instead.
    #[test]
    fn dead_border_lines_make_no_edge() {
        let mut image = RgbImage::from_fn(16, 12, |x, y| image::Rgb([(10 * x + 5 * y) as u8; 3]));
        for x in 0..16 {
            image.put_pixel(x, 11, image::Rgb([0; 3]));
        }
        for y in 0..12 {
            image.put_pixel(15, y, image::Rgb([0; 3]));
        }
        let border = ColourBorder {
            bottom: 1,
            right: 1,
            ..Default::default()
        };
        let gray = Gray::from_rgb(&image, &border);
        for x in 0..15 {
            assert_eq!(gray.at(x, 11), gray.at(x, 10));
        }
        for y in 0..11 {
            assert_eq!(gray.at(15, y), gray.at(14, y));
        }
        assert_eq!(gray.at(15, 11), gray.at(14, 10));
        let untouched = Gray::from_rgb(&image, &ColourBorder::default());
        assert_eq!(untouched.at(3, 11), 0.0);
        assert_eq!(untouched.at(3, 4), gray.at(3, 4));
    }
}
