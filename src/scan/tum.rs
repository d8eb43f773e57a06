//! The TUM RGB-D layout: `rgb.txt`, `depth.txt` (`timestamp filename`),
//! `groundtruth.txt` (`timestamp tx ty tz qx qy qz qw`, camera-to-world),
//! depth PNG in 1/5000 m. Each rgb image is associated with the nearest depth
//! image and the groundtruth (interpolated between its neighbouring samples)
//! within 20 ms; images that do not associate are skipped with a warning.
//! TUM has no intrinsics file: the Freiburg camera is chosen by an optional
//! `intrinsics.txt` or by the folder name.

use super::assemble::{check_frame_count, FrameSpec, Listing, PoseKind};
use super::files::{id_list, stem};
use super::native::require_file;
use super::text::{self, read_text, TextError};
use super::{Intrinsics, Layout, ScanError};
use nalgebra::{Isometry3, Matrix4, Translation3, UnitQuaternion, Vector3};
use std::path::{Path, PathBuf};

/// Largest timestamp gap accepted when associating, in seconds.
pub const MAX_ASSOCIATION_GAP: f64 = 0.020;
/// TUM depth PNG units per metre.
const DEPTH_UNITS_PER_METRE: f32 = 5000.0;
/// Resolution the Freiburg intrinsics are given for.
const TUM_SIZE: (u32, u32) = (640, 480);

/// Freiburg colour-camera intrinsics (fx, fy, cx, cy) of sensor 1, 2, 3.
pub const FREIBURG: [Intrinsics; 3] = [
    Intrinsics {
        fx: 517.3,
        fy: 516.5,
        cx: 318.6,
        cy: 255.3,
    },
    Intrinsics {
        fx: 520.9,
        fy: 521.0,
        cx: 325.1,
        cy: 249.7,
    },
    Intrinsics {
        fx: 535.4,
        fy: 539.2,
        cx: 320.1,
        cy: 247.6,
    },
];
/// ROS default used when the sensor is unknown.
pub const TUM_DEFAULT: Intrinsics = Intrinsics {
    fx: 525.0,
    fy: 525.0,
    cx: 319.5,
    cy: 239.5,
};

/// One groundtruth sample.
#[derive(Clone, Copy, Debug)]
struct Sample {
    t: f64,
    line: usize,
    translation: Vector3<f64>,
    rotation: UnitQuaternion<f64>,
}

/// List the frames of a TUM RGB-D sequence.
pub(crate) fn list(root: &Path) -> Result<Listing, ScanError> {
    let rgb_txt = require_file(root, "rgb.txt", "list of colour images 'timestamp filename'")?;
    let depth_txt = require_file(root, "depth.txt", "list of depth images 'timestamp filename'")?;
    let gt_txt = require_file(root, "groundtruth.txt", "trajectory 'timestamp tx ty tz qx qy qz qw'")?;
    let mut warnings = Vec::new();
    let (intrinsics, intrinsics_size, k_source) = choose_intrinsics(root, &mut warnings)?;
    let mut listing = Listing::new(root, Layout::Tum, PoseKind::CameraToWorld, k_source);
    listing.depth_metres_per_unit = 1.0 / DEPTH_UNITS_PER_METRE;
    listing.warnings = warnings;
    listing
        .inputs
        .extend([rgb_txt.clone(), depth_txt.clone(), gt_txt.clone()]);

    let rgb_all = read_image_list(&rgb_txt)?;
    check_frame_count(&rgb_txt, rgb_all.len())?;
    let depth_all = read_image_list(&depth_txt)?;
    check_frame_count(&depth_txt, depth_all.len())?;
    let samples = read_groundtruth(&gt_txt)?;

    let rgb = existing(root, &rgb_txt, rgb_all, &mut listing.warnings)?;
    let mut depth = existing(root, &depth_txt, depth_all, &mut listing.warnings).unwrap_or_default();
    depth.sort_by(|a, b| a.1.total_cmp(&b.1));

    let (mut no_depth, mut no_pose) = (Vec::new(), Vec::new());
    for (index, t, rgb_path) in &rgb {
        let Some(depth_path) = nearest(&depth, *t) else {
            no_depth.push(*index as u64);
            continue;
        };
        let Some((pose, line)) = pose_at(&samples, *t) else {
            no_pose.push(*index as u64);
            continue;
        };
        listing.frames.push(FrameSpec {
            id: *index as u64,
            name: stem(rgb_path),
            rgb: rgb_path.clone(),
            depth: Some(depth_path.clone()),
            pose,
            pose_source: format!("{} line {line}", gt_txt.display()),
            intrinsics,
            intrinsics_size,
        });
    }
    let ms = MAX_ASSOCIATION_GAP * 1000.0;
    if listing.frames.is_empty() {
        return Err(ScanError::Association {
            path: rgb_txt,
            reason: format!(
                "no rgb timestamp could be associated within {ms:.0} ms ({} image(s): {} without depth in depth.txt, \
                 {} without a pose in groundtruth.txt)",
                rgb.len(),
                no_depth.len(),
                no_pose.len()
            ),
        });
    }
    if !no_depth.is_empty() {
        listing.warnings.push(format!(
            "{}: {} frame(s) have no depth image within {ms:.0} ms and were skipped (rgb.txt entries {})",
            rgb_txt.display(),
            no_depth.len(),
            id_list(&no_depth)
        ));
    }
    if !no_pose.is_empty() {
        listing.warnings.push(format!(
            "{}: {} frame(s) have no groundtruth pose within {ms:.0} ms and were skipped (rgb.txt entries {})",
            rgb_txt.display(),
            no_pose.len(),
            id_list(&no_pose)
        ));
    }
    Ok(listing)
}

/// `(entry index, timestamp, path)` of every line of a TUM image list.
fn read_image_list(path: &Path) -> Result<Vec<(usize, f64, String)>, ScanError> {
    let text = read_text(path)?;
    let rows = text::timestamped(&text).map_err(|e| ScanError::parse(path, e))?;
    rows.into_iter()
        .enumerate()
        .map(|(index, (line, t, rest))| match rest.first() {
            Some(file) => Ok((index, t, file.to_string())),
            None => Err(ScanError::parse(
                path,
                TextError {
                    line,
                    reason: "expected 'timestamp filename'".into(),
                },
            )),
        })
        .collect()
}

/// Keep the listed images that exist; the others (TUM subsets list the
/// whole sequence) are counted in one warning. None existing is an error.
fn existing(
    root: &Path,
    list: &Path,
    entries: Vec<(usize, f64, String)>,
    warnings: &mut Vec<String>,
) -> Result<Vec<(usize, f64, PathBuf)>, ScanError> {
    let listed = entries.len();
    let found: Vec<(usize, f64, PathBuf)> = entries
        .into_iter()
        .map(|(i, t, file)| (i, t, root.join(file)))
        .filter(|(_, _, path)| path.is_file())
        .collect();
    if found.is_empty() {
        return Err(ScanError::NoFrames(
            list.to_path_buf(),
            format!("none of the {listed} image(s) it lists exist"),
        ));
    }
    if found.len() < listed {
        warnings.push(format!(
            "{}: {} of {listed} listed image(s) are missing and were skipped",
            list.display(),
            listed - found.len()
        ));
    }
    Ok(found)
}

/// Path of the image nearest in time to `t` (list sorted by time), if within the gap.
fn nearest(sorted: &[(usize, f64, PathBuf)], t: f64) -> Option<&PathBuf> {
    let at = sorted.partition_point(|e| e.1 < t);
    let candidates = [at.checked_sub(1), Some(at)];
    candidates
        .into_iter()
        .flatten()
        .filter_map(|i| sorted.get(i))
        .map(|e| ((e.1 - t).abs(), &e.2))
        .filter(|(gap, _)| *gap <= MAX_ASSOCIATION_GAP)
        .min_by(|a, b| a.0.total_cmp(&b.0))
        .map(|(_, path)| path)
}

/// Parse and sort the groundtruth trajectory.
fn read_groundtruth(path: &Path) -> Result<Vec<Sample>, ScanError> {
    let text = read_text(path)?;
    let rows = text::timestamped(&text).map_err(|e| ScanError::parse(path, e))?;
    let mut samples = Vec::with_capacity(rows.len());
    for (line, t, rest) in rows {
        let v = rest
            .iter()
            .map(|tok| text::number(tok, line))
            .collect::<Result<Vec<f64>, _>>()
            .map_err(|e| ScanError::parse(path, e))?;
        let [tx, ty, tz, qx, qy, qz, qw] = v[..] else {
            let reason = format!(
                "expected 'timestamp tx ty tz qx qy qz qw', found {} values",
                v.len() + 1
            );
            return Err(ScanError::parse(path, TextError { line, reason }));
        };
        let Some(pose) = super::rigid::pose_from_translation_quaternion([tx, ty, tz], [qx, qy, qz, qw]) else {
            let reason = "pose has NaN/infinite values or a zero quaternion".to_string();
            return Err(ScanError::parse(path, TextError { line, reason }));
        };
        let (rotation, translation) = (pose.rotation, pose.translation.vector);
        samples.push(Sample {
            t,
            line,
            translation,
            rotation,
        });
    }
    samples.sort_by(|a, b| a.t.total_cmp(&b.t));
    Ok(samples)
}

/// Camera-to-world at time `t`: interpolated between the samples around `t`
/// when both are close, else the nearest sample within the gap.
fn pose_at(samples: &[Sample], t: f64) -> Option<(Matrix4<f64>, usize)> {
    let at = samples.partition_point(|s| s.t < t);
    let before = at.checked_sub(1).and_then(|i| samples.get(i));
    let after = samples.get(at);
    let near = |s: &&Sample| (s.t - t).abs() <= MAX_ASSOCIATION_GAP;
    match (before.filter(near), after.filter(near)) {
        (Some(a), Some(b)) if b.t > a.t => {
            let alpha = (t - a.t) / (b.t - a.t);
            let translation = a.translation.lerp(&b.translation, alpha);
            // Shortest-path slerp; nearly equal rotations (no stable angle) interpolate linearly.
            let rotation = a.rotation.try_slerp(&b.rotation, alpha, 1e-12).unwrap_or_else(|| {
                let sign = if a.rotation.coords.dot(&b.rotation.coords) < 0.0 {
                    -1.0
                } else {
                    1.0
                };
                UnitQuaternion::new_normalize(a.rotation.into_inner().lerp(&(b.rotation.into_inner() * sign), alpha))
            });
            let line = if alpha < 0.5 { a.line } else { b.line };
            Some((pose(rotation, translation), line))
        }
        (Some(a), Some(b)) => Some((pose(b.rotation, b.translation), a.line.min(b.line))),
        (Some(s), None) | (None, Some(s)) => Some((pose(s.rotation, s.translation), s.line)),
        (None, None) => None,
    }
}

/// Rigid 4x4 from a rotation and a translation.
fn pose(rotation: UnitQuaternion<f64>, translation: Vector3<f64>) -> Matrix4<f64> {
    Isometry3::from_parts(Translation3::from(translation), rotation).to_homogeneous()
}

/// Intrinsics, the resolution they are for (None = the images'), and their source.
type ChosenIntrinsics = (Intrinsics, Option<(u32, u32)>, PathBuf);

/// Pick the intrinsics: `intrinsics.txt`, else the folder name, else the default.
fn choose_intrinsics(root: &Path, warnings: &mut Vec<String>) -> Result<ChosenIntrinsics, ScanError> {
    let k_path = root.join("intrinsics.txt");
    if k_path.is_file() {
        let text = read_text(&k_path)?;
        if let Some(sensor) = freiburg_hint(&text) {
            return Ok((FREIBURG[sensor], Some(TUM_SIZE), k_path));
        }
        let k = text::intrinsics(&text).map_err(|e| ScanError::parse(&k_path, e))?;
        return Ok((k, None, k_path));
    }
    let absolute = std::fs::canonicalize(root).unwrap_or_else(|_| root.to_path_buf());
    let names = [absolute.file_name(), absolute.parent().and_then(|p| p.file_name())];
    for name in names.into_iter().flatten() {
        if let Some(sensor) = freiburg_hint(&name.to_string_lossy()) {
            return Ok((FREIBURG[sensor], Some(TUM_SIZE), root.to_path_buf()));
        }
    }
    warnings.push(format!(
        "{}: no intrinsics.txt and no fr1/fr2/fr3 in the folder name: using the default 525, 525, 319.5, 239.5",
        root.display()
    ));
    Ok((TUM_DEFAULT, Some(TUM_SIZE), root.to_path_buf()))
}

/// Freiburg sensor index (0-based) named in `text`: `freiburg2`, or `fr2`
/// as a separate token (`tum_fr2_desk`, not `xfr2`).
pub(crate) fn freiburg_hint(text: &str) -> Option<usize> {
    let lower = text.to_ascii_lowercase();
    for (sensor, digit) in ['1', '2', '3'].into_iter().enumerate() {
        if lower.contains(&format!("freiburg{digit}")) {
            return Some(sensor);
        }
        let token = format!("fr{digit}");
        for (at, _) in lower.match_indices(&token) {
            let before_ok = lower[..at]
                .chars()
                .next_back()
                .is_none_or(|c| !c.is_ascii_alphanumeric());
            let after_ok = lower[at + token.len()..]
                .chars()
                .next()
                .is_none_or(|c| !c.is_ascii_digit());
            if before_ok && after_ok {
                return Some(sensor);
            }
        }
    }
    None
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn freiburg_hints() {
        assert_eq!(freiburg_hint("tum_fr1_desk_first9"), Some(0));
        assert_eq!(freiburg_hint("rgbd_dataset_freiburg3_cabinet"), Some(2));
        assert_eq!(freiburg_hint("FR2"), Some(1));
        assert_eq!(freiburg_hint(".tmpAbFr1x"), None);
        assert_eq!(freiburg_hint("fr12"), None);
        assert_eq!(freiburg_hint("desk"), None);
    }

    fn sample(t: f64, x: f64, yaw: f64) -> Sample {
        Sample {
            t,
            line: 1,
            translation: Vector3::new(x, 0.0, 0.0),
            rotation: UnitQuaternion::from_euler_angles(0.0, yaw, 0.0),
        }
    }

    #[test]
    fn poses_interpolate_within_gap() {
        let s = [sample(1.00, 0.0, 0.0), sample(1.01, 1.0, 0.2), sample(2.0, 5.0, 0.0)];
        let (m, _) = pose_at(&s, 1.005).unwrap();
        assert!((m[(0, 3)] - 0.5).abs() < 1e-12);
        let rot = nalgebra::Rotation3::from_matrix_unchecked(m.fixed_view::<3, 3>(0, 0).into_owned());
        assert!(rot.angle_to(&nalgebra::Rotation3::from_euler_angles(0.0, 0.1, 0.0)) < 1e-12);
        // Beyond the last sample but within 20 ms: nearest.
        assert_eq!(pose_at(&s, 2.015).unwrap().0[(0, 3)], 5.0);
        // Between samples that are both > 20 ms away: none.
        assert!(pose_at(&s, 1.5).is_none());
        assert!(pose_at(&[], 1.0).is_none());
    }

    #[test]
    fn nearest_image_within_gap() {
        let list = vec![(0, 1.0, PathBuf::from("a")), (1, 1.03, PathBuf::from("b"))];
        assert_eq!(nearest(&list, 1.02), Some(&PathBuf::from("b")));
        assert_eq!(nearest(&list, 1.005), Some(&PathBuf::from("a")));
        assert_eq!(nearest(&list, 1.06), None);
    }
}
