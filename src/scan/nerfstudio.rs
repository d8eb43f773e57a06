//! Placeholder loader (filled in by the scan-reading work).

use super::{LoadOptions, Scan, ScanError};
use std::path::Path;

pub(super) fn load(root: &Path, _options: &LoadOptions) -> Result<Scan, ScanError> {
    Err(ScanError::Invalid(root.to_path_buf(), "layout not supported yet".into()))
}
