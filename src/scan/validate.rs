//! Checks on poses, intrinsics and whole scans. Loaders call these on what
//! they read; [`super::load`] runs [`check_scan`] on every layout's result.

use super::rigid::{orthonormality_error, orthonormalize};
use super::{Intrinsics, Scan, ScanError, MAX_FRAMES};
use glam::{DMat3, DMat4, DVec4};

/// Tolerance on `|R^T R - I|` entries and on `det R - 1`.
pub const POSE_TOLERANCE: f64 = 1e-3;

/// Outcome of checking one pose.
#[derive(Clone, Debug, PartialEq)]
pub enum PoseCheck {
    /// A finite rigid transform.
    Ok,
    /// Some entry is NaN or infinite.
    NonFinite,
    /// The bottom row is not `0 0 0 1`.
    BadBottomRow,
    /// The rotation block has a negative determinant.
    Reflection,
    /// The rotation block is off orthonormal by `error` (largest deviation).
    NotOrthonormal { error: f64 },
}

impl PoseCheck {
    /// One-line description of the problem, `None` when the pose is fine.
    pub fn problem(&self) -> Option<String> {
        match self {
            PoseCheck::Ok => None,
            PoseCheck::NonFinite => Some("pose has NaN or infinite values".into()),
            PoseCheck::BadBottomRow => Some("pose's last row is not 0 0 0 1".into()),
            PoseCheck::Reflection => Some("rotation is a reflection (det R < 0), not a rotation".into()),
            PoseCheck::NotOrthonormal { error } => Some(format!(
                "rotation not orthonormal (deviation {error:.2e} > {POSE_TOLERANCE:.0e}, or det R != +1)"
            )),
        }
    }
}

/// Check a 4x4 rigid pose (either direction): finite, bottom row `0 0 0 1`,
/// rotation orthonormal with det +1 within [`POSE_TOLERANCE`].
pub fn check_pose(pose: &DMat4) -> PoseCheck {
    if !pose.is_finite() {
        return PoseCheck::NonFinite;
    }
    if !pose.row(3).abs_diff_eq(DVec4::new(0.0, 0.0, 0.0, 1.0), 1e-6) {
        return PoseCheck::BadBottomRow;
    }
    let det = DMat3::from_mat4(*pose).determinant();
    if det < 0.0 {
        return PoseCheck::Reflection;
    }
    let error = orthonormality_error(pose).max((det - 1.0).abs());
    if error > POSE_TOLERANCE {
        return PoseCheck::NotOrthonormal { error };
    }
    PoseCheck::Ok
}

/// Check intrinsics against the image size: finite, positive focal
/// lengths, principal point within [-0.5, 1.5] of the image on each axis.
pub fn check_intrinsics(k: &Intrinsics, width: u32, height: u32) -> Result<(), String> {
    let (w, h) = (width as f64, height as f64);
    if ![k.fx, k.fy, k.cx, k.cy].iter().all(|v| v.is_finite()) {
        return Err("intrinsics have NaN or infinite values".into());
    }
    if k.fx <= 0.0 || k.fy <= 0.0 {
        return Err(format!("focal lengths must be positive, found fx {} fy {}", k.fx, k.fy));
    }
    if !(-0.5 * w..=1.5 * w).contains(&k.cx) || !(-0.5 * h..=1.5 * h).contains(&k.cy) {
        return Err(format!(
            "principal point ({:.1}, {:.1}) is far outside the {width}x{height} image",
            k.cx, k.cy
        ));
    }
    Ok(())
}

/// Accept a pose read from `source` (a file name or `file line N`), or with
/// `fix` re-orthonormalise a bad rotation and record a warning.
pub(crate) fn accept_pose(
    pose: DMat4,
    source: &str,
    fix: bool,
    warnings: &mut Vec<String>,
) -> Result<DMat4, ScanError> {
    let check = check_pose(&pose);
    let Some(problem) = check.problem() else {
        return Ok(pose);
    };
    if fix {
        if let PoseCheck::NotOrthonormal { error } = check {
            if let Some(fixed) = orthonormalize(&pose) {
                warnings.push(format!("{source}: rotation re-orthonormalised (deviation {error:.2e})"));
                return Ok(fixed);
            }
        }
    }
    Err(ScanError::Pose {
        source_name: source.to_string(),
        reason: problem,
    })
}

/// Whole-scan invariants every loader must produce.
pub(crate) fn check_scan(scan: &Scan) -> Result<(), ScanError> {
    let Some(first) = scan.frames.first() else {
        return Err(ScanError::NoFrames(scan.root.clone(), "no frame could be read".into()));
    };
    if scan.frames.len() > MAX_FRAMES {
        return Err(ScanError::TooManyFrames {
            path: scan.root.clone(),
            count: scan.frames.len(),
            max: MAX_FRAMES,
        });
    }
    let size = first.size();
    for frame in &scan.frames {
        let frame_err = |reason: String| ScanError::Frame {
            frame: frame.name.clone(),
            reason,
        };
        let (w, h) = frame.size();
        if (w, h) != size {
            return Err(frame_err(format!(
                "image size {w}x{h} differs from frame {}'s {}x{}",
                first.name, size.0, size.1
            )));
        }
        check_intrinsics(&frame.intrinsics, w, h).map_err(frame_err)?;
        if let Some(problem) = check_pose(&frame.camera_to_world).problem() {
            return Err(frame_err(problem));
        }
        if let Some(depth) = &frame.depth {
            if (depth.width, depth.height) != (w, h) || depth.metres.len() != w as usize * h as usize {
                return Err(frame_err("depth is not on the colour grid".into()));
            }
            if depth.metres.iter().any(|d| !(d.is_finite() && *d >= 0.0)) {
                return Err(frame_err("depth has negative or non-finite values".into()));
            }
        }
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use glam::{DQuat, DVec3};

    #[test]
    fn pose_checks() {
        let good = DMat4::from_rotation_translation(DQuat::from_rotation_z(0.5), DVec3::new(1.0, 2.0, 3.0));
        assert_eq!(check_pose(&good), PoseCheck::Ok);
        let mut nan = good;
        nan.w_axis.x = f64::NAN;
        assert_eq!(check_pose(&nan), PoseCheck::NonFinite);
        let mut bottom = good;
        bottom.x_axis.w = 0.5;
        assert_eq!(check_pose(&bottom), PoseCheck::BadBottomRow);
        assert_eq!(
            check_pose(&DMat4::from_scale(DVec3::new(1.0, -1.0, 1.0))),
            PoseCheck::Reflection
        );
        let scaled = DMat4::from_scale(DVec3::splat(1.01));
        assert!(matches!(check_pose(&scaled), PoseCheck::NotOrthonormal { error } if error > 0.01));
        let mut tiny = good;
        tiny.x_axis.x += 5e-4;
        assert_eq!(check_pose(&tiny), PoseCheck::Ok);
    }

    #[test]
    fn accept_pose_fixes_only_when_asked() {
        let mut bad = DMat4::from_rotation_y(0.3);
        bad.x_axis.y += 0.01;
        let mut warnings = Vec::new();
        let err = accept_pose(bad, "pose/000004.txt", false, &mut warnings)
            .unwrap_err()
            .to_string();
        assert!(err.starts_with("pose/000004.txt: rotation not orthonormal"), "{err}");
        let fixed = accept_pose(bad, "pose/000004.txt", true, &mut warnings).unwrap();
        assert_eq!(check_pose(&fixed), PoseCheck::Ok);
        assert_eq!(warnings.len(), 1);
        assert!(warnings[0].contains("re-orthonormalised"));
        // A reflection is never "fixed".
        let mirror = DMat4::from_scale(DVec3::new(1.0, 1.0, -1.0));
        assert!(accept_pose(mirror, "p", true, &mut warnings).is_err());
    }

    #[test]
    fn intrinsics_checks() {
        let k = Intrinsics {
            fx: 500.0,
            fy: 500.0,
            cx: 320.0,
            cy: 240.0,
        };
        assert!(check_intrinsics(&k, 640, 480).is_ok());
        assert!(check_intrinsics(&Intrinsics { fx: 0.0, ..k }, 640, 480)
            .unwrap_err()
            .contains("fx 0"));
        assert!(check_intrinsics(&Intrinsics { fy: -3.0, ..k }, 640, 480).is_err());
        assert!(check_intrinsics(&Intrinsics { cx: 1000.0, ..k }, 640, 480)
            .unwrap_err()
            .contains("principal point"));
        assert!(check_intrinsics(&Intrinsics { cy: -250.0, ..k }, 640, 480).is_err());
        assert!(check_intrinsics(&Intrinsics { cx: f64::NAN, ..k }, 640, 480).is_err());
    }
}
