//! The fit report (`MODEL.report.json`): settings, phase timings, counters,
//! pose corrections and the error-against-run-time curve of one fit.

use crate::nerf::appearance::{strength, Affine, Vignetting};
use crate::nerf::field::FieldConfig;
use crate::nerf::train::photometric::{PhotometricAlignment, PhotometricCorrection};
use crate::nerf::train::settings::Preset;
use crate::nerf::train::settings::TrainConfig;
use crate::nerf::train::step::TrainCounters;
use crate::poses::{FrameCorrection, PoseRefinement};
use crate::scan::{ColourBorder, DepthNoise};
use serde::{Deserialize, Serialize};

/// One point of the error-against-run-time curve.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct CurvePoint {
    /// Wall time of the fit so far (preparation, training, earlier
    /// evaluations and checkpoints; this point's own evaluation excluded).
    pub seconds: f64,
    pub step: u64,
    pub psnr: f64,
    pub ssim: f64,
    pub depth_mae_m: Option<f64>,
    /// Training throughput since the previous point.
    pub samples_per_s: f64,
}

/// Seconds spent in each phase.
#[derive(Clone, Copy, Debug, Default, Serialize, Deserialize)]
pub struct Timings {
    /// Making the poses metric and aligning them to the depth
    /// (`FitOptions::pose_scale`, `FitOptions::refine_poses`).
    #[serde(default)]
    pub pose_refine_s: f64,
    /// Aligning the frames' images to the field (both passes).
    #[serde(default)]
    pub pose_align_s: f64,
    pub bounds_s: f64,
    pub views_s: f64,
    pub occupancy_seed_s: f64,
    pub train_s: f64,
    pub eval_s: f64,
    /// Writing checkpoints.
    #[serde(default)]
    pub checkpoint_s: f64,
    /// Wall time of the whole fit (what `--time` bounds), all runs of a resumed fit together.
    #[serde(default)]
    pub wall_s: f64,
}

/// Where the report of a model lives: `model.nlf` -> `model.report.json`,
/// so two models in one folder keep their own reports.
pub fn report_path(model: &std::path::Path) -> std::path::PathBuf {
    model.with_extension("report.json")
}

/// The report name of earlier versions (one per folder), read when a model
/// has no report of its own.
pub fn legacy_report_path(model: &std::path::Path) -> std::path::PathBuf {
    model.with_file_name("fit_report.json")
}

/// Contents of a fit report (`MODEL.report.json`).
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct FitReport {
    pub nerflabel_version: String,
    pub scan: String,
    pub seed: u64,
    pub preset: Preset,
    pub threads: usize,
    pub train_frames: usize,
    pub holdout_frames: Vec<String>,
    pub metres_per_unit: f64,
    pub param_count: usize,
    pub field: FieldConfig,
    pub train: TrainConfig,
    pub timings: Timings,
    pub counters: TrainCounters,
    /// Step-size scale the divergence guard left: 1 when it never backed
    /// off, halved for every skipped batch (`counters.skipped_batches`).
    #[serde(default = "one")]
    pub lr_scale: f32,
    pub interrupted: bool,
    /// Steps at which this fit was resumed from its checkpoint.
    #[serde(default)]
    pub resumed_from: Vec<u64>,
    pub occupied_fraction: f64,
    /// The scale applied to the camera positions, when not 1.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub pose_scale: Option<PoseScaleReport>,
    /// What pose refinement changed; `None` when it was off or the scan has
    /// too little depth.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub pose_refinement: Option<PoseRefinementReport>,
    /// What each pass of aligning the frames' images to the field changed
    /// (part-way, the training frames; at the end, every frame); empty when
    /// pose refinement was off or the fit ended before it.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub pose_alignment: Vec<PoseAlignmentReport>,
    /// What learning the training frames' poses with the field moved them
    /// by; `None` when pose refinement was off.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub pose_learning: Option<PoseLearningReport>,
    /// How far the learnt per-frame appearance strays from neutral; `None`
    /// when it was not learnt.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub appearance: Option<AppearanceReport>,
    /// The depth sensor's noise as the scan's depth showed it (metres);
    /// `None` when it had too few measured surfaces to tell.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub depth_noise: Option<DepthNoise>,
    /// Lines at the colour images' edges that show no scene, left out of
    /// the held-out scores; `None` when there are none.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub colour_border: Option<ColourBorder>,
    pub curve: Vec<CurvePoint>,
}

/// The report's account of the per-frame appearance maps: each map's
/// strength is the largest change it makes to a colour channel (0-1 scale).
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct AppearanceReport {
    pub frames: usize,
    pub median_strength: f32,
    pub largest_strength: f32,
    /// The frame of the largest strength.
    pub largest_frame: String,
    /// The lens's learnt vignetting (`nerf::appearance::Vignetting`).
    #[serde(default)]
    pub vignetting: Vignetting,
    /// The light it leaves in the frames' farthest image corner, as a
    /// share of the centre's (1: no falloff).
    #[serde(default = "no_falloff")]
    pub corner_light: f32,
}

fn no_falloff() -> f32 {
    1.0
}

impl AppearanceReport {
    /// Summary of the training frames' `maps`, named by `names`, and of the
    /// lens, which leaves `corner_light` in the farthest corner.
    pub fn new(
        maps: &[Affine],
        names: &[String],
        vignetting: Vignetting,
        corner_light: f32,
    ) -> Option<AppearanceReport> {
        let mut strengths: Vec<(f32, usize)> = maps.iter().map(strength).zip(0..).collect();
        strengths.sort_by(|a, b| a.0.total_cmp(&b.0));
        let &(largest, frame) = strengths.last()?;
        Some(AppearanceReport {
            frames: maps.len(),
            median_strength: strengths[strengths.len() / 2].0,
            largest_strength: largest,
            largest_frame: names.get(frame).cloned().unwrap_or_default(),
            vignetting,
            corner_light,
        })
    }
}

/// The report's account of the poses' scale.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct PoseScaleReport {
    /// Factor the camera positions were multiplied by.
    pub applied: f64,
    /// Given with `--pose-scale` rather than estimated.
    pub forced: bool,
    pub verdict: String,
}

/// The report's account of pose refinement.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct PoseRefinementReport {
    pub frames_refined: usize,
    /// Median over frames of the median distance between a frame's depth
    /// and the other frames' depth, with the captured and the fitted poses
    /// (absent when no frame's depth overlaps another's).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub median_disagreement_before_m: Option<f64>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub median_disagreement_after_m: Option<f64>,
    /// Largest change of a camera centre (m) and orientation (degrees).
    pub largest_translation_m: f64,
    pub largest_rotation_deg: f64,
    /// How well the captured poses agreed with the depth, in a sentence.
    pub verdict: String,
    /// Whether the frames were also aligned to each other by colour (then
    /// their images are not aligned to the field part-way).
    #[serde(default)]
    pub colour_aligned: bool,
    pub frames: Vec<FrameCorrection>,
}

impl PoseRefinementReport {
    pub fn new(r: &PoseRefinement) -> PoseRefinementReport {
        let (before, after) = r.median_residuals();
        let (translation, rotation) = r.largest_correction();
        PoseRefinementReport {
            frames_refined: r.refined_count(),
            median_disagreement_before_m: before.is_finite().then_some(before),
            median_disagreement_after_m: after.is_finite().then_some(after),
            largest_translation_m: translation,
            largest_rotation_deg: rotation,
            verdict: r.verdict(),
            colour_aligned: r.colour_aligned,
            frames: r.frames.clone(),
        }
    }
}

/// The report's account of the poses aligned to the field
/// (`train::photometric`).
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct PoseAlignmentReport {
    /// Training step before which the frames were aligned.
    pub at_step: u64,
    /// Frames aligned, and those whose correction was kept.
    pub frames_aligned: usize,
    pub frames_refined: usize,
    /// Median over the refined frames of how far the correction moved the
    /// frame's surface points in its image, pixels.
    pub median_shift_px: f64,
    /// Largest change of a camera centre (m) and orientation (degrees).
    pub largest_translation_m: f64,
    pub largest_rotation_deg: f64,
    pub frames: Vec<PhotometricCorrection>,
}

impl PoseAlignmentReport {
    pub fn new(at_step: u64, alignment: &PhotometricAlignment) -> PoseAlignmentReport {
        let refined: Vec<&PhotometricCorrection> = alignment.frames.iter().filter(|f| f.refined).collect();
        let mut shifts: Vec<f64> = refined.iter().map(|f| f.shift_px).collect();
        shifts.sort_by(f64::total_cmp);
        PoseAlignmentReport {
            at_step,
            frames_aligned: alignment.frames.len(),
            frames_refined: refined.len(),
            median_shift_px: shifts.get(shifts.len() / 2).copied().unwrap_or(0.0),
            largest_translation_m: alignment.frames.iter().map(|f| f.translation_m).fold(0.0, f64::max),
            largest_rotation_deg: alignment.frames.iter().map(|f| f.rotation_deg).fold(0.0, f64::max),
            frames: alignment.frames.clone(),
        }
    }
}

/// The report's account of the poses learnt with the field
/// (`train::pose_learning`).
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct PoseLearningReport {
    /// Median and largest change of a camera centre (m), largest change of
    /// an orientation (degrees), over the training frames.
    pub median_translation_m: f64,
    pub largest_translation_m: f64,
    pub largest_rotation_deg: f64,
    pub frames: Vec<LearntCorrection>,
}

/// One training frame's learnt correction.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct LearntCorrection {
    pub frame: String,
    pub translation_m: f64,
    pub rotation_deg: f64,
}

impl PoseLearningReport {
    /// From each training frame's summed steps (rotation radians,
    /// translation local units), named by `names`.
    pub fn new(moved: &[[f64; 6]], names: &[String], metres_per_unit: f64) -> PoseLearningReport {
        let frames: Vec<LearntCorrection> = moved
            .iter()
            .zip(names)
            .map(|(m, name)| LearntCorrection {
                frame: name.clone(),
                translation_m: (m[3] * m[3] + m[4] * m[4] + m[5] * m[5]).sqrt() * metres_per_unit,
                rotation_deg: (m[0] * m[0] + m[1] * m[1] + m[2] * m[2]).sqrt().to_degrees(),
            })
            .collect();
        let mut translations: Vec<f64> = frames.iter().map(|f| f.translation_m).collect();
        translations.sort_by(f64::total_cmp);
        PoseLearningReport {
            median_translation_m: translations.get(translations.len() / 2).copied().unwrap_or(0.0),
            largest_translation_m: translations.last().copied().unwrap_or(0.0),
            largest_rotation_deg: frames.iter().map(|f| f.rotation_deg).fold(0.0, f64::max),
            frames,
        }
    }
}

fn one() -> f32 {
    1.0
}

impl FitReport {
    /// Why this fit gave no usable model, if it did not: the divergence
    /// guard skipped most batches, no sample was trained, or the held-out
    /// error is absurd (not finite, or a depth error larger than the whole
    /// scene, the diagonal of the unit cube the scene was mapped into).
    pub fn failure(&self) -> Option<String> {
        let c = &self.counters;
        if c.steps > 0 && c.skipped_batches * 2 > c.steps {
            return Some(format!(
                "the divergence guard skipped {} of {} batches (a learning rate far too high, or data the field cannot fit)",
                c.skipped_batches, c.steps
            ));
        }
        if c.steps > 0 && c.samples == 0 {
            return Some("no training sample fell inside the scene: the scene bounds miss what the cameras see".into());
        }
        let point = self.curve.last()?;
        if !point.psnr.is_finite() {
            return Some(format!("the held-out PSNR is {}", point.psnr));
        }
        let scene_m = self.metres_per_unit * 3f64.sqrt();
        match point.depth_mae_m {
            Some(mae) if !(mae <= scene_m) => Some(format!(
                "the held-out depth error ({mae:.3} m) is larger than the whole scene ({scene_m:.3} m)"
            )),
            _ => None,
        }
    }
}
