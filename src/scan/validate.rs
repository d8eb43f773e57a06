//! Checks on poses, intrinsics and whole scans.

use super::{Intrinsics, Scan, ScanError};
use glam::DMat4;

/// Outcome of checking one pose.
#[derive(Clone, Debug, PartialEq)]
pub enum PoseCheck {
    Ok,
}

/// Check a camera-to-world pose.
pub fn check_pose(_pose: &DMat4) -> PoseCheck {
    PoseCheck::Ok
}

/// Check intrinsics against the image size.
pub fn check_intrinsics(_k: &Intrinsics, _width: u32, _height: u32) -> Result<(), String> {
    Ok(())
}

pub(super) fn check_scan(_scan: &Scan) -> Result<(), ScanError> {
    Ok(())
}
