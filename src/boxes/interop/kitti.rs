//! KITTI object labels (`label_2/<frame>.txt`), one object per line:
//!
//! ```text
//! type truncated occluded alpha x1 y1 x2 y2 h w l x y z rotation_y [score]
//! ```
//!
//! in the rectified camera-0 frame (x right, y down, z forward, metres):
//! `x y z` is the centre of the box's bottom face, `h w l` its height
//! (along camera y), width (along z) and length (along x) before it is
//! turned by `rotation_y` about the camera's y axis. `DontCare` lines are
//! skipped. The box becomes a nerflabel box of size `[l, h, w]` with centre
//! `(x, y - h/2, z)` and rotation `Ry(rotation_y)`, carried into the world
//! by a rigid camera-to-world matrix (`--calib`) when one is given.

use super::rotation::{from_rows, rows};
use super::{Candidate, InteropError};
use crate::boxes::parse::{orthonormalised, read_text, ROTATION_TOLERANCE};
use nalgebra::{IsometryMatrix3, Matrix3, Point3, Rotation3, Translation3, Vector3};
use std::path::Path;

/// Column names of a label line, for messages.
const COLUMNS: [&str; 16] = [
    "type",
    "truncated",
    "occluded",
    "alpha",
    "x1",
    "y1",
    "x2",
    "y2",
    "h",
    "w",
    "l",
    "x",
    "y",
    "z",
    "rotation_y",
    "score",
];

/// The boxes of a KITTI label file, in the world when `camera_to_world` is given.
pub(crate) fn read(
    text: &str,
    path: &Path,
    camera_to_world: Option<&IsometryMatrix3<f64>>,
) -> Result<(Vec<Candidate>, Vec<String>), InteropError> {
    let mut out = Vec::new();
    let mut skipped = 0usize;
    for (i, line) in text.lines().enumerate() {
        let place = format!("line {}", i + 1);
        let entry = |field: &str, problem: String| InteropError::Entry {
            path: path.to_path_buf(),
            place: place.clone(),
            field: field.to_string(),
            problem,
        };
        let fields: Vec<&str> = line.split_whitespace().collect();
        if fields.is_empty() {
            continue;
        }
        if !(15..=16).contains(&fields.len()) {
            return Err(entry(
                "",
                format!(
                    "expected 15 values (`{}`, and an optional score), found {}",
                    COLUMNS[..15].join(" "),
                    fields.len()
                ),
            ));
        }
        if fields[0] == "DontCare" {
            skipped += 1;
            continue;
        }
        let mut values = [0.0f64; 16];
        for (k, text) in fields.iter().enumerate().skip(1) {
            values[k] = match text.parse::<f64>() {
                Ok(v) if v.is_finite() => v,
                _ => return Err(entry(COLUMNS[k], format!("`{text}` is not a finite number"))),
            };
        }
        let [h, w, l] = [values[8], values[9], values[10]];
        let bottom = Point3::new(values[11], values[12], values[13]);
        let mut center = bottom - Vector3::new(0.0, h / 2.0, 0.0);
        let mut rotation = Rotation3::from_axis_angle(&Vector3::y_axis(), values[14]);
        if let Some(m) = camera_to_world {
            center = m * center;
            rotation = m.rotation * rotation;
        }
        out.push(Candidate {
            place,
            label: fields[0].to_string(),
            center: center.coords.into(),
            size: [l, h, w],
            rotation: rows(&rotation),
            fields: ["type", "x y z", "h w l", "rotation_y"],
        });
    }
    let warnings = if skipped > 0 {
        vec![format!("{}: skipped {skipped} DontCare line(s)", path.display())]
    } else {
        Vec::new()
    };
    Ok((out, warnings))
}

/// A rigid camera-to-world matrix: 16 numbers (4 rows of 4, the last
/// `0 0 0 1`) or 12 (3 rows of 4), separated by white space; the rotation
/// part must be orthonormal with determinant +1 (it is re-orthonormalised).
pub fn read_calib(path: &Path) -> Result<IsometryMatrix3<f64>, InteropError> {
    let text = read_text(path)?;
    let bad = |problem: String| InteropError::Format {
        path: path.to_path_buf(),
        problem,
    };
    let mut numbers = Vec::new();
    for word in text.split_whitespace() {
        match word.parse::<f64>() {
            Ok(v) if v.is_finite() => numbers.push(v),
            _ => {
                return Err(bad(format!(
                    "`{word}` is not a finite number (expected a camera-to-world matrix: 4 rows of 4 numbers, or 3 rows of 4)"
                )))
            }
        }
        if numbers.len() > 16 {
            break;
        }
    }
    if numbers.len() != 12 && numbers.len() != 16 {
        return Err(bad(format!(
            "expected 16 numbers (a 4x4 camera-to-world matrix) or 12 (its top 3 rows), found {}",
            if numbers.len() > 16 {
                "more than 16".to_string()
            } else {
                numbers.len().to_string()
            }
        )));
    }
    if numbers.len() == 16 {
        let last = &numbers[12..16];
        if (0..4).any(|k| (last[k] - [0.0, 0.0, 0.0, 1.0][k]).abs() > 1e-9) {
            return Err(bad(format!(
                "the last row is {last:?}, expected 0 0 0 1 (a rigid transform)"
            )));
        }
    }
    let r = |row: usize| [numbers[4 * row], numbers[4 * row + 1], numbers[4 * row + 2]];
    let m = from_rows([r(0), r(1), r(2)]);
    let off = (m.transpose() * m - Matrix3::identity())
        .iter()
        .fold(0.0f64, |a, x| a.max(x.abs()));
    if off > ROTATION_TOLERANCE || (m.determinant() - 1.0).abs() > ROTATION_TOLERANCE {
        return Err(bad(format!(
            "the top-left 3x3 is not a rotation (R^T R off identity by {off:.2e}, determinant {:.4}): expected a rigid camera-to-world matrix without scale",
            m.determinant()
        )));
    }
    let rotation = orthonormalised(&m);
    let t = Translation3::new(numbers[3], numbers[7], numbers[11]);
    Ok(IsometryMatrix3::from_parts(t, rotation))
}

#[cfg(test)]
mod tests {
    use super::super::{import_boxes, ImportFormat};
    use super::*;

    fn import(text: &str, calib: Option<&str>) -> Result<super::super::Imported, InteropError> {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("000042.txt");
        std::fs::write(&path, text).unwrap();
        let calib_path = dir.path().join("calib.txt");
        if let Some(c) = calib {
            std::fs::write(&calib_path, c).unwrap();
        }
        import_boxes(&path, ImportFormat::Kitti, calib.map(|_| calib_path.as_path()))
    }

    /// Lines from the KITTI object benchmark's training labels (000001.txt)
    /// as the devkit writes them: two decimals, a DontCare region.
    const LABELS: &str = "Truck 0.00 0 -1.57 599.41 156.40 629.75 189.25 2.85 2.63 12.34 0.47 1.49 69.44 -1.56\n\
Car 0.00 0 1.85 387.63 181.54 423.81 203.12 1.67 1.87 3.69 -16.53 2.39 58.49 1.57\n\
DontCare -1 -1 -10 503.89 169.71 590.61 190.13 -1 -1 -1 -1000 -1000 -1000 -10\n";

    #[test]
    fn camera_frame_boxes_stand_on_their_bottom_centre_and_turn_about_y() {
        let imported = import(LABELS, None).unwrap();
        assert_eq!(imported.warnings.len(), 1, "{:?}", imported.warnings);
        assert!(imported.warnings[0].contains("DontCare"));
        let set = imported.boxes;
        assert_eq!(set.categories, vec!["Truck".to_string(), "Car".to_string()]);
        let truck = &set.boxes[0];
        // Centre half the height above (y down: minus) the bottom centre.
        assert!((truck.center - Point3::new(0.47, 1.49 - 2.85 / 2.0, 69.44)).norm() < 1e-12);
        assert_eq!(<[f64; 3]>::from(truck.size), [12.34, 2.85, 2.63]);
        // rotation_y turns the length axis (box x) about camera y: Ry(a) x = (cos a, 0, -sin a).
        let a: f64 = -1.56;
        assert!((truck.rotation * Vector3::x() - Vector3::new(a.cos(), 0.0, -a.sin())).norm() < 1e-12);
        assert!(
            (truck.rotation * Vector3::y() - Vector3::y()).norm() < 1e-12,
            "height stays along camera y"
        );
        // The bottom face centre is where KITTI put the object's origin.
        let bottom = truck.center + truck.rotation * Vector3::new(0.0, truck.size.y / 2.0, 0.0);
        assert!((bottom - Point3::new(0.47, 1.49, 69.44)).norm() < 1e-12);
    }

    #[test]
    fn calib_carries_the_boxes_into_the_world() {
        // Camera at (1, 2, 3) looking along world +x, image y along world -z (z up).
        let calib = "0 0 1 1\n-1 0 0 2\n0 -1 0 3\n0 0 0 1\n";
        let line = "Car 0 0 0 0 0 10 10 1.5 1.8 4.0 0.5 1.2 10.0 0.3\n";
        let b = import(line, Some(calib)).unwrap().boxes.boxes.remove(0);
        // Camera point (0.5, 1.2 - 0.75, 10) -> world (1 + 10, 2 - 0.5, 3 - 0.45).
        assert!(
            (b.center - Point3::new(11.0, 1.5, 2.55)).norm() < 1e-12,
            "{:?}",
            b.center
        );
        // Height axis (camera y, down) is world -z; the yaw turns about world z.
        assert!((b.rotation * Vector3::y() + Vector3::z()).norm() < 1e-12);
        let a: f64 = 0.3;
        let length_axis_cam = Vector3::new(a.cos(), 0.0, -a.sin());
        let world = Vector3::new(length_axis_cam.z, -length_axis_cam.x, -length_axis_cam.y);
        assert!((b.rotation * Vector3::x() - world).norm() < 1e-12);
        // 12 numbers (3x4) mean the same.
        let short = import(line, Some("0 0 1 1 -1 0 0 2 0 -1 0 3"))
            .unwrap()
            .boxes
            .boxes
            .remove(0);
        assert_eq!(short, b);
    }

    #[test]
    fn bad_lines_and_calibrations_name_file_line_and_field() {
        let good = "Car 0 0 0 0 0 10 10 1.5 1.8 4.0 0.5 1.2 10.0 0.3";
        for (line, words) in [
            (
                "Car 0 0 0 0 0 10 10 1.5 1.8 4.0 0.5 1.2 10.0",
                "line 2: expected 15 values",
            ),
            (
                "Car 0 0 0 0 0 10 10 1.5 x 4.0 0.5 1.2 10.0 0.3",
                "line 2, field `w`: `x` is not a finite number",
            ),
            ("Car 0 0 0 0 0 10 10 1.5 1.8 4.0 0.5 1.2 NaN 0.3", "line 2, field `z`"),
            (
                "Car 0 0 0 0 0 10 10 -1.5 1.8 4.0 0.5 1.2 10.0 0.3",
                "line 2, field `h w l`: edge y is -1.5",
            ),
        ] {
            let msg = import(&format!("{good}\n{line}\n"), None).err().unwrap().to_string();
            assert!(msg.contains("000042.txt: ") && msg.contains(words), "{msg}");
        }
        let msg = import("DontCare -1 -1 -10 0 0 1 1 -1 -1 -1 -1000 -1000 -1000 -10\n", None)
            .err()
            .unwrap()
            .to_string();
        assert!(msg.contains("no boxes"), "{msg}");
        for (calib, words) in [
            ("1 0 0 0 0 1 0 0 0 0 1", "found 11"),
            ("1 0 0 0 0 1 0 0 0 0 1 0 0 0 0 2", "last row"),
            ("2 0 0 0 0 2 0 0 0 0 2 0", "not a rotation"),
            ("1 0 0 0 0 1 0 0 0 0 -1 0", "determinant"),
            ("1 0 0 0 0 1 0 0 0 0 1 z", "`z` is not a finite number"),
        ] {
            let msg = import(&format!("{good}\n"), Some(calib)).err().unwrap().to_string();
            assert!(msg.contains("calib.txt: ") && msg.contains(words), "{calib}: {msg}");
        }
    }
}
