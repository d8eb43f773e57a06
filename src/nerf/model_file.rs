//! The model file (`model.nlf`): the shared container (`container`) with
//! a JSON header (configs, scene transform, provenance), the field's
//! parameters and the occupancy grid as sections. Written atomically; every
//! defect on load is a clear error.

use crate::nerf::appearance::{Affine, Vignetting};
use crate::nerf::container::{self, ContainerError, Format, Section, SectionKind};
use crate::nerf::environment::{Environment, ENVIRONMENT_PARAMS};
use crate::nerf::field::{Field, FieldConfig};
use crate::nerf::occupancy::OccupancyGrid;
use crate::nerf::render::march::StepRule;
use crate::nerf::render::rays::{RenderOptions, RENDER_MAX_SAMPLES_PER_RAY};
use crate::nerf::train::settings::TrainConfig;
use crate::poses::{GeometryError, SceneTransform};
use crate::scan::fingerprint::scan_fingerprint;
use crate::scan::Scan;
use serde::{Deserialize, Serialize};
use std::path::{Path, PathBuf};

/// First bytes of every model file.
pub const MAGIC: &[u8; 8] = b"NERFLBL\0";
/// Format version written by this build.
pub const VERSION: u32 = 1;
/// Header JSON larger than this is rejected (room for the fitted poses of
/// the largest scan).
const MAX_HEADER: usize = 1 << 26;
/// Model files larger than this are rejected (4 GiB).
const MAX_FILE: u64 = 1 << 32;
/// The container as model files use it.
const FORMAT: Format = Format {
    magic: MAGIC,
    version: VERSION,
    max_header: MAX_HEADER,
    max_file: MAX_FILE,
    name: "model",
    contents: "parameters",
};
/// Kinds of the sections listed in `ModelHeader::sections`.
const SECTIONS: [SectionKind; 5] = {
    use SectionKind::{F32, U64};
    [F32, F32, F32, F32, U64]
};

/// Everything about a model except its parameters.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct ModelHeader {
    pub nerflabel_version: String,
    pub field: FieldConfig,
    pub train: TrainConfig,
    /// World-to-local similarity (`SceneTransform::to_array`).
    pub scene_transform: Vec<f64>,
    /// Local units per metre (the similarity's scale).
    pub units_per_metre: f64,
    pub occupancy_resolution: usize,
    pub background: [f32; 3],
    /// Coefficients of the learnt colour beyond the cube
    /// (`nerf::environment`); `None`: `background` in every direction.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub environment: Option<Vec<f32>>,
    pub render_step: StepRule,
    pub steps: u64,
    pub seed: u64,
    pub scan: String,
    /// Frame count and fingerprint (`scan::fingerprint`) of the scan it was
    /// fitted to; `None` in models of earlier versions.
    #[serde(default)]
    pub scan_frames: Option<usize>,
    #[serde(default)]
    pub scan_fingerprint: Option<u64>,
    /// Camera-to-world poses the model was fitted with (column-major), one
    /// per scan frame in scan order, where pose refinement changed them;
    /// `None`: the scan's own poses.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub fitted_poses: Option<Vec<[f64; 16]>>,
    /// Each scan frame's appearance map (`nerf::appearance`), in scan
    /// order; `None`: fitted without (the field's colour is every frame's).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub appearance: Option<Vec<Affine>>,
    /// The camera's vignetting (`nerf::appearance::Vignetting`), learnt
    /// with the appearance maps; `None`: fitted without, or before it was learnt.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub vignetting: Option<Vignetting>,
    /// Lengths of the sections: grid, density MLP, colour MLP, occupancy
    /// densities (f32 each), then carved-cell mask (u64 words).
    pub sections: [usize; 5],
}

/// A trained model: field, occupancy grid and header.
#[derive(Clone)]
pub struct Model {
    pub header: ModelHeader,
    pub field: Field,
    pub occupancy: OccupancyGrid,
}

impl Model {
    /// Render settings stored with the model.
    pub fn render_options(&self, color: bool) -> RenderOptions {
        RenderOptions {
            color,
            rule: self.header.render_step,
            max_samples_per_ray: RENDER_MAX_SAMPLES_PER_RAY,
            background: self.header.background,
            environment: self.header.environment.as_deref().and_then(Environment::from_slice),
        }
    }

    /// The appearance map of scan frame `frame`, when the model learnt
    /// appearance and has that frame.
    pub fn frame_appearance(&self, frame: usize) -> Option<Affine> {
        self.header.appearance.as_ref()?.get(frame).copied()
    }

    /// The camera's vignetting, when the model learnt it.
    pub fn vignetting(&self) -> Option<Vignetting> {
        self.header.vignetting
    }

    /// The world-to-local scene transform stored in the model.
    pub fn scene_transform(&self) -> Result<SceneTransform, GeometryError> {
        let values: [f64; SceneTransform::ARRAY_LEN] =
            self.header.scene_transform.as_slice().try_into().map_err(|_| {
                GeometryError::InvalidTransform("the model's scene transform has the wrong length".into())
            })?;
        SceneTransform::from_array(&values)
    }
}

/// Whether a model was fitted to a scan.
#[derive(Clone, Debug, PartialEq)]
pub enum ScanMatch {
    Same,
    /// The model predates scan fingerprints.
    Unknown,
    /// Another scan, or this one since changed: what differs.
    Other(String),
}

/// Why a model file could not be read or written.
#[derive(Debug, thiserror::Error)]
pub enum ModelError {
    #[error("{path}: cannot read the model file: {source}")]
    Read { path: PathBuf, source: std::io::Error },
    #[error("{path}: cannot write the model file: {source}")]
    Write { path: PathBuf, source: std::io::Error },
    #[error("{0}: not a nerflabel model (wrong magic bytes)")]
    Magic(PathBuf),
    #[error("{path}: model format version {found} is not supported (this build reads version {VERSION})")]
    Version { path: PathBuf, found: u32 },
    #[error("{0}: model file is corrupted (checksum mismatch)")]
    Checksum(PathBuf),
    #[error("{path}: model file is damaged: {what}")]
    Damaged { path: PathBuf, what: String },
}

impl Model {
    /// Whether this model was fitted to `scan` as it is now (frames, names,
    /// sizes, intrinsics, poses, which frames have depth).
    pub fn matches_scan(&self, scan: &Scan) -> ScanMatch {
        let (Some(frames), Some(fingerprint)) = (self.header.scan_frames, self.header.scan_fingerprint) else {
            return ScanMatch::Unknown;
        };
        if frames != scan.frames.len() {
            ScanMatch::Other(format!(
                "fitted to {frames} frames, this scan has {}",
                scan.frames.len()
            ))
        } else if fingerprint != scan_fingerprint(scan) {
            ScanMatch::Other(format!(
                "same {frames} frames, but other poses, intrinsics, image sizes or frame names"
            ))
        } else {
            ScanMatch::Same
        }
    }

    /// Give `scan` (the scan this model was fitted to) the poses the model
    /// was fitted with, so that what it renders lines up with the images.
    /// Returns how many frames changed.
    pub fn apply_fitted_poses(&self, scan: &mut Scan) -> usize {
        let Some(poses) = &self.header.fitted_poses else {
            return 0;
        };
        if poses.len() != scan.frames.len() {
            return 0;
        }
        let mut changed = 0;
        for (frame, pose) in scan.frames.iter_mut().zip(poses) {
            // Column-major, as written by `fit`.
            let pose = nalgebra::Matrix4::from_column_slice(pose);
            if pose.iter().all(|x| x.is_finite()) && pose != frame.camera_to_world.to_homogeneous() {
                frame.camera_to_world = crate::scan::isometry(&pose);
                changed += 1;
            }
        }
        changed
    }

    /// Serialise to bytes (header sections filled in from the parameters).
    pub fn to_bytes(&self) -> Vec<u8> {
        let (json, sections) = self
            .contents()
            .unwrap_or_else(|e| panic!("a model header always serialises: {e}"));
        let mut bytes = Vec::new();
        container::write(&mut bytes, &FORMAT, &json, &sections)
            .unwrap_or_else(|e| panic!("a model always fits its file format: {e}"));
        bytes
    }

    /// The header JSON (network configuration, grid resolution and section
    /// lengths taken from the parameters) and the sections; fails only if
    /// the header cannot be written as JSON.
    fn contents(&self) -> Result<(Vec<u8>, [Section<'_>; 5]), serde_json::Error> {
        let mut header = self.header.clone();
        header.field = self.field.config.clone();
        header.occupancy_resolution = self.occupancy.resolution();
        let sections = [
            Section::F32(&self.field.grid.params),
            Section::F32(&self.field.density.params),
            Section::F32(&self.field.color.params),
            Section::F32(self.occupancy.densities()),
            Section::U64(self.occupancy.carved_words()),
        ];
        header.sections = sections.map(|s| s.count());
        Ok((serde_json::to_vec(&header)?, sections))
    }

    /// Write atomically (temp file + rename).
    pub fn save(&self, path: &Path) -> Result<(), ModelError> {
        let write_error = |source| ModelError::Write {
            path: path.to_path_buf(),
            source,
        };
        let (json, sections) = self
            .contents()
            .map_err(|e| write_error(std::io::Error::other(format!("cannot encode the model header: {e}"))))?;
        container::save(path, &FORMAT, &json, &sections).map_err(write_error)
    }

    /// Read and verify a model file.
    pub fn load(path: &Path) -> Result<Model, ModelError> {
        let bytes = container::read(path, &FORMAT).map_err(|e| ModelError::from_container(path, e))?;
        Model::from_bytes(&bytes, path)
    }

    /// Parse bytes; `path` only names the source in errors.
    pub fn from_bytes(bytes: &[u8], path: &Path) -> Result<Model, ModelError> {
        let (header, [grid, density, color, occupancy, carved]) =
            container::decode(bytes, &FORMAT, &SECTIONS, |h: &ModelHeader| h.sections)
                .map_err(|e| ModelError::from_container(path, e))?;
        let field = Field::from_params(header.field.clone(), grid.f32s(), density.f32s(), color.f32s())
            .ok_or_else(|| damaged(path, "parameter counts do not match the network configuration".into()))?;
        let mut occupancy = OccupancyGrid::from_saved(header.occupancy_resolution, occupancy.f32s(), carved.u64s())
            .ok_or_else(|| damaged(path, "occupancy grid size does not match its resolution".into()))?;
        if header
            .environment
            .as_deref()
            .is_some_and(|e| Environment::from_slice(e).is_none())
        {
            return Err(damaged(
                path,
                format!(
                    "the environment needs {ENVIRONMENT_PARAMS} finite coefficients, the file has {}",
                    header.environment.as_ref().map_or(0, Vec::len)
                ),
            ));
        }
        // A model's grid is for rendering: the saved estimates decide what is marched.
        occupancy.restrict_to_rendering();
        Ok(Model {
            header,
            field,
            occupancy,
        })
    }
}

impl ModelError {
    /// The error for a container defect in the model file at `path`.
    fn from_container(path: &Path, error: ContainerError) -> ModelError {
        let path = path.to_path_buf();
        match error {
            ContainerError::Open(source) | ContainerError::Read(source) => ModelError::Read { path, source },
            ContainerError::Magic => ModelError::Magic(path),
            ContainerError::Version(found) => ModelError::Version { path, found },
            ContainerError::Checksum => ModelError::Checksum(path),
            ContainerError::Damaged(what) => ModelError::Damaged { path, what },
        }
    }
}

fn damaged(path: &Path, what: String) -> ModelError {
    ModelError::Damaged {
        path: path.to_path_buf(),
        what,
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::nerf::train::step::tests::small_config;

    fn sample_model() -> Model {
        let (field_cfg, train) = small_config(3);
        let mut rng = crate::rng::Rng::new(3, 0);
        let field = Field::new(field_cfg.clone(), &mut rng);
        let mut occupancy = OccupancyGrid::full(16);
        occupancy.seed_from_depth(
            &[crate::nerf::occupancy::DepthRay {
                origin: [0.53, 0.53, 0.0],
                dir: [0.0, 0.0, 1.0],
                t_hit: 0.9,
            }; 3],
            &[],
        );
        let header = ModelHeader {
            nerflabel_version: "test".into(),
            field: field_cfg,
            train: train.clone(),
            scene_transform: vec![0.0, 0.0, 0.0, 1.0, 0.1, 0.2, 0.3, 0.5],
            units_per_metre: 0.5,
            occupancy_resolution: 16,
            background: [0.1, 0.2, 0.3],
            environment: Some(Environment::uniform([0.7, 0.6, 0.5]).coeffs.to_vec()),
            render_step: train.step,
            steps: 7,
            seed: 3,
            scan: "scan".into(),
            scan_frames: Some(2),
            scan_fingerprint: Some(11),
            fitted_poses: Some(vec![
                std::array::from_fn(
                    |i| nalgebra::Translation3::new(1.0, 0.0, 0.0).to_homogeneous()[i]
                );
                2
            ]),
            appearance: Some(vec![
                crate::nerf::appearance::IDENTITY,
                [0.9, 0.0, 0.0, 0.02, 0.0, 1.1, 0.0, -0.01, 0.0, 0.0, 1.0, 0.0],
            ]),
            vignetting: Some([-0.25, 0.03, -0.01]),
            sections: [0; 5],
        };
        Model {
            header,
            field,
            occupancy,
        }
    }

    #[test]
    fn round_trip_preserves_every_parameter_and_the_occupancy() {
        let model = sample_model();
        let bytes = model.to_bytes();
        let back = Model::from_bytes(&bytes, Path::new("m.nlf")).unwrap();
        assert_eq!(back.field.grid.params, model.field.grid.params);
        assert_eq!(back.field.density.params, model.field.density.params);
        assert_eq!(back.field.color.params, model.field.color.params);
        assert_eq!(back.occupancy.bits(), model.occupancy.bits());
        assert_eq!(back.occupancy.carved_words(), model.occupancy.carved_words());
        assert_eq!(back.header.scene_transform, model.header.scene_transform);
        assert_eq!(
            back.render_options(true).environment,
            model.render_options(true).environment
        );
        assert!(back.render_options(true).environment.is_some());
        assert_eq!(back.to_bytes(), bytes, "saving again gives identical bytes");
    }

    #[test]
    fn an_environment_of_the_wrong_size_is_a_clear_error() {
        let mut model = sample_model();
        model.header.environment = Some(vec![0.5; 7]);
        let err = Model::from_bytes(&model.to_bytes(), Path::new("m.nlf")).err().unwrap();
        assert!(err.to_string().contains("the environment needs 48"), "{err}");
        // Models of earlier versions have none and render the flat background.
        model.header.environment = None;
        let back = Model::from_bytes(&model.to_bytes(), Path::new("m.nlf")).unwrap();
        assert!(back.render_options(true).environment.is_none());
    }

    #[test]
    fn corruption_truncation_and_wrong_magic_or_version_are_clear_errors() {
        let bytes = sample_model().to_bytes();
        let path = Path::new("dir/model.nlf");
        let msg = |b: &[u8]| {
            Model::from_bytes(b, path)
                .err()
                .map(|e| e.to_string())
                .unwrap_or_default()
        };
        // Every single-byte flip in the body is caught.
        for pos in [20usize, bytes.len() / 2, bytes.len() - 5] {
            let mut bad = bytes.clone();
            bad[pos] ^= 0x40;
            assert!(msg(&bad).contains("corrupted"), "flip at {pos}: {}", msg(&bad));
        }
        for cut in [0usize, 7, 15, 19, 100, bytes.len() - 1] {
            let m = msg(&bytes[..cut]);
            assert!(m.starts_with("dir/model.nlf"), "truncated to {cut}: {m}");
        }
        let mut magic = bytes.clone();
        magic[0] = b'X';
        assert!(msg(&magic).contains("not a nerflabel model"));
        let mut version = bytes.clone();
        version[8] = 99;
        assert!(msg(&version).contains("version 99"));
        assert!(msg(b"").contains("not a nerflabel model"));
    }

    #[test]
    fn save_is_atomic_and_load_names_missing_files() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("model.nlf");
        sample_model().save(&path).unwrap();
        assert!(Model::load(&path).is_ok());
        assert_eq!(std::fs::read_dir(dir.path()).unwrap().count(), 1, "no temp file left");
        let err = Model::load(&dir.path().join("missing.nlf")).err().unwrap().to_string();
        assert!(err.contains("missing.nlf"));
    }
}
