//! Errors of the batch module: each names the manifest line, the scan or
//! the file and what was wrong.

use std::path::PathBuf;

/// Why a manifest, a scan's batch run or a merge failed.
#[derive(Debug, thiserror::Error)]
pub enum BatchError {
    #[error("{path}: cannot read the manifest: {source}")]
    ReadManifest { path: PathBuf, source: std::io::Error },
    #[error("{path} line {line}: {problem}")]
    Manifest {
        path: PathBuf,
        line: usize,
        problem: String,
    },
    #[error("{path}: the manifest lists no scans (one JSON object a line, e.g. {{\"scan\": \"scans/kitchen\"}})")]
    EmptyManifest { path: PathBuf },
    #[error("{path}: more than {max} scans; split the manifest")]
    TooManyEntries { path: PathBuf, max: usize },
    #[error("index {index}{from} is past the manifest's last entry ({entries} scans, indices 0 to {last})", last = entries.saturating_sub(1))]
    IndexOutOfRange { index: usize, entries: usize, from: String },
    #[error("{var}={value}: expected an array task index (a whole number from 0)")]
    BadIndexVar { var: String, value: String },
    #[error("{scan}: the scan folder does not exist (manifest line {line})")]
    ScanMissing { scan: PathBuf, line: usize },
    #[error("{scan}: refusing to run this scan twice at once: {source}")]
    Busy {
        scan: PathBuf,
        source: crate::outputs::OutputError,
    },
    #[error("{path}: cannot {action}: {source}")]
    Io {
        path: PathBuf,
        action: String,
        source: std::io::Error,
    },
    #[error("{path}: {problem}")]
    Invalid { path: PathBuf, problem: String },
    #[error("{path}: cannot read or write Parquet: {source}")]
    Parquet {
        path: PathBuf,
        source: parquet::errors::ParquetError,
    },
    #[error("{path}: cannot build the record batch: {source}")]
    Arrow {
        path: PathBuf,
        source: arrow_schema::ArrowError,
    },
    #[error("{path}: {what}")]
    Output { path: PathBuf, what: String },
    #[error(transparent)]
    Outputs(#[from] crate::outputs::OutputError),
}

impl BatchError {
    /// An I/O error on `path` while doing `action` ("read the status file").
    pub fn io(path: &std::path::Path, action: &str) -> impl FnOnce(std::io::Error) -> BatchError {
        let path = path.to_path_buf();
        let action = action.to_string();
        move |source| BatchError::Io { path, action, source }
    }
}
