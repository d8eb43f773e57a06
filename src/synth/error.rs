//! Errors of `synth`; every message is one line that names the file, the
//! view and the problem.

use std::path::PathBuf;

/// Why rejected viewpoint candidates were turned down, counted per reason.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, serde::Serialize)]
pub struct Rejections {
    /// Camera closer than the clearance to the scanned point cloud.
    pub too_close: u64,
    /// The probe render saw no labelled object.
    pub no_object: u64,
    /// Too few probe pixels with opacity > 0.5: mostly space the scan never observed.
    pub unobserved: u64,
    /// A surface in space the scan vouches free (nearer than the clearance
    /// or half the nearest scanned point): a floater before the lens.
    pub near_surface: u64,
}

impl Rejections {
    /// All rejections.
    pub fn total(&self) -> u64 {
        self.too_close + self.no_object + self.unobserved + self.near_surface
    }
}

impl std::fmt::Display for Rejections {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(
            f,
            "{} too close to the scanned surface, {} saw no object, {} looked mostly at unobserved space, \
             {} had a floater before the lens",
            self.too_close, self.no_object, self.unobserved, self.near_surface
        )
    }
}

/// A problem in a `--poses` file.
#[derive(Debug, thiserror::Error)]
pub enum PosesFileError {
    /// The file could not be read.
    #[error("{path}: cannot read: {source}")]
    Io {
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
    /// The file as a whole is wrong (size, JSON syntax, top-level shape).
    #[error("{path}: {problem}")]
    File { path: PathBuf, problem: String },
    /// One field of one view is wrong.
    #[error("{path}: view {view}: `{field}`: {problem}")]
    View {
        path: PathBuf,
        view: usize,
        field: &'static str,
        problem: String,
    },
}

/// Why `synthesize` failed.
#[derive(Debug, thiserror::Error)]
pub enum SynthError {
    #[error(transparent)]
    Poses(#[from] PosesFileError),
    #[error("cannot place the scene: {0}")]
    Geometry(#[from] crate::poses::GeometryError),
    #[error("{0}")]
    Options(String),
    #[error("the scan has no frames to take the camera from")]
    NoFrames,
    #[error("--appearance {frame}: the model has no appearance for that frame (fitted with --no-appearance or by an earlier version); use --appearance neutral")]
    NoAppearance { frame: String },
    #[error("the scan has no depth, so the clearance of {clearance} m cannot be checked; pass --clearance 0")]
    NoCloud { clearance: f64 },
    #[error("cannot build the k-d tree of the scanned points: {0}")]
    KdTree(String),
    #[error(
        "gave up after {attempts} viewpoint candidates with only {accepted} of {wanted} views accepted \
         (rejected: {rejections}); try a smaller --clearance, fewer views or --poses"
    )]
    GaveUp {
        attempts: u64,
        accepted: usize,
        wanted: usize,
        rejections: Rejections,
    },
    #[error("view {view}: cannot encode the {what} PNG: {source}")]
    Png {
        view: usize,
        what: &'static str,
        #[source]
        source: image::ImageError,
    },
    #[error("{path}: cannot write: {source}")]
    Io {
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
    #[error("{path}: cannot write Parquet: {source}")]
    Parquet {
        path: PathBuf,
        #[source]
        source: parquet::errors::ParquetError,
    },
    #[error("{path}: interrupted after {views} views; nothing was written")]
    Interrupted { path: PathBuf, views: usize },
}
