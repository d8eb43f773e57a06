//! Errors from reading a scan; every message names the file or frame.

use std::path::PathBuf;

/// Why a scan could not be read.
#[derive(Debug, thiserror::Error)]
pub enum ScanError {
    #[error("{0}: scan folder does not exist")]
    MissingFolder(PathBuf),
    #[error("{0}: not a folder")]
    NotAFolder(PathBuf),
    #[error("{0}: {1}")]
    Invalid(PathBuf, String),
}
