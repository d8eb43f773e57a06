//! Pose refinement from depth: every frame's pose is aligned, point to
//! plane, to the depth the other frames measured (their fused cloud), all
//! frames at once and a few times over, so that their errors average out
//! instead of each frame keeping its own. The refined trajectory is then
//! moved back onto the captured one as a whole (the scene does not drift:
//! boxes drawn in the captured world frame stay where they were).
//!
//! Every threshold comes from the scan: correspondences are weighted by a
//! Tukey biweight whose scale is the residuals' own median absolute value.

use super::pairwise::PairwiseOptions;
use super::GeometryError;
use crate::scan::{Frame, Scan, EDGE_RELATIVE_GAP};
use kiddo::{ImmutableKdTree, SquaredEuclidean};
use nalgebra::{
    IsometryMatrix3, Matrix3, Matrix6, Point3, Rotation3, SymmetricEigen, Translation3, UnitQuaternion, Vector3,
    Vector6,
};
use rayon::prelude::*;
use serde::{Deserialize, Serialize};
use std::num::NonZeroUsize;

/// How a refinement runs.
#[derive(Clone, Copy, Debug)]
pub struct RefineOptions {
    /// Depth points sampled per frame.
    pub points_per_frame: usize,
    /// Most rounds of (cloud, correspondences, one Gauss-Newton step per
    /// frame); fewer when a round no longer pays.
    pub rounds: usize,
    /// Neighbours from other frames that fit the plane a point is matched to.
    pub plane_neighbours: usize,
    /// Then align the frames to each other by their colour
    /// ([`super::pairwise`]), which pins what their depth leaves free.
    pub align_colour: bool,
}

impl Default for RefineOptions {
    fn default() -> Self {
        RefineOptions {
            points_per_frame: 1500,
            rounds: 6,
            plane_neighbours: 12,
            align_colour: true,
        }
    }
}

/// What refinement did to one frame.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct FrameCorrection {
    pub frame: String,
    /// Displacement of the camera centre, metres.
    pub translation_m: f64,
    /// Rotation between the captured and the refined orientation, degrees.
    pub rotation_deg: f64,
    /// Median point-to-plane distance of the frame's depth to the other
    /// frames' depth, with the captured and with the kept pose, metres;
    /// `None` where too little of its depth overlaps theirs.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub residual_before_m: Option<f64>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub residual_after_m: Option<f64>,
    /// Whether the refined pose was kept (it must fit the other frames'
    /// depth better than the captured one).
    pub refined: bool,
}

/// Refined camera-to-world poses (one per frame, in scan order) and what
/// changed.
#[derive(Clone, Debug)]
pub struct PoseRefinement {
    pub camera_to_world: Vec<IsometryMatrix3<f64>>,
    pub frames: Vec<FrameCorrection>,
    /// Whether the frames were also aligned to each other by colour.
    pub colour_aligned: bool,
}

impl PoseRefinement {
    /// Frames whose refined pose was kept.
    pub fn refined_count(&self) -> usize {
        self.frames.iter().filter(|f| f.refined).count()
    }

    /// Median over frames of the residual before and after, metres; NaN
    /// when no frame overlaps another.
    pub fn median_residuals(&self) -> (f64, f64) {
        let before = median(self.frames.iter().filter_map(|f| f.residual_before_m).collect());
        let after = median(self.frames.iter().filter_map(|f| f.residual_after_m).collect());
        (before, after)
    }

    /// Runs of consecutive frames whose depth disagrees with the others far
    /// more than is usual in this scan (over `OUTLIER_RATIO` times the median
    /// disagreement, as captured): first and last index, and the run's
    /// median disagreement in metres.
    pub fn disagreeing_runs(&self) -> Vec<(usize, usize, f64)> {
        let (typical, _) = self.median_residuals();
        let bad = |f: &FrameCorrection| f.residual_before_m.is_some_and(|r| r > OUTLIER_RATIO * typical);
        let mut runs = Vec::new();
        let mut i = 0;
        while i < self.frames.len() {
            if !bad(&self.frames[i]) {
                i += 1;
                continue;
            }
            let start = i;
            while i < self.frames.len() && bad(&self.frames[i]) {
                i += 1;
            }
            let level = median(
                self.frames[start..i]
                    .iter()
                    .filter_map(|f| f.residual_before_m)
                    .collect(),
            );
            runs.push((start, i - 1, level));
        }
        runs
    }

    /// A plain sentence on how well the captured poses agree with the depth.
    pub fn verdict(&self) -> String {
        let (before, after) = self.median_residuals();
        if !before.is_finite() {
            return "too little of the frames' depth overlaps to compare the poses with it".into();
        }
        let mm = |m: f64| format!("{:.1} mm", m * 1e3);
        let runs = self.disagreeing_runs();
        if !runs.is_empty() {
            let listed: Vec<String> = runs
                .iter()
                .take(5)
                .map(|&(a, b, level)| {
                    let names = if a == b {
                        format!("frame {} disagrees", self.frames[a].frame)
                    } else {
                        format!("frames {}-{} disagree", self.frames[a].frame, self.frames[b].frame)
                    };
                    format!("{names} with the other frames' depth by ~{}", mm(level))
                })
                .collect();
            let more = if runs.len() > 5 {
                format!(" (and {} more runs)", runs.len() - 5)
            } else {
                String::new()
            };
            return format!("{}{more}; the rest agree to {}", listed.join("; "), mm(before));
        }
        if before > 1.5 * after {
            format!(
                "poses agree with the depth to {}; aligned to it, to {} (`fit` aligns them unless --no-pose-refine)",
                mm(before),
                mm(after)
            )
        } else {
            format!(
                "poses look consistent with the depth (median disagreement {})",
                mm(before)
            )
        }
    }

    /// Largest camera displacement and rotation among kept refinements.
    pub fn largest_correction(&self) -> (f64, f64) {
        self.frames.iter().filter(|f| f.refined).fold((0.0, 0.0), |(t, r), f| {
            (f64::max(t, f.translation_m), f64::max(r, f.rotation_deg))
        })
    }
}

/// Frames with fewer usable correspondences keep their pose: a handful of
/// points cannot pin six degrees of freedom against noise.
const MIN_CORRESPONDENCES: usize = 60;
/// Tukey biweight constant (95 % efficiency for Gaussian residuals).
pub(super) const TUKEY_C: f64 = 4.685;
/// Directions of motion with less than this share of the best-constrained
/// direction's information are not moved.
const WEAK_DIRECTION: f64 = 1e-2;
/// Refinement stops at the first round that shrinks the residual scale by
/// less than this share.
const MIN_ROUND_GAIN: f64 = 0.1;
/// A frame disagreeing with the others this many times more than the
/// scan's median frame is reported as wrong.
const OUTLIER_RATIO: f64 = 4.0;
/// Poses aligned by colour are kept while the frames' depth disagrees at
/// most this many times as much as with the poses aligned to the depth.
const COLOUR_DEPTH_SLACK: f64 = 1.25;
/// Median absolute deviation to standard deviation, Gaussian residuals.
pub(super) const MAD_TO_SIGMA: f64 = 1.4826;

/// Align every frame with depth to the other frames' depth. `None` when
/// fewer than two frames have depth (nothing to align against).
pub fn refine_poses(scan: &Scan, opts: &RefineOptions) -> Result<Option<PoseRefinement>, GeometryError> {
    let samples: Vec<Vec<Point3<f64>>> = scan
        .frames
        .par_iter()
        .enumerate()
        .map(|(i, f)| camera_points(f, opts.points_per_frame, i as u64))
        .collect::<Result<_, _>>()?;
    if samples.iter().filter(|s| s.len() >= MIN_CORRESPONDENCES).count() < 2 {
        return Ok(None);
    }
    let captured = scan.poses();
    let mut poses = captured.clone();
    let mut previous_scale = f64::INFINITY;
    for _ in 0..opts.rounds {
        let cloud = Cloud::new(&samples, &poses);
        let matches = cloud.correspondences(&samples, &poses, opts.plane_neighbours);
        let scale = robust_scale(&matches);
        // Once the frames agree as well as their depth noise allows, more
        // rounds only let the trajectory wander (measured: reprojection
        // error 1.75 px -> 0.60 px after 2 rounds, back to 1.3 px after 32).
        if !(scale > 0.0) || scale > (1.0 - MIN_ROUND_GAIN) * previous_scale {
            break;
        }
        previous_scale = scale;
        let steps: Vec<Option<IsometryMatrix3<f64>>> =
            matches.par_iter().map(|m| gauss_newton_step(m, scale)).collect();
        for (pose, step) in poses.iter_mut().zip(steps) {
            if let Some(step) = step {
                *pose = step * *pose;
            }
        }
    }
    // Depth leaves frames free to slide along what they see; their colour
    // pins that slide.
    let mut colour_aligned = false;
    // Each frame's misfit with the poses kept, when already measured (a
    // rigid move of every pose, as below, leaves it unchanged).
    let mut kept_misfits = None;
    if opts.align_colour {
        if let Some(aligned) = super::pairwise::align_pairs(&scan.frames, &poses, &PairwiseOptions::default()) {
            // Colour that pulls the frames' depth apart (colour registered
            // off its depth, lighting that changes with the view) is not
            // followed: the depth must still agree nearly as well.
            let misfits =
                |p: &[IsometryMatrix3<f64>]| Cloud::new(&samples, p).misfits(&samples, p, opts.plane_neighbours);
            let overall = |m: &[Option<f64>]| median(m.iter().flatten().copied().collect());
            let (by_depth, with_colour) = (misfits(&poses), misfits(&aligned));
            if overall(&with_colour) <= COLOUR_DEPTH_SLACK * overall(&by_depth) {
                poses = aligned;
                colour_aligned = true;
                kept_misfits = Some(with_colour);
            } else {
                kept_misfits = Some(by_depth);
            }
        }
    }
    // The scene as a whole stays where the captured poses put it.
    let gauge = best_rigid_fit(&samples, &poses, &captured);
    for pose in &mut poses {
        *pose = gauge * *pose;
    }
    let mut refinement = keep_what_fits(scan, &samples, &captured, poses, kept_misfits, opts.plane_neighbours);
    refinement.colour_aligned = colour_aligned;
    Ok(Some(refinement))
}

/// Compare each frame's captured and refined pose against the refined
/// cloud; keep the refined one only where it fits better.
fn keep_what_fits(
    scan: &Scan,
    samples: &[Vec<Point3<f64>>],
    captured: &[IsometryMatrix3<f64>],
    refined: Vec<IsometryMatrix3<f64>>,
    refined_misfits: Option<Vec<Option<f64>>>,
    neighbours: usize,
) -> PoseRefinement {
    let cloud = Cloud::new(samples, &refined);
    let after = refined_misfits.unwrap_or_else(|| cloud.misfits(samples, &refined, neighbours));
    let before = cloud.correspondences(samples, captured, neighbours);
    let mut poses = Vec::with_capacity(refined.len());
    let mut frames = Vec::with_capacity(refined.len());
    for (i, frame) in scan.frames.iter().enumerate() {
        let (r_before, r_after) = (before[i].median_misfit(), after[i]);
        let refined_better = matches!((r_before, r_after), (Some(b), Some(a)) if a < b);
        let pose = if refined_better { refined[i] } else { captured[i] };
        let (translation_m, rotation_deg) = pose_difference(&captured[i], &pose);
        poses.push(pose);
        frames.push(FrameCorrection {
            frame: frame.name.clone(),
            translation_m,
            rotation_deg,
            residual_before_m: r_before,
            residual_after_m: if refined_better { r_after } else { r_before },
            refined: refined_better,
        });
    }
    PoseRefinement {
        camera_to_world: poses,
        frames,
        colour_aligned: false,
    }
}

/// Camera displacement (metres) and rotation angle (degrees) from `a` to `b`.
pub fn pose_difference(a: &IsometryMatrix3<f64>, b: &IsometryMatrix3<f64>) -> (f64, f64) {
    let translation = (b.translation.vector - a.translation.vector).norm();
    let ra = UnitQuaternion::from_rotation_matrix(&a.rotation);
    let rb = UnitQuaternion::from_rotation_matrix(&b.rotation);
    (translation, ra.angle_to(&rb).to_degrees())
}

/// Camera-frame points of a frame's depth on a regular pixel grid, skipping
/// pixels beside a depth edge (mixed foreground and background returns).
pub(super) fn camera_points(frame: &Frame, wanted: usize, phase_seed: u64) -> Result<Vec<Point3<f64>>, GeometryError> {
    let Some(depth) = &frame.depth else {
        return Ok(Vec::new());
    };
    let Some(k) = super::bounds::depth_intrinsics(frame)? else {
        return Ok(Vec::new());
    };
    let (w, h) = (depth.width, depth.height);
    let reach = stored_pixel_reach(frame, depth);
    let stride = ((f64::from(w) * f64::from(h) / wanted.max(1) as f64).sqrt().floor() as u32)
        .max(reach)
        .max(1);
    let offset = crate::rng::Rng::new(phase_seed, 0).below(u64::from(stride)) as u32;
    let mut points = Vec::new();
    let mut y = offset.min(h.saturating_sub(1));
    while y < h {
        let mut x = offset.min(w.saturating_sub(1));
        while x < w {
            let z = depth.get(x, y);
            if z > 0.0 && z.is_finite() && away_from_edges(depth, x, y, z, reach) {
                points.push(Point3::from(k.unproject(f64::from(x), f64::from(y)) * f64::from(z)));
            }
            x += stride;
        }
        y += stride;
    }
    Ok(points)
}

/// Depth stored coarser than colour is repeated on the colour grid: a
/// neighbour one stored pixel away is this many grid pixels away.
pub(crate) fn stored_pixel_reach(frame: &Frame, depth: &crate::scan::DepthMap) -> u32 {
    let stored = frame.depth_size.unwrap_or((depth.width, depth.height));
    (f64::from(depth.width) / f64::from(stored.0.max(1))).ceil().max(1.0) as u32
}

/// Whether the four neighbours `reach` pixels from (x, y), of depth `z`,
/// were measured on the same surface (none missing, none across an edge).
pub(crate) fn away_from_edges(depth: &crate::scan::DepthMap, x: u32, y: u32, z: f32, reach: u32) -> bool {
    let neighbours = [
        (x.checked_sub(reach), Some(y)),
        (x.checked_add(reach), Some(y)),
        (Some(x), y.checked_sub(reach)),
        (Some(x), y.checked_add(reach)),
    ];
    neighbours.iter().all(|&(nx, ny)| match (nx, ny) {
        (Some(nx), Some(ny)) => {
            let n = depth.get(nx, ny);
            n > 0.0 && (n - z).abs() <= EDGE_RELATIVE_GAP * n.min(z)
        }
        _ => false,
    })
}

/// `p - origin` in f32: coordinates the search tree can hold without
/// losing what separates nearby points far from the world origin.
fn offset_f32(p: &[f64; 3], origin: &Point3<f64>) -> [f32; 3] {
    [0, 1, 2].map(|a| (p[a] - origin[a]) as f32)
}

/// All frames' depth points in the world, with the frame each came from.
/// The search tree holds them in f32 about their mean (neighbours picked
/// as in f64 at any distance from the world origin, and quicker to query);
/// planes are fitted to the f64 points.
pub(super) struct Cloud {
    tree: ImmutableKdTree<f32, 3>,
    origin: Point3<f64>,
    points: Vec<[f64; 3]>,
    frame_of: Vec<u32>,
}

/// One frame's matches: its world point (before the step), the plane it is
/// matched to and the signed distance to it.
struct FrameMatches {
    centre: Point3<f64>,
    points: Vec<Point3<f64>>,
    normals: Vec<Vector3<f64>>,
    residuals: Vec<f64>,
}

impl FrameMatches {
    /// Median point-to-plane distance of the frame's matched points;
    /// `None` with too few matches to tell.
    fn median_misfit(&self) -> Option<f64> {
        (self.residuals.len() >= MIN_CORRESPONDENCES).then(|| median(self.residuals.iter().map(|r| r.abs()).collect()))
    }
}

impl Cloud {
    pub(super) fn new(samples: &[Vec<Point3<f64>>], poses: &[IsometryMatrix3<f64>]) -> Cloud {
        let mut points = Vec::new();
        let mut frame_of = Vec::new();
        for (i, (s, pose)) in samples.iter().zip(poses).enumerate() {
            for p in s {
                points.push((pose * p).into());
                frame_of.push(i as u32);
            }
        }
        let sum = points
            .iter()
            .fold(Vector3::<f64>::zeros(), |acc, p: &[f64; 3]| acc + Vector3::from(*p));
        let origin = Point3::from(sum / points.len().max(1) as f64);
        let local: Vec<[f32; 3]> = points.iter().map(|p| offset_f32(p, &origin)).collect();
        let tree = ImmutableKdTree::new_from_slice(&local).unwrap_or_default();
        Cloud {
            tree,
            origin,
            points,
            frame_of,
        }
    }

    /// Query point in the tree's frame.
    fn local(&self, x: &Point3<f64>) -> [f32; 3] {
        offset_f32(&x.coords.into(), &self.origin)
    }

    /// Each frame's median point-to-plane misfit against the other frames
    /// (see [`FrameMatches::median_misfit`]).
    fn misfits(
        &self,
        samples: &[Vec<Point3<f64>>],
        poses: &[IsometryMatrix3<f64>],
        neighbours: usize,
    ) -> Vec<Option<f64>> {
        let matches = self.correspondences(samples, poses, neighbours);
        matches.iter().map(FrameMatches::median_misfit).collect()
    }

    /// Each frame's points matched to planes fitted to the nearest points of
    /// other frames.
    fn correspondences(
        &self,
        samples: &[Vec<Point3<f64>>],
        poses: &[IsometryMatrix3<f64>],
        neighbours: usize,
    ) -> Vec<FrameMatches> {
        samples
            .par_iter()
            .zip(poses)
            .enumerate()
            .map(|(i, (s, pose))| {
                let mut m = FrameMatches {
                    centre: Point3::origin(),
                    points: Vec::new(),
                    normals: Vec::new(),
                    residuals: Vec::new(),
                };
                let world: Vec<Point3<f64>> = s.iter().map(|p| pose * p).collect();
                m.centre =
                    Point3::from(world.iter().map(|x| x.coords).sum::<Vector3<f64>>() / world.len().max(1) as f64);
                for x in world {
                    if let Some((centroid, normal)) = self.plane_near(&x, i as u32, neighbours) {
                        m.residuals.push(normal.dot(&(x - centroid)));
                        m.points.push(x);
                        m.normals.push(normal);
                    }
                }
                m
            })
            .collect()
    }

    /// Distance from `x` to the nearest point another frame measured.
    pub(super) fn nearest_other(&self, x: &Point3<f64>, own_frame: u32) -> Option<f64> {
        let wanted = NonZeroUsize::new(8)?;
        let found = self
            .tree
            .query(&self.local(x))
            .nearest_n::<SquaredEuclidean<f32>>(wanted)
            .execute();
        found
            .iter()
            .find(|r| self.frame_of.get(r.item as usize).is_some_and(|&f| f != own_frame))
            .and_then(|r| self.points.get(r.item as usize))
            .map(|p| (Point3::from(*p) - x).norm())
    }

    /// Plane (centroid, unit normal) through the `neighbours` points nearest
    /// to `x` that other frames measured; `None` where they do not form one.
    pub(super) fn plane_near(
        &self,
        x: &Point3<f64>,
        own_frame: u32,
        neighbours: usize,
    ) -> Option<(Point3<f64>, Vector3<f64>)> {
        // Own points are a sampling stride apart, other frames' much denser:
        // a few extra candidates make up for the own ones dropped.
        let wanted = NonZeroUsize::new(neighbours + neighbours / 2)?;
        let found = self
            .tree
            .query(&self.local(x))
            .nearest_n::<SquaredEuclidean<f32>>(wanted)
            .execute();
        let near: Vec<Point3<f64>> = found
            .iter()
            .map(|r| r.item as usize)
            .filter(|&j| self.frame_of.get(j).is_some_and(|&f| f != own_frame))
            .filter_map(|j| self.points.get(j).map(|p| Point3::from(*p)))
            .take(neighbours)
            .collect();
        if near.len() < neighbours.div_ceil(2).max(3) {
            return None;
        }
        let centroid = Point3::from(near.iter().map(|p| p.coords).sum::<Vector3<f64>>() / near.len() as f64);
        let mut cov = Matrix3::<f64>::zeros();
        for p in &near {
            let d = p - centroid;
            cov += d * d.transpose();
        }
        let eig = SymmetricEigen::new(cov);
        let mut order = [0usize, 1, 2];
        order.sort_by(|&a, &b| eig.eigenvalues[a].total_cmp(&eig.eigenvalues[b]));
        let (smallest, middle) = (eig.eigenvalues[order[0]], eig.eigenvalues[order[1]]);
        // A line of points (an edge, a thin rod) has no plane to slide on.
        if !(middle > 0.0) || smallest > 0.25 * middle {
            return None;
        }
        let n = eig.eigenvectors.column(order[0]).into_owned();
        // Times the reciprocal length, as glam's normalize_or_zero did (same bits).
        let rcp = 1.0 / n.norm();
        (rcp.is_finite() && rcp > 0.0).then(|| (centroid, n * rcp))
    }
}

/// Robust residual scale over all frames: the median absolute residual as
/// a Gaussian sigma.
fn robust_scale(matches: &[FrameMatches]) -> f64 {
    let all: Vec<f64> = matches
        .iter()
        .flat_map(|m| m.residuals.iter().map(|r| r.abs()))
        .collect();
    MAD_TO_SIGMA * median(all)
}

/// One Tukey-weighted Gauss-Newton step of a frame's rigid motion (world
/// frame, rotation about the frame's own centroid); `None` when too few
/// points constrain it. Directions the frame's geometry barely constrains
/// (sliding along a wall it alone sees) are left alone rather than moved by
/// noise.
fn gauss_newton_step(m: &FrameMatches, scale: f64) -> Option<IsometryMatrix3<f64>> {
    let cutoff = TUKEY_C * scale;
    // Rotations are measured as the motion they cause at the frame's typical
    // point distance, so that all six directions are in metres.
    let lever_length =
        (m.points.iter().map(|x| (x - m.centre).norm_squared()).sum::<f64>() / m.points.len().max(1) as f64).sqrt();
    if !(lever_length > 0.0) {
        return None;
    }
    let mut hessian = Matrix6::<f64>::zeros();
    let mut gradient = Vector6::<f64>::zeros();
    let mut used = 0usize;
    for ((x, n), &r) in m.points.iter().zip(&m.normals).zip(&m.residuals) {
        if r.abs() >= cutoff {
            continue;
        }
        let u = 1.0 - (r / cutoff).powi(2);
        let weight = u * u;
        let lever = (x - m.centre).cross(n) / lever_length;
        let j = Vector6::new(lever.x, lever.y, lever.z, n.x, n.y, n.z);
        hessian += weight * j * j.transpose();
        gradient += weight * r * j;
        used += 1;
    }
    if used < MIN_CORRESPONDENCES {
        return None;
    }
    let delta = gauss_newton_solve(&hessian, &gradient, WEAK_DIRECTION)?;
    let omega = Vector3::new(delta[0], delta[1], delta[2]) / lever_length;
    let translation = Vector3::new(delta[3], delta[4], delta[5]);
    // x -> R (x - c) + c + t
    let rotation = IsometryMatrix3::from_parts(Translation3::identity(), Rotation3::new(omega));
    Some(Translation3::from(m.centre.coords + translation) * rotation * Translation3::from(-m.centre.coords))
}

/// The Gauss-Newton step `-H^-1 g` solved in `hessian`'s eigenbasis, leaving
/// out directions with less than `weak` times the information of the best
/// constrained one (they are not moved); `None` when nothing is constrained
/// or the step is not finite.
pub fn gauss_newton_solve(hessian: &Matrix6<f64>, gradient: &Vector6<f64>, weak: f64) -> Option<Vector6<f64>> {
    let eig = SymmetricEigen::new(*hessian);
    let strongest = eig.eigenvalues.max();
    if !(strongest > 0.0) {
        return None;
    }
    let mut delta = Vector6::<f64>::zeros();
    for k in 0..6 {
        let information = eig.eigenvalues[k];
        if information > weak * strongest {
            let v = eig.eigenvectors.column(k);
            delta -= v * (v.dot(gradient) / information);
        }
    }
    delta.iter().all(|v| v.is_finite()).then_some(delta)
}

/// The rigid motion that best carries every frame's points as `moved` puts
/// them onto where `reference` puts them.
fn best_rigid_fit(
    samples: &[Vec<Point3<f64>>],
    moved: &[IsometryMatrix3<f64>],
    reference: &[IsometryMatrix3<f64>],
) -> IsometryMatrix3<f64> {
    let mut from = Vec::new();
    let mut to = Vec::new();
    for ((s, a), b) in samples.iter().zip(moved).zip(reference) {
        for p in s {
            from.push(a * p);
            to.push(b * p);
        }
    }
    rigid_fit(&from, &to)
}

/// The rigid motion that best carries trajectory `moved` onto `reference`:
/// each camera's centre and points `reach` ahead of it along its axes.
pub fn trajectory_alignment(
    moved: &[IsometryMatrix3<f64>],
    reference: &[IsometryMatrix3<f64>],
    reach: f64,
) -> IsometryMatrix3<f64> {
    let probes = [
        Point3::origin(),
        Point3::new(reach, 0.0, 0.0),
        Point3::new(0.0, reach, 0.0),
        Point3::new(0.0, 0.0, reach),
    ];
    let from: Vec<Point3<f64>> = moved.iter().flat_map(|m| probes.map(|p| m * p)).collect();
    let to: Vec<Point3<f64>> = reference.iter().flat_map(|m| probes.map(|p| m * p)).collect();
    rigid_fit(&from, &to)
}

/// Least-squares rigid motion from `from` onto `to` (Kabsch, by SVD).
fn rigid_fit(from: &[Point3<f64>], to: &[Point3<f64>]) -> IsometryMatrix3<f64> {
    if from.len() < 3 || from.len() != to.len() {
        return IsometryMatrix3::identity();
    }
    let n = from.len() as f64;
    let (ca, cb) = (
        from.iter().map(|p| p.coords).sum::<Vector3<f64>>() / n,
        to.iter().map(|p| p.coords).sum::<Vector3<f64>>() / n,
    );
    let mut cov = Matrix3::<f64>::zeros();
    for (a, b) in from.iter().zip(to) {
        let (a, b) = (a.coords - ca, b.coords - cb);
        cov += b * a.transpose();
    }
    let svd = cov.svd(true, true);
    let (Some(u), Some(v_t)) = (svd.u, svd.v_t) else {
        return IsometryMatrix3::identity();
    };
    let mut fix = Matrix3::<f64>::identity();
    if (u * v_t).determinant() < 0.0 {
        fix[(2, 2)] = -1.0;
    }
    let rotation = Rotation3::from_matrix_unchecked(u * fix * v_t);
    let out = IsometryMatrix3::from_parts(Translation3::from(cb - rotation * ca), rotation);
    if out.to_homogeneous().iter().all(|x| x.is_finite()) {
        out
    } else {
        IsometryMatrix3::identity()
    }
}

/// Median of the finite values; NaN when there are none.
pub fn median(mut v: Vec<f64>) -> f64 {
    v.retain(|x| x.is_finite());
    if v.is_empty() {
        return f64::NAN;
    }
    let mid = v.len() / 2;
    *v.select_nth_unstable_by(mid, f64::total_cmp).1
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::poses::test_scene;

    /// The scan with every camera turned about its centre by about 0.3 deg
    /// and moved by about 4 mm (fixed random draws).
    fn perturbed(truth: &Scan) -> Scan {
        let mut scan = truth.clone();
        let mut rng = crate::rng::Rng::new(7, 0);
        for f in &mut scan.frames {
            let axis = Vector3::new(rng.normal(), rng.normal(), rng.normal()).normalize();
            let angle = 0.3f64.to_radians() * rng.normal();
            let shift = Vector3::new(rng.normal(), rng.normal(), rng.normal()) * 0.004;
            let centre = f.camera_center().coords;
            let perturb = Translation3::from(centre + shift)
                * IsometryMatrix3::from_parts(Translation3::identity(), Rotation3::new(axis * angle))
                * Translation3::from(-centre);
            f.camera_to_world = perturb * f.camera_to_world;
        }
        scan
    }

    /// A room of six planes constrains each frame only partly (a frame that
    /// sees one wall and the floor may slide along both): refinement makes
    /// the frames agree without moving them along what they cannot see.
    /// (`tests/pose_refine.rs` checks recovery on a scene with objects.)
    #[test]
    fn refinement_does_not_slide_frames_along_planes() {
        let truth = test_scene::Room {
            frames: 24,
            ..Default::default()
        }
        .scan();
        let scan = perturbed(&truth);
        let error = |poses: &[IsometryMatrix3<f64>]| {
            let (mut t, mut r) = (0.0, 0.0);
            for (p, f) in poses.iter().zip(&truth.frames) {
                let (dt, dr) = pose_difference(&f.camera_to_world, p);
                t += dt * dt;
                r += dr * dr;
            }
            ((t / poses.len() as f64).sqrt(), (r / poses.len() as f64).sqrt())
        };
        let perturbed = scan.poses();
        let (t0, r0) = error(&perturbed);
        let refined = refine_poses(&scan, &RefineOptions::default())
            .unwrap()
            .expect("the scan has depth");
        let (t1, r1) = error(&refined.camera_to_world);
        assert!(
            t1 < 1.15 * t0,
            "camera RMS error {:.2} mm -> {:.2} mm",
            t0 * 1e3,
            t1 * 1e3
        );
        assert!(r1 < r0, "rotation RMS error {r0:.3} deg -> {r1:.3} deg");
        assert!(
            refined.refined_count() >= scan.frames.len() * 3 / 4,
            "{} frames refined",
            refined.refined_count()
        );
        let (before, after) = refined.median_residuals();
        assert!(
            after < 0.2 * before,
            "median residual {:.2} mm -> {:.2} mm",
            before * 1e3,
            after * 1e3
        );
    }

    #[test]
    fn a_scene_far_from_the_origin_refines_as_one_near_it() {
        // World coordinates like a surveyed site's (hundreds of km): the
        // search tree must not round the points to its float's spacing there.
        let near = perturbed(
            &test_scene::Room {
                frames: 24,
                ..Default::default()
            }
            .scan(),
        );
        let mut far = near.clone();
        let offset = Translation3::new(412_345.0, 5_321_987.0, 250.0);
        for f in &mut far.frames {
            f.camera_to_world = offset * f.camera_to_world;
        }
        let options = RefineOptions {
            align_colour: false,
            ..RefineOptions::default()
        };
        let refine = |scan: &Scan| refine_poses(scan, &options).unwrap().expect("the scan has depth");
        let (near_refined, far_refined) = (refine(&near), refine(&far));
        assert!(
            near_refined.largest_correction().0 > 1e-3,
            "the test needs poses that move: {:?}",
            near_refined.largest_correction()
        );
        for (a, b) in near_refined.frames.iter().zip(&far_refined.frames) {
            assert_eq!(a.refined, b.refined, "frame {}", a.frame);
            assert!(
                (a.translation_m - b.translation_m).abs() < 1e-5,
                "frame {}: corrected by {:.4} mm near the origin, {:.4} mm far from it",
                a.frame,
                a.translation_m * 1e3,
                b.translation_m * 1e3
            );
        }
    }

    /// Exact poses stay (nearly) exact: refinement must not invent motion.
    #[test]
    fn exact_poses_stay_put() {
        let scan = test_scene::Room {
            frames: 16,
            ..Default::default()
        }
        .scan();
        let refined = refine_poses(&scan, &RefineOptions::default())
            .unwrap()
            .expect("the scan has depth");
        let (t, r) = refined.largest_correction();
        assert!(t < 2e-4 && r < 0.02, "largest correction {:.3} mm, {r:.4} deg", t * 1e3);
    }

    #[test]
    fn scans_without_depth_are_left_alone() {
        let mut scan = test_scene::Room {
            frames: 6,
            ..Default::default()
        }
        .scan();
        for f in &mut scan.frames {
            f.depth = None;
        }
        assert!(refine_poses(&scan, &RefineOptions::default()).unwrap().is_none());
    }
}
