//! Resumable training state, written beside the model (`model.checkpoint`
//! for `model.nlf`) during every fit: field parameters, Adam moments and
//! step counts, trainer counters, step-size scale and loss average, the
//! training occupancy grid, seconds trained, the curve so far, the fit
//! settings and a fingerprint of the scan, so resuming another scan or other
//! settings is a clear error. Same container as the model file
//! (`container`), written atomically.

use crate::nerf::container::{self, ContainerError, Format, Section, SectionKind};
use crate::nerf::field::{Field, FieldConfig};
use crate::nerf::occupancy::OccupancyGrid;
use crate::nerf::train::adam::Adam;
use crate::nerf::train::fit::FitOptions;
use crate::nerf::train::pose_learning::{PoseLearner, PoseLearnerState};
use crate::nerf::train::report::{CurvePoint, PoseAlignmentReport, Timings};
use crate::nerf::train::settings::{FitSettings, NerfSettings};
use crate::nerf::train::step::{TrainCounters, Trainer};
use crate::scan::fingerprint::{scan_fingerprint, Fnv};
use crate::scan::Scan;
use serde::{Deserialize, Serialize};
use std::io;
use std::path::{Path, PathBuf};

/// First bytes of every checkpoint file.
pub const MAGIC: &[u8; 8] = b"NLFCKPT\0";
/// Format version written by this build.
pub const VERSION: u32 = 1;
/// Header JSON larger than this is rejected (the curve grows by one point per evaluation).
const MAX_HEADER: usize = 64 << 20;
/// Checkpoint files larger than this are rejected (16 GiB).
const MAX_FILE: u64 = 1 << 34;
/// The container as checkpoints use it.
const FORMAT: Format = Format {
    magic: MAGIC,
    version: VERSION,
    max_header: MAX_HEADER,
    max_file: MAX_FILE,
    name: "checkpoint",
    contents: "arrays",
};
/// Sections: grid, density MLP, colour MLP, occupancy densities (f32),
/// carved mask (u64), then Adam first and second moments of grid, density
/// MLP and colour MLP (f32).
const SECTIONS: [SectionKind; 11] = {
    use SectionKind::{F32, U64};
    [F32, F32, F32, F32, U64, F32, F32, F32, F32, F32, F32]
};

/// Where the checkpoint of a model lives: `model.nlf` -> `model.checkpoint`.
pub fn checkpoint_path(model: &Path) -> PathBuf {
    if model.extension().is_some_and(|e| e == "checkpoint") {
        // Never the model path itself.
        let name = model
            .file_name()
            .map(|n| n.to_string_lossy().into_owned())
            .unwrap_or_default();
        return model.with_file_name(format!("{name}.checkpoint"));
    }
    model.with_extension("checkpoint")
}

/// What a checkpoint must match to be resumed: scan, settings and budget.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct FitIdentity {
    /// Hash of frame names, sizes, intrinsics, poses and depth presence.
    pub scan_fingerprint: u64,
    pub frames: usize,
    pub settings: FitSettings,
    /// Hash of the network and training configuration derived from the scan.
    pub settings_fingerprint: u64,
    /// Budget the fit was started with (a resume without one keeps it).
    pub time: Option<f64>,
    pub steps: Option<u64>,
}

impl FitIdentity {
    /// Identity of a fit of `scan` with `opts` and the derived `settings`.
    pub fn new(scan: &Scan, opts: &FitOptions, settings: &NerfSettings) -> FitIdentity {
        let derived = serde_json::to_string(&(
            &settings.field,
            &settings.train,
            settings.occupancy_resolution,
            &settings.render_step,
        ))
        .unwrap_or_default();
        let mut h = Fnv::new();
        h.bytes(derived.as_bytes());
        FitIdentity {
            scan_fingerprint: scan_fingerprint(scan),
            frames: scan.frames.len(),
            settings: opts.settings.clone(),
            settings_fingerprint: h.finish(),
            time: opts.time,
            steps: opts.steps,
        }
    }
}

/// Progress of a fit kept outside the trainer, saved with it.
#[derive(Clone, Debug, Default, Serialize, Deserialize)]
pub struct FitProgress {
    /// Training wall time so far (evaluation and checkpoints excluded).
    pub train_seconds: f64,
    /// Training seconds and samples at the last curve point.
    pub last_point: (f64, u64),
    pub timings: Timings,
    pub curve: Vec<CurvePoint>,
    /// Steps at which the fit was resumed.
    pub resumed_from: Vec<u64>,
    /// Whether training stopped on request before its budget.
    pub interrupted: bool,
    /// What each pass of aligning the images to the field did.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub pose_alignment: Vec<PoseAlignmentReport>,
    /// The poses training went on with after that (camera-to-world,
    /// column-major, scan order); empty when it changed none.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub aligned_poses: Vec<[f64; 16]>,
}

/// Everything in a checkpoint besides the arrays.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct CheckpointHeader {
    pub nerflabel_version: String,
    pub identity: FitIdentity,
    pub progress: FitProgress,
    pub field: FieldConfig,
    pub counters: TrainCounters,
    pub occupancy_resolution: usize,
    pub refresh_phase: usize,
    /// Updates applied by the grid, density and colour optimisers.
    pub adam_steps: [u64; 3],
    /// Bits of the f32 step-size scale and f64 loss average (exact round trip).
    pub lr_scale_bits: u32,
    pub loss_ema_bits: u64,
    /// Lengths of the sections (see `SECTIONS`).
    pub sections: [usize; SECTIONS.len()],
    /// The appearance maps and their optimiser, when learnt.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub appearance: Option<LearnerState>,
    /// The lens's vignetting and its optimiser, learnt with the maps
    /// (absent from checkpoints of earlier versions: those resume with a
    /// neutral lens).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub lens: Option<LearnerState>,
    /// The environment's coefficients and optimiser, when learnt.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub environment: Option<LearnerState>,
    /// The pose learner's optimiser, when poses are learnt.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub pose_learning: Option<PoseLearnerState>,
}

/// A small learnt parameter vector (appearance maps, the environment) and
/// its Adam state as f32 bit patterns (exact round trip through JSON; a few
/// hundred numbers per frame at most).
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct LearnerState {
    #[serde(rename = "deltas")]
    pub values: Vec<u32>,
    pub m: Vec<u32>,
    pub v: Vec<u32>,
    pub steps: u64,
}

impl LearnerState {
    fn of(values: &[f32], adam: &Adam) -> Self {
        let bits = |x: &[f32]| x.iter().map(|v| v.to_bits()).collect();
        let (m, v) = adam.moments();
        LearnerState {
            values: bits(values),
            m: bits(m),
            v: bits(v),
            steps: adam.steps(),
        }
    }

    /// Restore into `values` and `adam`; false when the sizes differ.
    fn restore(&self, values: &mut [f32], adam: &mut Adam) -> bool {
        let floats = |x: &[u32]| x.iter().map(|&b| f32::from_bits(b)).collect::<Vec<f32>>();
        if self.values.len() != values.len() {
            return false;
        }
        values.copy_from_slice(&floats(&self.values));
        adam.restore(floats(&self.m), floats(&self.v), self.steps)
    }
}

/// A checkpoint read from disk.
pub struct Checkpoint {
    pub path: PathBuf,
    pub header: CheckpointHeader,
    field: Field,
    occupancy: OccupancyGrid,
    /// Adam (first, second) moments of grid, density MLP and colour MLP.
    moments: [(Vec<f32>, Vec<f32>); 3],
}

/// Why a checkpoint could not be written, read or resumed.
#[derive(Debug, thiserror::Error)]
pub enum CheckpointError {
    #[error("{0}: no checkpoint to resume from (every fit writes one beside its model; run `nerflabel fit` without --resume first)")]
    Missing(PathBuf),
    #[error("{path}: cannot read the checkpoint: {source}")]
    Read { path: PathBuf, source: io::Error },
    #[error("{path}: cannot write the checkpoint: {source}")]
    Write { path: PathBuf, source: io::Error },
    #[error("{0}: not a nerflabel checkpoint (wrong magic bytes)")]
    Magic(PathBuf),
    #[error("{path}: checkpoint format version {found} is not supported (this build reads version {VERSION})")]
    Version { path: PathBuf, found: u32 },
    #[error("{0}: checkpoint is corrupted (checksum mismatch)")]
    Checksum(PathBuf),
    #[error("{path}: checkpoint is damaged: {what}")]
    Damaged { path: PathBuf, what: String },
    #[error("{path}: the checkpoint belongs to another scan ({what}); fit without --resume to start over")]
    OtherScan { path: PathBuf, what: String },
    #[error("{path}: the checkpoint was written with {what}; resume with the same settings or fit without --resume to start over")]
    OtherSettings { path: PathBuf, what: String },
}

/// Save the state of `trainer` and `progress` to `path` atomically.
pub fn save(
    path: &Path,
    identity: &FitIdentity,
    progress: &FitProgress,
    trainer: &Trainer,
) -> Result<(), CheckpointError> {
    let (adams, lr_scale, loss_ema) = trainer.optimiser();
    let field = &trainer.field;
    let [grid, density, color] = adams.map(|a| a.moments());
    let sections = [
        Section::F32(&field.grid.params),
        Section::F32(&field.density.params),
        Section::F32(&field.color.params),
        Section::F32(trainer.occupancy.densities()),
        Section::U64(trainer.occupancy.carved_words()),
        Section::F32(grid.0),
        Section::F32(grid.1),
        Section::F32(density.0),
        Section::F32(density.1),
        Section::F32(color.0),
        Section::F32(color.1),
    ];
    let header = CheckpointHeader {
        nerflabel_version: env!("CARGO_PKG_VERSION").to_string(),
        identity: identity.clone(),
        progress: progress.clone(),
        field: field.config.clone(),
        counters: trainer.counters,
        occupancy_resolution: trainer.occupancy.resolution(),
        refresh_phase: trainer.occupancy.refresh_phase(),
        adam_steps: adams.map(|a| a.steps()),
        lr_scale_bits: lr_scale.to_bits(),
        loss_ema_bits: loss_ema.to_bits(),
        sections: sections.map(|s| s.count()),
        appearance: trainer
            .appearance
            .as_ref()
            .map(|a| LearnerState::of(&a.deltas, &a.adam)),
        lens: trainer
            .appearance
            .as_ref()
            .map(|a| LearnerState::of(&a.lens, &a.lens_adam)),
        environment: trainer
            .environment
            .as_ref()
            .map(|e| LearnerState::of(&e.environment.coeffs, &e.adam)),
        pose_learning: trainer.poses.as_ref().map(PoseLearner::state),
    };
    let write_error = |source| CheckpointError::Write {
        path: path.to_path_buf(),
        source,
    };
    let json = serde_json::to_vec(&header).map_err(|e| write_error(e.into()))?;
    container::save(path, &FORMAT, &json, &sections).map_err(write_error)
}

impl CheckpointError {
    /// The error for a container defect in the checkpoint at `path`.
    fn from_container(path: &Path, error: ContainerError) -> CheckpointError {
        let path = path.to_path_buf();
        match error {
            ContainerError::Open(e) if e.kind() == io::ErrorKind::NotFound => CheckpointError::Missing(path),
            ContainerError::Open(source) | ContainerError::Read(source) => CheckpointError::Read { path, source },
            ContainerError::Magic => CheckpointError::Magic(path),
            ContainerError::Version(found) => CheckpointError::Version { path, found },
            ContainerError::Checksum => CheckpointError::Checksum(path),
            ContainerError::Damaged(what) => CheckpointError::Damaged { path, what },
        }
    }
}

fn damaged(path: &Path, what: impl Into<String>) -> CheckpointError {
    CheckpointError::Damaged {
        path: path.to_path_buf(),
        what: what.into(),
    }
}

impl Checkpoint {
    /// Read and verify a checkpoint file.
    pub fn load(path: &Path) -> Result<Checkpoint, CheckpointError> {
        let bytes = container::read(path, &FORMAT).map_err(|e| CheckpointError::from_container(path, e))?;
        Checkpoint::from_bytes(&bytes, path)
    }

    /// Parse bytes; `path` names the source in errors.
    pub fn from_bytes(bytes: &[u8], path: &Path) -> Result<Checkpoint, CheckpointError> {
        let (header, [grid, density, color, occ, carved, grid_m, grid_v, density_m, density_v, color_m, color_v]) =
            container::decode(bytes, &FORMAT, &SECTIONS, |h: &CheckpointHeader| h.sections)
                .map_err(|e| CheckpointError::from_container(path, e))?;
        let (grid, density, color) = (grid.f32s(), density.f32s(), color.f32s());
        let moments = [
            (grid_m.f32s(), grid_v.f32s()),
            (density_m.f32s(), density_v.f32s()),
            (color_m.f32s(), color_v.f32s()),
        ];
        let lengths = [grid.len(), density.len(), color.len()];
        if moments
            .iter()
            .zip(lengths)
            .any(|((m, v), n)| m.len() != n || v.len() != n)
        {
            return Err(damaged(path, "optimiser moments do not match the parameter counts"));
        }
        let field = Field::from_params(header.field.clone(), grid, density, color)
            .ok_or_else(|| damaged(path, "parameter counts do not match the network configuration"))?;
        let mut occupancy = OccupancyGrid::from_saved(header.occupancy_resolution, occ.f32s(), carved.u64s())
            .ok_or_else(|| damaged(path, "occupancy grid size does not match its resolution"))?;
        occupancy.set_refresh_phase(header.refresh_phase);
        Ok(Checkpoint {
            path: path.to_path_buf(),
            header,
            field,
            occupancy,
            moments,
        })
    }

    /// Steps trained so far.
    pub fn steps(&self) -> u64 {
        self.header.counters.steps
    }

    /// Whether this checkpoint continues a fit of `identity`'s scan and
    /// settings (the budget may differ); the error names what differs.
    pub fn check(&self, identity: &FitIdentity) -> Result<(), CheckpointError> {
        let saved = &self.header.identity;
        if saved.frames != identity.frames {
            return Err(CheckpointError::OtherScan {
                path: self.path.clone(),
                what: format!("written for {} frames, this scan has {}", saved.frames, identity.frames),
            });
        }
        if saved.scan_fingerprint != identity.scan_fingerprint {
            return Err(CheckpointError::OtherScan {
                path: self.path.clone(),
                what: format!(
                    "same {} frames, but other poses, intrinsics, image sizes or frame names",
                    saved.frames
                ),
            });
        }
        let diffs = saved.settings.differences(&identity.settings);
        if !diffs.is_empty() {
            return Err(CheckpointError::OtherSettings {
                path: self.path.clone(),
                what: diffs.join(", "),
            });
        }
        if saved.settings_fingerprint != identity.settings_fingerprint {
            return Err(CheckpointError::OtherSettings {
                path: self.path.clone(),
                what: format!(
                    "network and training settings of nerflabel {} that this build derives differently",
                    self.header.nerflabel_version
                ),
            });
        }
        Ok(())
    }

    /// Move the saved state into `trainer` (built for the same settings) and
    /// return the fit's progress.
    pub fn restore(self, trainer: &mut Trainer) -> Result<FitProgress, CheckpointError> {
        let path = self.path;
        if self.field.config != trainer.field.config || self.occupancy.resolution() != trainer.occupancy.resolution() {
            return Err(damaged(&path, "network or occupancy sizes differ from this fit's"));
        }
        let h = self.header;
        let appearance_restored = match (&h.appearance, &mut trainer.appearance) {
            (Some(saved), Some(learner)) => {
                let lens_restored = h
                    .lens
                    .as_ref()
                    .is_none_or(|lens| lens.restore(&mut learner.lens, &mut learner.lens_adam));
                saved.restore(&mut learner.deltas, &mut learner.adam) && lens_restored
            }
            (None, None) => true,
            _ => false,
        };
        let environment_restored = match (&h.environment, &mut trainer.environment) {
            (Some(saved), Some(learner)) => saved.restore(&mut learner.environment.coeffs, &mut learner.adam),
            (None, None) => true,
            _ => false,
        };
        if !environment_restored {
            return Err(damaged(&path, "the learnt environment does not match this fit's"));
        }
        if !appearance_restored {
            return Err(damaged(
                &path,
                "appearance maps do not match this fit's training frames",
            ));
        }
        let poses_restored = match (&h.pose_learning, &mut trainer.poses) {
            (Some(saved), Some(learner)) => learner.restore(saved),
            (None, None) => true,
            _ => false,
        };
        if !poses_restored {
            return Err(damaged(
                &path,
                "pose learning does not match this fit's training frames",
            ));
        }
        let (adams, lr_scale, loss_ema) = trainer.optimiser_mut();
        for ((adam, (m, v)), steps) in adams.into_iter().zip(self.moments).zip(h.adam_steps) {
            if !adam.restore(m, v, steps) {
                return Err(damaged(&path, "optimiser moments do not match the parameter counts"));
            }
        }
        *lr_scale = f32::from_bits(h.lr_scale_bits);
        *loss_ema = f64::from_bits(h.loss_ema_bits);
        trainer.field = self.field;
        trainer.occupancy = self.occupancy;
        trainer.counters = h.counters;
        Ok(h.progress)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::nerf::train::settings::Preset;
    use crate::nerf::train::step::tests::{plane_views, small_config};
    use crate::rng::Rng;

    fn trained(steps: usize) -> Trainer {
        let (field_cfg, train) = small_config(9);
        let field = Field::new(field_cfg, &mut Rng::new(9, 0));
        let mut t = Trainer::new(field, OccupancyGrid::full(16), train, [0.5; 3]);
        t.learn_appearance(3);
        t.learn_environment();
        let views = plane_views(3, 16, true);
        for s in 0..steps {
            t.step(&views, s as f32 / 70.0);
        }
        t
    }

    /// A trainer for the same settings as [`trained`], with other initial weights.
    fn untrained() -> Trainer {
        let (field_cfg, train) = small_config(9);
        Trainer::new(
            Field::new(field_cfg, &mut Rng::new(1, 0)),
            OccupancyGrid::full(16),
            train,
            [0.5; 3],
        )
    }

    fn identity() -> FitIdentity {
        FitIdentity {
            scan_fingerprint: 7,
            frames: 3,
            settings: FitSettings {
                seed: 9,
                preset: Preset::Fast,
                holdout_every: 0,
                lambda_depth: 0.3,
                unseen_objects: false,
                ..FitSettings::default()
            },
            settings_fingerprint: 11,
            time: None,
            steps: Some(40),
        }
    }

    #[test]
    fn save_then_restore_continues_bit_for_bit() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("model.checkpoint");
        let views = plane_views(3, 16, true);
        // Past warm-up (32) and two occupancy refreshes, so the refresh phase matters.
        let mut a = trained(50);
        let progress = FitProgress {
            train_seconds: 1.5,
            last_point: (1.0, 99),
            ..FitProgress::default()
        };
        save(&path, &identity(), &progress, &a).unwrap();
        assert_eq!(std::fs::read_dir(dir.path()).unwrap().count(), 1, "no temp file left");
        let ckpt = Checkpoint::load(&path).unwrap();
        assert_eq!(ckpt.steps(), 50);
        assert_ne!(ckpt.header.refresh_phase, 0);
        ckpt.check(&identity()).unwrap();
        // A fresh trainer (other initial weights) takes over the saved state.
        let mut b = untrained();
        b.learn_appearance(3);
        b.learn_environment();
        let back = ckpt.restore(&mut b).unwrap();
        assert_eq!((back.train_seconds, back.last_point), (1.5, (1.0, 99)));
        for s in 50..70 {
            a.step(&views, s as f32 / 70.0);
            b.step(&views, s as f32 / 70.0);
        }
        assert_eq!(a.field.grid.params, b.field.grid.params);
        assert_eq!(a.field.density.params, b.field.density.params);
        assert_eq!(a.field.color.params, b.field.color.params);
        let maps = |t: &Trainer| t.appearance.as_ref().unwrap().deltas.clone();
        assert_eq!(maps(&a), maps(&b));
        assert!(maps(&a).iter().any(|&d| d != 0.0), "the maps learnt after warm-up");
        let lens = |t: &Trainer| t.appearance.as_ref().unwrap().lens;
        assert_eq!(lens(&a), lens(&b));
        assert!(lens(&a).iter().any(|&k| k != 0.0), "the lens learnt after warm-up");
        let environment = |t: &Trainer| t.environment.as_ref().unwrap().environment;
        assert_eq!(environment(&a), environment(&b));
        assert_eq!(a.occupancy.densities(), b.occupancy.densities());
        assert_eq!(a.counters.steps, 70);
        assert!(a.counters.occupancy_refreshes >= 3);
        assert_eq!(b.counters.samples, a.counters.samples);
    }

    #[test]
    fn mismatches_and_damage_are_clear_errors() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("m.checkpoint");
        save(&path, &identity(), &FitProgress::default(), &trained(2)).unwrap();
        let ckpt = Checkpoint::load(&path).unwrap();
        let msg = |id: FitIdentity| ckpt.check(&id).unwrap_err().to_string();
        let m = msg(FitIdentity {
            frames: 4,
            ..identity()
        });
        assert!(
            m.contains("another scan") && m.contains("3 frames") && m.contains("has 4"),
            "{m}"
        );
        let m = msg(FitIdentity {
            scan_fingerprint: 8,
            ..identity()
        });
        assert!(m.contains("other poses"), "{m}");
        let mut other = identity();
        other.settings.seed = 1;
        other.settings.learning_rate = 10.0;
        other.settings.preset = Preset::Quality;
        other.settings.pose_scale = Some(2.0);
        let m = msg(other);
        assert!(
            m.contains("--seed 9 (this run: 1)")
                && m.contains("--learning-rate 0.01 (this run: 10)")
                && m.contains("--preset fast (this run: quality)")
                && m.contains("--pose-scale not given (this run: 2)"),
            "{m}"
        );
        let mut other = identity();
        other.settings.unseen_objects = true;
        let m = msg(other);
        assert!(
            m.contains("with --no-unseen-objects (this run: without --no-unseen-objects)"),
            "{m}"
        );
        let mut other = identity();
        other.settings.refine_poses = false;
        let m = msg(other);
        assert!(
            m.contains("without --no-pose-refine (this run: with --no-pose-refine)"),
            "{m}"
        );
        let mut other = identity();
        other.settings.per_frame_appearance = false;
        let m = msg(other);
        assert!(
            m.contains("without --no-appearance (this run: with --no-appearance)"),
            "{m}"
        );
        // Maps for another number of training frames, or none, are damage;
        // so is a trainer without the environment the checkpoint has.
        let restore_error = |t: &mut Trainer| Checkpoint::load(&path).unwrap().restore(t).err().unwrap().to_string();
        for frames in [None, Some(4)] {
            let mut t = untrained();
            t.learn_environment();
            if let Some(n) = frames {
                t.learn_appearance(n);
            }
            let m = restore_error(&mut t);
            assert!(m.contains("appearance maps do not match"), "{m}");
        }
        let mut t = untrained();
        t.learn_appearance(3);
        let m = restore_error(&mut t);
        assert!(m.contains("environment does not match"), "{m}");
        let m = msg(FitIdentity {
            settings_fingerprint: 12,
            ..identity()
        });
        assert!(m.contains("derives differently"), "{m}");
        // A larger budget is fine.
        ckpt.check(&FitIdentity {
            steps: Some(400),
            time: Some(3.0),
            ..identity()
        })
        .unwrap();

        let bytes = std::fs::read(&path).unwrap();
        for cut in [0usize, 8, 19, 100, bytes.len() / 2, bytes.len() - 1] {
            let m = Checkpoint::from_bytes(&bytes[..cut], &path).err().unwrap().to_string();
            assert!(
                m.starts_with(&path.display().to_string()) && !m.contains('\n'),
                "cut {cut}: {m}"
            );
        }
        let mut flipped = bytes.clone();
        flipped[bytes.len() / 2] ^= 4;
        assert!(Checkpoint::from_bytes(&flipped, &path)
            .err()
            .unwrap()
            .to_string()
            .contains("corrupted"));
        let missing = Checkpoint::load(&dir.path().join("none.checkpoint"))
            .err()
            .unwrap()
            .to_string();
        assert!(
            missing.contains("none.checkpoint") && missing.contains("without --resume"),
            "{missing}"
        );
    }

    #[test]
    fn checkpoint_path_sits_beside_the_model_and_never_on_it() {
        assert_eq!(
            checkpoint_path(Path::new("s/nerflabel/model.nlf")),
            Path::new("s/nerflabel/model.checkpoint")
        );
        assert_eq!(checkpoint_path(Path::new("m")), Path::new("m.checkpoint"));
        assert_eq!(
            checkpoint_path(Path::new("a.checkpoint")),
            Path::new("a.checkpoint.checkpoint")
        );
    }
}
