//! Pose refinement against the field being fitted: part-way through a fit
//! (once, or a few times while the poses still move), each frame's colour
//! image is aligned to what the field renders from the frame's pose (direct
//! image alignment). The field is the consensus of all frames, so a frame
//! whose pose disagrees with it is pulled back in line; training then goes
//! on with the corrected poses.
//!
//! One frame: the field's colour and depth at a few thousand pixels where
//! the frame's image has texture give points on the surface; a 6-dof
//! correction of the camera moves their projections until the frame's own
//! image (blurred coarse to fine, so that a few pixels of error are within
//! reach) shows the colours the field gave them. Where the frame has sensor
//! depth, the same points must also lie on the surface it measured (point
//! to plane, as depth-camera ICP): colour alone barely tells how far along
//! the view a camera is, and a field trained on imperfect poses can paint
//! its colours a little off its surface. Gauss-Newton with Huber losses whose
//! scales are each term's own residual spread. A correction is kept only
//! when it lowers that cost, stays within the reach of the coarsest blur
//! and moves the camera no further than the scan's poses can be off; the
//! corrected trajectory is then moved back onto the one before as
//! a whole, so the scene does not drift.

use crate::nerf::appearance::{as_photographed, off_axis_r2, Affine, Vignetting};
use crate::nerf::field::Field;
use crate::nerf::occupancy::OccupancyGrid;
use crate::nerf::render::rays::{render_pixels, RenderOptions};
use crate::nerf::train::dataset::local_camera;
use crate::poses::{gauss_newton_solve, median, pose_difference, trajectory_alignment, SceneTransform};
use crate::scan::Frame;
use nalgebra::{IsometryMatrix3, Matrix6, Point3, Rotation3, Translation3, Vector3, Vector6};
use rayon::prelude::*;
use serde::{Deserialize, Serialize};

/// How an alignment runs.
#[derive(Clone, Debug)]
pub struct PhotometricOptions {
    /// Surface points rendered per frame (a regular grid of pixels).
    pub points_per_frame: usize,
    /// Blur of the frame's image at each level, pixels, coarse to fine.
    pub sigmas: Vec<f32>,
    /// Gauss-Newton iterations per level.
    pub iterations: usize,
    /// Largest camera displacement a kept correction may make, metres (a
    /// correction far beyond the scan's pose error is a field not yet
    /// sharp enough to align to, not a pose error).
    pub max_translation_m: f64,
}

impl Default for PhotometricOptions {
    fn default() -> Self {
        PhotometricOptions {
            points_per_frame: 500,
            sigmas: vec![8.0, 4.0, 2.0, 1.0],
            iterations: 8,
            max_translation_m: f64::INFINITY,
        }
    }
}

/// Rendered pixels whose opacity is below this are not on a surface.
const MIN_OPACITY: f32 = 0.95;
/// Fewest surface points a frame needs to be aligned.
const MIN_POINTS: usize = 200;
/// Huber threshold in robust standard deviations of the residuals.
const HUBER_K: f64 = 1.345;
/// The field must explain the image: its colours' residual spread below
/// this fraction of the image's own colour spread at the same points.
const MAX_UNEXPLAINED: f64 = 0.5;
/// A correction may leave the sensor depth at most this much further (median)
/// from the field's surface than before.
const MAX_DEPTH_MISFIT_GROWTH: f64 = 1.25;
/// A direction of the correction constrained less than this fraction of
/// the best-constrained one is left alone (a frame of a flat wall cannot
/// tell sliding along it).
const WEAK_DIRECTION: f64 = 1e-6;

/// What the alignment did to one frame.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct PhotometricCorrection {
    pub frame: String,
    /// Displacement of the camera centre, metres.
    pub translation_m: f64,
    /// Rotation of the camera, degrees.
    pub rotation_deg: f64,
    /// Median displacement of the frame's surface points in its image by
    /// the correction found (kept or not), pixels.
    pub shift_px: f64,
    /// Robust colour cost (mean Huber loss, 0-1 colour scale) before and
    /// after, at the finest level; absent when the frame had too few
    /// surface points to be aligned.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub cost_before: Option<f64>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub cost_after: Option<f64>,
    /// Whether the correction was kept.
    pub refined: bool,
}

/// New camera-to-world poses (all frames, scan order) and what changed (the
/// aligned frames).
#[derive(Clone, Debug)]
pub struct PhotometricAlignment {
    pub camera_to_world: Vec<IsometryMatrix3<f64>>,
    pub frames: Vec<PhotometricCorrection>,
}

/// Align the frames `selected` (indices into `frames`, each with its
/// appearance map in `maps`, all through the camera's `lens`) to the field,
/// from their current poses; the other frames keep theirs.
#[allow(clippy::too_many_arguments)]
pub fn align_to_field(
    field: &Field,
    grid: &OccupancyGrid,
    render: &RenderOptions,
    transform: &SceneTransform,
    frames: &[Frame],
    maps: &[Affine],
    lens: &Vignetting,
    selected: &[usize],
    opts: &PhotometricOptions,
) -> PhotometricAlignment {
    let render = RenderOptions { color: true, ..*render };
    let before: Vec<IsometryMatrix3<f64>> = frames.iter().map(|f| f.camera_to_world).collect();
    let outcomes: Vec<(Option<FrameOutcome>, f64)> = selected
        .par_iter()
        .map_init(Workspace::default, |ws, &i| {
            let (frame, map) = (&frames[i], &maps[i]);
            let (points, depth) = surface_points(field, grid, &render, transform, frame, (map, lens), opts);
            (align_frame(frame, &points, opts, ws), depth)
        })
        .collect();
    let mut poses = before.clone();
    let mut corrections = Vec::with_capacity(frames.len());
    for (&i, (outcome, _)) in selected.iter().zip(&outcomes) {
        let refined = outcome.as_ref().is_some_and(|a| a.kept);
        if let Some(a) = outcome.as_ref().filter(|a| a.kept) {
            poses[i] = before[i] * a.correction;
        }
        corrections.push(PhotometricCorrection {
            frame: frames[i].name.clone(),
            translation_m: 0.0,
            rotation_deg: 0.0,
            shift_px: outcome.as_ref().map_or(0.0, |a| a.shift_px),
            cost_before: outcome.as_ref().map(|a| a.cost_before),
            cost_after: outcome.as_ref().map(|a| a.cost_after),
            refined,
        });
    }
    // The scene stays where it was: the corrected trajectory as a whole goes
    // back onto the one before (camera centres and points a scene's depth
    // ahead of them).
    let kept: Vec<usize> = selected
        .iter()
        .zip(&corrections)
        .filter(|(_, c)| c.refined)
        .map(|(&i, _)| i)
        .collect();
    if kept.len() >= 3 {
        let reach = median(outcomes.iter().map(|o| o.1).collect()).max(1e-6);
        let moved: Vec<_> = kept.iter().map(|&i| poses[i]).collect();
        let reference: Vec<_> = kept.iter().map(|&i| before[i]).collect();
        let gauge = trajectory_alignment(&moved, &reference, reach);
        for &i in &kept {
            poses[i] = gauge * poses[i];
        }
    }
    for (c, &i) in corrections.iter_mut().zip(selected) {
        (c.translation_m, c.rotation_deg) = pose_difference(&before[i], &poses[i]);
    }
    PhotometricAlignment {
        camera_to_world: poses,
        frames: corrections,
    }
}

/// Buffers reused from frame to frame.
#[derive(Default)]
struct Workspace {
    /// The frame's image, one plane per channel, 0-1.
    planes: [Vec<f32>; 3],
    /// The planes shrunk for a wide blur.
    small: [Vec<f32>; 3],
    blurred: [Vec<f32>; 3],
    scratch: Vec<f32>,
    /// One edge-padded row of the blur.
    padded: Vec<f32>,
    kernel: Vec<f32>,
}

/// A point on the surface the field renders, in the frame's camera
/// coordinates (metres), and its colour through the lens and the frame's
/// appearance.
struct SurfacePoint {
    camera: Point3<f64>,
    colour: [f32; 3],
}

/// The field's surface on a regular grid of the frame's pixels, and the
/// points' median depth (metres; NaN without any). A regular grid, not the
/// most textured pixels: those sit on edges, where the sharp rendered colour
/// and the blurred image disagree most and the rendered depth is least sure.
fn surface_points(
    field: &Field,
    grid: &OccupancyGrid,
    render: &RenderOptions,
    transform: &SceneTransform,
    frame: &Frame,
    (map, lens): (&Affine, &Vignetting),
    opts: &PhotometricOptions,
) -> (Vec<SurfacePoint>, f64) {
    let (w, h) = frame.size();
    let pixels = grid_pixels(w, h, opts.points_per_frame, border(opts));
    let camera = local_camera(frame, transform);
    let out = render_pixels(field, grid, render, &camera, &pixels);
    let metres_per_unit = 1.0 / transform.scale();
    let k = &frame.intrinsics;
    let mut points = Vec::with_capacity(pixels.len());
    let mut depths = Vec::with_capacity(pixels.len());
    for (&(u, v), r) in pixels.iter().zip(&out) {
        let Some(t) = r.depth_median else { continue };
        if r.opacity < MIN_OPACITY {
            continue;
        }
        let (_, norm) = camera.ray(u, v);
        let z = f64::from(t) * metres_per_unit / f64::from(norm);
        if !(z.is_finite() && z > 0.0) {
            continue;
        }
        let (x, y) = ((f64::from(u) - k.cx) / k.fx * z, (f64::from(v) - k.cy) / k.fy * z);
        let colour = as_photographed(map, lens, off_axis_r2(norm), r.rgb).map(|c| c.clamp(0.0, 1.0));
        points.push(SurfacePoint {
            camera: Point3::new(x, y, z),
            colour,
        });
        depths.push(z);
    }
    (points, median(depths))
}

/// Pixels kept clear of the border so the coarsest blur's gradients are whole.
fn border(opts: &PhotometricOptions) -> u32 {
    let sigma = opts.sigmas.iter().copied().fold(1.0f32, f32::max);
    (2.0 * sigma).ceil() as u32 + 2
}

fn load_planes(frame: &Frame, ws: &mut Workspace) {
    let n = frame.rgb.as_raw().len() / 3;
    for (c, plane) in ws.planes.iter_mut().enumerate() {
        plane.clear();
        plane.extend(
            frame.rgb.as_raw()[c..]
                .iter()
                .step_by(3)
                .take(n)
                .map(|&v| f32::from(v) / 255.0),
        );
    }
}

/// About `wanted` pixel centres on a square grid, `border` pixels clear of the edges.
fn grid_pixels(w: u32, h: u32, wanted: usize, border: u32) -> Vec<(f32, f32)> {
    if w <= 2 * border || h <= 2 * border {
        return Vec::new();
    }
    let (iw, ih) = (w - 2 * border, h - 2 * border);
    let step = ((f64::from(iw) * f64::from(ih) / wanted.max(1) as f64).sqrt().floor() as u32).max(1);
    let mut out = Vec::new();
    for y in (border + step / 2..h - border).step_by(step as usize) {
        for x in (border + step / 2..w - border).step_by(step as usize) {
            out.push((x as f32, y as f32));
        }
    }
    out
}

struct FrameOutcome {
    /// Camera-to-camera correction: the new pose is the old one times this.
    correction: IsometryMatrix3<f64>,
    kept: bool,
    shift_px: f64,
    cost_before: f64,
    cost_after: f64,
}

/// Align one frame's image to its surface points (see the module's text).
fn align_frame(
    frame: &Frame,
    points: &[SurfacePoint],
    opts: &PhotometricOptions,
    ws: &mut Workspace,
) -> Option<FrameOutcome> {
    if points.len() < MIN_POINTS || opts.sigmas.is_empty() {
        return None;
    }
    let (w, h) = frame.size();
    let k = frame.intrinsics;
    load_planes(frame, ws);
    let mut correction = IsometryMatrix3::<f64>::identity();
    let mut finest = None;
    let focal = 0.5 * (k.fx + k.fy);
    let depth = median(points.iter().map(|p| p.camera.z).collect());
    let sensor = SensorDepth::new(frame);
    for &sigma in &opts.sigmas {
        let (bw, bh, factor) = blur_planes(ws, w as usize, h as usize, sigma);
        let image = Image {
            planes: &ws.blurred,
            w: bw,
            h: bh,
            factor,
        };
        // The Huber scales of this level: the residuals' spread where it starts.
        let scale = robust_scale(&image, points, &k, &correction)?;
        let depth_term = sensor
            .as_ref()
            .and_then(|s| DepthTerm::new(s, points, &correction, depth));
        let joint = |candidate: &IsometryMatrix3<f64>| {
            let colour = cost(&image, points, &k, candidate, scale) / (scale * scale);
            colour + depth_term.as_ref().map_or(0.0, |d| d.cost(points, candidate))
        };
        let mut current = joint(&correction);
        for _ in 0..opts.iterations {
            let Some(step) = gauss_newton_step(&image, points, &k, &correction, scale, depth_term.as_ref()) else {
                break;
            };
            // Halve a step that does not lower the cost.
            let mut trial = step;
            let mut improved = false;
            for _ in 0..4 {
                let candidate = correction * exp(&trial);
                let c = joint(&candidate);
                if c < current {
                    (correction, current) = (candidate, c);
                    improved = true;
                    break;
                }
                trial *= 0.5;
            }
            // Converged when a step moves the points by a hundredth of a pixel.
            let moved_px = focal * (trial.fixed_rows::<3>(3).norm() + trial.fixed_rows::<3>(0).norm() / depth);
            if !improved || moved_px < 0.01 {
                break;
            }
        }
        finest = Some((scale, (bw, bh, factor)));
    }
    let (scale, (bw, bh, factor)) = finest?;
    let image = Image {
        planes: &ws.blurred,
        w: bw,
        h: bh,
        factor,
    };
    let cost_before = cost(&image, points, &k, &IsometryMatrix3::identity(), scale);
    // A field that does not yet explain the image has nothing to align to.
    let explained = scale < MAX_UNEXPLAINED * colour_spread(&image, points, &k)?;
    let cost_after = cost(&image, points, &k, &correction, scale);
    let shift_px = median(
        points
            .iter()
            .filter_map(|p| {
                let a = project(&k, &p.camera)?;
                let b = project(&k, &correction.inverse_transform_point(&p.camera))?;
                Some(((a.0 - b.0).powi(2) + (a.1 - b.1).powi(2)).sqrt())
            })
            .collect(),
    );
    // Beyond the coarsest blur the image held no information on where to go.
    let reach = 2.0 * f64::from(opts.sigmas[0]);
    // Colour must not pull the frame off its own depth: with the correction,
    // the sensor's depth must fit the field's surface about as well as before.
    let depth_ok = match depth_misfit(frame, points, &k, &correction) {
        Some((before, after)) => after <= MAX_DEPTH_MISFIT_GROWTH * before,
        None => true,
    };
    let plausible = correction.translation.vector.norm() <= opts.max_translation_m;
    let kept =
        explained && depth_ok && plausible && cost_after < cost_before && shift_px.is_finite() && shift_px <= reach;
    Some(FrameOutcome {
        correction,
        kept,
        shift_px,
        cost_before,
        cost_after,
    })
}

/// Median distance along the view between the field's surface points and
/// the frame's sensor depth at the pixel they project to, without and with
/// `correction`; `None` where too few points meet measured depth.
fn depth_misfit(
    frame: &Frame,
    points: &[SurfacePoint],
    k: &crate::scan::Intrinsics,
    correction: &IsometryMatrix3<f64>,
) -> Option<(f64, f64)> {
    let depth = frame.depth.as_ref()?;
    let misfit = |pose: &IsometryMatrix3<f64>| -> Vec<f64> {
        points
            .iter()
            .filter_map(|p| {
                let q = pose.inverse_transform_point(&p.camera);
                let (u, v) = project(k, &q)?;
                let (u, v) = (u.round(), v.round());
                if !(u >= 0.0 && v >= 0.0 && u < f64::from(depth.width) && v < f64::from(depth.height)) {
                    return None;
                }
                let z = f64::from(depth.get(u as u32, v as u32));
                (z > 0.0 && z.is_finite()).then(|| (z - q.z).abs())
            })
            .collect()
    };
    let (before, after) = (misfit(&IsometryMatrix3::identity()), misfit(correction));
    (before.len() >= MIN_POINTS / 4 && after.len() >= MIN_POINTS / 4).then(|| (median(before), median(after)))
}

/// A blurred image to sample (bilinear) with its gradient, stored
/// `factor` times smaller than the frame.
struct Image<'a> {
    planes: &'a [Vec<f32>; 3],
    w: usize,
    h: usize,
    factor: usize,
}

impl Image<'_> {
    /// Colour at continuous pixel (x, y) of the frame and its x and y
    /// derivatives; `None` outside the image.
    fn sample(&self, x: f64, y: f64) -> Option<[[f64; 3]; 3]> {
        let f = self.factor as f64;
        let (x, y) = ((x + 0.5) / f - 0.5, (y + 0.5) / f - 0.5);
        if !(x >= 1.0 && y >= 1.0 && x < (self.w - 2) as f64 && y < (self.h - 2) as f64) {
            return None;
        }
        let (x0, y0) = (x.floor() as usize, y.floor() as usize);
        let (fx, fy) = (x - x0 as f64, y - y0 as f64);
        let mut out = [[0.0; 3]; 3];
        for (c, plane) in self.planes.iter().enumerate() {
            let at = |xx: usize, yy: usize| f64::from(plane[yy * self.w + xx]);
            let (a, b, cc, d) = (at(x0, y0), at(x0 + 1, y0), at(x0, y0 + 1), at(x0 + 1, y0 + 1));
            out[0][c] = (a * (1.0 - fx) + b * fx) * (1.0 - fy) + (cc * (1.0 - fx) + d * fx) * fy;
            out[1][c] = ((b - a) * (1.0 - fy) + (d - cc) * fy) / f;
            out[2][c] = ((cc - a) * (1.0 - fx) + (d - b) * fx) / f;
        }
        Some(out)
    }
}

fn project(k: &crate::scan::Intrinsics, p: &Point3<f64>) -> Option<(f64, f64)> {
    (p.z > 1e-9).then(|| (k.fx * p.x / p.z + k.cx, k.fy * p.y / p.z + k.cy))
}

/// Colour residuals of every point seen through `correction`, passed to `each`
/// with the point in the corrected camera and the image sample.
fn for_each_residual(
    image: &Image,
    points: &[SurfacePoint],
    k: &crate::scan::Intrinsics,
    correction: &IsometryMatrix3<f64>,
    mut each: impl FnMut(&Point3<f64>, &[[f64; 3]; 3], [f64; 3]),
) {
    for p in points {
        let q = correction.inverse_transform_point(&p.camera);
        let Some((u, v)) = project(k, &q) else { continue };
        let Some(s) = image.sample(u, v) else { continue };
        let r = std::array::from_fn(|c| s[0][c] - f64::from(p.colour[c]));
        each(&q, &s, r);
    }
}

/// Robust standard deviation of the colour residuals (1.4826 x median
/// absolute value); `None` when too few points are in view.
fn robust_scale(
    image: &Image,
    points: &[SurfacePoint],
    k: &crate::scan::Intrinsics,
    correction: &IsometryMatrix3<f64>,
) -> Option<f64> {
    let mut abs = Vec::with_capacity(3 * points.len());
    for_each_residual(image, points, k, correction, |_, _, r| abs.extend(r.map(f64::abs)));
    if abs.len() < 3 * MIN_POINTS {
        return None;
    }
    // Floor: an 8-bit colour step, so a perfect match does not divide by zero.
    Some((1.4826 * median(abs)).max(1.0 / 255.0))
}

/// Robust spread of the image's colours at the points (1.4826 x median
/// absolute deviation from each channel's median).
fn colour_spread(image: &Image, points: &[SurfacePoint], k: &crate::scan::Intrinsics) -> Option<f64> {
    let mut channels: [Vec<f64>; 3] = Default::default();
    for_each_residual(image, points, k, &IsometryMatrix3::identity(), |_, s, _| {
        for (c, values) in channels.iter_mut().enumerate() {
            values.push(s[0][c]);
        }
    });
    let mut deviations = Vec::new();
    for values in &channels {
        let centre = median(values.clone());
        deviations.extend(values.iter().map(|v| (v - centre).abs()));
    }
    (deviations.len() >= 3 * MIN_POINTS).then(|| 1.4826 * median(deviations))
}

/// Mean Huber loss of the residuals; points out of view count as outliers
/// (so a correction cannot lower the cost by looking away).
fn cost(
    image: &Image,
    points: &[SurfacePoint],
    k: &crate::scan::Intrinsics,
    correction: &IsometryMatrix3<f64>,
    scale: f64,
) -> f64 {
    let threshold = HUBER_K * scale;
    let outlier = huber(3.0 * threshold, threshold);
    let mut total = 0.0;
    let mut seen = 0usize;
    for_each_residual(image, points, k, correction, |_, _, r| {
        total += r.iter().map(|&x| huber(x, threshold)).sum::<f64>();
        seen += 1;
    });
    total += 3.0 * outlier * (points.len() - seen) as f64;
    total / (3 * points.len()).max(1) as f64
}

fn huber(r: f64, threshold: f64) -> f64 {
    let a = r.abs();
    if a <= threshold {
        0.5 * a * a
    } else {
        threshold * (a - 0.5 * threshold)
    }
}

/// One Gauss-Newton step of the correction's increment (translation, then
/// rotation, in the camera frame).
fn gauss_newton_step(
    image: &Image,
    points: &[SurfacePoint],
    k: &crate::scan::Intrinsics,
    correction: &IsometryMatrix3<f64>,
    scale: f64,
    depth_term: Option<&DepthTerm>,
) -> Option<Vector6<f64>> {
    let threshold = HUBER_K * scale;
    let mut hessian = Matrix6::<f64>::zeros();
    let mut gradient = Vector6::<f64>::zeros();
    // Both terms in units of their own robust spread.
    let colour_weight = 1.0 / (scale * scale);
    for_each_residual(image, points, k, correction, |q, s, r| {
        let (x, y, z) = (q.x, q.y, q.z);
        let iz = 1.0 / z;
        // d(u, v)/dq
        let du = [k.fx * iz, 0.0, -k.fx * x * iz * iz];
        let dv = [0.0, k.fy * iz, -k.fy * y * iz * iz];
        for c in 0..3 {
            let g = [s[1][c], s[2][c]];
            let dq = Vector3::new(
                g[0] * du[0] + g[1] * dv[0],
                g[0] * du[1] + g[1] * dv[1],
                g[0] * du[2] + g[1] * dv[2],
            );
            let j = increment_jacobian(q, &dq);
            let weight = colour_weight * huber_weight(r[c], threshold);
            hessian += j * j.transpose() * weight;
            gradient += j * (weight * r[c]);
        }
    });
    if let Some(d) = depth_term {
        d.accumulate(points, correction, &mut hessian, &mut gradient);
    }
    // Directions the image cannot tell are left alone.
    gauss_newton_solve(&hessian, &gradient, WEAK_DIRECTION)
}

/// Derivative with respect to the increment (translation, then rotation)
/// of a residual whose derivative with respect to the point q (corrected
/// camera frame) is `dq`: q' = q - v - w x q = q - v + q x w.
fn increment_jacobian(q: &Point3<f64>, dq: &Vector3<f64>) -> Vector6<f64> {
    let rotation = dq.cross(&q.coords);
    Vector6::new(-dq.x, -dq.y, -dq.z, rotation.x, rotation.y, rotation.z)
}

/// Iteratively reweighted least squares weight of the Huber loss.
fn huber_weight(r: f64, threshold: f64) -> f64 {
    if r.abs() <= threshold {
        1.0
    } else {
        threshold / r.abs()
    }
}

/// The frame's sensor depth, looked up where a surface point projects
/// (projective association, as depth-camera ICP does): the measured point
/// and the normal of the measured surface there, in the camera frame.
struct SensorDepth<'a> {
    depth: &'a crate::scan::DepthMap,
    k: crate::scan::Intrinsics,
    /// Pixels between neighbours the normal is taken from: one stored
    /// pixel of depth stored coarser than the colour.
    reach: u32,
}

impl<'a> SensorDepth<'a> {
    fn new(frame: &'a Frame) -> Option<SensorDepth<'a>> {
        let depth = frame.depth.as_ref()?;
        let k = crate::poses::depth_intrinsics(frame).ok()??;
        let reach = crate::poses::stored_pixel_reach(frame, depth);
        Some(SensorDepth { depth, k, reach })
    }

    /// Measured point and unit normal (facing the camera) at the pixel
    /// nearest to where `q` projects; `None` off the depth, in a hole or
    /// beside a depth edge (mixed returns, no one surface).
    fn surface_at(&self, q: &Point3<f64>) -> Option<(Point3<f64>, Vector3<f64>)> {
        let (u, v) = project(&self.k, q)?;
        let (u, v) = (u.round(), v.round());
        let r = f64::from(self.reach);
        let (w, h) = (f64::from(self.depth.width), f64::from(self.depth.height));
        if !(u >= r && v >= r && u + r < w && v + r < h) {
            return None;
        }
        let centre = self.depth.get(u as u32, v as u32);
        let measured = centre > 0.0 && centre.is_finite();
        if !(measured && crate::poses::away_from_edges(self.depth, u as u32, v as u32, centre, self.reach)) {
            return None;
        }
        let at = |du: f64, dv: f64| {
            let z = f64::from(self.depth.get((u + du) as u32, (v + dv) as u32));
            Point3::from(self.k.unproject(u + du, v + dv) * z)
        };
        let point = at(0.0, 0.0);
        let across = at(r, 0.0) - at(-r, 0.0);
        let down = at(0.0, r) - at(0.0, -r);
        let normal = across.cross(&down).try_normalize(1e-12)?;
        Some((
            point,
            if normal.dot(&point.coords) > 0.0 {
                -normal
            } else {
                normal
            },
        ))
    }
}

/// The depth term of an alignment: the field's surface points, moved by
/// the correction, against the sensor's surface where they project
/// (point to plane), with a Huber scale from their spread at the start of
/// a level.
struct DepthTerm<'a> {
    sensor: &'a SensorDepth<'a>,
    scale: f64,
}

impl<'a> DepthTerm<'a> {
    /// `None` when too few points meet measured depth.
    fn new(
        sensor: &'a SensorDepth<'a>,
        points: &[SurfacePoint],
        correction: &IsometryMatrix3<f64>,
        median_depth: f64,
    ) -> Option<DepthTerm<'a>> {
        let mut abs = Vec::with_capacity(points.len());
        sensor.for_each_residual(points, correction, |_, _, r| abs.push(r.abs()));
        if abs.len() < MIN_POINTS {
            return None;
        }
        // Floor: a tenth of a millimetre at a metre, so a perfect match
        // does not divide by zero.
        let scale = (1.4826 * median(abs)).max(1e-4 * median_depth);
        Some(DepthTerm { sensor, scale })
    }

    /// Huber cost in units of the scale, summed and divided by the colour
    /// residuals' count (as the colour cost is), so that a point weighs
    /// the same in both terms.
    fn cost(&self, points: &[SurfacePoint], correction: &IsometryMatrix3<f64>) -> f64 {
        let (threshold, mut total, mut seen) = (HUBER_K * self.scale, 0.0, 0usize);
        self.sensor.for_each_residual(points, correction, |_, _, r| {
            total += huber(r, threshold);
            seen += 1;
        });
        // Points that lose their measured depth count at the mean, so that a
        // correction cannot lower the cost by looking into a hole.
        let mean = if seen > 0 { total / seen as f64 } else { 0.0 };
        mean * points.len() as f64 / (3 * points.len()).max(1) as f64 / (self.scale * self.scale)
    }

    fn accumulate(
        &self,
        points: &[SurfacePoint],
        correction: &IsometryMatrix3<f64>,
        hessian: &mut Matrix6<f64>,
        gradient: &mut Vector6<f64>,
    ) {
        let threshold = HUBER_K * self.scale;
        let unit = 1.0 / (self.scale * self.scale);
        self.sensor.for_each_residual(points, correction, |q, normal, r| {
            let j = increment_jacobian(q, normal);
            let weight = unit * huber_weight(r, threshold);
            *hessian += j * j.transpose() * weight;
            *gradient += j * (weight * r);
        });
    }
}

impl SensorDepth<'_> {
    /// Point-to-plane residual of every point that meets measured depth
    /// through `correction`, passed to `each` with the point in the
    /// corrected camera and the measured normal.
    fn for_each_residual(
        &self,
        points: &[SurfacePoint],
        correction: &IsometryMatrix3<f64>,
        mut each: impl FnMut(&Point3<f64>, &Vector3<f64>, f64),
    ) {
        for p in points {
            let q = correction.inverse_transform_point(&p.camera);
            if let Some((measured, normal)) = self.surface_at(&q) {
                each(&q, &normal, normal.dot(&(q - measured)));
            }
        }
    }
}

/// The camera-to-camera motion of an increment: points q become
/// `exp(step)^-1 q`, so the correction composes on the right.
fn exp(step: &Vector6<f64>) -> IsometryMatrix3<f64> {
    let translation = Vector3::new(step[0], step[1], step[2]);
    let rotation = Rotation3::new(Vector3::new(step[3], step[4], step[5]));
    IsometryMatrix3::from_parts(Translation3::from(translation), rotation)
}

/// The planes blurred by `sigma` (frame pixels) into `ws.blurred`, at the
/// resolution the blur allows: a wide blur works on an image shrunk by a
/// power of two (box averages), at most half the blur. Returns the blurred
/// image's size and how many times smaller it is.
fn blur_planes(ws: &mut Workspace, w: usize, h: usize, sigma: f32) -> (usize, usize, usize) {
    let mut factor = 1;
    while 2.0 * (2 * factor) as f32 <= sigma && w / (2 * factor) >= 16 && h / (2 * factor) >= 16 {
        factor *= 2;
    }
    let (sw, sh) = (w / factor, h / factor);
    for c in 0..3 {
        let small = &mut ws.small[c];
        small.clear();
        small.resize(sw * sh, 0.0);
        let plane = &ws.planes[c];
        for y in 0..sh * factor {
            let row = &plane[y * w..y * w + sw * factor];
            for (x, block) in row.chunks_exact(factor).enumerate() {
                small[(y / factor) * sw + x] += block.iter().sum::<f32>();
            }
        }
        let area = (factor * factor) as f32;
        small.iter_mut().for_each(|v| *v /= area);
    }
    gaussian(ws, sw, sh, sigma / factor as f32);
    (sw, sh, factor)
}

/// Separable Gaussian blur of `ws.small` into `ws.blurred` (the border
/// repeats the edge pixel).
fn gaussian(ws: &mut Workspace, w: usize, h: usize, sigma: f32) {
    let radius = ((3.0 * sigma).ceil().max(1.0) as usize).min(w.min(h) / 2);
    ws.kernel.clear();
    ws.kernel
        .extend((0..=2 * radius).map(|i| (-((i as f32 - radius as f32).powi(2)) / (2.0 * sigma * sigma)).exp()));
    let total: f32 = ws.kernel.iter().sum();
    ws.kernel.iter_mut().for_each(|v| *v /= total);
    let padded = &mut ws.padded;
    padded.clear();
    padded.resize(w + 2 * radius, 0.0);
    for c in 0..3 {
        ws.scratch.clear();
        ws.scratch.resize(w * h, 0.0);
        // Rows: each through an edge-padded copy, tap by tap (vectorises over x).
        for (src, dst) in ws.small[c].chunks_exact(w).zip(ws.scratch.chunks_exact_mut(w)) {
            padded[..radius].fill(src[0]);
            padded[radius..radius + w].copy_from_slice(src);
            padded[radius + w..].fill(src[w - 1]);
            for (i, &kv) in ws.kernel.iter().enumerate() {
                for (d, s) in dst.iter_mut().zip(&padded[i..i + w]) {
                    *d += kv * s;
                }
            }
        }
        // Columns: each output row is a weighted sum of nearby rows.
        let dst = &mut ws.blurred[c];
        dst.clear();
        dst.resize(w * h, 0.0);
        for (y, out) in dst.chunks_exact_mut(w).enumerate() {
            for (i, &kv) in ws.kernel.iter().enumerate() {
                let yy = (y + i).saturating_sub(radius).min(h - 1);
                for (d, s) in out.iter_mut().zip(&ws.scratch[yy * w..(yy + 1) * w]) {
                    *d += kv * s;
                }
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::scan::Intrinsics;
    use image::RgbImage;

    /// Colour of the textured plane z = 1 (camera frame of the true pose)
    /// at (x, y): smooth blobs of several sizes, like a real surface.
    fn texture(x: f64, y: f64) -> [f32; 3] {
        let wave = |a: f64, b: f64, f: f64| 0.5 + 0.25 * (f * x + a).sin() * (f * 1.3 * y + b).cos();
        [
            (wave(0.0, 1.0, 9.0) + 0.2 * wave(2.0, 0.3, 31.0) - 0.1) as f32,
            (wave(1.5, 0.2, 13.0) + 0.2 * wave(0.7, 1.9, 27.0) - 0.1) as f32,
            (wave(0.4, 2.2, 7.0) + 0.2 * wave(1.1, 0.5, 23.0) - 0.1) as f32,
        ]
    }

    fn intrinsics() -> Intrinsics {
        Intrinsics {
            fx: 300.0,
            fy: 300.0,
            cx: 159.5,
            cy: 119.5,
        }
    }

    /// The frame the true camera (identity) sees of the plane.
    fn frame() -> Frame {
        let k = intrinsics();
        let image = RgbImage::from_fn(320, 240, |u, v| {
            let (x, y) = ((f64::from(u) - k.cx) / k.fx, (f64::from(v) - k.cy) / k.fy);
            image::Rgb(texture(x, y).map(|c| (c.clamp(0.0, 1.0) * 255.0).round() as u8))
        });
        Frame::new(0, "000000", image, None, IsometryMatrix3::identity(), k)
    }

    /// Surface points as a field would render them from `believed` (a
    /// camera-to-camera offset of the true pose), in that camera's frame.
    fn points_seen_from(believed: &IsometryMatrix3<f64>) -> Vec<SurfacePoint> {
        let k = intrinsics();
        let mut out = Vec::new();
        for v in (12..228).step_by(5) {
            for u in (12..308).step_by(5) {
                // The ray through (u, v) of the believed camera meets z = 1 (true frame).
                let dir =
                    believed.rotation * Vector3::new((f64::from(u) - k.cx) / k.fx, (f64::from(v) - k.cy) / k.fy, 1.0);
                let origin = believed.translation.vector;
                let t = (1.0 - origin.z) / dir.z;
                let hit = origin + dir * t;
                out.push(SurfacePoint {
                    camera: believed.inverse_transform_point(&Point3::from(hit)),
                    colour: texture(hit.x, hit.y),
                });
            }
        }
        out
    }

    fn align(frame: &Frame, points: &[SurfacePoint]) -> Option<FrameOutcome> {
        align_frame(frame, points, &PhotometricOptions::default(), &mut Workspace::default())
    }

    #[test]
    fn a_known_pose_error_is_undone() {
        let frame = frame();
        // 6 mm and 0.4 degrees at 1 m: several pixels of error.
        let error = IsometryMatrix3::from_parts(
            Translation3::new(0.004, -0.003, 0.003),
            Rotation3::new(Vector3::new(0.004, -0.005, 0.003)),
        );
        let points = points_seen_from(&error);
        let outcome = align(&frame, &points).unwrap();
        assert!(outcome.kept, "cost {} -> {}", outcome.cost_before, outcome.cost_after);
        assert!(
            outcome.shift_px > 2.0,
            "the error was several pixels: {}",
            outcome.shift_px
        );
        // The corrected pose is the true one (identity) up to a fraction of a pixel.
        let corrected = error * outcome.correction;
        let (t, r) = pose_difference(&IsometryMatrix3::identity(), &corrected);
        assert!(t < 0.0005 && r < 0.03, "left {:.2} mm, {:.3} deg", t * 1e3, r);
        // The same correction is refused where the scan's poses are known
        // to be off by far less than it moves the camera.
        let strict = PhotometricOptions {
            max_translation_m: 0.5 * outcome.correction.translation.vector.norm(),
            ..PhotometricOptions::default()
        };
        let refused = align_frame(&frame, &points, &strict, &mut Workspace::default()).unwrap();
        assert!(!refused.kept);
        assert!(refused.cost_after < refused.cost_before);
    }

    #[test]
    fn an_exact_pose_stays_and_a_flat_image_is_left_alone() {
        let frame = frame();
        let points = points_seen_from(&IsometryMatrix3::identity());
        let outcome = align(&frame, &points).unwrap();
        let (t, r) = pose_difference(&IsometryMatrix3::identity(), &outcome.correction);
        assert!(t < 0.0003 && r < 0.02, "moved {:.2} mm, {:.3} deg", t * 1e3, r);
        // Without texture nothing constrains the pose: no correction is kept.
        let mut flat = frame.clone();
        flat.rgb = RgbImage::from_pixel(320, 240, image::Rgb([128, 128, 128]));
        let grey: Vec<SurfacePoint> = points
            .iter()
            .map(|p| SurfacePoint {
                camera: p.camera,
                colour: [128.0 / 255.0; 3],
            })
            .collect();
        let outcome = align_frame(&flat, &grey, &PhotometricOptions::default(), &mut Workspace::default());
        assert!(outcome.is_none_or(|o| !o.kept || o.shift_px < 1e-6));
    }

    /// Depth of the plane through (0, 0, 1) with normal `n` (camera frame)
    /// at every pixel of the test camera.
    fn plane_depth(n: Vector3<f64>) -> crate::scan::DepthMap {
        let k = intrinsics();
        let metres = (0..240u32)
            .flat_map(|v| (0..320u32).map(move |u| (u, v)))
            .map(|(u, v)| {
                let ray = k.unproject(f64::from(u), f64::from(v));
                (n.z / n.dot(&ray)) as f32
            })
            .collect();
        crate::scan::DepthMap {
            width: 320,
            height: 240,
            metres,
        }
    }

    #[test]
    fn sensor_depth_gives_the_measured_point_and_its_normal() {
        let normal = Vector3::new(0.3, -0.2, -1.0).normalize();
        let mut frame = frame();
        let mut depth = plane_depth(normal);
        // A hole, and a step of 10 cm (an object's edge) from column 250 on.
        depth.metres[100 * 320 + 100] = 0.0;
        for v in 0..240 {
            for u in 250..320 {
                depth.metres[v * 320 + u] -= 0.1;
            }
        }
        frame.depth = Some(depth);
        let sensor = SensorDepth::new(&frame).unwrap();
        let (point, n) = sensor.surface_at(&Point3::new(-0.1, 0.05, 2.0)).unwrap();
        // The pixel the query projects to, on the plane, facing the camera.
        let (u, v) = project(&intrinsics(), &point).unwrap();
        assert!((u - 144.5).abs() < 0.51 && (v - 127.0).abs() < 0.51, "({u}, {v})");
        assert!((point.coords.dot(&normal) - normal.z).abs() < 1e-5);
        assert!((n - normal).norm() < 1e-4, "{n}");
        // No surface at or beside the hole, across the step or off the image.
        let at = |u: f64, v: f64| sensor.surface_at(&Point3::from(intrinsics().unproject(u, v)));
        assert!(at(100.0, 100.0).is_none() && at(101.0, 100.0).is_none());
        assert!(at(250.0, 120.0).is_none() && at(249.0, 120.0).is_none());
        assert!(at(251.0, 120.0).is_some() && at(248.0, 120.0).is_some());
        assert!(at(-5.0, 120.0).is_none() && at(319.0, 120.0).is_none());
    }

    #[test]
    fn depth_pins_the_distance_the_colours_barely_tell() {
        // 12 mm along the view at 1 m moves the image by at most 2 px (a
        // zoom); the field's colours carry noise, as a field trained on
        // slightly wrong poses does.
        let error = IsometryMatrix3::from_parts(
            Translation3::new(0.001, 0.0, 0.012),
            Rotation3::new(Vector3::new(0.002, 0.0, -0.001)),
        );
        let mut rng = crate::rng::Rng::new(7, 0);
        let points: Vec<SurfacePoint> = points_seen_from(&error)
            .into_iter()
            .map(|p| SurfacePoint {
                colour: p.colour.map(|c| c + 0.05 * rng.normal() as f32),
                ..p
            })
            .collect();
        let mut frame = frame();
        frame.depth = Some(plane_depth(Vector3::new(0.0, 0.0, -1.0)));
        let outcome = align(&frame, &points).unwrap();
        assert!(outcome.kept, "cost {} -> {}", outcome.cost_before, outcome.cost_after);
        let corrected = error * outcome.correction;
        let left = corrected.translation.vector;
        assert!(left.z.abs() < 0.0003, "left {:.2} mm along the view", left.z * 1e3);
        let (t, r) = pose_difference(&IsometryMatrix3::identity(), &corrected);
        assert!(t < 0.001 && r < 0.05, "left {:.2} mm, {:.3} deg", t * 1e3, r);
    }

    #[test]
    fn blur_keeps_a_constant_and_the_mean() {
        let mut ws = Workspace::default();
        let (w, h) = (37, 23);
        ws.planes = [
            vec![0.25; w * h],
            (0..w * h).map(|i| (i % 7) as f32).collect(),
            vec![0.0; w * h],
        ];
        ws.planes[2][11 * w + 18] = 1.0;
        assert_eq!(blur_planes(&mut ws, w, h, 2.0), (w, h, 1));
        assert!(ws.blurred[0].iter().all(|&v| (v - 0.25).abs() < 1e-6));
        // An impulse far from the border keeps its mass.
        let mass: f32 = ws.blurred[2].iter().sum();
        assert!((mass - 1.0).abs() < 1e-4, "{mass}");
        assert!(ws.blurred[2][11 * w + 18] > ws.blurred[2][11 * w + 20]);
        // A wide blur works on a smaller image and keeps the constant.
        let (w, h) = (96, 64);
        ws.planes = [vec![0.25; w * h], vec![0.5; w * h], vec![0.75; w * h]];
        assert_eq!(blur_planes(&mut ws, w, h, 8.0), (24, 16, 4));
        assert!(ws.blurred[1].iter().all(|&v| (v - 0.5).abs() < 1e-6));
    }
}
