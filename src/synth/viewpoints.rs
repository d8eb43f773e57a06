//! The stream of accepted viewpoints: candidates from [`PoseSampler`],
//! probed in parallel with a low-resolution render and accepted in candidate
//! order, so the views and the rejection counts depend only on the seed.
//!
//! A probe rejects a view that looks mostly at space the scan never observed
//! (fewer than `min_observed` of its pixels with opacity > 0.5 at a surface
//! just behind space the sensor saw free) or, when there are boxes, that sees
//! no labelled object. The untrained field is a faint fog wherever the scan
//! never looked: rays into it pile up opacity > 0.5 deep inside unseen space,
//! so opacity alone would count a view full of fog as observed. It also
//! rejects a view with a surface nearer than the clearance or half the
//! distance to the nearest scanned point (the space a frame's own depth
//! vouches free): the scan has no such surface, so it is a floater left
//! where no training view constrained the field.

use super::error::{Rejections, SynthError};
use super::poses_file::ViewSpec;
use super::sampling::{Candidate, PoseSampler};
use super::triplet::Instances;
use crate::nerf::camera::LocalRay;
use crate::nerf::occupancy::OccupancyGrid;
use crate::nerf::render::rays::render_pixels;
use crate::nerf::render::view::ViewRenderer;
use crate::scan::{Intrinsics, FREE_FRACTION};
use nalgebra::{IsometryMatrix3, Point3};
use rayon::prelude::*;
use std::collections::VecDeque;
use std::sync::atomic::{AtomicBool, Ordering};

/// Width of the probe render (its height follows the view's aspect ratio).
pub const PROBE_WIDTH: u32 = 32;
/// Default fraction of probe pixels that must have opacity > 0.5.
pub const MIN_OBSERVED: f64 = 0.5;
/// Candidates allowed per requested view before giving up.
pub const ATTEMPTS_PER_VIEW: u64 = 50;
/// Fewest candidates tried before giving up, whatever the view count.
pub const MIN_ATTEMPTS: u64 = 1000;
/// Candidates evaluated per parallel round.
const CHUNK: u64 = 32;

/// Why a candidate was turned down, or its pose.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Verdict {
    Accept(IsometryMatrix3<f64>),
    TooClose,
    Unobserved,
    NoObject,
    NearSurface,
}

/// Share of probe pixels with a surface in vouched-free space that
/// rejects a view (one probe pixel of a 32-wide probe is about 0.13 %).
pub const MAX_NEAR_SURFACE: f64 = 0.01;

/// How far (in occupancy cells) a probe pixel's surface may lie behind the
/// nearest space the sensor saw free and still count as observed: carving
/// leaves a margin of a few cells uncarved in front of measured surfaces
/// (held-out scan views keep 65-98 % of their pixels at 6 cells on the
/// tabletop fixture, fog-filled views under 30 %).
pub const OBSERVED_MARGIN_CELLS: f32 = 6.0;

/// Whether the ray passes through space the sensor saw free (an unoccupied
/// cell) within `margin` before reaching `t`.
fn free_space_before(grid: &OccupancyGrid, ray: &LocalRay, t: f32, margin: f32) -> bool {
    let step = 0.25 / grid.resolution() as f32;
    let mut s = (t - margin).max(0.0);
    while s < t {
        if !grid.is_occupied(ray.at(s)) {
            return true;
        }
        s += step;
    }
    false
}

/// Probe a view: opacity and depth at [`PROBE_WIDTH`] pixels across.
pub fn probe(
    renderer: &ViewRenderer,
    spec: &ViewSpec,
    instances: &Instances,
    min_observed: f64,
    vouched_free_m: f64,
) -> Verdict {
    let pw = PROBE_WIDTH.min(spec.width).max(1);
    let ph =
        ((f64::from(spec.height) * f64::from(pw) / f64::from(spec.width)).round() as u32).clamp(1, spec.height.max(1));
    let k = spec.intrinsics.scaled((spec.width, spec.height), (pw, ph));
    let camera = renderer.local_camera(&spec.camera_to_world, &k, pw, ph);
    let pixels: Vec<(f32, f32)> = (0..ph)
        .flat_map(|v| (0..pw).map(move |u| (u as f32, v as f32)))
        .collect();
    let model = renderer.model;
    let out = render_pixels(
        &model.field,
        renderer.grid(),
        &model.render_options(false),
        &camera,
        &pixels,
    );
    // Checked first: a floater over the lens also fails the tests below.
    let metres_per_unit = 1.0 / renderer.transform.scale();
    let near = out
        .iter()
        .filter(|o| {
            o.opacity > 0.5
                && o.depth_median
                    .is_some_and(|t| f64::from(t) * metres_per_unit < vouched_free_m)
        })
        .count();
    if near as f64 > MAX_NEAR_SURFACE * pixels.len() as f64 {
        return Verdict::NearSurface;
    }
    // Observed space is what the sensor saw free: the model's own grid.
    let grid = &model.occupancy;
    // Without any carved cell (a scan without depth) opacity is all there is to go by.
    let carved = grid.carved_words().iter().any(|&w| w != 0);
    let margin = OBSERVED_MARGIN_CELLS / grid.resolution() as f32;
    let observed = out
        .iter()
        .zip(&pixels)
        .filter(|(o, &(u, v))| {
            o.opacity > 0.5
                && (!carved
                    || o.depth_median
                        .is_some_and(|t| free_space_before(grid, &camera.ray(u, v).0, t, margin)))
        })
        .count();
    if (observed as f64) < min_observed * pixels.len() as f64 {
        return Verdict::Unobserved;
    }
    if instances.max_id() > 0 {
        let depth: Vec<f32> = out
            .iter()
            .zip(&pixels)
            .map(|(o, &(u, v))| {
                o.depth_median
                    .map_or(0.0, |t| (f64::from(t / camera.ray(u, v).1) * metres_per_unit) as f32)
            })
            .collect();
        if !sees_object(&depth, &spec.camera_to_world, &k, &pixels, instances) {
            return Verdict::NoObject;
        }
    }
    Verdict::Accept(spec.camera_to_world)
}

/// Whether any probe pixel's surface lies in a box.
fn sees_object(
    depth: &[f32],
    c2w: &IsometryMatrix3<f64>,
    k: &Intrinsics,
    pixels: &[(f32, f32)],
    instances: &Instances,
) -> bool {
    depth.iter().zip(pixels).any(|(&z, &(u, v))| {
        z > 0.0
            && z.is_finite()
            && (instances.classify)(
                c2w * Point3::from(k.unproject(f64::from(u), f64::from(v)) * f64::from(z)),
                &|_| None,
            ) > 0
    })
}

/// Accepted sampled views, in order, with the rejections counted on the way.
pub struct ViewStream<'a> {
    sampler: PoseSampler<'a>,
    renderer: &'a ViewRenderer<'a>,
    instances: &'a Instances<'a>,
    intrinsics: Intrinsics,
    width: u32,
    height: u32,
    seed: u64,
    min_observed: f64,
    wanted: usize,
    max_attempts: u64,
    /// Next candidate index to evaluate.
    next: u64,
    /// Evaluated candidates not consumed yet, in index order.
    queue: VecDeque<Verdict>,
    accepted: usize,
    attempts: u64,
    rejections: Rejections,
}

impl<'a> ViewStream<'a> {
    /// A stream of `wanted` views of `width` x `height` with intrinsics `k`.
    #[allow(clippy::too_many_arguments)]
    pub fn new(
        sampler: PoseSampler<'a>,
        renderer: &'a ViewRenderer<'a>,
        instances: &'a Instances<'a>,
        intrinsics: Intrinsics,
        (width, height): (u32, u32),
        seed: u64,
        min_observed: f64,
        wanted: usize,
    ) -> ViewStream<'a> {
        let max_attempts = (wanted as u64).saturating_mul(ATTEMPTS_PER_VIEW).max(MIN_ATTEMPTS);
        ViewStream {
            sampler,
            renderer,
            instances,
            intrinsics,
            width,
            height,
            seed,
            min_observed,
            wanted,
            max_attempts,
            next: 0,
            queue: VecDeque::new(),
            accepted: 0,
            attempts: 0,
            rejections: Rejections::default(),
        }
    }

    /// Candidates consumed so far (accepted and rejected).
    pub fn attempts(&self) -> u64 {
        self.attempts
    }

    /// Rejections among the consumed candidates.
    pub fn rejections(&self) -> Rejections {
        self.rejections
    }

    /// The view of an accepted pose.
    fn spec(&self, camera_to_world: IsometryMatrix3<f64>) -> ViewSpec {
        ViewSpec {
            camera_to_world,
            intrinsics: self.intrinsics,
            width: self.width,
            height: self.height,
        }
    }

    /// Distance before a candidate camera within which no surface can be
    /// one the scan has: the clearance, or the share of the nearest scanned
    /// point that a frame's own depth vouches free ([`FREE_FRACTION`]).
    fn vouched_free_m(&self, nearest_scanned_m: f64) -> f64 {
        let vouched = f64::from(FREE_FRACTION) * nearest_scanned_m;
        self.sampler
            .clearance()
            .max(if vouched.is_finite() { vouched } else { 0.0 })
    }

    /// Evaluate the next chunk of candidates in parallel.
    fn evaluate_chunk(&mut self) {
        let first = self.next;
        let verdicts: Vec<Verdict> = (first..first + CHUNK)
            .into_par_iter()
            .map(|i| match self.sampler.candidate(self.seed, i) {
                Candidate::TooClose => Verdict::TooClose,
                Candidate::Pose {
                    camera_to_world,
                    nearest_scanned_m,
                    ..
                } => probe(
                    self.renderer,
                    &self.spec(camera_to_world),
                    self.instances,
                    self.min_observed,
                    self.vouched_free_m(nearest_scanned_m),
                ),
            })
            .collect();
        self.queue.extend(verdicts);
        self.next += CHUNK;
    }

    /// The next `count` accepted views (fewer at the end of the `wanted`);
    /// `None` when `stop` was raised.
    pub fn next_views(&mut self, count: usize, stop: &AtomicBool) -> Result<Option<Vec<ViewSpec>>, SynthError> {
        let count = count.min(self.wanted - self.accepted.min(self.wanted));
        let mut out = Vec::with_capacity(count);
        while out.len() < count {
            if self.attempts >= self.max_attempts {
                return Err(SynthError::GaveUp {
                    attempts: self.attempts,
                    accepted: self.accepted,
                    wanted: self.wanted,
                    rejections: self.rejections,
                });
            }
            let Some(verdict) = self.queue.pop_front() else {
                if stop.load(Ordering::Relaxed) {
                    return Ok(None);
                }
                self.evaluate_chunk();
                continue;
            };
            self.attempts += 1;
            match verdict {
                Verdict::Accept(pose) => {
                    out.push(self.spec(pose));
                    self.accepted += 1;
                }
                Verdict::TooClose => self.rejections.too_close += 1,
                Verdict::Unobserved => self.rejections.unobserved += 1,
                Verdict::NoObject => self.rejections.no_object += 1,
                Verdict::NearSurface => self.rejections.near_surface += 1,
            }
        }
        Ok(Some(out))
    }
}
