//! Model and training settings derived from the scene itself: the finest
//! grid cell, step sizes and depth-loss widths follow the scene's scale, so
//! a tabletop and a room (or the same scene at 1/100 scale) get the same
//! treatment in local units.

use crate::nerf::field::hash_grid::HashGridConfig;
use crate::nerf::field::{FieldConfig, GridSpec};
use crate::nerf::occupancy::DEFAULT_RESOLUTION;
use crate::nerf::render::march::StepRule;
use serde::{Deserialize, Deserializer, Serialize};

/// Speed/quality trade-off.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize, clap::ValueEnum)]
#[serde(rename_all = "lowercase")]
pub enum Preset {
    /// Coarser grid, fewer samples per step (32 Ki against 48 Ki).
    Fast,
    Default,
    /// Finer grid, more samples per step (128 Ki against 48 Ki).
    Quality,
}

impl std::fmt::Display for Preset {
    /// The name `--preset` takes.
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        let value = clap::ValueEnum::to_possible_value(self).expect("every preset is a value");
        f.write_str(value.get_name())
    }
}

impl Preset {
    /// Finest grid cell as a multiple of the typical pixel footprint.
    fn pixels_per_cell(self) -> f64 {
        match self {
            Preset::Fast => 12.0,
            Preset::Default => 3.0,
            Preset::Quality => 2.0,
        }
    }

    /// Fewest finest cells across the unit cube: low-resolution scans still
    /// get geometry finer than their pixels (depth supervision resolves it).
    fn min_cells(self) -> f64 {
        match self {
            Preset::Fast => 128.0,
            Preset::Default => 256.0,
            Preset::Quality => 384.0,
        }
    }

    /// Samples drawn per step. The default's 48 Ki steps about as fast per
    /// sample as 64 Ki (the optimiser's pass over the touched table is paid
    /// per step, the rest per sample: 783 against 785 k samples/s) and takes
    /// a third more steps in the same time, which pays at short budgets.
    /// `bench_fit DIR --time 60 --seed 2`, 64 Ki -> 48 Ki: realistic tabletop
    /// seed 2 28.41 -> 28.77 dB, seed 3 28.51 -> 28.79 dB (chosen on these),
    /// clutter seed 4 30.32 -> 30.41 dB, room seed 1 29.71 -> 29.85 dB; the
    /// real cabinet (`fit --time 60 --seed 1`) 24.91 / 25.25 -> 25.61 /
    /// 25.52 dB. At `--time 120` within run-to-run spread: seed 2 30.01 ->
    /// 29.98, seed 3 29.84 -> 29.74 dB. 32 Ki gained more at 60 s (seed 3
    /// 29.00 dB) but lost at 120 s (seed 2 29.70 dB); 128 Ki lost 0.9 dB.
    fn samples_per_step(self) -> usize {
        match self {
            Preset::Fast => 1 << 15,
            Preset::Default => 3 << 14,
            Preset::Quality => 1 << 17,
        }
    }
}

/// Adam learning rate unless `fit --learning-rate` says otherwise.
pub const DEFAULT_LEARNING_RATE: f32 = 1e-2;
/// Weight of the depth loss unless `fit --lambda-depth` says otherwise.
pub const DEFAULT_LAMBDA_DEPTH: f32 = 0.1;

/// The settings of a fit that shape what it trains. This one definition
/// gives each its command-line flag, default and help (`fit` flattens it),
/// its place in the checkpoint, and the resume check: a checkpoint resumes
/// only with equal settings, and the error names the flags that differ.
/// Serde field names are the flags' ids, which [`FitSettings::differences`]
/// relies on.
#[derive(clap::Args, Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct FitSettings {
    /// Random seed.
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
    /// Quality/speed preset.
    #[arg(long, value_enum, default_value_t = Preset::Default)]
    pub preset: Preset,
    /// Hold out every K-th frame for evaluation (0 = none).
    #[arg(long = "holdout", value_name = "K", default_value_t = 10)]
    pub holdout_every: usize,
    /// Weight of the depth loss.
    #[arg(long, default_value_t = DEFAULT_LAMBDA_DEPTH)]
    #[serde(deserialize_with = "lambda_depth_or_default")]
    pub lambda_depth: f32,
    /// Adam learning rate.
    #[arg(long, default_value_t = DEFAULT_LEARNING_RATE)]
    #[serde(deserialize_with = "learning_rate_or_default")]
    pub learning_rate: f32,
    /// Do not read wide regions without depth as objects the sensor cannot
    /// see. By default a region without depth that is enclosed by measured
    /// depth, and is not a projector shadow beside a depth edge, is taken as
    /// an object (glass, some black plastics) and the model is kept from
    /// looking through it. Turn it off for a scan whose depth drops out on
    /// ordinary surfaces in the middle of the frame.
    #[arg(long = "no-unseen-objects", action = clap::ArgAction::SetFalse)]
    #[serde(default)]
    pub unseen_objects: bool,
    /// Keep the scan's poses as captured (still made metric when they are
    /// clearly not; see --pose-scale). By default every frame's
    /// pose is first aligned to the depth the other frames measured, then
    /// the frames to each other by colour (frames whose depth fits better
    /// with the aligned pose take it; the scene as a whole does not move).
    /// Where the colour alignment is not followed (see --no-colour-align),
    /// each frame's image and depth are aligned to the field during the fit
    /// (at 45 % of the budget, again while frames still move, and at the
    /// end). The model keeps the aligned poses for `label` and `synth`, so
    /// that masks line up with the images, and the report lists each
    /// frame's correction.
    #[arg(long = "no-pose-refine", action = clap::ArgAction::SetFalse)]
    #[serde(default)]
    pub refine_poses: bool,
    /// Align the poses to the depth only, not the frames to each other by
    /// colour (then their images are aligned to the field during the fit).
    /// By default each frame's image, carried by its depth into the frames
    /// that see the same surfaces, pins what the depth leaves free (frames
    /// sliding along a table top: SLAM-like tabletop labels 0.760 -> 0.980);
    /// the colour is followed only while the depth agrees nearly as well,
    /// so colour registered off the depth is ignored on its own.
    #[arg(long = "no-colour-align", action = clap::ArgAction::SetFalse)]
    #[serde(default)]
    pub colour_align: bool,
    /// Also learn each training frame's pose with the field, from the same
    /// losses (pose gradients through the hash grid, as BARF), at a pace set
    /// by the scan's pose error as the depth measured it. For scans with
    /// centimetre pose error (SLAM drift): measured labels +0.003 to +0.06
    /// mIoU on SLAM-like scenes, unchanged on well-posed ones; held-out
    /// frames are not learnt, so their PSNR can drop (real cabinet scan
    /// -0.45 dB). Needs pose refinement (ignored with --no-pose-refine).
    #[arg(long = "learn-poses")]
    #[serde(default)]
    pub learn_poses: bool,
    /// Multiply every camera position by this factor before fitting, for
    /// poses known only up to scale (structure from motion). By default the
    /// scale is estimated from the depth and applied, with a warning, when
    /// the poses are clearly not metric; `--pose-scale 1` keeps them as they
    /// are. Boxes are given in the metric frame that results (same origin
    /// and axes as the poses).
    #[arg(long, value_name = "S")]
    #[serde(default)]
    pub pose_scale: Option<f64>,
    /// Do not learn each frame's exposure and white balance, nor the lens's
    /// vignetting. By default every training frame's colour is the model's
    /// colour through an affine colour map of its own (3x3 matrix and
    /// offset), so that exposure changes during the capture do not bend the
    /// geometry, and through the lens's falloff towards the image corners
    /// (one for the scan); the model's own colour is the scan's average
    /// appearance without falloff, which `synth` renders unless told
    /// otherwise.
    #[arg(long = "no-appearance", action = clap::ArgAction::SetFalse)]
    #[serde(default)]
    pub per_frame_appearance: bool,
}

/// Checkpoints of earlier versions wrote `null` for a default weight.
fn lambda_depth_or_default<'de, D: Deserializer<'de>>(d: D) -> Result<f32, D::Error> {
    Ok(Option::<f32>::deserialize(d)?.unwrap_or(DEFAULT_LAMBDA_DEPTH))
}

fn learning_rate_or_default<'de, D: Deserializer<'de>>(d: D) -> Result<f32, D::Error> {
    Ok(Option::<f32>::deserialize(d)?.unwrap_or(DEFAULT_LEARNING_RATE))
}

/// The command line with no flag given, for [`FitSettings::default`].
#[derive(clap::Parser)]
struct NoFlags {
    #[command(flatten)]
    settings: FitSettings,
}

impl Default for FitSettings {
    /// The defaults the flags declare.
    fn default() -> Self {
        <NoFlags as clap::Parser>::parse_from(["fit"]).settings
    }
}

/// A setting no fit can train with, named by its flag.
#[derive(Debug, thiserror::Error)]
#[error("{flag} {reason}")]
pub struct SettingError {
    pub flag: &'static str,
    pub reason: String,
}

impl FitSettings {
    /// Refuse values no fit can train with.
    pub fn validate(&self) -> Result<(), SettingError> {
        let bad = |flag: &'static str, reason: String| Err(SettingError { flag, reason });
        if let Some(s) = self.pose_scale {
            if !(s.is_finite() && s > 0.0) {
                return bad("--pose-scale", format!("must be a positive factor, got {s}"));
            }
        }
        if !(self.lambda_depth.is_finite() && self.lambda_depth >= 0.0) {
            return bad(
                "--lambda-depth",
                format!("must be a finite number >= 0, got {}", self.lambda_depth),
            );
        }
        if !(self.learning_rate.is_finite() && self.learning_rate > 0.0) {
            return bad(
                "--learning-rate",
                format!("must be a positive finite number, got {}", self.learning_rate),
            );
        }
        Ok(())
    }

    /// Where `self` (a checkpoint's) and `this_run` differ, each as the flag
    /// that sets it: `--seed 1 (this run: 2)`, `with --no-pose-refine (this
    /// run: without --no-pose-refine)`.
    pub fn differences(&self, this_run: &FitSettings) -> Vec<String> {
        use clap::{ArgAction, Args};
        let as_map = |s: &FitSettings| match serde_json::to_value(s) {
            Ok(serde_json::Value::Object(map)) => map,
            _ => serde_json::Map::new(),
        };
        let (saved, now) = (as_map(self), as_map(this_run));
        let show = |v: &serde_json::Value| match v {
            serde_json::Value::Null => "not given".to_string(),
            serde_json::Value::String(s) => s.clone(),
            // An f32 setting widened to f64 by JSON prints as it was typed.
            serde_json::Value::Number(n) if n.is_f64() => match n.as_f64() {
                Some(x) if (x as f32) as f64 == x => (x as f32).to_string(),
                _ => n.to_string(),
            },
            other => other.to_string(),
        };
        let command = FitSettings::augment_args(clap::Command::new("fit"));
        let mut out = Vec::new();
        for arg in command.get_arguments() {
            let id = arg.get_id().as_str();
            let (a, b) = (&saved[id], &now[id]);
            if a == b {
                continue;
            }
            let flag = format!("--{}", arg.get_long().unwrap_or(id));
            match arg.get_action() {
                ArgAction::SetFalse | ArgAction::SetTrue => {
                    let flag_given = matches!(arg.get_action(), ArgAction::SetTrue);
                    let describe = |v: &serde_json::Value| {
                        if v.as_bool() == Some(flag_given) {
                            format!("with {flag}")
                        } else {
                            format!("without {flag}")
                        }
                    };
                    out.push(format!("{} (this run: {})", describe(a), describe(b)));
                }
                _ => out.push(format!("{flag} {} (this run: {})", show(a), show(b))),
            }
        }
        out
    }
}

/// Training hyper-parameters (local units where lengths are involved).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct TrainConfig {
    pub samples_per_step: usize,
    pub max_samples_per_ray: usize,
    pub learning_rate: f32,
    pub warmup_steps: u64,
    /// Weight of the L1 loss on expected depth.
    pub lambda_depth: f32,
    /// Weight of the line-of-sight terms (empty space before the surface,
    /// all weight within the surface window).
    pub lambda_line_of_sight: f32,
    /// Half-width of the surface window around measured depth (local units).
    pub surface_window: f32,
    /// Weight of the no-return term: a ray the sensor could not measure is
    /// penalised by the light it lets through to the first surface the
    /// sensor measured from elsewhere (see `occupancy/measured.rs`).
    #[serde(default)]
    pub lambda_no_return: f32,
    pub step: StepRule,
    pub occupancy_every: u64,
    pub occupancy_decay: f32,
    pub seed: u64,
}

/// Everything needed to build and train a model for one scene.
#[derive(Clone, Debug, PartialEq)]
pub struct NerfSettings {
    pub field: FieldConfig,
    pub train: TrainConfig,
    pub occupancy_resolution: usize,
    pub render_step: StepRule,
}

/// Weight of the no-return term, on unless `fit --no-unseen-objects`: the
/// line-of-sight weight, so no return counts as much as free space seen.
pub const NO_RETURN_WEIGHT: f32 = 0.1;

/// Most finest-level cells across the unit cube.
const FINEST_CELLS: f64 = 2048.0;

/// Settings for a scene whose unit cube spans `metres_per_unit` metres and
/// whose cameras see `pixel_footprint_m` metres per pixel at their typical
/// viewing distance: the finest cell is a few pixel footprints, so detail
/// follows what the sensor resolves, at any scene scale. `fit` gives the
/// preset, seed, loss weights and learning rate, and whether the no-return
/// term is on.
pub fn settings_for_scene(metres_per_unit: f64, pixel_footprint_m: f64, fit: &FitSettings) -> NerfSettings {
    let preset = fit.preset;
    let wanted = pixel_footprint_m * preset.pixels_per_cell();
    let cells = if wanted.is_finite() && wanted > 0.0 {
        metres_per_unit / wanted
    } else {
        256.0
    };
    let cells = cells.clamp(preset.min_cells(), FINEST_CELLS);
    let grid = HashGridConfig::for_scene(metres_per_unit, metres_per_unit / cells);
    let finest = grid.finest_resolution.max(16) as f32;
    // About one finest cell per step; far steps grow slowly for big scenes.
    let step = StepRule {
        min_step: 0.75 / finest,
        max_step: 1.0 / 32.0,
        cone: 1.0 / 256.0,
    };
    let train = TrainConfig {
        samples_per_step: preset.samples_per_step(),
        max_samples_per_ray: 1024,
        learning_rate: fit.learning_rate,
        warmup_steps: 128,
        lambda_depth: fit.lambda_depth,
        lambda_line_of_sight: 0.1,
        surface_window: 1.5 / finest,
        lambda_no_return: if fit.unseen_objects { NO_RETURN_WEIGHT } else { 0.0 },
        step,
        occupancy_every: 16,
        occupancy_decay: 0.95,
        seed: fit.seed,
    };
    NerfSettings {
        field: FieldConfig {
            grid: GridSpec::from(&grid),
            density_hidden: vec![64],
            color_hidden: vec![64, 64],
        },
        train,
        occupancy_resolution: DEFAULT_RESOLUTION,
        render_step: step,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn presets_order_from_coarse_and_cheap_to_fine_and_costly() {
        // Tabletop-like (6 m cube, 2 mm pixels) and room-like (20 m, 8 mm) scenes.
        for (metres, footprint) in [(6.0, 0.002), (20.0, 0.008)] {
            let [fast, default, quality] = [Preset::Fast, Preset::Default, Preset::Quality].map(|preset| {
                settings_for_scene(
                    metres,
                    footprint,
                    &FitSettings {
                        preset,
                        ..FitSettings::default()
                    },
                )
            });
            let finest = |s: &NerfSettings| s.field.grid.finest_resolution;
            assert!(
                finest(&fast) < finest(&default) && finest(&default) < finest(&quality),
                "{metres} m"
            );
            assert!(fast.train.samples_per_step <= default.train.samples_per_step);
            assert!(default.train.samples_per_step <= quality.train.samples_per_step);
            // The step follows the finest cell.
            assert!(quality.train.step.min_step < default.train.step.min_step);
        }
    }

    #[test]
    fn every_fit_setting_is_a_flag_with_its_declared_default() {
        use clap::Args;
        let defaults = FitSettings::default();
        assert_eq!(defaults.learning_rate, DEFAULT_LEARNING_RATE);
        assert_eq!(defaults.lambda_depth, DEFAULT_LAMBDA_DEPTH);
        assert!(defaults.unseen_objects && defaults.refine_poses && defaults.pose_scale.is_none());
        // `differences` finds each saved field by its flag's id: none may be missing.
        let command = FitSettings::augment_args(clap::Command::new("fit"));
        let ids: Vec<&str> = command.get_arguments().map(|a| a.get_id().as_str()).collect();
        let serde_json::Value::Object(saved) = serde_json::to_value(&defaults).unwrap() else {
            panic!()
        };
        for key in saved.keys() {
            assert!(ids.contains(&key.as_str()), "{key} has no flag");
        }
        assert_eq!(saved.len(), ids.len());
        assert!(defaults.differences(&defaults).is_empty());
    }

    #[test]
    fn checkpoints_of_earlier_versions_read_null_weights_as_the_defaults() {
        let old = r#"{"seed": 3, "preset": "fast", "holdout_every": 0, "lambda_depth": null, "learning_rate": null}"#;
        let s: FitSettings = serde_json::from_str(old).unwrap();
        assert_eq!(
            (s.lambda_depth, s.learning_rate),
            (DEFAULT_LAMBDA_DEPTH, DEFAULT_LEARNING_RATE)
        );
        assert_eq!((s.seed, s.preset, s.holdout_every), (3, Preset::Fast, 0));
    }
}
