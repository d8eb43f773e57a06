//! Errors from scene geometry; every message names the frame, file or value.

use std::path::PathBuf;

/// Why scene bounds, the normalisation or the point cloud could not be made.
#[derive(Debug, thiserror::Error)]
pub enum GeometryError {
    #[error("scan has no frames, so it has no scene bounds")]
    NoFrames,
    #[error("frame {frame}: camera-to-world pose has non-finite entries")]
    BadPose { frame: String },
    #[error("frame {frame}: depth map has {found} values, expected {width}x{height}")]
    BadDepthSize {
        frame: String,
        width: u32,
        height: u32,
        found: usize,
    },
    #[error(
        "scene bounds (bbox.txt) are invalid: min {min:?} max {max:?}; \
         expected finite values with min < max on every axis"
    )]
    InvalidUserBounds { min: [f64; 3], max: [f64; 3] },
    #[error(
        "scene bounds (bbox.txt) min {min:?} max {max:?} hold {inside} of {total} sampled depth points: \
         they miss the scene the depth shows; fix or delete bbox.txt"
    )]
    UserBoundsMissScene {
        min: [f64; 3],
        max: [f64; 3],
        inside: usize,
        total: usize,
    },
    #[error(
        "cannot size the scene: no usable depth and all {cameras} camera centres \
         coincide, so nothing gives the scene a scale"
    )]
    NoScale { cameras: usize },
    #[error("scene transform: {0}")]
    InvalidTransform(String),
    #[error("voxel size {voxel} m is invalid for a scene extent of {extent} m: {reason}")]
    BadVoxelSize { voxel: f64, extent: f64, reason: String },
    #[error("{path}: {source}")]
    Io { path: PathBuf, source: std::io::Error },
}
