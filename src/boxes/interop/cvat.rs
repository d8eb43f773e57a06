//! CVAT 3D cuboids from its "Sly Point Cloud Format 1.0" export (CVAT's
//! dataset export for point-cloud tasks, written by Datumaro's
//! `sly_pointcloud` exporter in the Supervisely point cloud annotation
//! format). The export zip holds one annotation file per point cloud,
//! `ds0/ann/<name>.pcd.json`:
//!
//! ```json
//! {"description": "", "key": "…", "tags": [],
//!  "objects": [{"key": "b1…", "classTitle": "car", "tags": [], …}],
//!  "figures": [{"key": "…", "objectKey": "b1…", "geometryType": "cuboid_3d",
//!               "geometry": {"position": {"x": 1, "y": 2, "z": 0.5},
//!                            "rotation": {"x": 0, "y": 0, "z": 1.57},
//!                            "dimensions": {"x": 4, "y": 1.8, "z": 1.5}}, …}]}
//! ```
//!
//! `position` is the cuboid's centre and `dimensions` its full edges along
//! its own x, y and z, in the point cloud's frame; `rotation` holds the
//! three.js Euler angles of CVAT's 3D canvas (radians, order `XYZ`:
//! R = Rx Ry Rz). A figure's label is the `classTitle` of the object its
//! `objectKey` names. Figures of other shapes are skipped.

use super::rotation::{rows, xyz};
use super::{json, kind, triple, Candidate, InteropError};
use std::collections::BTreeMap;
use std::path::Path;

/// The cuboids of one Sly point cloud annotation file.
pub(crate) fn read(text: &str, path: &Path) -> Result<(Vec<Candidate>, Vec<String>), InteropError> {
    let format = |problem: String| InteropError::Format {
        path: path.to_path_buf(),
        problem,
    };
    let root = json(text, path)?;
    let root = root.as_object().ok_or_else(|| {
        format(format!(
            "expected a Supervisely point cloud annotation object with `objects` and `figures`, found {}",
            kind(&root)
        ))
    })?;
    let list = |key: &str| {
        match root.get(key) {
        Some(serde_json::Value::Array(list)) => Ok(list),
        Some(other) => Err(format(format!("`{key}` must be an array, found {}", kind(other)))),
        None => Err(format(format!(
            "missing the `{key}` array of a Supervisely point cloud annotation (a CVAT \"Sly Point Cloud\" export's ds0/ann/*.pcd.json)"
        ))),
    }
    };
    let (objects, figures) = (list("objects")?, list("figures")?);
    let mut classes: BTreeMap<&str, &str> = BTreeMap::new();
    for (i, object) in objects.iter().enumerate() {
        let entry = |field: &str, problem: String| InteropError::Entry {
            path: path.to_path_buf(),
            place: format!("object {} (objects[{i}])", i + 1),
            field: field.to_string(),
            problem,
        };
        let string = |field: &str| match object.get(field) {
            Some(serde_json::Value::String(s)) => Ok(s.as_str()),
            Some(other) => Err(entry(field, format!("expected a string, found {}", kind(other)))),
            None => Err(entry(field, "missing".into())),
        };
        if !object.is_object() {
            return Err(entry("", format!("expected an object, found {}", kind(object))));
        }
        classes.insert(string("key")?, string("classTitle")?);
    }
    let (mut out, mut skipped) = (Vec::new(), 0usize);
    for (i, figure) in figures.iter().enumerate() {
        let place = format!("figure {} (figures[{i}])", i + 1);
        let entry = |(field, problem): (String, String)| InteropError::Entry {
            path: path.to_path_buf(),
            place: place.clone(),
            field,
            problem,
        };
        let fig = figure
            .as_object()
            .ok_or_else(|| entry((String::new(), format!("expected an object, found {}", kind(figure)))))?;
        match fig.get("geometryType").and_then(|v| v.as_str()) {
            Some("cuboid_3d") => {}
            Some(_) => {
                skipped += 1;
                continue;
            }
            None => return Err(entry(("geometryType".into(), "missing or not a string".into()))),
        }
        let label = match fig.get("objectKey") {
            Some(serde_json::Value::String(key)) => classes.get(key.as_str()).copied().ok_or_else(|| {
                entry((
                    "objectKey".into(),
                    format!("`{key}` is not the key of any entry of `objects`"),
                ))
            })?,
            Some(other) => {
                return Err(entry((
                    "objectKey".into(),
                    format!("expected a string, found {}", kind(other)),
                )))
            }
            None => return Err(entry(("objectKey".into(), "missing".into()))),
        };
        let geometry = match fig.get("geometry") {
            Some(serde_json::Value::Object(g)) => g,
            Some(other) => {
                return Err(entry((
                    "geometry".into(),
                    format!("expected an object, found {}", kind(other)),
                )))
            }
            None => return Err(entry(("geometry".into(), "missing".into()))),
        };
        let prefixed = |(field, problem): (String, String)| entry((format!("geometry.{field}"), problem));
        let center = triple(geometry, "position", ["x", "y", "z"]).map_err(prefixed)?;
        let turns = triple(geometry, "rotation", ["x", "y", "z"]).map_err(prefixed)?;
        let size = triple(geometry, "dimensions", ["x", "y", "z"]).map_err(prefixed)?;
        out.push(Candidate {
            place: place.clone(),
            label: label.to_string(),
            center,
            size,
            rotation: rows(&xyz(turns[0], turns[1], turns[2])),
            fields: [
                "classTitle",
                "geometry.position",
                "geometry.dimensions",
                "geometry.rotation",
            ],
        });
    }
    let warnings = if skipped > 0 {
        vec![format!(
            "{}: skipped {skipped} figure(s) that are not cuboid_3d",
            path.display()
        )]
    } else {
        Vec::new()
    };
    Ok((out, warnings))
}

#[cfg(test)]
mod tests {
    use super::super::{import_boxes, ImportFormat};
    use super::*;
    use nalgebra::Vector3;

    fn import(text: &str) -> Result<super::super::Imported, InteropError> {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("scene.pcd.json");
        std::fs::write(&path, text).unwrap();
        import_boxes(&path, ImportFormat::Cvat, None)
    }

    /// As Datumaro's sly_pointcloud exporter writes a CVAT task's export:
    /// two objects, two cuboids, user fields and tags around them.
    const EXPORT: &str = r#"{
  "description": "",
  "key": "6c4b6d3e-0d84-4c1c-9a3c-2f2f4a1f5b10",
  "tags": [],
  "objects": [
    {"key": "0f1c8a2e-6a55-4bd4-9f65-0f7e1e2c6a01", "classTitle": "chair", "tags": [], "objects": [], "figures": [],
     "labelerLogin": "admin", "createdAt": "2024-05-02 10:00:00.000000", "updatedAt": "2024-05-02 10:00:00.000000"},
    {"key": "9a7b3c4d-1e2f-4a5b-8c9d-0e1f2a3b4c5d", "classTitle": "table", "tags": [], "objects": [], "figures": [],
     "labelerLogin": "admin", "createdAt": "2024-05-02 10:00:00.000000", "updatedAt": "2024-05-02 10:00:00.000000"}
  ],
  "figures": [
    {"key": "f1", "objectKey": "9a7b3c4d-1e2f-4a5b-8c9d-0e1f2a3b4c5d", "geometryType": "cuboid_3d",
     "geometry": {"position": {"x": 1.5, "y": -0.25, "z": 0.375},
                  "rotation": {"x": 0.0, "y": 0.0, "z": 0.5235987755982988},
                  "dimensions": {"x": 1.2, "y": 0.8, "z": 0.75}},
     "labelerLogin": "admin", "createdAt": "2024-05-02 10:00:00.000000", "updatedAt": "2024-05-02 10:00:00.000000"},
    {"key": "f2", "objectKey": "0f1c8a2e-6a55-4bd4-9f65-0f7e1e2c6a01", "geometryType": "cuboid_3d",
     "geometry": {"position": {"x": 0.0, "y": 1.0, "z": 0.45},
                  "rotation": {"x": 1.5707963267948966, "y": 0.0, "z": 1.5707963267948966},
                  "dimensions": {"x": 0.5, "y": 0.9, "z": 0.4}},
     "labelerLogin": "admin", "createdAt": "2024-05-02 10:00:00.000000", "updatedAt": "2024-05-02 10:00:00.000000"},
    {"key": "f3", "objectKey": "0f1c8a2e-6a55-4bd4-9f65-0f7e1e2c6a01", "geometryType": "point", "geometry": {}}
  ]
}"#;

    #[test]
    fn cuboids_keep_centre_size_and_three_js_rotation() {
        let imported = import(EXPORT).unwrap();
        assert_eq!(imported.warnings.len(), 1, "the point figure is skipped");
        let set = imported.boxes;
        assert_eq!(set.categories, vec!["table".to_string(), "chair".to_string()]);
        let table = &set.boxes[0];
        assert_eq!(<[f64; 3]>::from(table.center.coords), [1.5, -0.25, 0.375]);
        assert_eq!(<[f64; 3]>::from(table.size), [1.2, 0.8, 0.75]);
        let a = std::f64::consts::FRAC_PI_6;
        assert!((table.rotation * Vector3::x() - Vector3::new(a.cos(), a.sin(), 0.0)).norm() < 1e-12);
        // XYZ order: z by 90 first (x -> y), then x by 90 (y -> z): the box's x axis ends up along world z.
        let chair = &set.boxes[1];
        assert!((chair.rotation * Vector3::x() - Vector3::z()).norm() < 1e-12);
        assert!((chair.rotation * Vector3::z() + Vector3::y()).norm() < 1e-12);
    }

    #[test]
    fn bad_figures_name_the_file_figure_and_field() {
        let swap = |from: &str, to: &str| EXPORT.replacen(from, to, 1);
        for (text, words) in [
            (
                swap(r#""objectKey": "9a7b"#, r#""objectKey": "zz9a7b"#),
                "figure 1 (figures[0]), field `objectKey`: `zz9a7b",
            ),
            (
                swap(r#""x": 1.5,"#, r#""x": "1.5","#),
                "figure 1 (figures[0]), field `geometry.position.x`",
            ),
            (
                swap(r#""dimensions": {"x": 1.2"#, r#""dimensions": {"x": -1.2"#),
                "figure 1 (figures[0]), field `geometry.dimensions`: edge x is -1.2",
            ),
            (
                swap(r#""classTitle": "chair""#, r#""classTitle": 5"#),
                "object 1 (objects[0]), field `classTitle`",
            ),
            (
                swap(r#""geometryType": "cuboid_3d""#, r#""geometryType": 3"#),
                "figure 1 (figures[0]), field `geometryType`",
            ),
            (r#"{"objects": []}"#.to_string(), "missing the `figures` array"),
            (r#"{"objects": [], "figures": []}"#.to_string(), "no boxes"),
        ] {
            let msg = import(&text).err().unwrap().to_string();
            assert!(msg.contains("scene.pcd.json: ") && msg.contains(words), "{msg}");
        }
    }
}
