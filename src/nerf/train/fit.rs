//! `fit`: normalise the scene, build views, seed the occupancy grid from
//! sensor depth, train within a time or step budget while measuring
//! held-out accuracy against training time, and produce the model and the
//! fit report. Writes a resumable checkpoint when asked ([`resume`]
//! continues from one). Reports progress through a callback; never prints.

use crate::nerf::appearance;
use crate::nerf::field::Field;
use crate::nerf::model_file::{Model, ModelHeader};
use crate::nerf::occupancy::measured::MeasuredSurfaces;
use crate::nerf::occupancy::{CameraSpace, OccupancyGrid};
use crate::nerf::render::rays::RenderOptions;
use crate::nerf::train::checkpoint::{self, Checkpoint, CheckpointError, FitIdentity, FitProgress};
use crate::nerf::train::dataset::{self, Dataset};
use crate::nerf::train::photometric::{align_to_field, PhotometricOptions};
use crate::nerf::train::pose_learning::PoseLearner;
use crate::nerf::train::report::{
    AppearanceReport, CurvePoint, FitReport, PoseAlignmentReport, PoseLearningReport, PoseRefinementReport,
    PoseScaleReport, Timings,
};
use crate::nerf::train::settings::{settings_for_scene, FitSettings, NerfSettings, SettingError};
use crate::nerf::train::step::{StepStats, Trainer};
use crate::nerf::train::validation::{validate, Validation};
use crate::poses::{
    estimate_pose_scale, normalize, refine_poses, scale_poses, scene_bounds, BoundsOptions, GeometryError,
    NormalizeOptions, PoseRefinement, RefineOptions, SceneTransform,
};
use crate::rng::Rng;
use crate::scan::{depth_noise, ColourBorder, DepthNoise, Scan};
use nalgebra::{IsometryMatrix3, Rotation3, Translation3, Vector3};
use std::path::PathBuf;
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::Instant;

/// Budget and knobs of one fit.
#[derive(Clone, Debug)]
pub struct FitOptions {
    /// Wall-time budget of the whole fit, seconds: preparation, training,
    /// evaluation and checkpoints all fit inside it, counted from `started`.
    pub time: Option<f64>,
    /// Step budget.
    pub steps: Option<u64>,
    /// What shapes training (flags, defaults, resume check).
    pub settings: FitSettings,
    /// Training seconds between held-out evaluations (and checkpoints).
    pub eval_interval_s: f64,
    /// Longer side of the evaluation pixel grid.
    pub eval_max_side: u32,
    /// When the command began (loading the scan counts too); `None` = when
    /// `fit` is called.
    pub started: Option<Instant>,
    /// Write a resumable checkpoint here at every evaluation point and at the end.
    pub checkpoint: Option<PathBuf>,
}

impl Default for FitOptions {
    fn default() -> Self {
        FitOptions {
            time: None,
            steps: None,
            settings: FitSettings::default(),
            eval_interval_s: 10.0,
            eval_max_side: 160,
            checkpoint: None,
            started: None,
        }
    }
}

/// Training seconds between evaluations are at least this multiple of the
/// last evaluation's cost (bounds its overhead to 25 % of training).
const EVAL_COST_RATIO: f64 = 4.0;
/// ... but never more than this many intervals apart (an untrained model
/// renders slowly; the curve still needs its points).
const MAX_EVAL_SPACING: f64 = 3.0;

/// With a time budget, each periodic held-out evaluation renders as many
/// pixels as fit in this share of the training time between evaluations,
/// and the final one as many as fit in `FINAL_EVAL_BUDGET_SHARE` of the
/// budget: a short fit must not spend its time rendering an untrained model.
const EVAL_INTERVAL_SHARE: f64 = 0.05;
const FINAL_EVAL_BUDGET_SHARE: f64 = 0.04;
/// A time budget's curve gets about this many points (a long budget spaces
/// its evaluations out; each costs the same).
const CURVE_POINTS: f64 = 12.0;
/// The first periodic evaluation's pixel grid (longer side), before its
/// cost is known; later ones are sized from what it cost.
const FIRST_EVAL_SIDE: u32 = 64;
/// Fewest pixels along the longer side of an evaluation grid.
const MIN_EVAL_SIDE: u32 = 24;
/// Default training time when neither `time` nor `steps` is given.
pub const DEFAULT_TIME_S: f64 = 120.0;

impl FitOptions {
    /// Refuse settings no fit can train with, naming the setting.
    pub fn validate(&self) -> Result<(), FitError> {
        self.settings.validate()?;
        let bad = |flag: &'static str, reason: String| Err(FitError::Setting(SettingError { flag, reason }));
        if let Some(t) = self.time {
            if !(t.is_finite() && t > 0.0) {
                return bad("--time", format!("must be a positive number of seconds, got {t}"));
            }
        }
        if self.steps == Some(0) {
            return bad("--steps", "must be at least 1".into());
        }
        if !(self.eval_interval_s.is_finite() && self.eval_interval_s > 0.0) {
            return bad(
                "eval_interval_s",
                format!("must be a positive number of seconds, got {}", self.eval_interval_s),
            );
        }
        Ok(())
    }
}

/// What the caller hears during a fit.
pub enum FitEvent<'a> {
    /// The camera positions were scaled to metres (before anything else).
    PosesScaled(&'a PoseScaleReport),
    /// The poses were aligned to the depth.
    PosesRefined(&'a PoseRefinementReport),
    /// The frames' images were aligned to the field (part-way through
    /// training, and at its end).
    PosesAligned(&'a PoseAlignmentReport),
    /// What learning the poses with the field moved the training frames by.
    PosesLearnt(&'a PoseLearningReport),
    /// Set-up done; training starts.
    Prepared {
        train_views: usize,
        holdout_views: usize,
        param_count: usize,
        occupied_fraction: f64,
        /// The depth sensor's noise as measured on the scan (metres).
        depth_noise: Option<&'a DepthNoise>,
        /// Dead lines at the edges of the first frame's colour image.
        colour_border: ColourBorder,
    },
    /// A step finished; `progress` in [0, 1].
    Step {
        step: u64,
        stats: &'a StepStats,
        train_seconds: f64,
        progress: f64,
    },
    /// A held-out evaluation finished.
    Eval(&'a CurvePoint),
    /// A checkpoint was written after this step.
    CheckpointSaved { step: u64 },
    /// Writing a checkpoint failed; training goes on.
    CheckpointFailed(&'a CheckpointError),
}

/// A trained model and its report.
pub struct FitOutcome {
    pub model: Model,
    pub report: FitReport,
}

/// Why fitting could not start.
#[derive(Debug, thiserror::Error)]
pub enum FitError {
    #[error("cannot place the scene: {0}")]
    Geometry(#[from] GeometryError),
    #[error("the scan has no frame left for training")]
    NoTrainingFrames,
    #[error(transparent)]
    Setting(#[from] SettingError),
    #[error(transparent)]
    Checkpoint(#[from] CheckpointError),
}

/// The dead colour border of the scan's first frame (train or held out).
fn scan_colour_border(data: &Dataset) -> ColourBorder {
    data.train
        .first()
        .or(data.holdout.first())
        .map(|v| v.colour_border)
        .unwrap_or_default()
}

/// Metres covered by one pixel at the typical viewing distance: the median
/// sensor depth, or without depth the median camera distance to the scene
/// centre, over the mean focal length.
pub fn pixel_footprint(scan: &Scan, bounds: &crate::poses::SceneBounds) -> f64 {
    let focal = mean_focal(scan);
    let distance = if bounds.stats.depth_median > 0.0 {
        bounds.stats.depth_median
    } else {
        let centre = bounds.aabb.center();
        let mut d: Vec<f64> = bounds.cameras.iter().map(|c| nalgebra::distance(c, &centre)).collect();
        d.sort_by(|a, b| a.total_cmp(b));
        d.get(d.len() / 2).copied().unwrap_or(1.0)
    };
    distance / focal.max(1e-9)
}

/// Mean focal length of the frames, in pixels.
fn mean_focal(scan: &Scan) -> f64 {
    let sum: f64 = scan
        .frames
        .iter()
        .map(|f| 0.5 * (f.intrinsics.fx + f.intrinsics.fy))
        .sum();
    sum / scan.frames.len().max(1) as f64
}

/// Largest step of a camera learnt with the field per training step, in
/// pixels it moves the scene at the typical viewing distance (rotation
/// about the camera centre or translation).
const POSE_STEP_PX: f64 = 0.05;

/// Everything a fit sets up before training: views, settings and a trainer at step 0.
pub struct Prepared {
    pub data: Dataset,
    /// The depth sensor's noise (metres), when the scan's depth shows it.
    pub depth_noise: Option<DepthNoise>,
    pub settings: NerfSettings,
    pub transform: SceneTransform,
    pub metres_per_unit: f64,
    /// Metres one pixel covers at the typical viewing distance.
    pub pixel_footprint_m: f64,
    pub trainer: Trainer,
    pub timings: Timings,
}

/// The longer side of an evaluation pixel grid whose rendering takes about
/// `target_s`, given that a grid of `side` took `render_s` (rendering time
/// grows with the pixel count, the side squared); within
/// [`MIN_EVAL_SIDE`, `max_side`].
fn evaluation_side(side: u32, render_s: f64, target_s: f64, max_side: u32) -> u32 {
    if !(render_s > 0.0 && target_s >= 0.0) {
        return side;
    }
    let scaled = side as f64 * (target_s / render_s).sqrt();
    (scaled.round() as u32).clamp(MIN_EVAL_SIDE.min(max_side), max_side)
}

/// Normalise the scene, build the views, seed the occupancy grid from
/// sensor depth and build the trainer, as [`fit`] does before training.
pub fn prepare(scan: &Scan, opts: &FitOptions) -> Result<Prepared, FitError> {
    prepare_with(scan, opts, true)
}

fn prepare_with(scan: &Scan, opts: &FitOptions, seed_occupancy: bool) -> Result<Prepared, FitError> {
    opts.validate()?;
    let mut timings = Timings::default();
    let t = Instant::now();
    let bounds = scene_bounds(scan, &BoundsOptions::default())?;
    let norm = normalize(&bounds, &NormalizeOptions::default())?;
    let transform = norm.transform;
    let metres_per_unit = 1.0 / transform.scale();
    timings.bounds_s = t.elapsed().as_secs_f64();

    let t = Instant::now();
    let mut data: Dataset = dataset::build(scan, &transform, opts.settings.holdout_every);
    if opts.settings.unseen_objects {
        dataset::mark_no_return(&mut data, scan);
    }
    if data.train.is_empty() {
        return Err(FitError::NoTrainingFrames);
    }
    timings.views_s = t.elapsed().as_secs_f64();

    let footprint = pixel_footprint(scan, &bounds);
    let settings = settings_for_scene(metres_per_unit, footprint, &opts.settings);
    let pose_learner = (opts.settings.refine_poses && opts.settings.learn_poses).then(|| {
        PoseLearner::new(
            data.train.len(),
            POSE_STEP_PX / mean_focal(scan),
            POSE_STEP_PX * footprint * transform.scale(),
            settings.field.grid.levels,
            settings.train.warmup_steps,
        )
    });
    let t = Instant::now();
    let mut occupancy = OccupancyGrid::full(settings.occupancy_resolution);
    if seed_occupancy {
        carve_seen_space(&mut occupancy, &data);
    }
    timings.occupancy_seed_s = t.elapsed().as_secs_f64();

    let mut rng = Rng::new(opts.settings.seed, 0);
    let field = Field::new(settings.field.clone(), &mut rng);
    let mut trainer = Trainer::new(field, occupancy, settings.train.clone(), data.background);
    if opts.settings.per_frame_appearance {
        trainer.learn_appearance(data.train.len());
    }
    trainer.learn_environment();
    if let Some(learner) = pose_learner {
        trainer.learn_poses(learner);
    }
    // The training frames' depth only, as everywhere in the fit.
    let noise = depth_noise(data.train_frames.iter().map(|&i| &scan.frames[i]));
    if let Some(noise) = &noise {
        trainer.set_depth_noise(noise.scaled(transform.scale() as f32));
    }
    if opts.settings.unseen_objects {
        set_measured_surfaces(&mut trainer, &data, &settings);
    }
    Ok(Prepared {
        data,
        depth_noise: noise,
        settings,
        transform,
        metres_per_unit,
        pixel_footprint_m: footprint,
        trainer,
        timings,
    })
}

/// Shares of the budget at which the training frames' images may be aligned
/// to the field. The first pass comes once the field is sharp enough to
/// align to, with time left to train on the corrected poses. Each further
/// one aligns to a field trained on better poses (alternating alignment and
/// training approaches a joint optimisation of both), but it costs a few
/// seconds of training: it runs only while the pass before still moved
/// many frames (`worth_another_pass`).
const POSE_ALIGN_AT: [f64; 4] = [0.45, 0.60, 0.75, 0.90];
/// A pass that moved at least this share of the frames it aligned by more
/// than `MOVED_PX` pixels calls for another. Measured share of frames moved
/// by over a pixel at the first pass: 0.31 and 0.48 on SLAM-like tabletop
/// and room scans (1 cm, 0.5 degree per frame and 2 cm drift), 0.02 to 0.14
/// on the realistic fixtures and the real cabinet scan.
const ANOTHER_PASS_SHARE: f64 = 0.25;
/// A correction below a pixel is within what aligning to the field resolves.
const MOVED_PX: f64 = 1.0;

/// Largest camera displacement an image alignment may make: twice what
/// aligning to the depth moved nine frames in ten by, the scan's own measure
/// of its pose error (unbounded when the depth corrected no frame). On a
/// realistic tabletop (1.5 mm pose error) a field barely past its warm-up
/// (`fit --time 60`) otherwise moved frames by up to 31 mm.
fn plausible_correction_m(refinement: Option<&PoseRefinement>) -> f64 {
    typical_correction(refinement).map_or(f64::INFINITY, |(_, translation_m)| 2.0 * translation_m)
}

/// What aligning to the depth moved nine frames in ten by, in rotation
/// (radians) and translation (metres); `None` when it corrected no frame.
fn typical_correction(refinement: Option<&PoseRefinement>) -> Option<(f64, f64)> {
    let refined: Vec<_> = refinement?.frames.iter().filter(|f| f.refined).collect();
    if refined.is_empty() {
        return None;
    }
    let p90 = |mut v: Vec<f64>| {
        v.sort_by(f64::total_cmp);
        v[(v.len() - 1) * 9 / 10]
    };
    Some((
        p90(refined.iter().map(|f| f.rotation_deg.to_radians()).collect()),
        p90(refined.iter().map(|f| f.translation_m).collect()),
    ))
}

/// Steps in which a camera learnt with the field may move by the scan's
/// typical pose error at the full learning rate.
const POSE_ERROR_STEPS: f64 = 100.0;

/// Share of the training time spent: `trained` seconds so far, `remaining`
/// seconds of the budget still free for training (1 once none is left).
fn training_time_share(trained: f64, remaining: f64) -> f64 {
    if remaining <= 0.0 {
        1.0
    } else {
        (trained / (trained + remaining)).clamp(0.0, 1.0)
    }
}

/// Whether the training frames are to be aligned to the field now, after
/// the passes `done`: a pass is due at `progress` (share of the training
/// time), the field has trained through the warm-up and, since the last
/// pass, half a warm-up more, and the last pass still moved many frames.
fn pose_alignment_due(done: &[PoseAlignmentReport], progress: f64, steps: u64, warmup: u64) -> bool {
    let passes_due = POSE_ALIGN_AT.iter().filter(|&&at| progress >= at).count();
    if done.len() >= passes_due || steps < warmup {
        return false;
    }
    match done.last() {
        None => true,
        Some(last) => steps >= last.at_step + warmup / 2 && worth_another_pass(last),
    }
}

fn worth_another_pass(pass: &PoseAlignmentReport) -> bool {
    let moved = pass
        .frames
        .iter()
        .filter(|f| f.refined && f.shift_px > MOVED_PX)
        .count();
    moved as f64 >= ANOTHER_PASS_SHARE * pass.frames_aligned.max(1) as f64
}

/// Align the images of `frames` to the field (`train::photometric`), move
/// the scan's poses and the views' cameras to the result, and record the
/// pass (its report, time and the poses training goes on with) in `state`.
#[allow(clippy::too_many_arguments)]
fn align_poses_to_field(
    scan: &mut Scan,
    data: &mut Dataset,
    trainer: &mut Trainer,
    transform: &SceneTransform,
    render: &RenderOptions,
    frames: &[usize],
    options: &PhotometricOptions,
    state: &mut FitProgress,
    on_event: &mut dyn FnMut(FitEvent),
) {
    let t = Instant::now();
    let grid = trainer.rendering_occupancy();
    let (maps, lens) = match &trainer.appearance {
        Some(learner) => (
            appearance::per_frame(&data.train_frames, &learner.maps(), scan.frames.len()),
            learner.lens,
        ),
        None => (vec![appearance::IDENTITY; scan.frames.len()], appearance::NO_VIGNETTING),
    };
    let alignment = align_to_field(
        &trainer.field,
        &grid,
        render,
        transform,
        &scan.frames,
        &maps,
        &lens,
        frames,
        options,
    );
    let report = PoseAlignmentReport::new(trainer.counters.steps, &alignment);
    if report.frames_refined > 0 {
        scan.set_poses(&alignment.camera_to_world);
        set_view_cameras(scan, data, transform);
        state.aligned_poses = scan.frames.iter().map(|f| column_major(&f.camera_to_world)).collect();
    }
    on_event(FitEvent::PosesAligned(&report));
    state.pose_alignment.push(report);
    state.timings.pose_align_s += t.elapsed().as_secs_f64();
}

/// Carve the space the training views' depth saw free, through their
/// poses as they stand, and the space no training camera sees.
fn carve_seen_space(occupancy: &mut OccupancyGrid, data: &Dataset) {
    let rays = dataset::depth_rays(&data.train, 4);
    // Every frame's camera stood in free space, the held-out ones too
    // (only their positions: their depth stays out of the fit). A
    // floater there blinds that frame's whole view.
    let mut cameras = dataset::camera_spaces(&data.train);
    cameras.extend(data.holdout.iter().map(|v| CameraSpace {
        origin: v.camera.origin,
        free_distance: 0.0,
    }));
    let no_return = dataset::no_return_rays(&data.train, 4);
    occupancy.seed_from_depth_and_no_return(&rays, &no_return, &cameras);
    occupancy.carve_unseen(&data.train.iter().map(|v| v.camera).collect::<Vec<_>>());
}

/// Where the training views' depth measured surfaces, through their poses
/// as they stand (the no-return term's evidence).
fn set_measured_surfaces(trainer: &mut Trainer, data: &Dataset, settings: &NerfSettings) {
    let measured = dataset::depth_rays(&data.train, 2);
    if !measured.is_empty() {
        let res = settings.field.grid.finest_resolution as usize / 2;
        trainer.set_measured_surfaces(MeasuredSurfaces::from_depth_rays(&measured, res));
    }
}

/// After a pass moved the training frames, read their depth again through
/// the corrected poses: free space carved through the poses as captured
/// stays empty for good, and where those were off sideways it holds parts
/// of objects the sensor does not see (glass), which rays from the other
/// frames then never sample. SLAM-like tabletop seed 2
/// (`fit --steps 900`): the object without depth labelled 0.72 with the
/// first carving kept, 0.975 carved again (0.976 fitted from the start
/// with the poses the passes found).
fn carve_again(trainer: &mut Trainer, data: &Dataset, settings: &NerfSettings, unseen_objects: bool) {
    trainer.occupancy.forget_carving();
    carve_seen_space(&mut trainer.occupancy, data);
    if unseen_objects {
        set_measured_surfaces(trainer, data, settings);
    }
}

/// Whether a pass moved some frame's surface points far enough to redo the
/// carving: half an occupancy cell. Since no-return pixels vote against
/// carving, redoing it after smaller corrections measured no better
/// (`fit --steps 900 --no-colour-align`, SLAM-like tabletop seed 2: 0.9743
/// redone after every pass, 0.9759 not; the real cabinet 24.91 against
/// 25.03 dB), and it costs about 2 s a pass: 6 s of the cabinet's 60 s
/// budget, whose passes moved frames by a quarter of its 5.7 cm cells.
fn moves_carving(pass: &PoseAlignmentReport, pixel_footprint_m: f64, cell_m: f64) -> bool {
    pass.frames
        .iter()
        .any(|f| f.refined && f.shift_px * pixel_footprint_m >= 0.5 * cell_m)
}

/// Rebuild every view's camera from its frame's pose.
fn set_view_cameras(scan: &Scan, data: &mut Dataset, transform: &SceneTransform) {
    let train = data.train.iter_mut().zip(&data.train_frames);
    for (view, &i) in train.chain(data.holdout.iter_mut().zip(&data.holdout_frames)) {
        view.camera = dataset::local_camera(&scan.frames[i], transform);
    }
}

/// Moves each training view's camera by its learnt step (rotation about
/// the camera centre, translation; local units), in the scan and the view.
fn move_training_cameras(scan: &mut Scan, data: &mut Dataset, transform: &SceneTransform, steps: &[[f64; 6]]) {
    for ((view, &i), s) in data.train.iter_mut().zip(&data.train_frames).zip(steps) {
        if s.iter().all(|&x| x == 0.0) {
            continue;
        }
        let frame = &mut scan.frames[i];
        let local = transform.world_to_local_pose(&frame.camera_to_world);
        let turn = Rotation3::new(Vector3::new(s[0], s[1], s[2]));
        let moved = IsometryMatrix3::from_parts(
            Translation3::from(local.translation.vector + Vector3::new(s[3], s[4], s[5])),
            turn * local.rotation,
        );
        frame.camera_to_world = transform.local_to_world_pose(&moved);
        view.camera = dataset::local_camera(frame, transform);
    }
}

/// A pose as the column-major 4x4 matrix FORMATS.md stores.
fn column_major(pose: &IsometryMatrix3<f64>) -> [f64; 16] {
    let m = pose.to_homogeneous();
    std::array::from_fn(|i| m[i])
}

fn from_column_major(m: &[f64; 16]) -> IsometryMatrix3<f64> {
    crate::scan::isometry(&nalgebra::Matrix4::from_column_slice(m))
}

/// Scale the scan's camera positions: by `forced`, else by the estimate
/// from the depth when the poses are clearly not metric. `None`: unchanged.
fn apply_pose_scale(scan: &mut Scan, forced: Option<f64>) -> Result<Option<PoseScaleReport>, FitError> {
    let (applied, verdict) = match forced {
        Some(1.0) => return Ok(None),
        Some(s) => (s, format!("camera positions multiplied by {s} (--pose-scale)")),
        None => match estimate_pose_scale(scan)? {
            Some(e) if e.is_determined() && !e.looks_metric() => (e.scale, e.verdict()),
            _ => return Ok(None),
        },
    };
    scan.set_poses(&scale_poses(&scan.poses(), applied));
    Ok(Some(PoseScaleReport {
        applied,
        forced: forced.is_some(),
        verdict,
    }))
}

/// Fit a model to `scan`. `stop` ends training early (Ctrl-C) with a usable
/// model. With `opts.settings.refine_poses` the scan's poses are first aligned to its
/// depth, in place; the model records them (`Model::apply_fitted_poses`).
pub fn fit(
    scan: &mut Scan,
    opts: &FitOptions,
    stop: &AtomicBool,
    on_event: &mut dyn FnMut(FitEvent),
) -> Result<FitOutcome, FitError> {
    run(scan, opts, None, stop, on_event)
}

/// Continue the fit saved in `from`: same scan and settings (checked), the
/// budget counts the steps and seconds already trained (without one in
/// `opts`, the checkpoint's budget), and the curve goes on.
pub fn resume(
    scan: &mut Scan,
    opts: &FitOptions,
    from: Checkpoint,
    stop: &AtomicBool,
    on_event: &mut dyn FnMut(FitEvent),
) -> Result<FitOutcome, FitError> {
    run(scan, opts, Some(from), stop, on_event)
}

fn run(
    scan: &mut Scan,
    opts: &FitOptions,
    from: Option<Checkpoint>,
    stop: &AtomicBool,
    on_event: &mut dyn FnMut(FitEvent),
) -> Result<FitOutcome, FitError> {
    let started = opts.started.unwrap_or_else(Instant::now);
    crate::nerf::field::simd::flush_subnormals_on_all_threads();
    // Models and checkpoints name the scan as captured.
    let captured_fingerprint = crate::scan::fingerprint::scan_fingerprint(scan);
    let t = Instant::now();
    let scale_report = apply_pose_scale(scan, opts.settings.pose_scale)?;
    if let Some(r) = &scale_report {
        on_event(FitEvent::PosesScaled(r));
    }
    let refinement = if opts.settings.refine_poses {
        let options = RefineOptions {
            align_colour: opts.settings.colour_align,
            ..RefineOptions::default()
        };
        refine_poses(scan, &options)?
    } else {
        None
    };
    if let Some(r) = &refinement {
        scan.set_poses(&r.camera_to_world);
    }
    let refinement_report = refinement.as_ref().map(PoseRefinementReport::new);
    if let Some(r) = &refinement_report {
        on_event(FitEvent::PosesRefined(r));
    }
    let alignment_options = PhotometricOptions {
        max_translation_m: plausible_correction_m(refinement.as_ref()),
        ..PhotometricOptions::default()
    };
    let pose_refine_s = t.elapsed().as_secs_f64();
    // Frames aligned to each other by colour agree to a tenth of a pixel;
    // aligned to a field still blurred by training they would drift to a
    // third of one (SLAM-like tabletop, seed 4: 0.05 -> 0.37 px).
    let align_to_field = opts.settings.refine_poses && !refinement.as_ref().is_some_and(|r| r.colour_aligned);
    let scaled = scale_report.is_some();
    let Prepared {
        mut data,
        depth_noise,
        settings,
        transform,
        metres_per_unit,
        pixel_footprint_m,
        mut trainer,
        mut timings,
    } = prepare_with(scan, opts, from.is_none())?;
    timings.pose_refine_s = pose_refine_s;
    // With depth, the cameras learn at a pace set by the scan's own pose
    // error, as aligning to the depth measured it.
    if let (Some(learner), Some((rotation_rad, translation_m))) =
        (trainer.poses.as_mut(), typical_correction(refinement.as_ref()))
    {
        learner.set_rates(
            rotation_rad / POSE_ERROR_STEPS,
            translation_m * transform.scale() / POSE_ERROR_STEPS,
        );
    }
    let mut identity = FitIdentity::new(scan, opts, &settings);
    identity.scan_fingerprint = captured_fingerprint;
    let mut state = match from {
        None => FitProgress {
            timings,
            ..FitProgress::default()
        },
        Some(ckpt) => {
            ckpt.check(&identity)?;
            if opts.time.is_none() && opts.steps.is_none() {
                (identity.time, identity.steps) = (ckpt.header.identity.time, ckpt.header.identity.steps);
            }
            let mut state = ckpt.restore(&mut trainer)?;
            state.resumed_from.push(trainer.counters.steps);
            state.interrupted = false;
            state.timings.pose_refine_s += timings.pose_refine_s;
            state.timings.bounds_s += timings.bounds_s;
            state.timings.views_s += timings.views_s;
            state
        }
    };
    let param_count = trainer.field.param_count();
    on_event(FitEvent::Prepared {
        train_views: data.train.len(),
        holdout_views: data.holdout.len(),
        param_count,
        occupied_fraction: trainer.occupancy.occupied_fraction(),
        depth_noise: depth_noise.as_ref(),
        colour_border: scan_colour_border(&data),
    });

    let time_budget = match (identity.time, identity.steps) {
        (None, None) => Some(DEFAULT_TIME_S),
        (time, _) => time,
    };
    let step_budget = identity.steps;
    let render_opts = RenderOptions {
        color: true,
        rule: settings.render_step,
        max_samples_per_ray: 4096,
        background: data.background,
        environment: None,
    };
    // Wall seconds of earlier runs (a resumed fit), then of this one.
    let earlier_wall = state.timings.wall_s.max(state.train_seconds);
    let spent = || earlier_wall + started.elapsed().as_secs_f64();
    // What finishing costs (final evaluation, checkpoint, model and report):
    // training stops early enough for it to fit in the budget.
    let mut finish_cost = 0.0f64;
    let interval = if opts.eval_interval_s.is_finite() {
        opts.eval_interval_s.max(1e-3)
    } else {
        DEFAULT_TIME_S
    };
    // A short budget evaluates sooner: the curve gets its points, and the
    // first evaluation tells what finishing will cost; a long one later.
    let interval = time_budget.map_or(interval, |limit| interval.max(limit / CURVE_POINTS).min(limit / 4.0));
    let mut next_eval = ((state.train_seconds / interval).floor() + 1.0) * interval;
    let frame_count = scan.frames.len();
    // Pixel grid of the evaluations: sized to the time budget (see
    // EVAL_INTERVAL_SHARE); a step budget always renders the full grid.
    let mut eval_side = match time_budget {
        Some(_) => opts.eval_max_side.min(FIRST_EVAL_SIDE),
        None => opts.eval_max_side,
    };
    let side_for = |side: u32, render_s: f64, target_s: f64| match time_budget {
        Some(_) => evaluation_side(side, render_s, target_s, opts.eval_max_side),
        None => side,
    };
    let final_eval_s = time_budget.map_or(0.0, |limit| FINAL_EVAL_BUDGET_SHARE * limit);
    let mut last_render: Option<(u32, f64)> = None;
    // The rendering grid of the latest evaluation: the model's, when no
    // step came after it.
    let mut latest_grid: Option<(u64, OccupancyGrid)> = None;
    let evaluate_now = |trainer: &mut Trainer,
                        state: &mut FitProgress,
                        data: &Dataset,
                        side: u32|
     -> Option<(CurvePoint, f64, OccupancyGrid)> {
        if data.holdout.is_empty() {
            return None;
        }
        let wall = spent();
        let t = Instant::now();
        let grid = trainer.rendering_occupancy();
        // A held-out frame is seen with its training neighbours' appearance.
        let holdout_maps = trainer.appearance.as_ref().map(|learner| {
            let table = appearance::per_frame(&data.train_frames, &learner.maps(), frame_count);
            let maps = data.holdout_frames.iter().map(|&f| table[f]).collect::<Vec<_>>();
            (maps, learner.lens)
        });
        let rendering = Instant::now();
        let r: Validation = validate(
            &trainer.field,
            &grid,
            &trainer.render_options(&render_opts),
            &data.holdout,
            metres_per_unit,
            side,
            holdout_maps.as_ref().map(|(maps, lens)| (maps.as_slice(), lens)),
        );
        let render_s = rendering.elapsed().as_secs_f64();
        state.timings.eval_s += t.elapsed().as_secs_f64();
        let samples = trainer.counters.samples;
        let dt = (state.train_seconds - state.last_point.0).max(1e-9);
        let point = CurvePoint {
            seconds: wall,
            step: trainer.counters.steps,
            psnr: r.psnr,
            ssim: r.ssim,
            depth_mae_m: r.depth_mae_m,
            samples_per_s: samples.saturating_sub(state.last_point.1) as f64 / dt,
        };
        state.last_point = (state.train_seconds, samples);
        state.curve.push(point);
        Some((point, render_s, grid))
    };
    let save_checkpoint = |trainer: &Trainer, state: &mut FitProgress, on_event: &mut dyn FnMut(FitEvent)| {
        let Some(path) = &opts.checkpoint else { return };
        let t = Instant::now();
        let result = checkpoint::save(path, &identity, state, trainer);
        state.timings.checkpoint_s += t.elapsed().as_secs_f64();
        match result {
            Ok(()) => on_event(FitEvent::CheckpointSaved {
                step: trainer.counters.steps,
            }),
            Err(e) => on_event(FitEvent::CheckpointFailed(&e)),
        }
    };
    // What the last pass of aligning the images to the field will cost.
    let mut final_align_s = 0.0;
    // A resumed fit goes on with the poses its images were aligned to.
    if state.aligned_poses.len() == scan.frames.len() {
        let poses: Vec<_> = state.aligned_poses.iter().map(from_column_major).collect();
        scan.set_poses(&poses);
        set_view_cameras(scan, &mut data, &transform);
    }
    loop {
        // `progress` is the share of the budget used (the stop and the
        // progress bar); `training` the share of the training time, which the
        // learning-rate schedule and the pose passes follow: preparation and
        // finishing must not eat into the schedule's full-rate phase. With the
        // wall share, `--time 60` on the realistic tabletop (seed 2) left the
        // full rate after 37 % of its 578 steps and scored 27.04 dB held out;
        // `--steps 569` (schedule by steps) 27.50 dB.
        let step_share = |steps: u64| trainer.counters.steps as f64 / steps.max(1) as f64;
        let wall_share = |limit: f64| (spent() + finish_cost) / limit;
        let training_share = |limit: f64| training_time_share(state.train_seconds, limit - spent() - finish_cost);
        let (progress, training) = match (time_budget, step_budget) {
            (Some(limit), Some(steps)) => (
                wall_share(limit).max(step_share(steps)),
                training_share(limit).max(step_share(steps)),
            ),
            (Some(limit), None) => (wall_share(limit), training_share(limit)),
            (None, Some(steps)) => (step_share(steps), step_share(steps)),
            (None, None) => (1.0, 1.0),
        };
        // At least one step, so that even a budget spent on preparation gives a model.
        if progress >= 1.0 && trainer.counters.steps > 0 {
            break;
        }
        if stop.load(Ordering::Relaxed) {
            state.interrupted = true;
            break;
        }
        // Training frames only: the held-out ones must not learn from
        // their own images before they are scored. After the warm-up at
        // least: an untrained field has nothing to align to.
        let (steps, warmup) = (trainer.counters.steps, trainer.config.warmup_steps);
        if align_to_field && pose_alignment_due(&state.pose_alignment, training, steps, warmup) {
            let frames = data.train_frames.clone();
            let before = state.timings.pose_align_s;
            let render = trainer.render_options(&render_opts);
            align_poses_to_field(
                scan,
                &mut data,
                &mut trainer,
                &transform,
                &render,
                &frames,
                &alignment_options,
                &mut state,
                &mut *on_event,
            );
            // The last pass (every frame) comes out of the budget too.
            let seconds = state.timings.pose_align_s - before;
            final_align_s = seconds * frame_count as f64 / frames.len().max(1) as f64;
            let cell_m = metres_per_unit / trainer.occupancy.resolution() as f64;
            if state
                .pose_alignment
                .last()
                .is_some_and(|pass| moves_carving(pass, pixel_footprint_m, cell_m))
            {
                let t = Instant::now();
                carve_again(&mut trainer, &data, &settings, opts.settings.unseen_objects);
                state.timings.occupancy_seed_s += t.elapsed().as_secs_f64();
            }
            continue;
        }
        let t = Instant::now();
        let stats = trainer.step(&data.train, training as f32);
        if let Some(steps) = trainer.take_pose_steps() {
            move_training_cameras(scan, &mut data, &transform, &steps);
            state.aligned_poses = scan.frames.iter().map(|f| column_major(&f.camera_to_world)).collect();
        }
        state.train_seconds += t.elapsed().as_secs_f64();
        on_event(FitEvent::Step {
            step: trainer.counters.steps,
            stats: &stats,
            train_seconds: state.train_seconds,
            progress,
        });
        // The final evaluation comes soon anyway: no periodic one just before it.
        let near_end = time_budget.is_some_and(|limit| spent() + 2.0 * finish_cost >= limit);
        if state.train_seconds >= next_eval && !near_end {
            let eval_s_before = state.timings.eval_s;
            if let Some((point, render_s, grid)) = evaluate_now(&mut trainer, &mut state, &data, eval_side) {
                on_event(FitEvent::Eval(&point));
                latest_grid = Some((point.step, grid));
                last_render = Some((eval_side, render_s));
                eval_side = side_for(eval_side, render_s, EVAL_INTERVAL_SHARE * interval);
            }
            let checkpoint_s_before = state.timings.checkpoint_s;
            state.timings.wall_s = spent();
            save_checkpoint(&trainer, &mut state, &mut *on_event);
            // Evaluation must not dominate a fit: the next one comes after
            // at least four times the last one's cost in training time.
            let last_cost = state.timings.eval_s - eval_s_before;
            // The final evaluation renders its own grid (rendering time grows
            // with its pixels); the model and report together are about half
            // a checkpoint.
            let final_eval = last_render.map_or(last_cost, |(side, render_s)| {
                let final_side = side_for(side, render_s, final_eval_s);
                last_cost + render_s * ((final_side as f64 / side as f64).powi(2) - 1.0)
            });
            finish_cost = final_eval + 1.5 * (state.timings.checkpoint_s - checkpoint_s_before) + final_align_s;
            let spacing = (EVAL_COST_RATIO * last_cost).min(MAX_EVAL_SPACING * interval);
            next_eval = (next_eval + interval).max(state.train_seconds + spacing);
            while next_eval <= state.train_seconds {
                next_eval += interval;
            }
        }
    }
    if state.curve.last().map(|p| p.step) != Some(trainer.counters.steps) {
        let side = last_render.map_or(eval_side, |(side, render_s)| side_for(side, render_s, final_eval_s));
        if let Some((point, _, grid)) = evaluate_now(&mut trainer, &mut state, &data, side) {
            on_event(FitEvent::Eval(&point));
            latest_grid = Some((point.step, grid));
        }
    }
    // Last, every frame (held-out ones too: `label` draws through them all)
    // is aligned to the final field, once the first pass ran.
    if opts.settings.refine_poses && !state.pose_alignment.is_empty() && !state.interrupted {
        let frames: Vec<usize> = (0..frame_count).collect();
        let render = trainer.render_options(&render_opts);
        align_poses_to_field(
            scan,
            &mut data,
            &mut trainer,
            &transform,
            &render,
            &frames,
            &alignment_options,
            &mut state,
            &mut *on_event,
        );
    }
    state.timings.train_s = state.train_seconds;
    state.timings.wall_s = spent();
    save_checkpoint(&trainer, &mut state, &mut *on_event);
    state.timings.wall_s = spent();

    let header = ModelHeader {
        nerflabel_version: env!("CARGO_PKG_VERSION").to_string(),
        field: settings.field.clone(),
        train: settings.train.clone(),
        scene_transform: transform.to_array().to_vec(),
        units_per_metre: transform.scale(),
        occupancy_resolution: trainer.occupancy.resolution(),
        background: data.background,
        environment: trainer.environment.as_ref().map(|e| e.environment.coeffs.to_vec()),
        render_step: settings.render_step,
        steps: trainer.counters.steps,
        seed: opts.settings.seed,
        scan: scan.root.display().to_string(),
        scan_frames: Some(scan.frames.len()),
        scan_fingerprint: Some(captured_fingerprint),
        fitted_poses: (scaled || refinement.is_some() || !state.aligned_poses.is_empty())
            .then(|| scan.frames.iter().map(|f| column_major(&f.camera_to_world)).collect()),
        appearance: trainer
            .appearance
            .as_ref()
            .map(|learner| appearance::per_frame(&data.train_frames, &learner.maps(), scan.frames.len())),
        vignetting: trainer.appearance.as_ref().map(|learner| learner.lens),
        sections: [0; 5],
    };
    let occupancy = match latest_grid {
        Some((step, grid)) if step == trainer.counters.steps => grid,
        _ => trainer.rendering_occupancy(),
    };
    let pose_learning = trainer.poses.as_ref().map(|learner| {
        let names: Vec<String> = data.train_frames.iter().map(|&i| scan.frames[i].name.clone()).collect();
        PoseLearningReport::new(&learner.moved, &names, metres_per_unit)
    });
    if let Some(r) = &pose_learning {
        on_event(FitEvent::PosesLearnt(r));
    }
    let report = FitReport {
        nerflabel_version: header.nerflabel_version.clone(),
        scan: header.scan.clone(),
        seed: opts.settings.seed,
        preset: opts.settings.preset,
        threads: rayon::current_num_threads(),
        train_frames: data.train.len(),
        holdout_frames: data
            .holdout_frames
            .iter()
            .map(|&i| scan.frames[i].name.clone())
            .collect(),
        metres_per_unit,
        param_count,
        field: settings.field,
        train: settings.train,
        timings: state.timings,
        counters: trainer.counters,
        lr_scale: trainer.optimiser().1,
        interrupted: state.interrupted,
        resumed_from: state.resumed_from,
        occupied_fraction: occupancy.occupied_fraction(),
        pose_scale: scale_report,
        pose_refinement: refinement_report,
        pose_alignment: state.pose_alignment.clone(),
        pose_learning,
        appearance: trainer.appearance.as_ref().and_then(|learner| {
            let names: Vec<String> = data.train_frames.iter().map(|&i| scan.frames[i].name.clone()).collect();
            let corner_light = scan.frames.first().map_or(1.0, |f| {
                let (w, h) = f.size();
                appearance::corner_gain(&learner.lens, &f.intrinsics, w, h)
            });
            AppearanceReport::new(&learner.maps(), &names, learner.lens, corner_light)
        }),
        depth_noise,
        colour_border: Some(scan_colour_border(&data)).filter(|b| !b.is_none()),
        curve: state.curve,
    };
    let model = Model {
        header,
        field: trainer.field,
        occupancy,
    };
    Ok(FitOutcome { model, report })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::nerf::train::photometric::PhotometricCorrection;

    #[test]
    fn evaluation_grids_are_sized_to_render_in_their_share_of_the_budget() {
        // 64 px took 2 s; 0.5 s allows a quarter of the pixels: half the side.
        assert_eq!(evaluation_side(64, 2.0, 0.5, 160), 32);
        // A fast render grows the grid, up to the full evaluation grid.
        assert_eq!(evaluation_side(64, 0.1, 0.4, 160), 128);
        assert_eq!(evaluation_side(64, 0.01, 10.0, 160), 160);
        // Never below the floor, and unchanged when nothing was measured.
        assert_eq!(evaluation_side(64, 100.0, 0.01, 160), MIN_EVAL_SIDE);
        assert_eq!(evaluation_side(64, 0.0, 1.0, 160), 64);
        assert_eq!(evaluation_side(64, f64::NAN, 1.0, 160), 64);
        // A grid smaller than the floor stays what was asked for.
        assert_eq!(evaluation_side(16, 1.0, 0.001, 16), 16);
    }

    /// A pass at `at_step` over `aligned` frames that moved `moved` of them
    /// by `shift_px` and left the others alone.
    fn pass(at_step: u64, aligned: usize, moved: usize, shift_px: f64) -> PoseAlignmentReport {
        let frames = (0..aligned)
            .map(|i| PhotometricCorrection {
                frame: format!("{i:06}"),
                translation_m: 0.0,
                rotation_deg: 0.0,
                shift_px,
                cost_before: Some(1.0),
                cost_after: Some(0.5),
                refined: i < moved,
            })
            .collect();
        PoseAlignmentReport {
            at_step,
            frames_aligned: aligned,
            frames_refined: moved,
            median_shift_px: shift_px,
            largest_translation_m: 0.0,
            largest_rotation_deg: 0.0,
            frames,
        }
    }

    #[test]
    fn image_corrections_are_bounded_by_what_the_depth_corrected() {
        let correction = |i: usize, translation_m: f64, refined: bool| crate::poses::FrameCorrection {
            frame: format!("{i:06}"),
            translation_m,
            rotation_deg: 0.0,
            residual_before_m: None,
            residual_after_m: None,
            refined,
        };
        // Nine frames in ten moved by at most 4 mm (one by 40): 8 mm.
        let mut frames: Vec<_> = (0..20)
            .map(|i| correction(i, 0.004 * (i + 1).min(4) as f64 / 4.0, true))
            .collect();
        frames[19].translation_m = 0.04;
        frames.push(correction(20, 0.5, false));
        let refinement = PoseRefinement {
            camera_to_world: vec![IsometryMatrix3::identity(); 21],
            frames,
            colour_aligned: false,
        };
        assert!((plausible_correction_m(Some(&refinement)) - 0.008).abs() < 1e-9);
        // Without depth, or where it corrected nothing, colour alone decides.
        assert_eq!(plausible_correction_m(None), f64::INFINITY);
        let untouched = PoseRefinement {
            camera_to_world: vec![IsometryMatrix3::identity()],
            frames: vec![correction(0, 0.0, false)],
            colour_aligned: false,
        };
        assert_eq!(plausible_correction_m(Some(&untouched)), f64::INFINITY);
    }

    #[test]
    fn the_first_pass_waits_for_its_share_of_the_budget_and_the_warm_up() {
        assert!(!pose_alignment_due(&[], 0.44, 500, 128));
        assert!(!pose_alignment_due(&[], 0.5, 100, 128));
        assert!(pose_alignment_due(&[], 0.45, 128, 128));
    }

    #[test]
    fn further_passes_run_only_while_the_last_moved_many_frames() {
        // 40 of 100 frames moved by 2 px: another pass once one is due and
        // half a warm-up has been trained since.
        let busy = [pass(400, 100, 40, 2.0)];
        assert!(!pose_alignment_due(&busy, 0.59, 600, 128));
        assert!(!pose_alignment_due(&busy, 0.6, 450, 128));
        assert!(pose_alignment_due(&busy, 0.6, 464, 128));
        // Few frames moved, or many by under a pixel: the poses have settled.
        assert!(!pose_alignment_due(&[pass(400, 100, 10, 3.0)], 0.8, 700, 128));
        assert!(!pose_alignment_due(&[pass(400, 100, 90, 0.6)], 0.8, 700, 128));
        // No more than the scheduled passes, however much they move.
        let four: Vec<_> = (0..4).map(|i| pass(100 * i, 100, 50, 2.0)).collect();
        assert!(!pose_alignment_due(&four, 0.99, 1000, 128));
    }

    #[test]
    fn carving_is_redone_only_after_a_pass_moved_a_frame_half_a_cell() {
        // 2.8 mm pixels, 5.7 cm cells (the real cabinet): 4.6 px moves a
        // frame's surface 13 mm, a quarter of a cell; 11 px moves it half.
        let (footprint, cell) = (0.0028, 0.057);
        assert!(!moves_carving(&pass(200, 50, 40, 4.6), footprint, cell));
        assert!(moves_carving(&pass(200, 50, 1, 11.0), footprint, cell));
        // Frames whose correction was not kept do not count.
        assert!(!moves_carving(&pass(200, 50, 0, 20.0), footprint, cell));
    }

    #[test]
    fn the_schedule_follows_training_time_not_preparation_or_finishing() {
        // 6 s of preparation and 8 s of finishing in a 60 s budget: after
        // 23 s of training, half of the 46 s the steps get is used, whereas
        // the wall clock stands at (6 + 23 + 8) / 60 = 0.62.
        let (limit, prep, finish, trained) = (60.0, 6.0, 8.0, 23.0);
        let share = training_time_share(trained, limit - (prep + trained) - finish);
        assert!((share - 0.5).abs() < 1e-12, "{share}");
        // Nothing trained yet: 0; budget gone (or overrun): 1.
        assert_eq!(training_time_share(0.0, 50.0), 0.0);
        assert_eq!(training_time_share(10.0, 0.0), 1.0);
        assert_eq!(training_time_share(0.0, -3.0), 1.0);
    }
}
