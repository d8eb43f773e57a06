//! Scan layouts, their names for `--format`, and detection from the files
//! present in a scan folder.

use super::ScanError;
use std::fmt;
use std::path::Path;
use std::str::FromStr;

/// Supported scan layouts (FORMATS.md section 1).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, clap::ValueEnum)]
pub enum Layout {
    /// nerflabel / autolabel: `rgb/`, `depth/`, `pose/` (world-to-camera), `intrinsics.txt`.
    #[value(alias = "autolabel")]
    Native,
    /// TUM RGB-D: `rgb.txt`, `depth.txt`, `groundtruth.txt`.
    #[value(alias = "tum-rgbd")]
    Tum,
    /// nerfstudio / instant-ngp `transforms.json`.
    #[value(aliases = ["instant-ngp", "ngp", "transforms"])]
    Nerfstudio,
    /// ScanNet export: `color/`, `depth/`, `pose/`, `intrinsic/`.
    Scannet,
    /// Stray Scanner with extracted frames: `rgb/` or `frames/`, `odometry.csv`, `camera_matrix.csv`.
    #[value(alias = "strayscanner")]
    Stray,
    /// COLMAP text model: `sparse/0/cameras.txt` + `images.txt`, `images/`, optional `depth/`.
    Colmap,
}

impl Layout {
    /// Every layout, in detection order.
    pub const ALL: [Layout; 6] = [
        Layout::Native,
        Layout::Nerfstudio,
        Layout::Tum,
        Layout::Scannet,
        Layout::Stray,
        Layout::Colmap,
    ];

    /// Name used by `--format` and in reports.
    pub fn name(self) -> &'static str {
        match self {
            Layout::Native => "native",
            Layout::Tum => "tum",
            Layout::Nerfstudio => "nerfstudio",
            Layout::Scannet => "scannet",
            Layout::Stray => "stray",
            Layout::Colmap => "colmap",
        }
    }
}

impl fmt::Display for Layout {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.name())
    }
}

/// A `--format` value that names no layout.
#[derive(Clone, Debug, PartialEq, Eq, thiserror::Error)]
#[error("unknown scan format '{0}' (expected one of: {names})", names = crate::value_names::<Layout>())]
pub struct ParseLayoutError(pub String);

impl FromStr for Layout {
    type Err = ParseLayoutError;

    /// Accepts the names of [`Layout::name`] (case-insensitive) and a few aliases.
    fn from_str(s: &str) -> Result<Layout, ParseLayoutError> {
        <Layout as clap::ValueEnum>::from_str(s.trim(), true).map_err(|_| ParseLayoutError(s.to_string()))
    }
}

/// Guess the layout of the scan in `root` from the files present.
pub fn detect_layout(root: &Path) -> Result<Layout, ScanError> {
    let has = |name: &str| root.join(name).exists();
    let dir = |name: &str| root.join(name).is_dir();
    if dir("rgb") && dir("pose") {
        return Ok(Layout::Native);
    }
    if has("transforms.json") {
        return Ok(Layout::Nerfstudio);
    }
    if has("rgb.txt") && (has("groundtruth.txt") || has("depth.txt")) {
        return Ok(Layout::Tum);
    }
    if dir("color") && dir("pose") {
        return Ok(Layout::Scannet);
    }
    if has("odometry.csv") {
        return Ok(Layout::Stray);
    }
    if super::colmap::model_dir(root).is_some() {
        return Ok(Layout::Colmap);
    }
    Err(ScanError::UnknownLayout(
        root.to_path_buf(),
        "expected rgb/ + pose/ (native), transforms.json (nerfstudio), rgb.txt + groundtruth.txt (tum), \
         color/ + pose/ (scannet), odometry.csv (stray) or sparse/0/cameras.txt + images.txt (colmap); force one with --format"
            .into(),
    ))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn names_round_trip() {
        for layout in Layout::ALL {
            assert_eq!(layout.name().parse::<Layout>(), Ok(layout));
            assert_eq!(layout.to_string(), layout.name());
        }
        assert_eq!("TUM".parse::<Layout>(), Ok(Layout::Tum));
        assert!("meshroom"
            .parse::<Layout>()
            .unwrap_err()
            .to_string()
            .contains("meshroom"));
    }

    #[test]
    fn detects_from_files() {
        let dir = tempfile::tempdir().unwrap();
        let root = dir.path();
        assert!(matches!(detect_layout(root), Err(ScanError::UnknownLayout(..))));
        std::fs::create_dir_all(root.join("sparse/0")).unwrap();
        std::fs::write(root.join("sparse/0/cameras.txt"), "").unwrap();
        std::fs::write(root.join("sparse/0/images.txt"), "").unwrap();
        assert_eq!(detect_layout(root).unwrap(), Layout::Colmap);
        std::fs::write(root.join("odometry.csv"), "").unwrap();
        assert_eq!(detect_layout(root).unwrap(), Layout::Stray);
        std::fs::create_dir(root.join("color")).unwrap();
        std::fs::create_dir(root.join("pose")).unwrap();
        assert_eq!(detect_layout(root).unwrap(), Layout::Scannet);
        std::fs::write(root.join("rgb.txt"), "").unwrap();
        std::fs::write(root.join("groundtruth.txt"), "").unwrap();
        assert_eq!(detect_layout(root).unwrap(), Layout::Tum);
        std::fs::write(root.join("transforms.json"), "{}").unwrap();
        assert_eq!(detect_layout(root).unwrap(), Layout::Nerfstudio);
        std::fs::create_dir(root.join("rgb")).unwrap();
        assert_eq!(detect_layout(root).unwrap(), Layout::Native);
    }
}
