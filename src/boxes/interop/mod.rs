//! Boxes from and to other labelling tools (`nerflabel boxes import` /
//! `export`): labelCloud's centroid JSON, KITTI `label_2` text and CVAT's
//! "Sly Point Cloud" export are read into a [`BoxSet`] (every box checked
//! by the boxes.json rules of [`super::parse`]) and written as FORMATS.md
//! section 2 `boxes.json`; a [`BoxSet`] is written as labelCloud JSON.
//!
//! Depends only on [`super::parse`]; never on scans, models or the CLI.

pub mod cvat;
pub mod kitti;
pub mod labelcloud;
pub mod rotation;

use super::parse::{parse_box, read_text, BoxError, BoxSet, MAX_BOXES};
use std::path::{Path, PathBuf};

/// A file format boxes are imported from.
#[derive(Clone, Copy, Debug, PartialEq, Eq, clap::ValueEnum)]
pub enum ImportFormat {
    /// labelCloud `centroid_rel` JSON (rotations in radians).
    Labelcloud,
    /// labelCloud `centroid_abs` JSON (rotations in degrees).
    LabelcloudAbs,
    /// KITTI `label_2` text, one object per line, in the camera-0 frame.
    Kitti,
    /// CVAT's "Sly Point Cloud Format 1.0" export: one `ds0/ann/<name>.pcd.json`.
    Cvat,
}

impl ImportFormat {
    /// Name used on the command line.
    pub fn name(self) -> &'static str {
        match self {
            ImportFormat::Labelcloud => "labelcloud",
            ImportFormat::LabelcloudAbs => "labelcloud-abs",
            ImportFormat::Kitti => "kitti",
            ImportFormat::Cvat => "cvat",
        }
    }
}

/// A file format boxes are exported to.
#[derive(Clone, Copy, Debug, PartialEq, Eq, clap::ValueEnum)]
pub enum ExportFormat {
    /// labelCloud `centroid_rel` JSON (rotations in radians).
    Labelcloud,
    /// labelCloud `centroid_abs` JSON (rotations in degrees).
    LabelcloudAbs,
}

impl ExportFormat {
    /// Name used on the command line.
    pub fn name(self) -> &'static str {
        match self {
            ExportFormat::Labelcloud => "labelcloud",
            ExportFormat::LabelcloudAbs => "labelcloud-abs",
        }
    }
}

/// Why a file could not be imported.
#[derive(Debug, thiserror::Error)]
pub enum InteropError {
    /// Unreadable, too large or not text (the message names the file).
    #[error(transparent)]
    Read(#[from] BoxError),
    #[error("{path}: not valid JSON: {error}")]
    Json { path: PathBuf, error: serde_json::Error },
    #[error("{path}: {problem}")]
    Format { path: PathBuf, problem: String },
    /// `place` names the entry (`object 2 (objects[1])`, `line 7`); an
    /// empty `field` is the whole entry.
    #[error("{path}: {place}{}: {problem}", field_part(.field))]
    Entry {
        path: PathBuf,
        place: String,
        field: String,
        problem: String,
    },
}

fn field_part(field: &str) -> String {
    if field.is_empty() {
        String::new()
    } else {
        format!(", field `{field}`")
    }
}

/// Boxes read from another tool's file.
#[derive(Clone, Debug)]
pub struct Imported {
    pub boxes: BoxSet,
    /// Entries skipped (KITTI `DontCare`, CVAT shapes that are not cuboids).
    pub warnings: Vec<String>,
}

/// One box as another tool describes it, before the boxes.json checks:
/// where it is in its file and which of its fields hold the label, centre,
/// size and rotation (for error messages).
pub(crate) struct Candidate {
    pub place: String,
    pub label: String,
    pub center: [f64; 3],
    pub size: [f64; 3],
    /// Box-to-world, rows.
    pub rotation: [[f64; 3]; 3],
    /// Source field names of `label`, `center`, `size` and `rotation`.
    pub fields: [&'static str; 4],
}

/// Read `path` in `format`; `calib` is KITTI's camera-to-world matrix file.
pub fn import_boxes(path: &Path, format: ImportFormat, calib: Option<&Path>) -> Result<Imported, InteropError> {
    if calib.is_some() && format != ImportFormat::Kitti {
        return Err(InteropError::Format {
            path: path.to_path_buf(),
            problem: format!(
                "--calib places KITTI camera-frame boxes in the world; `{}` boxes are already in the point cloud's frame",
                format.name()
            ),
        });
    }
    let text = read_text(path)?;
    let text = text.strip_prefix('\u{feff}').unwrap_or(&text);
    let (candidates, warnings) = match format {
        ImportFormat::Labelcloud => labelcloud::read(text, path, labelcloud::Angles::Radians)?,
        ImportFormat::LabelcloudAbs => labelcloud::read(text, path, labelcloud::Angles::Degrees)?,
        ImportFormat::Kitti => {
            let camera_to_world = match calib {
                Some(c) => Some(kitti::read_calib(c)?),
                None => None,
            };
            kitti::read(text, path, camera_to_world.as_ref())?
        }
        ImportFormat::Cvat => cvat::read(text, path)?,
    };
    Ok(Imported {
        boxes: checked(candidates, path)?,
        warnings,
    })
}

/// The boxes.json checks on every candidate; an error names the entry and
/// its field in the source file's own terms.
fn checked(candidates: Vec<Candidate>, path: &Path) -> Result<BoxSet, InteropError> {
    if candidates.is_empty() {
        return Err(InteropError::Format {
            path: path.to_path_buf(),
            problem: "no boxes in the file: nothing to import".into(),
        });
    }
    if candidates.len() > MAX_BOXES {
        return Err(InteropError::Format {
            path: path.to_path_buf(),
            problem: format!(
                "{} boxes is more than the {MAX_BOXES} a 16-bit mask can hold",
                candidates.len()
            ),
        });
    }
    let mut boxes = Vec::with_capacity(candidates.len());
    for (i, c) in candidates.into_iter().enumerate() {
        let entry = serde_json::json!({
            "label": c.label, "center": c.center, "size": c.size, "rotation": c.rotation,
        });
        let b = parse_box(&entry, i + 1).map_err(|(field, problem)| {
            let source = match field.as_str() {
                "label" => c.fields[0],
                "center" => c.fields[1],
                "size" => c.fields[2],
                _ => c.fields[3],
            };
            InteropError::Entry {
                path: path.to_path_buf(),
                place: c.place.clone(),
                field: source.to_string(),
                problem,
            }
        })?;
        boxes.push(b);
    }
    Ok(BoxSet::from_boxes(boxes))
}

/// FORMATS.md section 2 `boxes.json` of a box set, one box per line
/// (label, center, size, rotation as rows).
pub fn boxes_json(set: &BoxSet) -> String {
    let lines: Vec<String> = set
        .boxes
        .iter()
        .map(|b| {
            format!(
                "    {{\"label\": {}, \"center\": {}, \"size\": {}, \"rotation\": {}}}",
                compact(&b.label),
                compact(&<[f64; 3]>::from(b.center.coords)),
                compact(&<[f64; 3]>::from(b.size)),
                compact(&rotation::rows(&b.rotation)),
            )
        })
        .collect();
    format!("{{\n  \"boxes\": [\n{}\n  ]\n}}\n", lines.join(",\n"))
}

/// Compact JSON text of a value (floats in their shortest exact form).
fn compact<T: serde::Serialize + ?Sized>(value: &T) -> String {
    serde_json::to_string(value).unwrap_or_default()
}

/// A box set in another tool's format; `cloud` is the point cloud the
/// boxes belong to (labelCloud records its folder, name and path).
pub fn export_boxes(set: &BoxSet, format: ExportFormat, cloud: &Path) -> String {
    let angles = match format {
        ExportFormat::Labelcloud => labelcloud::Angles::Radians,
        ExportFormat::LabelcloudAbs => labelcloud::Angles::Degrees,
    };
    labelcloud::write(set, cloud, angles)
}

/// The JSON kind of a value, for messages.
pub(crate) fn kind(v: &serde_json::Value) -> &'static str {
    use serde_json::Value;
    match v {
        Value::Null => "null",
        Value::Bool(_) => "a boolean",
        Value::Number(_) => "a number",
        Value::String(_) => "a string",
        Value::Array(_) => "an array",
        Value::Object(_) => "an object",
    }
}

/// Parse a JSON file's text, naming the file in the error.
pub(crate) fn json(text: &str, path: &Path) -> Result<serde_json::Value, InteropError> {
    serde_json::from_str(text).map_err(|error| InteropError::Json {
        path: path.to_path_buf(),
        error,
    })
}

/// `obj[key]` as an object with finite numbers under `axes`, for the
/// `{"x": .., "y": .., "z": ..}` triples of labelCloud and CVAT.
pub(crate) fn triple(
    obj: &serde_json::Map<String, serde_json::Value>,
    key: &str,
    axes: [&str; 3],
) -> Result<[f64; 3], (String, String)> {
    let value = obj.get(key).ok_or_else(|| (key.to_string(), "missing".to_string()))?;
    let inner = value.as_object().ok_or_else(|| {
        (
            key.to_string(),
            format!("expected an object with {}, found {}", axes.join(", "), kind(value)),
        )
    })?;
    let mut out = [0.0; 3];
    for (x, axis) in out.iter_mut().zip(axes) {
        let field = format!("{key}.{axis}");
        let v = inner.get(axis).ok_or_else(|| (field.clone(), "missing".to_string()))?;
        *x = match v.as_f64() {
            Some(n) if n.is_finite() => n,
            _ => return Err((field, format!("expected a finite number, found {}", kind(v)))),
        };
    }
    Ok(out)
}
