//! The model file (`model.nlf`): magic, version, JSON header (configs,
//! scene transform, provenance), raw little-endian f32 sections, and a CRC32
//! of everything before it. Written atomically; every defect on load is a
//! clear error.

use crate::nerf::field::{Field, FieldConfig};
use crate::nerf::occupancy::OccupancyGrid;
use crate::nerf::render::march::StepRule;
use crate::nerf::render::rays::{RenderOptions, RENDER_MAX_SAMPLES_PER_RAY};
use crate::poses::{GeometryError, SceneTransform};
use crate::nerf::train::settings::TrainConfig;
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
        }
    }

    /// The world-to-local scene transform stored in the model.
    pub fn scene_transform(&self) -> Result<SceneTransform, GeometryError> {
        let values: [f64; SceneTransform::ARRAY_LEN] = self
            .header
            .scene_transform
            .as_slice()
            .try_into()
            .map_err(|_| GeometryError::InvalidTransform("the model's scene transform has the wrong length".into()))?;
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
            ScanMatch::Other(format!("fitted to {frames} frames, this scan has {}", scan.frames.len()))
        } else if fingerprint != scan_fingerprint(scan) {
            ScanMatch::Other(format!("same {frames} frames, but other poses, intrinsics, image sizes or frame names"))
        } else {
            ScanMatch::Same
        }
    }

    /// Give `scan` (the scan this model was fitted to) the poses the model
    /// was fitted with, so that what it renders lines up with the images.
    /// Returns how many frames changed.
    pub fn apply_fitted_poses(&self, scan: &mut Scan) -> usize {
        let Some(poses) = &self.header.fitted_poses else { return 0 };
        if poses.len() != scan.frames.len() {
            return 0;
        }
        let mut changed = 0;
        for (frame, pose) in scan.frames.iter_mut().zip(poses) {
            let pose = glam::DMat4::from_cols_array(pose);
            if pose.is_finite() && pose != frame.camera_to_world {
                frame.camera_to_world = pose;
                changed += 1;
            }
        }
        changed
    }

    /// Serialise to bytes (header sections filled in from the parameters).
    pub fn to_bytes(&self) -> Vec<u8> {
        self.try_to_bytes().unwrap_or_else(|e| panic!("a model header always serialises: {e}"))
    }

    /// Serialise to bytes; fails only if the header cannot be written as JSON.
    fn try_to_bytes(&self) -> Result<Vec<u8>, serde_json::Error> {
        let mut header = self.header.clone();
        header.field = self.field.config.clone();
        header.occupancy_resolution = self.occupancy.resolution();
        let sections: [&[f32]; 4] =
            [&self.field.grid.params, &self.field.density.params, &self.field.color.params, self.occupancy.densities()];
        let carved = self.occupancy.carved_words();
        let [g, d, c, o] = sections.map(|s| s.len());
        header.sections = [g, d, c, o, carved.len()];
        let json = serde_json::to_vec(&header)?;
        let floats: usize = sections.iter().map(|s| s.len()).sum();
        let mut bytes = Vec::with_capacity(20 + json.len() + 4 * floats + 8 * carved.len() + 4);
        bytes.extend_from_slice(MAGIC);
        bytes.extend_from_slice(&VERSION.to_le_bytes());
        bytes.extend_from_slice(&(json.len() as u32).to_le_bytes());
        bytes.extend_from_slice(&json);
        for section in sections {
            for v in section {
                bytes.extend_from_slice(&v.to_le_bytes());
            }
        }
        for w in carved {
            bytes.extend_from_slice(&w.to_le_bytes());
        }
        let crc = crc32fast::hash(&bytes);
        bytes.extend_from_slice(&crc.to_le_bytes());
        Ok(bytes)
    }

    /// Write atomically (temp file + rename).
    pub fn save(&self, path: &Path) -> Result<(), ModelError> {
        let bytes = self.try_to_bytes().map_err(|e| ModelError::Write { path: path.to_path_buf(), source: std::io::Error::other(format!("cannot encode the model header: {e}")) })?;
        crate::atomic::write_file(path, &bytes).map_err(|source| ModelError::Write { path: path.to_path_buf(), source })
    }

    /// Read and verify a model file.
    pub fn load(path: &Path) -> Result<Model, ModelError> {
        let read_err = |source| ModelError::Read { path: path.to_path_buf(), source };
        let size = std::fs::metadata(path).map_err(read_err)?.len();
        if size > MAX_FILE {
            return Err(damaged(path, format!("{size} bytes is larger than any model")));
        }
        let bytes = std::fs::read(path).map_err(read_err)?;
        Model::from_bytes(&bytes, path)
    }

    /// Parse bytes; `path` only names the source in errors.
    pub fn from_bytes(bytes: &[u8], path: &Path) -> Result<Model, ModelError> {
        if bytes.len() < 8 || &bytes[..8] != MAGIC {
            return Err(ModelError::Magic(path.to_path_buf()));
        }
        if bytes.len() < 20 {
            return Err(damaged(path, "truncated header".into()));
        }
        let version = u32::from_le_bytes([bytes[8], bytes[9], bytes[10], bytes[11]]);
        if version != VERSION {
            return Err(ModelError::Version { path: path.to_path_buf(), found: version });
        }
        let (body, crc_bytes) = bytes.split_at(bytes.len() - 4);
        let stored = u32::from_le_bytes([crc_bytes[0], crc_bytes[1], crc_bytes[2], crc_bytes[3]]);
        if crc32fast::hash(body) != stored {
            return Err(ModelError::Checksum(path.to_path_buf()));
        }
        let header_len = u32::from_le_bytes([bytes[12], bytes[13], bytes[14], bytes[15]]) as usize;
        if header_len > MAX_HEADER || 16 + header_len > body.len() {
            return Err(damaged(path, format!("header length {header_len} does not fit the file")));
        }
        let header: ModelHeader = serde_json::from_slice(&body[16..16 + header_len])
            .map_err(|e| damaged(path, format!("header is not valid: {e}")))?;
        let [g, d, c, o, words] = header.sections;
        let floats = [g, d, c, o].iter().try_fold(0usize, |acc, &n| acc.checked_add(n));
        let bytes_needed = floats
            .and_then(|f| f.checked_mul(4))
            .and_then(|f| words.checked_mul(8).and_then(|w| w.checked_add(f)))
            .ok_or_else(|| damaged(path, "section sizes overflow".into()))?;
        let data = &body[16 + header_len..];
        if bytes_needed != data.len() {
            return Err(damaged(path, format!("expected {bytes_needed} bytes of parameters, found {}", data.len())));
        }
        let (float_bytes, word_bytes) = data.split_at(bytes_needed - 8 * words);
        let mut values = float_bytes.chunks_exact(4).map(|c| f32::from_le_bytes([c[0], c[1], c[2], c[3]]));
        let mut take = |n: usize| -> Vec<f32> { values.by_ref().take(n).collect() };
        let (grid, density, color, occupancy) = (take(g), take(d), take(c), take(o));
        let carved: Vec<u64> =
            word_bytes.chunks_exact(8).map(|c| u64::from_le_bytes([c[0], c[1], c[2], c[3], c[4], c[5], c[6], c[7]])).collect();
        let field = Field::from_params(header.field.clone(), grid, density, color)
            .ok_or_else(|| damaged(path, "parameter counts do not match the network configuration".into()))?;
        let mut occupancy = OccupancyGrid::from_saved(header.occupancy_resolution, occupancy, carved)
            .ok_or_else(|| damaged(path, "occupancy grid size does not match its resolution".into()))?;
        // A model's grid is for rendering: the saved estimates decide what is marched.
        occupancy.restrict_to_rendering();
        Ok(Model { header, field, occupancy })
    }
}

fn damaged(path: &Path, what: String) -> ModelError {
    ModelError::Damaged { path: path.to_path_buf(), what }
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
        occupancy.seed_from_depth(&[crate::nerf::occupancy::DepthRay { origin: [0.53, 0.53, 0.0], dir: [0.0, 0.0, 1.0], t_hit: 0.9 }; 3], &[]);
        let header = ModelHeader {
            nerflabel_version: "test".into(),
            field: field_cfg,
            train: train.clone(),
            scene_transform: vec![0.0, 0.0, 0.0, 1.0, 0.1, 0.2, 0.3, 0.5],
            units_per_metre: 0.5,
            occupancy_resolution: 16,
            background: [0.1, 0.2, 0.3],
            render_step: train.step,
            steps: 7,
            seed: 3,
            scan: "scan".into(),
            scan_frames: Some(2),
            scan_fingerprint: Some(11),
            fitted_poses: Some(vec![glam::DMat4::from_translation(glam::DVec3::X).to_cols_array(); 2]),
            sections: [0; 5],
        };
        Model { header, field, occupancy }
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
        assert_eq!(back.to_bytes(), bytes, "saving again gives identical bytes");
    }

    #[test]
    fn corruption_truncation_and_wrong_magic_or_version_are_clear_errors() {
        let bytes = sample_model().to_bytes();
        let path = Path::new("dir/model.nlf");
        let msg = |b: &[u8]| Model::from_bytes(b, path).err().map(|e| e.to_string()).unwrap_or_default();
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
