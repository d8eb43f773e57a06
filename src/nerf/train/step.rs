//! One training step: draw a fixed number of samples worth of rays, render
//! them, apply the photometric + depth losses, backpropagate through
//! compositing and the field, and update with Adam, guarded against NaN and
//! divergence. Chunks map to threads deterministically for a given seed and
//! thread count.

use crate::nerf::appearance::{apply, apply_backward, off_axis_r2, vignetting_backward, vignetting_gain};
use crate::nerf::environment::{Environment, ENVIRONMENT_PARAMS};
use crate::nerf::field::hash_grid::GridGrad;
use crate::nerf::field::sh::{self, SH_COEFFS};
use crate::nerf::field::{Field, FieldGrad, FieldSeconds, FieldWorkspace};
use crate::nerf::occupancy::measured::MeasuredSurfaces;
use crate::nerf::occupancy::OccupancyGrid;
use crate::nerf::render::composite::{optical_depth_backward, weights_from_optical_depth};
use crate::nerf::render::march::{march, march_until, ray_interval, Segment, StepRule, ThinSteps};
use crate::nerf::render::rays::RenderOptions;
use crate::nerf::train::adam::Adam;
use crate::nerf::train::appearance::AppearanceLearner;
use crate::nerf::train::dataset::View;
use crate::nerf::train::detail::DetailSampler;
use crate::nerf::train::environment::{self, EnvironmentLearner};
use crate::nerf::train::pose_learning::{self, PoseGradient, PoseLearner};
use crate::nerf::train::settings::TrainConfig;
use crate::rng::Rng;
use crate::scan::DepthNoise;
use nalgebra::Matrix3;
use rayon::prelude::*;
use serde::{Deserialize, Serialize};
use std::time::Instant;

/// Share of the training rays drawn where the image has detail (see
/// [`crate::nerf::train::detail`]) once [`DETAIL_FROM`] of the training is
/// done; the rest, and every ray before, are uniform over the image. Each
/// ray's losses are weighted back to uniform sampling (see
/// [`RayRecord::importance`]): drawn without the weights, smooth surfaces
/// got too few rays on the real cabinet scan (held-out SSIM 0.81 -> 0.71).
/// `fit --steps 620` (deterministic), held-out PSNR against exact truth,
/// realistic tabletop seeds 2 / 3: uniform 27.73 / 27.72 dB; this 27.90 /
/// 27.93 dB; half the rays from the start 28.02 / 28.18 dB, from 0.3 of
/// the steps 28.03 / 27.99 dB, half by the end in a linear ramp 27.81 /
/// 27.94 dB.
const DETAIL_SHARE: f32 = 0.75;
/// Rays are drawn by detail only in the second half, as the learning rate
/// decays: while the coarse geometry forms, the weighted losses' extra
/// noise costs more than the detail gains. The small scene of
/// `tests/robustness_inputs.rs` (150 steps) placed its surfaces 5.6 % of
/// its size off with half the rays drawn by detail from the start, 4.9 %
/// from 0.3 of the steps, 1.7 % with this (uniform: 1.8-1.9 %).
const DETAIL_FROM: f32 = 0.5;

/// Share of a step's rays drawn by detail at `progress` (share of the training time).
fn detail_share(progress: f32) -> f32 {
    if progress >= DETAIL_FROM {
        DETAIL_SHARE
    } else {
        0.0
    }
}

/// Half-width of a ray's surface window in deviations of the sensor's noise
/// at its measured depth (never below the scene's window). Narrower than
/// the scatter, the line-of-sight term erodes a surface from the rays that
/// measured it too far and pushes it back. `fit --steps 620`, realistic
/// tabletop seed 2 (noise 1.5 mm z^2: 24 mm at 4 m against a 15 mm
/// window), held-out against exact truth: scene's window only 27.73 dB,
/// 12.3 mm; 1 deviation 28.22 dB, 9.0 mm; 2 deviations 28.34 dB, 9.7 mm;
/// 3 deviations 28.39 dB, 11.3 mm.
const NOISE_WINDOW_SIGMAS: f32 = 2.0;

/// Loss gradients are scaled by this (Adam is scale invariant; it keeps
/// magnitudes moderate).
const GRAD_SCALE: f32 = 1.0 / 1024.0;
/// Estimated optical depth after which a training ray without measured
/// depth stops (transmittance e^-20: several surface cells deep).
const ABSORBED_OPTICAL_DEPTH: f32 = 20.0;
/// Step of the samples in front of the surface window, in minimum steps.
const SPARSE_STEP_FACTOR: f32 = 8.0;
/// Step of rays without measured depth, in minimum steps: they carry only
/// colour, and at the base step they would cost most of a batch's samples.
const COLOUR_ONLY_STEP_FACTOR: f32 = 4.0;
/// Through space the grid estimates thin, those rays take 4 times longer
/// steps still (at most 2 grid cells), while such a step gathers under 0.1
/// optical depth (about 10 % of the light; the sum over it is off by a
/// fraction of that). Most of their samples crossed faint haze over the
/// scene (what lies past the walls, or the sky); now each step trains on
/// more rays. Realistic tabletop, seeds 2 / 3, `fit --time 60`: held-out
/// 27.25 / 27.55 dB and depth 11.8 / 10.7 mm against exact truth, 26.97 /
/// 26.97 dB and 16.0 / 16.0 mm before. Rays the sensor missed something on
/// (no return) keep the shorter step: with it too, seed 2's object without
/// depth was labelled worse (fused 0.952 against 0.971). Without the cap,
/// the coarse grid of the fast preset let steps cross a tenth of the scene
/// and a small scan's depth error grew sixfold (tests/robustness_inputs.rs).
const COLOUR_ONLY_THIN_STEPS: ThinSteps = ThinSteps {
    factor: 4.0,
    max_optical_depth: 0.1,
    max_cells: 2.0,
};
/// Depth coverage of the training pixels below which rays without depth are
/// the scan's main signal: they then march at the base step with the full
/// sample cap (coarse, capped rays would stop short of the scene when
/// nothing is carved).
const COLOUR_ONLY_COARSE_MIN_COVERAGE: f32 = 0.5;
/// Samples of whole rays processed together by the field.
const SUB_BATCH: usize = 4096;
/// Largest step of an MLP, as RMS over its parameters relative to their RMS
/// when training started, before the step counts as divergent. Adam moves
/// every weight by about the learning rate whatever the gradient's size, so
/// a learning rate far too high shows here at once even while the loss
/// looks flat; a normal fit stays several times below (docs/robustness.md).
const MAX_RELATIVE_UPDATE: f32 = 0.1;
/// L2 pull of the MLP weights towards zero.
const MLP_WEIGHT_DECAY: f32 = 1e-6;
/// Grid parameters per part of the parallel Adam update (16 summary words).
const ADAM_PART_PARAMS: usize = 16 * GridGrad::BLOCK;
/// L2 prior on the hash-grid entries touched in a step, relative to the RMS
/// of their gradients (Adam ignores the gradient's scale, so the prior
/// follows it): the pull on a value of 1 is this fraction of a typical
/// gradient. Entries whose gradient is vanishingly small but of constant
/// sign (coarse cells over free space, behind saturated activations) would
/// otherwise move by the learning rate at every step for ever (Adam eps is
/// 1e-15); the prior holds them near `gradient / decay` instead.
const GRID_PRIOR: f32 = 1e-3;
/// Learning-rate decay knots over the budget: full rate for the first half,
/// a third until three quarters, a tenth to the end (Instant-NGP-style
/// step decay: late steps refine rather than move).
const LR_DECAY: [(f32, f32); 2] = [(0.5, 0.33), (0.75, 0.1)];
/// The divergence guard watches only after this many steps (early losses
/// swing widely while the field is still empty).
const DIVERGENCE_GRACE_STEPS: u64 = 50;
/// A step whose loss exceeds this multiple of the running average (plus
/// [`DIVERGENCE_FLOOR`]) is taken as diverging and skipped.
const DIVERGENCE_RATIO: f64 = 20.0;
/// Absolute slack of the divergence test, for losses near zero.
const DIVERGENCE_FLOOR: f64 = 1e-3;
/// Weight of the newest loss in the running loss average (about a
/// 20-step memory).
const LOSS_EMA_WEIGHT: f64 = 0.05;
/// A skipped batch halves the step size, never below this fraction.
const MIN_LR_SCALE: f32 = 1e-4;
/// RNG streams: step s, chunk c draws from `1 + s * STEP_STREAMS + c`
/// (up to this many chunks per step); occupancy refreshes count down from
/// `u64::MAX`, the rendering grid uses `u64::MAX / 2`, so none overlap.
const STEP_STREAMS: u64 = 1024;
const RENDERING_GRID_STREAM: u64 = u64::MAX / 2;
/// The first occupancy refresh after warm-up visits every cell: this many
/// passes of the random subset a later refresh covers.
const FIRST_REFRESH_PASSES: usize = 8;
/// Samples that take part in the cameras' gradient: those carrying at least
/// this share of their ray's light (the others move the losses too little
/// to steer a camera, and skipping them keeps the pass cheap).
const POSE_SAMPLE_MIN_WEIGHT: f32 = 1e-3;

/// What one step did.
#[derive(Clone, Copy, Debug, Default)]
pub struct StepStats {
    pub loss: f64,
    pub loss_rgb: f64,
    /// Depth, line-of-sight, no-return and distortion terms: the geometry's.
    pub loss_depth: f64,
    pub rays: usize,
    pub samples: usize,
    pub rays_without_depth: usize,
    pub samples_without_depth: usize,
    /// The step's largest MLP update relative to the weights' starting scale
    /// (see [`MAX_RELATIVE_UPDATE`]); computed before deciding to skip.
    pub relative_update: f32,
    /// Learning rate of the step (schedule and back-off applied).
    pub learning_rate: f32,
    pub skipped: bool,
    /// Where the step's time went.
    pub phases: PhaseSeconds,
}

/// Time of a step by phase, in thread-seconds: summed over the worker
/// threads for the first four, the update's wall time times the threads.
#[derive(Clone, Copy, Debug, Default)]
pub struct PhaseSeconds {
    /// Drawing rays and marching them through the occupancy grid.
    pub march: f64,
    /// Hash-grid encoding and its backward.
    pub grid: f64,
    /// Both MLPs forward and backward (with activations and direction encoding).
    pub mlp: f64,
    /// Sample positions, compositing, losses and their gradients.
    pub composite: f64,
    /// Merging the threads' gradients and the Adam updates (on one thread
    /// while the others wait, so wall seconds times the threads).
    pub update: f64,
}

impl PhaseSeconds {
    pub fn add(&mut self, other: &PhaseSeconds) {
        self.march += other.march;
        self.grid += other.grid;
        self.mlp += other.mlp;
        self.composite += other.composite;
        self.update += other.update;
    }

    pub fn total(&self) -> f64 {
        self.march + self.grid + self.mlp + self.composite + self.update
    }
}

/// Counters kept over a whole fit.
#[derive(Clone, Copy, Debug, Default, Serialize, Deserialize)]
pub struct TrainCounters {
    pub steps: u64,
    pub skipped_batches: u64,
    pub samples: u64,
    pub rays: u64,
    pub occupancy_refreshes: u64,
    /// Rays (and their samples) without measured depth: colour only.
    #[serde(default)]
    pub rays_without_depth: u64,
    #[serde(default)]
    pub samples_without_depth: u64,
}

struct RayRecord {
    first: usize,
    count: usize,
    target: [f32; 3],
    /// Measured depth as distance along the ray (local units).
    depth_t: Option<f32>,
    t_end: f32,
    /// The sensor returned nothing here (see [`View::no_return`]).
    no_return: bool,
    /// Marching stopped where the grid says the ray is absorbed: the light
    /// left over is the surface's, not the environment's.
    absorbed: bool,
    /// Index of the ray's training view.
    view: usize,
    /// Squared tangent of the ray's angle off the optical axis (the lens's
    /// vignetting depends on it).
    lens_r2: f32,
    /// Half-width of the ray's surface window (local units, along the ray).
    window: f32,
    /// Weight of the ray's colour and depth losses: how often uniform
    /// sampling draws its pixel relative to the detail-weighted draw, so
    /// that the losses' expectation is the uniform one (1 without a sampler).
    importance: f32,
}

#[derive(Default)]
struct ChunkStats {
    loss_rgb: f64,
    loss_depth: f64,
    rays: usize,
    samples: usize,
    rays_without_depth: usize,
    samples_without_depth: usize,
    march_s: f64,
    /// Whole sub-batches, the field's passes included.
    sub_batches_s: f64,
    field: FieldSeconds,
}

/// Per-thread buffers, allocated once and reused every step.
struct Chunk {
    ws: FieldWorkspace,
    grad: FieldGrad,
    rays: Vec<RayRecord>,
    segments: Vec<Segment>,
    ray_origins: Vec<[f32; 3]>,
    ray_dirs: Vec<[f32; 3]>,
    sample_positions: Vec<[f32; 3]>,
    sample_dirs: Vec<[f32; 3]>,
    /// Samples of the sub-batch that go on past the density pass.
    kept: Vec<u32>,
    tau: Vec<f32>,
    weights: Vec<f32>,
    grad_w: Vec<f32>,
    grad_tau: Vec<f32>,
    d_sigma: Vec<f32>,
    d_rgb: Vec<f32>,
    /// Gradient of the training views' appearance maps (12 per view).
    grad_appearance: Vec<f32>,
    /// Gradient of the environment's coefficients, when learnt.
    grad_environment: Vec<f32>,
    /// Gradient of the training views' pose corrections, when learnt.
    grad_pose: Vec<PoseGradient>,
    /// Loss gradient with respect to each sample's position, and the
    /// samples it is taken at.
    d_position: Vec<[f32; 3]>,
    pose_samples: Vec<usize>,
}

/// Trains a [`Field`] on a set of views.
pub struct Trainer {
    pub field: Field,
    pub occupancy: OccupancyGrid,
    pub config: TrainConfig,
    pub counters: TrainCounters,
    background: [f32; 3],
    adam_grid: Adam,
    adam_density: Adam,
    adam_color: Adam,
    chunks: Vec<Chunk>,
    lr_scale: f32,
    loss_ema: f64,
    /// RMS of the density and colour MLPs' parameters when the trainer was
    /// built: the scale their updates are measured against.
    mlp_scale: [f32; 2],
    occupancy_positions: Vec<[f32; 3]>,
    occupancy_sigmas: Vec<f32>,
    /// Fraction of training pixels with measured depth, found at the first step.
    depth_coverage: Option<f32>,
    /// Per training view, where its image has detail (built at the first step).
    detail: Vec<Option<DetailSampler>>,
    /// Surfaces the sensor measured, for the no-return term.
    measured: Option<MeasuredSurfaces>,
    /// The depth sensor's noise in local units (see [`Trainer::set_depth_noise`]).
    depth_noise: Option<DepthNoise>,
    /// Per-frame appearance maps, when learnt.
    pub appearance: Option<AppearanceLearner>,
    /// The colour beyond the cube, when learnt (else `background`).
    pub environment: Option<EnvironmentLearner>,
    /// Per-frame pose corrections, when learnt.
    pub poses: Option<PoseLearner>,
    /// The pose steps of the last training step, one per training view
    /// (empty when none were taken), for the caller to apply.
    pose_steps: Vec<[f64; 6]>,
}

impl Trainer {
    /// Trainer for `field`; `background` is the colour behind empty rays.
    pub fn new(field: Field, occupancy: OccupancyGrid, config: TrainConfig, background: [f32; 3]) -> Trainer {
        let threads = rayon::current_num_threads().max(1);
        let chunks = (0..threads)
            .map(|_| Chunk {
                ws: FieldWorkspace::default(),
                grad: field.new_grad(),
                rays: Vec::new(),
                segments: Vec::new(),
                ray_origins: Vec::new(),
                ray_dirs: Vec::new(),
                sample_positions: Vec::new(),
                sample_dirs: Vec::new(),
                kept: Vec::new(),
                tau: Vec::new(),
                weights: Vec::new(),
                grad_w: Vec::new(),
                grad_tau: Vec::new(),
                d_sigma: Vec::new(),
                d_rgb: Vec::new(),
                grad_appearance: Vec::new(),
                grad_environment: Vec::new(),
                grad_pose: Vec::new(),
                d_position: Vec::new(),
                pose_samples: Vec::new(),
            })
            .collect();
        let mlp_scale = [rms(&field.density.params), rms(&field.color.params)];
        Trainer {
            adam_grid: Adam::new(field.grid.param_count()),
            adam_density: Adam::new(field.density.param_count()),
            adam_color: Adam::new(field.color.param_count()),
            field,
            occupancy,
            config,
            counters: TrainCounters::default(),
            background,
            chunks,
            lr_scale: 1.0,
            loss_ema: 0.0,
            mlp_scale,
            occupancy_positions: Vec::new(),
            occupancy_sigmas: Vec::new(),
            depth_coverage: None,
            detail: Vec::new(),
            measured: None,
            depth_noise: None,
            appearance: None,
            environment: None,
            poses: None,
            pose_steps: Vec::new(),
        }
    }

    /// Learn the colour beyond the cube (`nerf::environment`), starting
    /// from the background colour.
    pub fn learn_environment(&mut self) {
        self.environment = Some(EnvironmentLearner::new(self.background));
    }

    /// `base` rendering what the trainer has learnt beyond the field (the environment).
    pub fn render_options(&self, base: &RenderOptions) -> RenderOptions {
        RenderOptions {
            environment: self.environment.as_ref().map(|e| e.environment),
            ..*base
        }
    }

    /// Learn each training view's pose with the field (`pose_learning`).
    pub fn learn_poses(&mut self, learner: PoseLearner) {
        self.poses = Some(learner);
    }

    /// The pose steps the last training step took (rotation about the camera
    /// centre and translation, local units, per training view), once: the
    /// caller moves the views' cameras by them.
    pub fn take_pose_steps(&mut self) -> Option<Vec<[f64; 6]>> {
        (!self.pose_steps.is_empty()).then(|| std::mem::take(&mut self.pose_steps))
    }

    /// Learn an appearance map per training view (`nerf::appearance`).
    pub fn learn_appearance(&mut self, views: usize) {
        self.appearance = Some(AppearanceLearner::new(views));
    }

    /// Surfaces the sensor measured in the training views: enables the
    /// no-return term (see [`TrainConfig::lambda_no_return`]).
    pub fn set_measured_surfaces(&mut self, measured: MeasuredSurfaces) {
        self.measured = Some(measured);
    }

    /// The depth sensor's noise in local units: each ray's surface window
    /// widens to [`NOISE_WINDOW_SIGMAS`] deviations of its measured depth.
    pub fn set_depth_noise(&mut self, noise: DepthNoise) {
        self.depth_noise = Some(noise);
    }

    /// Learning-rate multiplier: warm-up, then step decay over `progress` in [0, 1].
    fn schedule(&self, progress: f32) -> f32 {
        let warm = self.config.warmup_steps.max(1) as f32;
        let warmup = ((self.counters.steps as f32 + 1.0) / warm).min(1.0);
        let decay = LR_DECAY
            .iter()
            .rev()
            .find(|(from, _)| progress >= *from)
            .map_or(1.0, |(_, factor)| *factor);
        warmup * decay
    }

    /// Run one step; `progress` is the fraction of the budget already used.
    pub fn step(&mut self, views: &[View], progress: f32) -> StepStats {
        let step_index = self.counters.steps;
        let schedule = self.schedule(progress);
        self.maybe_refresh_occupancy(step_index);
        let threads = self.chunks.len();
        let budget = (self.config.samples_per_step / threads).max(64);
        let coverage = *self.depth_coverage.get_or_insert_with(|| depth_coverage(views));
        if self.detail.len() != views.len() {
            self.detail = views
                .par_iter()
                .map(|v| DetailSampler::from_rgb(&v.rgb, v.camera.width as usize, v.camera.height as usize))
                .collect();
        }
        let rule = self.config.step;
        let (colour_only, colour_only_cap, colour_only_thin) = if coverage >= COLOUR_ONLY_COARSE_MIN_COVERAGE {
            (
                coarser(&rule, COLOUR_ONLY_STEP_FACTOR),
                self.config.max_samples_per_ray / 16,
                Some(COLOUR_ONLY_THIN_STEPS),
            )
        } else {
            (rule, self.config.max_samples_per_ray, None)
        };
        let ctx = StepContext {
            field: &self.field,
            occupancy: &self.occupancy,
            views,
            detail: &self.detail,
            detail_share: detail_share(progress),
            config: &self.config,
            rule,
            colour_only,
            colour_only_cap,
            colour_only_thin,
            background: self.background,
            measured: self.measured.as_ref().filter(|_| self.config.lambda_no_return > 0.0),
            depth_noise: self.depth_noise.as_ref(),
            appearance: self.appearance.as_ref(),
            environment: self.environment.as_ref().map(|e| &e.environment),
            pose_levels: self
                .poses
                .as_ref()
                .filter(|p| step_index >= p.start_step && p.views() == views.len())
                .map(|p| p.levels),
        };
        let appearance_len = self.appearance.as_ref().map_or(0, AppearanceLearner::grad_len);
        let environment_len = if self.environment.is_some() {
            ENVIRONMENT_PARAMS
        } else {
            0
        };
        let pose_len = if ctx.pose_levels.is_some() { views.len() } else { 0 };
        let seed = self.config.seed;
        let stats: Vec<ChunkStats> = self
            .chunks
            .par_iter_mut()
            .enumerate()
            .map(|(c, chunk)| {
                let mut rng = Rng::new(seed, 1 + step_index * STEP_STREAMS + c as u64);
                chunk.grad.clear();
                chunk.grad_appearance.clear();
                chunk.grad_appearance.resize(appearance_len, 0.0);
                chunk.grad_environment.clear();
                chunk.grad_environment.resize(environment_len, 0.0);
                chunk.grad_pose.clear();
                chunk.grad_pose.resize(pose_len, [0.0; 6]);
                chunk.ws.seconds = FieldSeconds::default();
                run_chunk(&ctx, chunk, &mut rng, budget)
            })
            .collect();
        let update_started = Instant::now();
        // Merge in chunk order so results do not depend on scheduling.
        let (first, rest) = self.chunks.split_at_mut(1);
        for other in rest.iter_mut() {
            first[0].grad.drain_from(&mut other.grad);
            for (g, o) in first[0].grad_appearance.iter_mut().zip(&other.grad_appearance) {
                *g += o;
            }
            for (g, o) in first[0].grad_environment.iter_mut().zip(&other.grad_environment) {
                *g += o;
            }
            for (g, o) in first[0].grad_pose.iter_mut().zip(&other.grad_pose) {
                for k in 0..6 {
                    g[k] += o[k];
                }
            }
        }
        let mut total = StepStats::default();
        for s in &stats {
            total.loss_rgb += s.loss_rgb;
            total.loss_depth += s.loss_depth;
            total.rays += s.rays;
            total.samples += s.samples;
            total.rays_without_depth += s.rays_without_depth;
            total.samples_without_depth += s.samples_without_depth;
            total.phases.march += s.march_s;
            // The field's passes run inside the sub-batches.
            total.phases.composite += s.sub_batches_s - s.field.grid - s.field.mlp;
            total.phases.grid += s.field.grid;
            total.phases.mlp += s.field.mlp;
        }

        let rays = total.rays.max(1) as f64;
        total.loss_rgb /= rays;
        total.loss_depth /= rays;
        total.loss = total.loss_rgb + total.loss_depth;
        self.counters.steps += 1;
        self.counters.samples += total.samples as u64;
        self.counters.rays += total.rays as u64;
        self.counters.rays_without_depth += total.rays_without_depth as u64;
        self.counters.samples_without_depth += total.samples_without_depth as u64;

        let grad = &first[0].grad;
        let diverged = self.counters.steps > DIVERGENCE_GRACE_STEPS
            && self.loss_ema > 0.0
            && total.loss > DIVERGENCE_RATIO * self.loss_ema + DIVERGENCE_FLOOR;
        let lr = self.config.learning_rate * schedule * self.lr_scale;
        total.learning_rate = lr;
        let grad_appearance = &first[0].grad_appearance;
        let grid_rms = grad.grid.touched_rms();
        let finite = total.loss.is_finite()
            && grad.mlps_finite()
            && grid_rms.is_some()
            && grad_appearance.iter().all(|g| g.is_finite())
            && first[0].grad_environment.iter().all(|g| g.is_finite());
        if finite {
            let density = self
                .adam_density
                .dense_step_rms(&self.field.density.params, &grad.density, MLP_WEIGHT_DECAY);
            let color = self
                .adam_color
                .dense_step_rms(&self.field.color.params, &grad.color, MLP_WEIGHT_DECAY);
            total.relative_update =
                relative(lr * density, self.mlp_scale[0]).max(relative(lr * color, self.mlp_scale[1]));
        }
        if !finite || diverged || total.relative_update > MAX_RELATIVE_UPDATE || total.rays == 0 {
            // Skip the batch (nothing applied: parameters and moments stay
            // as they were) and halve the step size for the rest of the fit:
            // the warm-up would otherwise climb straight back to the step
            // size that diverged.
            total.skipped = true;
            self.counters.skipped_batches += 1;
            self.lr_scale = (self.lr_scale * 0.5).max(MIN_LR_SCALE);
            total.phases.update = update_started.elapsed().as_secs_f64() * threads as f64;
            return total;
        }
        self.loss_ema = if self.loss_ema == 0.0 {
            total.loss
        } else {
            (1.0 - LOSS_EMA_WEIGHT) * self.loss_ema + LOSS_EMA_WEIGHT * total.loss
        };
        let grid_decay = GRID_PRIOR * grid_rms.unwrap_or(0.0);
        // The grid's touched entries are updated on every thread, consuming
        // their gradients, in many small parts: the finest levels are touched
        // far more densely than the coarse ones, so halves would not balance.
        let grad = &mut first[0].grad;
        let (grid_grads, touched) = grad.grid.values_and_touched();
        let parts = self.field.grid.params.len() / ADAM_PART_PARAMS;
        self.adam_grid.step_sparse_decayed_parallel(
            &mut self.field.grid.params,
            grid_grads,
            |start, len| touched.words_in(start, len),
            GridGrad::BLOCK,
            parts.max(threads),
            lr,
            grid_decay,
        );
        grad.grid.forget_zeroed();
        self.adam_density
            .step_dense(&mut self.field.density.params, &grad.density, lr, MLP_WEIGHT_DECAY);
        self.adam_color
            .step_dense(&mut self.field.color.params, &grad.color, lr, MLP_WEIGHT_DECAY);
        // The maps start after the warm-up: until then the field's colour is
        // far from every frame's, and the maps would chase that instead.
        if let Some(appearance) = self
            .appearance
            .as_mut()
            .filter(|_| step_index >= self.config.warmup_steps)
        {
            appearance.step(grad_appearance, lr);
        }
        if let Some(learner) = self.environment.as_mut() {
            let rate = environment::LEARNING_RATE * schedule * self.lr_scale;
            learner.step(&first[0].grad_environment, rate);
        }
        if let (Some(learner), true) = (self.poses.as_mut(), pose_len > 0) {
            let centres: Vec<[f64; 3]> = views.iter().map(|v| v.camera.origin.map(f64::from)).collect();
            let rotations: Vec<Matrix3<f64>> = views.iter().map(|v| v.camera.rotation_matrix()).collect();
            let rate = (schedule * self.lr_scale) as f64;
            self.pose_steps = learner.step(&first[0].grad_pose, rate, &centres, &rotations, [0.5; 3]);
        }
        total.phases.update = update_started.elapsed().as_secs_f64() * threads as f64;
        total
    }

    /// An occupancy grid for rendering the current field: every cell
    /// re-evaluated, untrained space dropped.
    pub fn rendering_occupancy(&mut self) -> OccupancyGrid {
        let mut grid = self.occupancy.clone();
        let mut rng = Rng::new(self.config.seed, RENDERING_GRID_STREAM);
        let field = &self.field;
        grid.prune_for_rendering(
            &mut rng,
            &mut self.occupancy_positions,
            &mut self.occupancy_sigmas,
            |p, s| density_batched(field, p, s),
        );
        grid
    }

    fn maybe_refresh_occupancy(&mut self, step: u64) {
        let warmup = self.config.warmup_steps;
        let every = self.config.occupancy_every.max(1);
        if step < warmup || !(step - warmup).is_multiple_of(every) {
            return;
        }
        // The first refresh after warm-up covers every cell; later ones a subset each.
        let passes = if step == warmup { FIRST_REFRESH_PASSES } else { 1 };
        let mut rng = Rng::new(self.config.seed, u64::MAX - step);
        for _ in 0..passes {
            let field = &self.field;
            self.occupancy.refresh(
                self.config.occupancy_decay,
                &mut rng,
                &mut self.occupancy_positions,
                &mut self.occupancy_sigmas,
                |positions, sigmas| density_batched(field, positions, sigmas),
            );
        }
        self.counters.occupancy_refreshes += 1;
    }
}

/// Root mean square of `values` (0 when empty).
fn rms(values: &[f32]) -> f32 {
    let sum: f64 = values.iter().map(|&v| v as f64 * v as f64).sum();
    (sum / values.len().max(1) as f64).sqrt() as f32
}

/// `step / scale`, or 0 when the scale gives no reference (all-zero weights).
fn relative(step: f32, scale: f32) -> f32 {
    if scale > 0.0 && scale.is_finite() {
        step / scale
    } else {
        0.0
    }
}

/// Density for many points, in parallel blocks.
pub fn density_batched(field: &Field, positions: &[[f32; 3]], sigmas: &mut [f32]) {
    const BLOCK: usize = 8192;
    positions
        .par_chunks(BLOCK)
        .zip(sigmas.par_chunks_mut(BLOCK))
        .for_each_init(FieldWorkspace::default, |ws, (p, s)| {
            field.density_only(p, ws, s);
        });
}

/// Optimiser state that checkpoints save and restore (`checkpoint.rs`).
impl Trainer {
    /// Adam state of the grid, density MLP and colour MLP; step-size scale; loss average.
    pub(crate) fn optimiser(&self) -> ([&Adam; 3], f32, f64) {
        (
            [&self.adam_grid, &self.adam_density, &self.adam_color],
            self.lr_scale,
            self.loss_ema,
        )
    }

    /// The same state, mutable, to restore a checkpoint.
    pub(crate) fn optimiser_mut(&mut self) -> ([&mut Adam; 3], &mut f32, &mut f64) {
        (
            [&mut self.adam_grid, &mut self.adam_density, &mut self.adam_color],
            &mut self.lr_scale,
            &mut self.loss_ema,
        )
    }
}

struct StepContext<'a> {
    field: &'a Field,
    occupancy: &'a OccupancyGrid,
    views: &'a [View],
    detail: &'a [Option<DetailSampler>],
    /// Share of this step's rays drawn by detail.
    detail_share: f32,
    config: &'a TrainConfig,
    rule: StepRule,
    /// Marching of rays without measured depth, and their sample cap.
    colour_only: StepRule,
    colour_only_cap: usize,
    /// Their longer steps through thin space, except on no-return rays
    /// (the sensor missed something there: it gets the step of surfaces).
    colour_only_thin: Option<ThinSteps>,
    background: [f32; 3],
    measured: Option<&'a MeasuredSurfaces>,
    /// The depth sensor's noise (local units), when measured.
    depth_noise: Option<&'a DepthNoise>,
    appearance: Option<&'a AppearanceLearner>,
    environment: Option<&'a Environment>,
    /// Grid levels of the cameras' gradient, when poses are learnt this step.
    pose_levels: Option<usize>,
}

/// Fraction of the pixels of `views` with measured depth.
fn depth_coverage(views: &[View]) -> f32 {
    let (mut with, mut all) = (0usize, 0usize);
    for v in views {
        all += v.rgb.len() / 3;
        with += v
            .depth
            .as_ref()
            .map_or(0, |d| d.iter().filter(|&&z| z > 0.0 && z.is_finite()).count());
    }
    with as f32 / all.max(1) as f32
}

fn run_chunk(ctx: &StepContext, chunk: &mut Chunk, rng: &mut Rng, budget: usize) -> ChunkStats {
    let started = Instant::now();
    draw_rays(ctx, chunk, rng, budget);
    let mut stats = ChunkStats {
        rays: chunk.rays.len(),
        samples: chunk.segments.len(),
        march_s: started.elapsed().as_secs_f64(),
        ..Default::default()
    };
    let started = Instant::now();
    for ray in chunk.rays.iter().filter(|r| r.depth_t.is_none()) {
        stats.rays_without_depth += 1;
        stats.samples_without_depth += ray.count;
    }
    let mut start = 0;
    while start < chunk.rays.len() {
        // Whole rays up to SUB_BATCH samples (a longer single ray goes alone).
        let mut end = start;
        let mut samples = 0;
        while end < chunk.rays.len() && (end == start || samples + chunk.rays[end].count <= SUB_BATCH) {
            samples += chunk.rays[end].count;
            end += 1;
        }
        train_sub_batch(ctx, chunk, start..end, &mut stats);
        start = end;
    }
    stats.sub_batches_s = started.elapsed().as_secs_f64();
    stats.field = chunk.ws.seconds;
    stats
}

/// Draw random pixels of random views and march them until `budget` samples.
fn draw_rays(ctx: &StepContext, chunk: &mut Chunk, rng: &mut Rng, budget: usize) {
    chunk.rays.clear();
    chunk.segments.clear();
    chunk.ray_origins.clear();
    chunk.ray_dirs.clear();
    let cfg = ctx.config;
    let scene_window = cfg.surface_window;
    let scene_fine_step = 0.75 * ctx.rule.min_step;
    // In front of the surface window only sparse samples: enough to push
    // free space empty and to find occluders the sensor missed.
    let sparse = coarser(&ctx.rule, SPARSE_STEP_FACTOR);
    let mut attempts = 0usize;
    // Bounded attempts: views that see nothing must not hang the step.
    while chunk.segments.len() < budget && attempts < 4 * budget {
        attempts += 1;
        let view_index = rng.below(ctx.views.len() as u64) as usize;
        let view = &ctx.views[view_index];
        let pixel = match &ctx.detail[view_index] {
            Some(detail) if ctx.detail_share > 0.0 && rng.f32() < ctx.detail_share => detail.sample(rng),
            _ => rng.below(view.camera.pixels() as u64) as usize,
        };
        let importance = match &ctx.detail[view_index] {
            Some(detail) if ctx.detail_share > 0.0 => {
                let share = ctx.detail_share as f64;
                (1.0 / ((1.0 - share) + share * detail.density_ratio(pixel))) as f32
            }
            // Uniform draws: every ray counts once (no ratio to look up).
            _ => 1.0,
        };
        let width = view.camera.width as usize;
        let (ray, t_per_z) = view.camera.ray((pixel % width) as f32, (pixel / width) as f32);
        let Some((t0, t1)) = ray_interval(&ray, ctx.rule.min_step) else {
            continue;
        };
        let depth_t = view.depth.as_ref().and_then(|d| {
            let z = d[pixel];
            (z > 0.0 && z.is_finite()).then_some(z * t_per_z)
        });
        let no_return = depth_t.is_none() && view.no_return.as_ref().is_some_and(|m| m[pixel]);
        let first = chunk.segments.len();
        let max = cfg.max_samples_per_ray;
        let jitter = rng.f32();
        // The window spans the sensor's scatter at that depth, with as many
        // samples as the scene's own window.
        let window = match (depth_t, ctx.depth_noise) {
            (Some(td), Some(noise)) => scene_window.max(NOISE_WINDOW_SIGMAS * noise.sigma(td / t_per_z) * t_per_z),
            _ => scene_window,
        };
        let fine_step = scene_fine_step * window / scene_window;
        let t_end = match depth_t {
            Some(td) if td - window < t1 && td + window > t0 => {
                // Occupancy-skipped up to the surface window, dense inside it
                // whatever the grid says, and nothing behind it.
                let (w0, w1) = ((td - window).max(t0), (td + window).min(t1));
                march(&ray, t0, w0, ctx.occupancy, &sparse, jitter, max, &mut chunk.segments);
                let mut t = w0 + jitter * fine_step;
                while t < w1 && chunk.segments.len() - first < max {
                    chunk.segments.push(Segment {
                        t,
                        dt: fine_step.min(w1 - t),
                    });
                    t += fine_step;
                }
                w1
            }
            // Without depth: stop where the grid says the ray is surely absorbed.
            _ => march_until(
                &ray,
                t0,
                t1,
                ctx.occupancy,
                &ctx.colour_only,
                jitter,
                ctx.colour_only_cap,
                ABSORBED_OPTICAL_DEPTH,
                ctx.colour_only_thin.filter(|_| !no_return),
                &mut chunk.segments,
            )
            .min(t1),
        };
        let count = chunk.segments.len() - first;
        if count == 0 {
            continue;
        }
        // A ray without depth that stopped where the grid's estimate (a
        // running maximum per cell) says it is absorbed may still carry
        // light the field has not taken. Rendering marches on into the
        // surface, so training gives that light the colour of the last
        // sample, not the environment's. No-return rays keep the
        // environment: its wrong colour is what makes an object the sensor
        // cannot see opaque (with the surface's colour the tabletop's glass
        // fell from 0.984 to 0.951 IoU).
        let absorbed = depth_t.is_none() && !no_return && t_end < t1 && count < ctx.colour_only_cap;

        if chunk.segments.len() > budget && !chunk.rays.is_empty() {
            chunk.segments.truncate(first);
            break;
        }
        let px = 3 * pixel;
        let target = [
            view.rgb[px] as f32 / 255.0,
            view.rgb[px + 1] as f32 / 255.0,
            view.rgb[px + 2] as f32 / 255.0,
        ];
        chunk.rays.push(RayRecord {
            first,
            count,
            target,
            depth_t,
            t_end,
            no_return,
            absorbed,
            view: view_index,
            lens_r2: off_axis_r2(t_per_z),
            window,
            importance,
        });
        chunk.ray_origins.push(ray.origin);
        chunk.ray_dirs.push(ray.dir);
    }
}

/// `rule` with its smallest step multiplied by `factor`.
fn coarser(rule: &StepRule, factor: f32) -> StepRule {
    let min_step = factor * rule.min_step;
    StepRule {
        min_step,
        max_step: rule.max_step.max(min_step),
        cone: rule.cone,
    }
}

fn sized<T: Copy + Default>(buf: &mut Vec<T>, len: usize) -> &mut [T] {
    if buf.len() < len {
        buf.resize(len, T::default());
    }
    &mut buf[..len]
}

// A ray's samples `i` sit at `o + i` in the sub-batch arrays.
#[allow(clippy::needless_range_loop)]
fn train_sub_batch(ctx: &StepContext, chunk: &mut Chunk, rays: std::ops::Range<usize>, stats: &mut ChunkStats) {
    let cfg = ctx.config;
    let ray_range = rays.clone();
    let base = chunk.rays[rays.start].first;
    let last = &chunk.rays[rays.end - 1];
    let n = last.first + last.count - base;
    chunk.sample_positions.clear();
    chunk.sample_dirs.clear();
    for r in rays.clone() {
        let rec = &chunk.rays[r];
        let (o, d) = (chunk.ray_origins[r], chunk.ray_dirs[r]);
        for seg in &chunk.segments[rec.first..rec.first + rec.count] {
            let t = seg.mid();
            chunk
                .sample_positions
                .push([o[0] + t * d[0], o[1] + t * d[1], o[2] + t * d[2]]);
            chunk.sample_dirs.push(d);
        }
    }
    let n = keep_lit_samples(ctx, chunk, ray_range.clone(), n);
    let tau = sized(&mut chunk.tau, n);
    let weights = sized(&mut chunk.weights, n);
    let grad_w = sized(&mut chunk.grad_w, n);
    let grad_tau = sized(&mut chunk.grad_tau, n);
    let d_sigma = sized(&mut chunk.d_sigma, n);
    let d_rgb = sized(&mut chunk.d_rgb, 3 * n);
    let sigma = &chunk.ws.sigma;
    let rgb = &chunk.ws.rgb;
    let (lambda_d0, lambda_los0) = (cfg.lambda_depth, cfg.lambda_line_of_sight);
    for r in rays {
        let rec = &chunk.rays[r];
        let window = rec.window;
        // Colour, depth and line-of-sight terms count as often as uniform
        // sampling would draw the ray.
        let wc = rec.importance;
        let (lambda_d, lambda_los) = (lambda_d0 * wc, lambda_los0 * wc);
        let o = rec.first - base;
        let segs = &chunk.segments[rec.first..rec.first + rec.count];
        let k = rec.count;
        for i in 0..k {
            tau[o + i] = sigma[o + i] * segs[i].dt;
        }
        let comp = weights_from_optical_depth(&tau[o..o + k], &mut weights[o..o + k]);
        let t_final = comp.transmittance;
        // The colour behind the ray: the surface it stopped in, or else
        // the environment's by direction, or the scan's mean.
        let mut basis = [0.0f32; SH_COEFFS];
        let last = o + k - 1;
        let bg = match ctx.environment {
            _ if rec.absorbed => [rgb[last], rgb[n + last], rgb[2 * n + last]],
            Some(env) => {
                sh::encode(chunk.ray_dirs[r], &mut basis);
                env.colour_of_basis(&basis)
            }
            None => ctx.background,
        };
        let mut color = [bg[0] * t_final, bg[1] * t_final, bg[2] * t_final];
        let mut depth = t_final * rec.t_end;
        for i in 0..k {
            let w = weights[o + i];
            for c in 0..3 {
                color[c] += w * rgb[c * n + o + i];
            }
            depth += w * segs[i].mid();
        }
        // Between the field's colour and the photo: the lens's falloff, then
        // the frame's appearance map.
        let lens = ctx.appearance.map(|a| (a.map(rec.view), a.lens, a.lens_offset()));
        let gain = lens.as_ref().map_or(1.0, |(_, k, _)| vignetting_gain(k, rec.lens_r2));
        let shaded = color.map(|c| gain * c);
        let seen = lens.as_ref().map_or(shaded, |(a, _, _)| apply(a, shaded));
        let err = [
            seen[0] - rec.target[0],
            seen[1] - rec.target[1],
            seen[2] - rec.target[2],
        ];
        stats.loss_rgb += (err[0] * err[0] + err[1] * err[1] + err[2] * err[2]) as f64 / 3.0;
        let mut two_err = [
            2.0 * wc * err[0] / 3.0,
            2.0 * wc * err[1] / 3.0,
            2.0 * wc * err[2] / 3.0,
        ];
        if let Some((a, k, lens_offset)) = &lens {
            // From here on, the gradient with respect to the field's colour.
            let grad_map = &mut chunk.grad_appearance[12 * rec.view..12 * rec.view + 12];
            let scaled = two_err.map(|g| g * GRAD_SCALE);
            let back = apply_backward(a, shaded, scaled, grad_map);
            let grad_gain = back[0] * color[0] + back[1] * color[1] + back[2] * color[2];
            vignetting_backward(k, rec.lens_r2, grad_gain, &mut chunk.grad_appearance[*lens_offset..]);
            two_err = back.map(|g| gain * g / GRAD_SCALE);
        }
        let mut g_t = two_err[0] * bg[0] + two_err[1] * bg[1] + two_err[2] * bg[2];
        if ctx.environment.is_some() && t_final > 0.0 && !rec.absorbed {
            let g_bg = two_err.map(|g| g * t_final);
            Environment::backward(bg, &basis, g_bg, &mut chunk.grad_environment);
        }
        for i in 0..k {
            let j = o + i;
            grad_w[j] = two_err[0] * rgb[j] + two_err[1] * rgb[n + j] + two_err[2] * rgb[2 * n + j];
        }
        if let Some(td) = rec.depth_t {
            // L1 on expected depth (the paper's term).
            let sign = (depth - td).signum();
            stats.loss_depth += (lambda_d * (depth - td).abs()) as f64;
            g_t += lambda_d * sign * rec.t_end;
            // Line of sight: no weight in front of the surface, all of it near the surface.
            let mut near = 0.0f32;
            for i in 0..k {
                let m = segs[i].mid();
                let j = o + i;
                grad_w[j] += lambda_d * sign * m;
                if m < td - window {
                    stats.loss_depth += (lambda_los * weights[j]) as f64;
                    grad_w[j] += lambda_los;
                } else if m <= td + window {
                    near += weights[j];
                }
            }
            let miss = 1.0 - near;
            stats.loss_depth += (lambda_los * miss * miss) as f64;
            for i in 0..k {
                let m = segs[i].mid();
                if m >= td - window && m <= td + window {
                    grad_w[o + i] -= 2.0 * lambda_los * miss;
                }
            }
        }
        if rec.depth_t.is_none() && ctx.environment.is_some() {
            // Colour seen through empty space belongs to the environment, not to fog.
            stats.loss_depth += distortion(segs, &weights[o..o + k], DISTORTION_WEIGHT, &mut grad_w[o..o + k]) as f64;
        }
        if let (true, Some(measured)) = (rec.no_return, ctx.measured) {
            let positions = &chunk.sample_positions[o..o + k];
            let loss = no_return_term(
                positions,
                &weights[o..o + k],
                measured,
                cfg.lambda_no_return,
                &mut grad_w[o..o + k],
            );
            stats.loss_depth += loss as f64;
        }
        for g in grad_w[o..o + k].iter_mut() {
            *g *= GRAD_SCALE;
        }
        optical_depth_backward(
            &tau[o..o + k],
            &weights[o..o + k],
            &comp,
            &grad_w[o..o + k],
            g_t * GRAD_SCALE,
            &mut grad_tau[o..o + k],
        );
        for i in 0..k {
            let j = o + i;
            d_sigma[j] = grad_tau[j] * segs[i].dt;
            let w = weights[j] * GRAD_SCALE;
            d_rgb[j] = two_err[0] * w;
            d_rgb[n + j] = two_err[1] * w;
            d_rgb[2 * n + j] = two_err[2] * w;
        }
        if rec.absorbed {
            let w = t_final * GRAD_SCALE;
            for c in 0..3 {
                d_rgb[c * n + last] += two_err[c] * w;
            }
        }
    }
    ctx.field.backward(
        &chunk.sample_positions,
        &mut chunk.ws,
        &chunk.d_sigma[..n],
        &chunk.d_rgb[..3 * n],
        &mut chunk.grad,
    );
    if let Some(levels) = ctx.pose_levels {
        pose_gradient(ctx, chunk, ray_range, levels);
    }
    let _ = stats;
}

/// The sub-batch's density pass, then the training forward of the samples
/// before each ray's light is used up: those after it get no weight, so
/// they would carry no gradient through the colour network and the
/// backward (after the first few hundred steps, about a sixth of all
/// samples, mostly in the surface window behind a surface). Shortens the
/// rays, their segments and the sample buffers to what is kept; returns
/// the samples kept.
fn keep_lit_samples(ctx: &StepContext, chunk: &mut Chunk, rays: std::ops::Range<usize>, n: usize) -> usize {
    let base = chunk.rays[rays.start].first;
    let sigma = ctx.field.density_for_training(&chunk.sample_positions, &mut chunk.ws);
    let tau = sized(&mut chunk.tau, n);
    let weights = sized(&mut chunk.weights, n);
    chunk.kept.clear();
    for r in rays {
        let rec = &mut chunk.rays[r];
        let (o, k) = (rec.first - base, rec.count);
        let segs = &chunk.segments[rec.first..rec.first + k];
        for (i, seg) in segs.iter().enumerate() {
            tau[o + i] = sigma[o + i] * seg.dt;
        }
        let lit = weights_from_optical_depth(&tau[o..o + k], &mut weights[o..o + k]).used;
        // In place, moving left: a kept sample's new index is at most its old one.
        let first = base + chunk.kept.len();
        for i in 0..lit {
            let (from, to) = (o + i, chunk.kept.len());
            chunk.segments[base + to] = chunk.segments[rec.first + i];
            chunk.sample_positions[to] = chunk.sample_positions[from];
            chunk.sample_dirs[to] = chunk.sample_dirs[from];
            chunk.kept.push(from as u32);
        }
        (rec.first, rec.count) = (first, lit);
    }
    let m = chunk.kept.len();
    chunk.sample_positions.truncate(m);
    chunk.sample_dirs.truncate(m);
    ctx.field
        .forward_train_kept(&chunk.kept, &chunk.sample_dirs, &mut chunk.ws);
    m
}

/// Adds the sub-batch's gradient with respect to each ray's camera pose to
/// its view's entry (after the field's backward).
fn pose_gradient(ctx: &StepContext, chunk: &mut Chunk, rays: std::ops::Range<usize>, levels: usize) {
    let base = chunk.rays[rays.start].first;
    let n = chunk.sample_positions.len();
    chunk.pose_samples.clear();
    chunk
        .pose_samples
        .extend((0..n).filter(|&j| chunk.weights[j] >= POSE_SAMPLE_MIN_WEIGHT));
    let d_position = sized(&mut chunk.d_position, n);
    for &j in &chunk.pose_samples {
        d_position[j] = [0.0; 3];
    }
    ctx.field.position_gradient(
        &chunk.sample_positions,
        &mut chunk.ws,
        levels,
        &chunk.pose_samples,
        d_position,
    );
    for r in rays {
        let rec = &chunk.rays[r];
        let origin = chunk.ray_origins[r];
        let grad = &mut chunk.grad_pose[rec.view];
        let o = rec.first - base;
        for j in o..o + rec.count {
            if chunk.weights[j] >= POSE_SAMPLE_MIN_WEIGHT {
                pose_learning::accumulate(grad, origin, chunk.sample_positions[j], chunk.d_position[j]);
            }
        }
    }
}

/// Weight of the distortion term on rays without measured depth.
const DISTORTION_WEIGHT: f32 = 0.01;

/// Distortion term of one ray (Mip-NeRF 360): `lambda` times
/// `sum_ij w_i w_j |m_i - m_j| + 1/3 sum_i w_i^2 dt_i` over its samples'
/// midpoints `m`. Small when the weight sits in one short interval, large
/// for weight spread along the ray (fog), so colour seen through empty
/// space goes to the environment instead. Adds its gradient with respect to
/// the weights to `grad_w` and returns the loss.
fn distortion(segs: &[Segment], weights: &[f32], lambda: f32, grad_w: &mut [f32]) -> f32 {
    let (total_w, total_wm) = segs
        .iter()
        .zip(weights)
        .fold((0.0f32, 0.0f32), |(a, b), (s, &w)| (a + w, b + w * s.mid()));
    let (mut before_w, mut before_wm) = (0.0f32, 0.0f32);
    let mut loss = 0.0f32;
    for ((s, &w), g) in segs.iter().zip(weights).zip(grad_w.iter_mut()) {
        let m = s.mid();
        let (after_w, after_wm) = (total_w - before_w - w, total_wm - before_wm - w * m);
        // sum_j w_j |m - m_j|
        let spread = m * before_w - before_wm + after_wm - m * after_w;
        loss += w * spread + w * w * s.dt / 3.0;
        *g += lambda * (2.0 * spread + 2.0 / 3.0 * w * s.dt);
        before_w += w;
        before_wm += w * m;
    }
    lambda * loss
}

/// No-return term of one ray without sensor depth: `lambda` times the light
/// that reaches the first sample on a surface the sensor measured (from
/// other views). The sensor would have returned that surface, so something
/// it cannot see (glass) most likely stops the ray in front; without the
/// term, colour alone may paint such an object onto the surfaces behind
/// it instead. Adds the gradient with respect to each weight to `grad_w`;
/// returns the loss (0 when the ray meets no measured surface).
fn no_return_term(
    positions: &[[f32; 3]],
    weights: &[f32],
    measured: &MeasuredSurfaces,
    lambda: f32,
    grad_w: &mut [f32],
) -> f32 {
    let Some(first) = positions.iter().position(|&p| measured.contains(p)) else {
        return 0.0;
    };
    // Light through = 1 - sum of the weights in front.
    let through = 1.0 - weights[..first].iter().sum::<f32>();
    for g in &mut grad_w[..first] {
        *g -= lambda;
    }
    lambda * through
}

#[cfg(test)]
#[allow(clippy::needless_range_loop)] // index loops mirror the formulas they check
pub(crate) mod tests {
    use super::*;
    use crate::nerf::camera::LocalCamera;
    use crate::nerf::field::{FieldConfig, GridSpec};
    use crate::nerf::occupancy::DepthRay;
    use crate::nerf::render::composite::optical_depth_backward;
    use crate::nerf::render::rays::{render_image, render_pixels, RayOutput};
    use crate::scan::Intrinsics;

    /// Views of a textured plane at local z = 0.6 seen from z ~ 0.15.
    pub(crate) fn plane_views(n: usize, size: u32, with_depth: bool) -> Vec<View> {
        (0..n)
            .map(|i| {
                let a = i as f64 / n as f64 * std::f64::consts::TAU;
                // Camera looking along +z (OpenCV: x right, y down, z forward).
                let pose = nalgebra::IsometryMatrix3::translation(0.5 + 0.1 * a.cos(), 0.5 + 0.1 * a.sin(), 0.15);
                let f = size as f64 * 0.8;
                let k = Intrinsics {
                    fx: f,
                    fy: f,
                    cx: size as f64 / 2.0 - 0.5,
                    cy: size as f64 / 2.0 - 0.5,
                };
                let camera = LocalCamera::new(&pose, &k, size, size);
                let mut rgb = Vec::new();
                let mut depth = Vec::new();
                for v in 0..size {
                    for u in 0..size {
                        let (ray, t_per_z) = camera.ray(u as f32, v as f32);
                        let t = (0.6 - ray.origin[2]) / ray.dir[2];
                        let p = ray.at(t);
                        let checker = ((p[0] * 20.0).floor() as i64 + (p[1] * 20.0).floor() as i64) & 1;
                        let c = if checker == 0 { [220u8, 60, 40] } else { [30, 90, 200] };
                        rgb.extend_from_slice(&c);
                        depth.push(t / t_per_z);
                    }
                }
                View {
                    camera,
                    rgb,
                    depth: with_depth.then_some(depth),
                    no_return: None,
                    colour_border: Default::default(),
                }
            })
            .collect()
    }

    pub(crate) fn small_config(seed: u64) -> (FieldConfig, TrainConfig) {
        let grid = crate::nerf::field::hash_grid::HashGridConfig::for_scene(1.0, 1.0 / 128.0);
        let field = FieldConfig {
            grid: GridSpec::from(&grid),
            density_hidden: vec![64],
            color_hidden: vec![64, 64],
        };
        let step = StepRule {
            min_step: 1.0 / 160.0,
            max_step: 1.0 / 32.0,
            cone: 0.0,
        };
        let train = TrainConfig {
            samples_per_step: 1 << 14,
            max_samples_per_ray: 512,
            learning_rate: 1e-2,
            warmup_steps: 32,
            lambda_depth: 0.1,
            lambda_line_of_sight: 0.1,
            surface_window: 2.0 / 128.0,
            lambda_no_return: 0.1,
            step,
            occupancy_every: 16,
            occupancy_decay: 0.95,
            seed,
        };
        (field, train)
    }

    /// Mean absolute colour error (0-1 per channel) of rendered rays
    /// against the 8-bit colours they should show.
    fn mean_colour_error<'a>(out: &[RayOutput], wanted: impl Iterator<Item = &'a [u8]>) -> f32 {
        let sum: f32 = out
            .iter()
            .zip(wanted)
            .map(|(o, want)| (0..3).map(|c| (o.rgb[c] - want[c] as f32 / 255.0).abs()).sum::<f32>() / 3.0)
            .sum();
        sum / out.len() as f32
    }

    /// Colour rendering with the training step rule, grey behind.
    pub(crate) fn colour_options(train_cfg: &TrainConfig) -> RenderOptions {
        RenderOptions {
            color: true,
            rule: train_cfg.step,
            max_samples_per_ray: 4096,
            background: [0.5; 3],
            environment: None,
        }
    }

    /// Signed depth offsets (local units, positive = too far; no surface
    /// counts as 1) of the trained plane, seen from view 0 every `stride`
    /// pixels of its centre.
    fn plane_depth_offsets(trainer: &Trainer, views: &[View], train_cfg: &TrainConfig, stride: usize) -> Vec<f32> {
        let opts = colour_options(train_cfg);
        let cam = views[0].camera;
        let pixels: Vec<(f32, f32)> = (8..40)
            .step_by(stride)
            .flat_map(|v| (8..40).step_by(stride).map(move |u| (u as f32, v as f32)))
            .collect();
        let out = render_pixels(&trainer.field, &trainer.occupancy, &opts, &cam, &pixels);
        out.iter()
            .zip(&pixels)
            .map(|(o, &(u, v))| {
                let (ray, _) = cam.ray(u, v);
                let t_true = (0.6 - ray.origin[2]) / ray.dir[2];
                o.depth_median.map_or(1.0, |t| t - t_true)
            })
            .collect()
    }

    /// Mean depth error (local units) of the trained plane seen from view 0.
    fn plane_depth_error(trainer: &Trainer, views: &[View], train_cfg: &TrainConfig) -> f32 {
        let offsets = plane_depth_offsets(trainer, views, train_cfg, 4);
        offsets.iter().map(|o| o.abs()).sum::<f32>() / offsets.len() as f32
    }

    /// Measured surface: the plane z = 0.6 over x, y in [0.2, 0.8].
    fn measured_plane() -> MeasuredSurfaces {
        let rays: Vec<DepthRay> = (0..100)
            .flat_map(|i| (0..100).map(move |j| (i, j)))
            .map(|(i, j)| DepthRay {
                origin: [0.2 + i as f32 * 0.006, 0.2 + j as f32 * 0.006, 0.1],
                dir: [0.0, 0.0, 1.0],
                t_hit: 0.5,
            })
            .collect();
        MeasuredSurfaces::from_depth_rays(&rays, 64)
    }

    /// Views from inside the cube that see nothing: each pixel shows a sky
    /// whose colour changes with the ray's direction (no depth).
    fn sky_views(n: usize, size: u32) -> Vec<View> {
        plane_views(n, size, false)
            .into_iter()
            .map(|mut view| {
                let camera = view.camera;
                view.rgb = (0..camera.pixels())
                    .flat_map(|p| {
                        let (ray, _) = camera.ray((p % size as usize) as f32, (p / size as usize) as f32);
                        let [x, y, _] = ray.dir;
                        [0.3 + 0.5 * x.abs(), 0.5 + 0.4 * y, 0.8].map(|c| (c * 255.0) as u8)
                    })
                    .collect();
                view
            })
            .collect()
    }

    #[test]
    fn colour_beyond_the_scene_is_learnt_as_environment_not_fog() {
        let views = sky_views(4, 24);
        let (field_cfg, train_cfg) = small_config(5);
        let render = |trainer: &mut Trainer| {
            let grid = trainer.rendering_occupancy();
            let opts = trainer.render_options(&colour_options(&train_cfg));
            let out = render_image(&trainer.field, &grid, &opts, &views[1].camera);
            let samples = out.iter().map(|o| o.samples as f32).sum::<f32>() / out.len() as f32;
            let opacity = out.iter().map(|o| o.opacity).sum::<f32>() / out.len() as f32;
            let colour_error = mean_colour_error(&out, views[1].rgb.chunks_exact(3));
            (samples, opacity, colour_error)
        };
        let trained = |environment: bool| {
            let field = Field::new(field_cfg.clone(), &mut Rng::new(5, 0));
            let mut trainer = Trainer::new(field, OccupancyGrid::full(32), train_cfg.clone(), [0.5; 3]);
            if environment {
                trainer.learn_environment();
            }
            for s in 0..400 {
                trainer.step(&views, s as f32 / 400.0);
            }
            render(&mut trainer)
        };
        let (fog_samples, fog_opacity, _) = trained(false);
        let (samples, opacity, error) = trained(true);
        assert!(error < 0.03, "the environment shows the sky: mean error {error}");
        // 0.39 against 0.62 after 400 steps when this was written.
        assert!(
            opacity < 0.8 * fog_opacity,
            "less fog: opacity {opacity} against {fog_opacity} without"
        );
        assert!(samples <= fog_samples, "{samples} samples against {fog_samples}");
    }

    #[test]
    fn light_left_where_a_ray_stops_inside_a_surface_is_that_surface_colour() {
        // The top rows have no depth (the sensor's range ran out there, open
        // to the border): their rays march coarse and stop where the grid's
        // estimate (a running maximum over each cell) says they are
        // absorbed, often before the field has taken all of their light.
        let size = 48;
        let mut views = plane_views(6, size, true);
        for view in &mut views {
            view.depth.as_mut().unwrap()[..16 * size as usize].fill(0.0);
        }
        let (field_cfg, mut train_cfg) = small_config(5);
        // The grid holds such an estimate: dense over the plane's cells, and
        // it is not refreshed.
        train_cfg.occupancy_every = u64::MAX / 2;
        let res = 64;
        let plane_cell = (0.6 * res as f32) as usize;
        let density: Vec<f32> = (0..res * res * res)
            .map(|c| if c / (res * res) == plane_cell { 4000.0 } else { 0.1 })
            .collect();
        let grid = OccupancyGrid::from_saved(res, density, vec![0; (res * res * res).div_ceil(64)]).unwrap();
        let field = Field::new(field_cfg, &mut Rng::new(5, 0));
        let bright = [0.9; 3];
        let mut trainer = Trainer::new(field, grid, train_cfg.clone(), bright);
        trainer.learn_environment();
        for s in 0..300 {
            trainer.step(&views, s as f32 / 300.0);
        }
        let opts = trainer.render_options(&colour_options(&train_cfg));
        let view = &views[1];
        let pixels: Vec<(f32, f32)> = (2..14)
            .flat_map(|v| (4..44).map(move |u| (u as f32, v as f32)))
            .collect();
        let out = render_pixels(&trainer.field, &OccupancyGrid::full(res), &opts, &view.camera, &pixels);
        let wanted = pixels.iter().map(|&(u, v)| {
            let p = 3 * (v as usize * size as usize + u as usize);
            &view.rgb[p..p + 3]
        });
        let error = mean_colour_error(&out, wanted);
        let env = trainer
            .environment
            .as_ref()
            .unwrap()
            .environment
            .colour(view.camera.ray(24.0, 8.0).0.dir);
        // 0.013 and 0.87-0.89 when this was written; with the environment
        // behind every stopped ray, 0.25 and green at 0.61.
        assert!(error < 0.05, "mean colour error {error} where the plane has no depth");
        assert!(
            env.iter().all(|c| (c - bright[0]).abs() < 0.05),
            "the environment behind the plane learnt its colour: {env:?}"
        );
    }

    #[test]
    fn distortion_gradient_matches_finite_differences_and_spread_weight_costs_more() {
        let segs: Vec<Segment> = (0..12)
            .map(|i| Segment {
                t: 0.1 + 0.02 * i as f32 + 0.003 * (i % 3) as f32,
                dt: 0.02,
            })
            .collect();
        let weights: Vec<f32> = (0..12).map(|i| 0.02 + 0.05 * ((i as f32) * 1.3).sin().abs()).collect();
        let mut grad = vec![0.0f32; 12];
        let loss = distortion(&segs, &weights, 0.5, &mut grad);
        for k in 0..12 {
            let h = 1e-3;
            let mut up = weights.clone();
            up[k] += h;
            let mut down = weights.clone();
            down[k] -= h;
            let mut scratch = vec![0.0f32; 12];
            let numeric =
                (distortion(&segs, &up, 0.5, &mut scratch) - distortion(&segs, &down, 0.5, &mut scratch)) / (2.0 * h);
            assert!(
                (numeric - grad[k]).abs() < 2e-3 * (1.0 + numeric.abs()),
                "weight {k}: {numeric} vs {}",
                grad[k]
            );
        }
        // The same total weight in one sample costs far less than spread along the ray.
        let total: f32 = weights.iter().sum();
        let mut one = vec![0.0f32; 12];
        one[6] = total;
        let concentrated = distortion(&segs, &one, 0.5, &mut [0.0; 12]);
        assert!(concentrated < 0.2 * loss, "{concentrated} vs spread {loss}");
    }

    #[test]
    fn no_return_term_is_the_light_reaching_the_first_measured_surface() {
        let measured = measured_plane();
        // A ray along +z through x = y = 0.5, samples every 0.01 from z = 0.1.
        let positions: Vec<[f32; 3]> = (0..80).map(|i| [0.5, 0.5, 0.1 + 0.01 * i as f32]).collect();
        let first = positions.iter().position(|&p| measured.contains(p)).unwrap();
        // The plane's cell starts at z = 38/64, grown by one cell.
        assert!(
            (positions[first][2] - 37.0 / 64.0).abs() <= 0.01,
            "first measured sample at z {}",
            positions[first][2]
        );
        let mut rng = Rng::new(9, 0);
        let tau: Vec<f32> = (0..80).map(|_| 0.05 * rng.f32()).collect();
        let mut weights = vec![0.0; 80];
        let comp = weights_from_optical_depth(&tau, &mut weights);
        let mut grad_w = vec![0.0; 80];
        let lambda = 0.3;
        let loss = no_return_term(&positions, &weights, &measured, lambda, &mut grad_w);
        let through = (-tau[..first].iter().sum::<f32>()).exp();
        assert!(
            (loss - lambda * through).abs() < 1e-5,
            "loss {loss} vs {}",
            lambda * through
        );
        // Through the compositing: d loss / d tau_i = -lambda * through in front, 0 behind.
        let mut grad_tau = vec![0.0; 80];
        optical_depth_backward(&tau, &weights, &comp, &grad_w, 0.0, &mut grad_tau);
        for i in 0..80 {
            let want = if i < first { -lambda * through } else { 0.0 };
            assert!((grad_tau[i] - want).abs() < 1e-4, "tau {i}: {} vs {want}", grad_tau[i]);
        }
        // A ray that meets no measured surface costs nothing.
        let beside: Vec<[f32; 3]> = positions.iter().map(|p| [0.95, p[1], p[2]]).collect();
        let mut grad = vec![0.0; 80];
        assert_eq!(no_return_term(&beside, &weights, &measured, lambda, &mut grad), 0.0);
        assert!(grad.iter().all(|&g| g == 0.0));
    }

    /// Views of the textured plane z = 0.6 behind a striped square at z =
    /// 0.45 (x, y in [0.42, 0.58]) that the sensor cannot see: its pixels
    /// have no depth.
    fn views_with_an_unseen_patch(n: usize, size: u32) -> Vec<View> {
        let mut views = plane_views(n, size, true);
        let in_patch = |p: [f32; 3]| (0.42..0.58).contains(&p[0]) && (0.42..0.58).contains(&p[1]);
        for view in &mut views {
            let depth = view.depth.as_mut().unwrap();
            for v in 0..size {
                for u in 0..size {
                    let (ray, _) = view.camera.ray(u as f32, v as f32);
                    let p = ray.at((0.45 - ray.origin[2]) / ray.dir[2]);
                    if in_patch(p) {
                        let i = (v * size + u) as usize;
                        let stripe = ((p[0] * 60.0).floor() as i64) & 1 == 0;
                        view.rgb[3 * i..3 * i + 3].copy_from_slice(if stripe {
                            &[60, 200, 90]
                        } else {
                            &[235, 240, 235]
                        });
                        depth[i] = 0.0;
                    }
                }
            }
            view.no_return = crate::nerf::train::dataset::no_return_mask(depth, size, size, 1.0);
        }
        views
    }

    #[test]
    fn an_object_without_sensor_depth_is_placed_where_the_colour_puts_it() {
        let views = views_with_an_unseen_patch(8, 48);
        let cam = views[0].camera;
        let pixels: Vec<(f32, f32)> = (0..48 * 48)
            .filter(|&i| views[0].no_return.as_ref().unwrap()[i])
            .map(|i| ((i % 48) as f32, (i / 48) as f32))
            .collect();
        assert!(pixels.len() > 40, "{} patch pixels", pixels.len());
        // With the no-return term (0.1 in `small_config`); without it this
        // scene also fits (measured 0.015), so the term itself is tested by
        // `no_return_term_is_the_light_reaching_the_first_measured_surface`.
        let (field_cfg, train_cfg) = small_config(5);
        let mut rng = Rng::new(5, 0);
        let mut trainer = Trainer::new(
            Field::new(field_cfg, &mut rng),
            OccupancyGrid::full(64),
            train_cfg.clone(),
            [0.5; 3],
        );
        trainer.set_measured_surfaces(measured_plane());
        for s in 0..200 {
            trainer.step(&views, s as f32 / 200.0);
        }
        let opts = RenderOptions {
            color: false,
            rule: train_cfg.step,
            max_samples_per_ray: 4096,
            background: [0.5; 3],
            environment: None,
        };
        let out = render_pixels(&trainer.field, &trainer.occupancy, &opts, &cam, &pixels);
        let mut err: Vec<f32> = out
            .iter()
            .zip(&pixels)
            .map(|(o, &(u, v))| {
                let (ray, _) = cam.ray(u, v);
                o.depth_median
                    .map_or(1.0, |t| (t - (0.45 - ray.origin[2]) / ray.dir[2]).abs())
            })
            .collect();
        err.sort_by(f32::total_cmp);
        let median = err[err.len() / 2];
        // The patch is 0.15 in front of the plane behind it; measured 0.0097.
        assert!(median < 0.02, "median depth error {median} (local units)");
    }

    /// Where the centre pixel of `camera` meets the plane z = 0.6.
    fn centre_on_plane(camera: &LocalCamera) -> [f32; 3] {
        let (ray, _) = camera.ray(camera.cx, camera.cy);
        ray.at((0.6 - ray.origin[2]) / ray.dir[2])
    }

    #[test]
    fn a_camera_placed_wrongly_is_moved_back_while_the_field_trains() {
        let mut views = plane_views(8, 48, true);
        let truth: Vec<[f32; 3]> = views.iter().map(|v| centre_on_plane(&v.camera)).collect();
        // View 3 is told it stands 0.02 (about 1.7 px) off along x.
        views[3].camera.origin[0] += 0.02;
        let (field_cfg, train_cfg) = small_config(7);
        let mut rng = Rng::new(7, 0);
        let mut trainer = Trainer::new(
            Field::new(field_cfg.clone(), &mut rng),
            OccupancyGrid::full(64),
            train_cfg.clone(),
            [0.5; 3],
        );
        let levels = crate::nerf::field::hash_grid::HashGridConfig::from(field_cfg.grid).levels;
        trainer.learn_poses(PoseLearner::new(
            views.len(),
            1e-3,
            2e-4,
            levels,
            train_cfg.warmup_steps,
        ));
        let off = |views: &[View], i: usize| {
            let p = centre_on_plane(&views[i].camera);
            ((p[0] - truth[i][0]).powi(2) + (p[1] - truth[i][1]).powi(2)).sqrt()
        };
        let before = off(&views, 3);
        for s in 0..300 {
            trainer.step(&views, s as f32 / 300.0);
            if let Some(steps) = trainer.take_pose_steps() {
                for (view, st) in views.iter_mut().zip(&steps) {
                    let turn = nalgebra::Rotation3::new(nalgebra::Vector3::new(st[0], st[1], st[2]));
                    let turned = turn.matrix() * view.camera.rotation_matrix();
                    for i in 0..3 {
                        view.camera.origin[i] += st[3 + i] as f32;
                        for j in 0..3 {
                            view.camera.rotation[i][j] = turned[(i, j)] as f32;
                        }
                    }
                }
            }
        }
        let after = off(&views, 3);
        let others = (0..views.len())
            .filter(|&i| i != 3)
            .map(|i| off(&views, i))
            .fold(0.0, f32::max);
        eprintln!("view 3 off by {before} -> {after}; others at most {others}");
        assert!(after < 0.4 * before, "view 3 off by {before} -> {after}");
        assert!(others < 0.25 * before, "other views moved by up to {others}");
    }

    #[test]
    fn depth_supervised_training_recovers_a_plane() {
        let views = plane_views(6, 48, true);
        let (field_cfg, train_cfg) = small_config(5);
        let mut rng = Rng::new(5, 0);
        let field = Field::new(field_cfg, &mut rng);
        let mut trainer = Trainer::new(field, OccupancyGrid::full(64), train_cfg.clone(), [0.5; 3]);
        let mut first_loss = None;
        let mut last = StepStats::default();
        for s in 0..150 {
            last = trainer.step(&views, s as f32 / 150.0);
            first_loss.get_or_insert(last.loss);
        }
        assert!(
            last.loss < 0.3 * first_loss.unwrap(),
            "loss {} -> {}",
            first_loss.unwrap(),
            last.loss
        );
        assert_eq!(trainer.counters.skipped_batches, 0);
        // Every phase of a step is timed, and the field's passes are not
        // counted twice (the compositing share would then go negative).
        let p = last.phases;
        assert!(
            p.march > 0.0 && p.grid > 0.0 && p.mlp > 0.0 && p.composite > 0.0 && p.update > 0.0,
            "{p:?}"
        );
        let err = plane_depth_error(&trainer, &views, &train_cfg);
        eprintln!("normal learning rate: mean depth error {err}");
        assert!(err < 0.01, "mean depth error {err} (local units)");
    }

    /// Mean signed depth error (local units, positive = too far) of the
    /// trained plane seen from view 0.
    fn plane_depth_bias(trainer: &Trainer, views: &[View], train_cfg: &TrainConfig) -> f32 {
        let offsets = plane_depth_offsets(trainer, views, train_cfg, 2);
        offsets.iter().sum::<f32>() / offsets.len() as f32
    }

    #[test]
    fn depth_noise_wider_than_the_surface_window_does_not_push_surfaces_back() {
        // The plane measured with noise of twice the window: narrow windows
        // let the rays measured too far erode it from the front.
        let (field_cfg, train_cfg) = small_config(6);
        let sigma = 2.0 * train_cfg.surface_window;
        let mut views = plane_views(6, 48, true);
        let mut rng = Rng::new(6, 99);
        for view in &mut views {
            for z in view.depth.as_mut().unwrap() {
                *z += sigma * rng.normal() as f32;
            }
        }
        let bias = |noise: Option<DepthNoise>| {
            let mut rng = Rng::new(6, 0);
            let field = Field::new(field_cfg.clone(), &mut rng);
            let mut trainer = Trainer::new(field, OccupancyGrid::full(64), train_cfg.clone(), [0.5; 3]);
            if let Some(noise) = noise {
                trainer.set_depth_noise(noise);
            }
            for s in 0..200 {
                trainer.step(&views, s as f32 / 200.0);
            }
            plane_depth_bias(&trainer, &views, &train_cfg)
        };
        let noise = DepthNoise {
            depths: vec![0.0, 1.0],
            sigmas: vec![sigma, sigma],
        };
        let (narrow, widened) = (bias(None), bias(Some(noise)));
        eprintln!("plane pushed back by {narrow} with the scene's window, {widened} with the noise's");
        // Measured: 0.32 and 0.18 of the noise (seed 6).
        assert!(
            narrow > 0.25 * sigma,
            "narrow windows pushed the plane back by only {narrow}"
        );
        assert!(widened.abs() < 0.75 * narrow, "narrow {narrow}, widened {widened}");
    }

    #[test]
    fn detail_draws_start_after_the_coarse_geometry() {
        assert_eq!(detail_share(0.0), 0.0);
        assert_eq!(detail_share(DETAIL_FROM - 1e-3), 0.0);
        assert_eq!(detail_share(DETAIL_FROM), DETAIL_SHARE);
        assert_eq!(detail_share(1.0), DETAIL_SHARE);
    }

    #[test]
    fn learning_rate_1000x_too_high_is_caught_and_the_plane_still_fits() {
        let views = plane_views(6, 48, true);
        let (field_cfg, mut train_cfg) = small_config(5);
        train_cfg.learning_rate *= 1000.0;
        let mut rng = Rng::new(5, 0);
        let field = Field::new(field_cfg, &mut rng);
        let mut trainer = Trainer::new(field, OccupancyGrid::full(64), train_cfg.clone(), [0.5; 3]);
        let mut losses = Vec::new();
        for s in 0..150 {
            let stats = trainer.step(&views, s as f32 / 150.0);
            assert!(
                stats.skipped || stats.relative_update <= MAX_RELATIVE_UPDATE,
                "step {s}: {stats:?}"
            );
            if !stats.skipped {
                losses.push(stats.loss);
            }
        }
        let skipped = trainer.counters.skipped_batches;
        assert!(skipped > 0 && skipped < 30, "{skipped} of 150 batches skipped");
        let f = &trainer.field;
        assert!(f
            .grid
            .params
            .iter()
            .chain(&f.density.params)
            .chain(&f.color.params)
            .all(|v| v.is_finite()));
        let (first, last) = (losses[0], losses[losses.len() - 1]);
        // Measured 0.0087 (the normal learning rate: 0.0054).
        let err = plane_depth_error(&trainer, &views, &train_cfg);
        eprintln!("1000x: {skipped} skipped, loss {first} -> {last}, mean depth error {err}");
        assert!(last < 0.5 * first, "loss {first} -> {last}");
        assert!(err < 0.015, "mean depth error {err} (local units)");
    }
}
