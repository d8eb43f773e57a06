//! Detect a scan's layout from the files present.

use super::ScanError;
use std::path::Path;

/// Supported scan layouts (FORMATS.md section 1).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Layout {
    Native,
    Tum,
    Nerfstudio,
    Scannet,
    Stray,
}

/// Guess the layout of the scan in `root`.
pub fn detect_layout(root: &Path) -> Result<Layout, ScanError> {
    Err(ScanError::Invalid(root.to_path_buf(), "layout detection not implemented".into()))
}
