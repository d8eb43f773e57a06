//! Errors from reading a scan; every message is one line that names the
//! file or frame and the problem.

use std::path::PathBuf;

/// Why a scan could not be read.
#[derive(Debug, thiserror::Error)]
pub enum ScanError {
    /// The scan folder itself is missing.
    #[error("{0}: scan folder does not exist")]
    MissingFolder(PathBuf),
    /// The scan path is a file.
    #[error("{0}: not a folder")]
    NotAFolder(PathBuf),
    /// Anything else wrong with a file, with a free-form reason.
    #[error("{0}: {1}")]
    Invalid(PathBuf, String),
    /// A file or folder the layout needs is absent.
    #[error("{path}: missing ({what})")]
    MissingFile { path: PathBuf, what: String },
    /// A file could not be read from disk.
    #[error("{path}: cannot read: {source}")]
    Io {
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
    /// A text file does not parse; `line` is 1-based, 0 for the whole file.
    #[error("{}", fmt_parse(path, *line, reason))]
    Parse { path: PathBuf, line: usize, reason: String },
    /// The layout could not be recognised from the files present.
    #[error("{0}: cannot tell the scan layout: {1}")]
    UnknownLayout(PathBuf, String),
    /// No usable frame was found.
    #[error("{0}: no frames: {1}")]
    NoFrames(PathBuf, String),
    /// More frames than [`super::MAX_FRAMES`].
    #[error("{path}: too many frames ({count}, at most {max} are accepted)")]
    TooManyFrames { path: PathBuf, count: usize, max: usize },
    /// A frame lacks a part it needs (rgb or pose), or has it twice.
    #[error("frame {frame}: {reason}")]
    Frame { frame: String, reason: String },
    /// A pose is not a finite rigid transform.
    #[error("{source_name}: {reason}")]
    Pose { source_name: String, reason: String },
    /// An image does not decode or has an unusable header.
    #[error("{path}: {reason}")]
    Image { path: PathBuf, reason: String },
    /// A depth image is not a 16-bit single-channel PNG.
    #[error("{path}: expected a 16-bit single-channel PNG, found {found}")]
    DepthFormat { path: PathBuf, found: String },
    /// Colour frames do not all have the same size.
    #[error("{path}: image size {found_w}x{found_h} differs from the first frame's {want_w}x{want_h} ({first})")]
    SizeMismatch {
        path: PathBuf,
        found_w: u32,
        found_h: u32,
        want_w: u32,
        want_h: u32,
        first: String,
    },
    /// Intrinsics are not plausible for the image they belong to.
    #[error("{path}: bad intrinsics: {reason}")]
    Intrinsics { path: PathBuf, reason: String },
    /// TUM timestamps could not be associated.
    #[error("{path}: {reason}")]
    Association { path: PathBuf, reason: String },
}

fn fmt_parse(path: &std::path::Path, line: usize, reason: &str) -> String {
    if line == 0 {
        format!("{}: {reason}", path.display())
    } else {
        format!("{}: line {line}: {reason}", path.display())
    }
}

impl ScanError {
    /// Wrap an I/O error with the path it happened on.
    pub(crate) fn io(path: &std::path::Path, source: std::io::Error) -> ScanError {
        ScanError::Io {
            path: path.to_path_buf(),
            source,
        }
    }

    /// Attach a path to a text parse error.
    pub(crate) fn parse(path: &std::path::Path, err: super::text::TextError) -> ScanError {
        ScanError::Parse {
            path: path.to_path_buf(),
            line: err.line,
            reason: err.reason,
        }
    }
}
