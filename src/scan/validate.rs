//! Checks on poses, intrinsics and whole scans. Loaders call these on what
//! they read; [`super::load`] runs [`check_scan`] on every layout's result.

use super::rigid::{orthonormality_error, orthonormalize};
use super::{Intrinsics, Scan, ScanError, MAX_FRAMES};
use nalgebra::{Matrix4, Point3, RowVector4};

/// Tolerance on `|R^T R - I|` entries and on `det R - 1`.
pub const POSE_TOLERANCE: f64 = 1e-3;
/// `--fix-poses` repairs rotations at most this far from orthonormal
/// (rounding in exported text); a rotation scaled x2 (deviation 3) is a
/// wrong matrix, not a rounding error.
pub const FIX_POSES_MAX_ERROR: f64 = 0.05;
/// Plausible field of view of a pinhole camera, degrees.
const MIN_FOV_DEG: f64 = 1.0;
const MAX_FOV_DEG: f64 = 179.0;

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
pub fn check_pose(pose: &Matrix4<f64>) -> PoseCheck {
    if !pose.iter().all(|v| v.is_finite()) {
        return PoseCheck::NonFinite;
    }
    if !((pose.row(3) - RowVector4::new(0.0, 0.0, 0.0, 1.0)).amax() <= 1e-6) {
        return PoseCheck::BadBottomRow;
    }
    let det = pose.fixed_view::<3, 3>(0, 0).determinant();
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
    // A pinhole camera sees between 1 and 179 degrees; fx = 1e-300 (180) or
    // 1e9 (0) are typos or wrong units, and nothing trains with them.
    let fov = |f: f64, size: f64| (2.0 * (0.5 * size / f).atan()).to_degrees();
    let (fov_x, fov_y) = (fov(k.fx, w), fov(k.fy, h));
    if !(MIN_FOV_DEG..=MAX_FOV_DEG).contains(&fov_x) || !(MIN_FOV_DEG..=MAX_FOV_DEG).contains(&fov_y) {
        return Err(format!(
            "focal lengths fx {} fy {} give a field of view of {fov_x:.3} x {fov_y:.3} degrees on the {width}x{height} image; expected {MIN_FOV_DEG} to {MAX_FOV_DEG} (wrong units, or intrinsics for another resolution?)",
            k.fx, k.fy
        ));
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
    pose: Matrix4<f64>,
    source: &str,
    fix: bool,
    warnings: &mut Vec<String>,
) -> Result<Matrix4<f64>, ScanError> {
    let check = check_pose(&pose);
    let Some(problem) = check.problem() else {
        return Ok(pose);
    };
    if fix {
        if let PoseCheck::NotOrthonormal { error } = check {
            if error > FIX_POSES_MAX_ERROR {
                return Err(ScanError::Pose {
                    source_name: source.to_string(),
                    reason: format!("{problem}; too far from a rotation for --fix-poses (it repairs deviations up to {FIX_POSES_MAX_ERROR})"),
                });
            }
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
        if let Some(problem) = check_pose(&frame.camera_to_world.to_homogeneous()).problem() {
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

/// A camera this many times farther from the trajectory's median centre
/// than the typical frame (or than the scene's viewing distance, or a step
/// of the trajectory) is an outlier: a straight walk reaches 2x, a room scan
/// about 3x, a wrong pose file orders of magnitude more.
const OUTLIER_DISTANCE_RATIO: f64 = 20.0;
/// More outliers than this share of the frames means the trajectory itself
/// is not trustworthy: refuse rather than guess which frames are right.
const MAX_OUTLIER_SHARE: f64 = 0.25;

/// Exclude frames whose camera lies far outside the rest of the trajectory
/// (a translation typed in the wrong unit, a corrupted pose file), with a
/// warning naming each; refuse when too many frames would go. The scale is
/// the scan's own: the median distance of the cameras from their median
/// centre, the median step between consecutive frames and the median
/// measured depth, whichever is largest.
pub(crate) fn exclude_outlier_poses(scan: &mut Scan) -> Result<(), ScanError> {
    let n = scan.frames.len();
    if n < 3 {
        return Ok(());
    }
    let centres: Vec<Point3<f64>> = scan.frames.iter().map(|f| f.camera_center()).collect();
    let median = |mut v: Vec<f64>| -> f64 {
        v.sort_by(|a, b| a.total_cmp(b));
        v.get(v.len() / 2).copied().unwrap_or(0.0)
    };
    let centre = Point3::new(
        median(centres.iter().map(|c| c.x).collect()),
        median(centres.iter().map(|c| c.y).collect()),
        median(centres.iter().map(|c| c.z).collect()),
    );
    let distances: Vec<f64> = centres.iter().map(|c| nalgebra::distance(c, &centre)).collect();
    let spread = median(distances.clone());
    let step = median(centres.windows(2).map(|w| nalgebra::distance(&w[0], &w[1])).collect());
    let depth = median(
        scan.frames
            .iter()
            .filter_map(|f| f.depth.as_ref())
            .flat_map(|d| d.metres.iter().step_by(97).copied().filter(|&z| z > 0.0).map(f64::from))
            .collect(),
    );
    let scale = spread.max(step).max(depth);
    if !(scale > 0.0) {
        return Ok(());
    }
    let limit = OUTLIER_DISTANCE_RATIO * scale;
    let outliers: Vec<usize> = (0..n).filter(|&i| distances[i] > limit).collect();
    if outliers.is_empty() {
        return Ok(());
    }
    let names: Vec<String> = outliers
        .iter()
        .map(|&i| format!("{} ({:.3e} m)", scan.frames[i].name, distances[i]))
        .collect();
    if outliers.len() as f64 > MAX_OUTLIER_SHARE * n as f64 {
        return Err(ScanError::Invalid(
            scan.root.clone(),
            format!(
                "{} of {n} cameras lie more than {limit:.3} m ({OUTLIER_DISTANCE_RATIO}x the scan's scale of {scale:.3} m) from the trajectory's centre: {}; the poses are not trustworthy (wrong units, or a broken export?)",
                outliers.len(),
                names.join(", ")
            ),
        ));
    }
    scan.warnings.push(format!(
        "excluded {} frame(s) whose camera lies far from the rest of the trajectory (more than {limit:.3} m from its centre, {OUTLIER_DISTANCE_RATIO}x the scan's scale of {scale:.3} m): {}; check their pose files",
        outliers.len(),
        names.join(", ")
    ));
    let drop: std::collections::BTreeSet<usize> = outliers.into_iter().collect();
    let mut index = 0;
    scan.frames.retain(|_| {
        let keep = !drop.contains(&index);
        index += 1;
        keep
    });
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::{Isometry3, UnitQuaternion, Vector3};

    fn scaling(x: f64, y: f64, z: f64) -> Matrix4<f64> {
        Matrix4::new_nonuniform_scaling(&Vector3::new(x, y, z))
    }

    #[test]
    fn pose_checks() {
        let good = Isometry3::new(Vector3::new(1.0, 2.0, 3.0), Vector3::z() * 0.5).to_homogeneous();
        assert_eq!(check_pose(&good), PoseCheck::Ok);
        let mut nan = good;
        nan[(0, 3)] = f64::NAN;
        assert_eq!(check_pose(&nan), PoseCheck::NonFinite);
        let mut bottom = good;
        bottom[(3, 0)] = 0.5;
        assert_eq!(check_pose(&bottom), PoseCheck::BadBottomRow);
        assert_eq!(check_pose(&scaling(1.0, -1.0, 1.0)), PoseCheck::Reflection);
        let scaled = scaling(1.01, 1.01, 1.01);
        assert!(matches!(check_pose(&scaled), PoseCheck::NotOrthonormal { error } if error > 0.01));
        let mut tiny = good;
        tiny[(0, 0)] += 5e-4;
        assert_eq!(check_pose(&tiny), PoseCheck::Ok);
    }

    #[test]
    fn accept_pose_fixes_only_when_asked() {
        let mut bad = UnitQuaternion::from_euler_angles(0.0, 0.3, 0.0).to_homogeneous();
        bad[(1, 0)] += 0.01;
        let mut warnings = Vec::new();
        let err = accept_pose(bad, "pose/000004.txt", false, &mut warnings)
            .unwrap_err()
            .to_string();
        assert!(err.starts_with("pose/000004.txt: rotation not orthonormal"), "{err}");
        let fixed = accept_pose(bad, "pose/000004.txt", true, &mut warnings).unwrap();
        assert_eq!(check_pose(&fixed), PoseCheck::Ok);
        assert_eq!(warnings.len(), 1);
        assert!(warnings[0].contains("re-orthonormalised"));
        // Regression: a rotation scaled x2 is a wrong matrix, not rounding.
        let doubled = scaling(2.0, 2.0, 2.0);
        let err = accept_pose(doubled, "pose/000001.txt", true, &mut warnings)
            .unwrap_err()
            .to_string();
        assert!(err.contains("too far from a rotation for --fix-poses"), "{err}");
        // A reflection is never "fixed".
        let mirror = scaling(1.0, 1.0, -1.0);
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
        // Regression: fx = 1e-300 (a 180-degree view) trained nothing and exited 0.
        let err = check_intrinsics(&Intrinsics { fx: 1e-300, ..k }, 640, 480).unwrap_err();
        assert!(err.contains("field of view"), "{err}");
        assert!(check_intrinsics(&Intrinsics { fy: 1e9, ..k }, 640, 480).is_err());
        assert!(
            check_intrinsics(
                &Intrinsics {
                    fx: 30.0,
                    fy: 30.0,
                    ..k
                },
                640,
                480
            )
            .is_ok(),
            "a 169-degree wide angle is fine"
        );
    }
}
