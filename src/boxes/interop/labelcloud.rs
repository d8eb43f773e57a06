//! labelCloud's centroid label files (one JSON file per point cloud,
//! `labels/<cloud stem>.json`), as its `CentroidFormat` writes them:
//!
//! ```json
//! {"folder": "pointclouds", "filename": "cloud.ply", "path": "pointclouds/cloud.ply",
//!  "objects": [{"name": "mug",
//!               "centroid": {"x": 0.41, "y": -0.12, "z": 0.05},
//!               "dimensions": {"length": 0.10, "width": 0.12, "height": 0.11},
//!               "rotations": {"x": 0, "y": 0, "z": 1.5708}}]}
//! ```
//!
//! The centroid is the box centre in the point cloud's frame; length,
//! width and height are the full edges along the box's x, y and z axes;
//! the box is turned about world x by `rotations.x`, then y, then z
//! (R = Rz Ry Rx, labelCloud's `rotate_around_zyx`). `centroid_rel` files
//! hold the angles in radians (-pi..pi), `centroid_abs` files in degrees
//! (0..360).

use super::rotation::{to_zyx, zyx};
use super::{json, kind, triple, Candidate, InteropError};
use crate::boxes::parse::BoxSet;
use serde::Serialize;
use std::path::Path;

/// Unit of the rotation angles.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Angles {
    /// `centroid_rel`: radians in -pi..pi.
    Radians,
    /// `centroid_abs`: degrees in 0..360.
    Degrees,
}

/// Keys of one labelCloud object.
const OBJECT_KEYS: [&str; 4] = ["name", "centroid", "dimensions", "rotations"];

/// The boxes of a labelCloud file.
pub(crate) fn read(text: &str, path: &Path, angles: Angles) -> Result<(Vec<Candidate>, Vec<String>), InteropError> {
    let format = |problem: String| InteropError::Format {
        path: path.to_path_buf(),
        problem,
    };
    let root = json(text, path)?;
    let root = root.as_object().ok_or_else(|| {
        format(format!(
            "expected a labelCloud label object with `objects`, found {}",
            kind(&root)
        ))
    })?;
    if root.contains_key("boxes") && !root.contains_key("objects") {
        return Err(format(
            "this is a nerflabel boxes.json (`boxes`), not a labelCloud file (`objects`)".into(),
        ));
    }
    let objects = match root.get("objects") {
        Some(serde_json::Value::Array(list)) => list,
        Some(other) => return Err(format(format!("`objects` must be an array, found {}", kind(other)))),
        None => return Err(format("missing the `objects` array of a labelCloud label file".into())),
    };
    let mut out = Vec::with_capacity(objects.len());
    for (i, object) in objects.iter().enumerate() {
        let place = format!("object {} (objects[{i}])", i + 1);
        let entry = |(field, problem): (String, String)| InteropError::Entry {
            path: path.to_path_buf(),
            place: place.clone(),
            field,
            problem,
        };
        let obj = object
            .as_object()
            .ok_or_else(|| entry((String::new(), format!("expected an object, found {}", kind(object)))))?;
        if obj.contains_key("vertices") {
            return Err(entry((
                "vertices".into(),
                "labelCloud's `vertices` format is not read: export the labels as centroid_rel or centroid_abs".into(),
            )));
        }
        if let Some(key) = obj.keys().find(|k| !OBJECT_KEYS.contains(&k.as_str())) {
            return Err(entry((
                key.clone(),
                format!("unknown key (expected {})", OBJECT_KEYS.join(", ")),
            )));
        }
        let label = match obj.get("name") {
            Some(serde_json::Value::String(s)) => s.clone(),
            Some(other) => {
                return Err(entry((
                    "name".into(),
                    format!("expected a string, found {}", kind(other)),
                )))
            }
            None => return Err(entry(("name".into(), "missing".into()))),
        };
        let center = triple(obj, "centroid", ["x", "y", "z"]).map_err(entry)?;
        let size = triple(obj, "dimensions", ["length", "width", "height"]).map_err(entry)?;
        let turns = triple(obj, "rotations", ["x", "y", "z"]).map_err(entry)?;
        let radians = match angles {
            Angles::Degrees => turns.map(f64::to_radians),
            Angles::Radians => {
                let limit = std::f64::consts::TAU + 1e-6;
                if let Some(a) = (0..3).find(|&a| turns[a].abs() > limit) {
                    return Err(entry((
                        format!("rotations.{}", ["x", "y", "z"][a]),
                        format!(
                            "{} is beyond 2 pi: centroid_rel angles are radians; for a centroid_abs file (degrees) use --from labelcloud-abs",
                            turns[a]
                        ),
                    )));
                }
                turns
            }
        };
        out.push(Candidate {
            place,
            label,
            center,
            size,
            rotation: super::rotation::rows(&zyx(radians[0], radians[1], radians[2])),
            fields: ["name", "centroid", "dimensions", "rotations"],
        });
    }
    Ok((out, Vec::new()))
}

#[derive(Serialize)]
struct Xyz {
    x: f64,
    y: f64,
    z: f64,
}

/// labelCloud reads the dimensions in this order (older versions by position).
#[derive(Serialize)]
struct Dimensions {
    length: f64,
    width: f64,
    height: f64,
}

#[derive(Serialize)]
struct Object<'a> {
    name: &'a str,
    centroid: Xyz,
    dimensions: Dimensions,
    rotations: Xyz,
}

#[derive(Serialize)]
struct File<'a> {
    folder: String,
    filename: String,
    path: String,
    objects: Vec<Object<'a>>,
}

/// A labelCloud file of `set` for the point cloud `cloud`.
pub(crate) fn write(set: &BoxSet, cloud: &Path, angles: Angles) -> String {
    let name = |p: Option<&std::ffi::OsStr>| p.map(|n| n.to_string_lossy().into_owned()).unwrap_or_default();
    let objects = set
        .boxes
        .iter()
        .map(|b| {
            let (x, y, z) = to_zyx(&b.rotation);
            // + 0.0 turns -0.0 into 0.0.
            let turns = match angles {
                Angles::Radians => [x + 0.0, y + 0.0, z + 0.0],
                // labelCloud's absolute angles lie in [0, 360).
                Angles::Degrees => [x, y, z].map(|a| {
                    let d = a.to_degrees() + 0.0;
                    if d < 0.0 {
                        d + 360.0
                    } else {
                        d
                    }
                }),
            };
            Object {
                name: &b.label,
                centroid: Xyz {
                    x: b.center.x,
                    y: b.center.y,
                    z: b.center.z,
                },
                dimensions: Dimensions {
                    length: b.size.x,
                    width: b.size.y,
                    height: b.size.z,
                },
                rotations: Xyz {
                    x: turns[0],
                    y: turns[1],
                    z: turns[2],
                },
            }
        })
        .collect();
    let file = File {
        folder: name(cloud.parent().and_then(|p| p.file_name())),
        filename: name(cloud.file_name()),
        path: cloud.to_string_lossy().into_owned(),
        objects,
    };
    let mut text = serde_json::to_string_pretty(&file).unwrap_or_default();
    text.push('\n');
    text
}

#[cfg(test)]
mod tests {
    use super::super::{import_boxes, ExportFormat, ImportFormat};
    use super::*;
    use crate::boxes::parse::{Box3, BoxSet};
    use crate::rng::Rng;
    use nalgebra::{Point3, Rotation3, Vector3};

    fn import(text: &str, format: ImportFormat) -> Result<BoxSet, InteropError> {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("cloud.json");
        std::fs::write(&path, text).unwrap();
        import_boxes(&path, format, None).map(|i| i.boxes)
    }

    /// labelCloud's own test file (`test_label_import.py`): a cart turned
    /// about z, read as centroid_rel (radians) and as centroid_abs (degrees).
    const CART: &str = r#"{"folder": "pointclouds", "filename": "test.ply", "path": "pointclouds/test.ply",
        "objects": [{"name": "cart", "centroid": { "x": -0.186338, "y": -0.241696, "z": 0.054818},
        "dimensions": {"length": 0.80014, "width": 0.512493, "height": 0.186055},
        "rotations": {"x": 0, "y": 0, "z": 1.616616} } ] }"#;

    #[test]
    fn centroid_files_give_centre_size_and_yaw() {
        for (format, yaw) in [
            (ImportFormat::Labelcloud, 1.616616),
            (ImportFormat::LabelcloudAbs, 1.616616f64.to_radians()),
        ] {
            let set = import(CART, format).unwrap();
            let b = &set.boxes[0];
            assert_eq!(b.label, "cart");
            assert_eq!(<[f64; 3]>::from(b.center.coords), [-0.186338, -0.241696, 0.054818]);
            assert_eq!(<[f64; 3]>::from(b.size), [0.80014, 0.512493, 0.186055]);
            // The length axis points at the yaw angle from world x, in the xy plane.
            let length_axis = b.rotation * Vector3::x();
            assert!((length_axis - Vector3::new(yaw.cos(), yaw.sin(), 0.0)).norm() < 1e-12);
            assert!((b.rotation * Vector3::z() - Vector3::z()).norm() < 1e-12);
        }
        // Order of rotation: x first, then y, then z (labelCloud's rotate_around_zyx).
        let text = r#"{"objects": [{"name": "a", "centroid": {"x": 1, "y": 2, "z": 3},
            "dimensions": {"length": 1, "width": 2, "height": 3}, "rotations": {"x": 90, "y": 0, "z": 90}}]}"#;
        let b = import(text, ImportFormat::LabelcloudAbs).unwrap().boxes.remove(0);
        // x by 90: the width (y) axis goes up; z by 90 leaves it up and turns the length axis to +y.
        assert!((b.rotation * Vector3::y() - Vector3::z()).norm() < 1e-12);
        assert!((b.rotation * Vector3::x() - Vector3::y()).norm() < 1e-12);
        assert!((b.rotation * Vector3::z() - Vector3::x()).norm() < 1e-12);
    }

    #[test]
    fn export_then_import_gives_the_same_boxes() {
        let mut rng = Rng::new(11, 0);
        let boxes: Vec<Box3> = (1..=20)
            .map(|i| Box3 {
                label: ["mug", "box", "can"][i % 3].into(),
                instance_id: i as u32,
                center: Point3::new(rng.range(-2.0, 2.0), rng.range(-2.0, 2.0), rng.range(-1.0, 1.0)),
                size: Vector3::new(rng.range(0.01, 1.0), rng.range(0.01, 1.0), rng.range(0.01, 1.0)),
                rotation: if i % 4 == 0 {
                    Rotation3::from_axis_angle(&Vector3::z_axis(), rng.range(-3.0, 3.0))
                } else {
                    zyx(rng.range(-3.1, 3.1), rng.range(-1.5, 1.5), rng.range(-3.1, 3.1))
                },
            })
            .collect();
        let set = BoxSet::from_boxes(boxes);
        for (to, from) in [
            (ExportFormat::Labelcloud, ImportFormat::Labelcloud),
            (ExportFormat::LabelcloudAbs, ImportFormat::LabelcloudAbs),
        ] {
            let text = super::super::export_boxes(&set, to, Path::new("/data/pointclouds/room.ply"));
            let doc: serde_json::Value = serde_json::from_str(&text).unwrap();
            assert_eq!(doc["folder"], "pointclouds");
            assert_eq!(doc["filename"], "room.ply");
            assert_eq!(doc["path"], "/data/pointclouds/room.ply");
            // Dimensions in labelCloud's order (older versions read them by position).
            let dims = text.find("\"length\"").unwrap();
            assert!(
                dims < text.find("\"width\"").unwrap()
                    && text.find("\"width\"").unwrap() < text.find("\"height\"").unwrap()
            );
            let back = import(&text, from).unwrap();
            assert_eq!(back.categories, set.categories);
            for (a, b) in set.boxes.iter().zip(&back.boxes) {
                assert_eq!((&a.label, a.instance_id), (&b.label, b.instance_id));
                assert!((a.center - b.center).abs().max() < 1e-9);
                assert!((a.size - b.size).abs().max() < 1e-9);
                assert!((a.rotation.matrix() - b.rotation.matrix()).amax() < 1e-9, "{to:?}");
            }
            if to == ExportFormat::LabelcloudAbs {
                let z = doc["objects"][0]["rotations"]["z"].as_f64().unwrap();
                assert!((0.0..360.0).contains(&z), "{z}");
            }
        }
    }

    #[test]
    fn bad_objects_name_the_file_object_and_field() {
        let good = r#"{"name": "a", "centroid": {"x": 0, "y": 0, "z": 0}, "dimensions": {"length": 1, "width": 1, "height": 1}, "rotations": {"x": 0, "y": 0, "z": 0}}"#;
        let cases: &[(&str, &str, &str)] = &[
            (r#"{"centroid": {"x": 0, "y": 0, "z": 0}}"#, "`name`", "missing"),
            (r#"{"name": 3}"#, "`name`", "expected a string"),
            (
                r#"{"name": "", "centroid": {"x": 0, "y": 0, "z": 0}, "dimensions": {"length": 1, "width": 1, "height": 1}, "rotations": {"x": 0, "y": 0, "z": 0}}"#,
                "`name`",
                "empty",
            ),
            (
                r#"{"name": "a", "centroid": {"x": 0, "z": 0}}"#,
                "`centroid.y`",
                "missing",
            ),
            (
                r#"{"name": "a", "centroid": [0, 0, 0]}"#,
                "`centroid`",
                "expected an object",
            ),
            (
                r#"{"name": "a", "centroid": {"x": 0, "y": "1", "z": 0}}"#,
                "`centroid.y`",
                "finite number",
            ),
            (
                r#"{"name": "a", "centroid": {"x": 0, "y": 0, "z": 0}, "dimensions": {"length": 1, "width": -1, "height": 1}, "rotations": {"x": 0, "y": 0, "z": 0}}"#,
                "`dimensions`",
                "negative",
            ),
            (
                r#"{"name": "a", "centroid": {"x": 0, "y": 0, "z": 0}, "dimensions": {"length": 1, "width": 1, "height": 1}, "rotations": {"x": 0, "y": 0, "z": 92.6}}"#,
                "`rotations.z`",
                "--from labelcloud-abs",
            ),
            (
                r#"{"name": "a", "vertices": [[0, 0, 0]]}"#,
                "`vertices`",
                "centroid_rel",
            ),
            (r#"{"name": "a", "colour": "red"}"#, "`colour`", "unknown key"),
        ];
        for (object, field, words) in cases {
            let text = format!(r#"{{"objects": [{good}, {object}]}}"#);
            let msg = import(&text, ImportFormat::Labelcloud).unwrap_err().to_string();
            assert!(
                msg.contains(&format!("cloud.json: object 2 (objects[1]), field {field}: ")),
                "{msg}"
            );
            assert!(msg.contains(words), "{object}: {msg}");
        }
        let msg = import(&format!(r#"{{"objects": [{good}, 7]}}"#), ImportFormat::Labelcloud)
            .unwrap_err()
            .to_string();
        assert!(
            msg.ends_with("cloud.json: object 2 (objects[1]): expected an object, found a number"),
            "{msg}"
        );
        for (text, words) in [
            ("{", "not valid JSON"),
            ("[]", "expected a labelCloud label object"),
            (r#"{"folder": "x"}"#, "missing the `objects`"),
            (r#"{"objects": {}}"#, "must be an array"),
            (r#"{"objects": []}"#, "no boxes"),
            (r#"{"boxes": []}"#, "nerflabel boxes.json"),
        ] {
            let msg = import(text, ImportFormat::Labelcloud).unwrap_err().to_string();
            assert!(msg.contains("cloud.json: ") && msg.contains(words), "{text}: {msg}");
        }
    }
}
