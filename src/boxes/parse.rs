//! Read and validate `boxes.json` (FORMATS.md section 2): oriented 3D boxes
//! in the scan's world frame, each with a label; its 1-based position in the
//! list is its instance id.

use nalgebra::{IsometryMatrix3, Matrix3, Point3, Quaternion, Rotation3, Translation3, UnitQuaternion, Vector3};
use serde_json::{Map, Value};
use std::path::{Path, PathBuf};

/// Most boxes one file may hold (instance ids must fit a 16-bit mask).
pub const MAX_BOXES: usize = 65_535;
/// Largest boxes file read, bytes.
pub const MAX_FILE_BYTES: u64 = 64 << 20;
/// Longest accepted label, bytes.
pub const MAX_LABEL_BYTES: usize = 256;
/// Tolerance on orthonormality and determinant of a given rotation.
pub const ROTATION_TOLERANCE: f64 = 1e-3;

/// Keys a box entry may have.
const BOX_KEYS: [&str; 5] = ["label", "center", "size", "rotation", "quaternion"];

/// One oriented box in world coordinates (metres).
#[derive(Clone, Debug, PartialEq)]
pub struct Box3 {
    pub label: String,
    /// 1-based index in the file.
    pub instance_id: u32,
    pub center: Point3<f64>,
    /// Full edge lengths along the box's own x, y, z axes.
    pub size: Vector3<f64>,
    /// Box-to-world rotation (columns are the box axes in world coordinates).
    pub rotation: Rotation3<f64>,
}

impl Box3 {
    /// Rigid object pose: box frame (origin at the centre) to world.
    pub fn object_to_world(&self) -> IsometryMatrix3<f64> {
        IsometryMatrix3::from_parts(Translation3::from(self.center.coords), self.rotation)
    }

    /// Volume in cubic metres.
    pub fn volume(&self) -> f64 {
        self.size.x * self.size.y * self.size.z
    }

    /// World point to box coordinates (centre at the origin, box axes).
    #[inline]
    pub fn to_local(&self, p: &Point3<f64>) -> Vector3<f64> {
        self.rotation.transpose() * (p - self.center)
    }

    /// Half the box's extent along the unit world direction `axis`.
    pub fn reach(&self, axis: &Vector3<f64>) -> f64 {
        let half = self.size * 0.5;
        (0..3)
            .map(|a| half[a] * axis.dot(&self.rotation.matrix().column(a)).abs())
            .sum()
    }

    /// Half extents of the box's world-aligned bounding box.
    pub fn world_half_extent(&self) -> Vector3<f64> {
        Vector3::new(
            self.reach(&Vector3::x()),
            self.reach(&Vector3::y()),
            self.reach(&Vector3::z()),
        )
    }

    /// Whether the world point lies inside the box (faces included).
    pub fn contains(&self, p: &Point3<f64>) -> bool {
        let q = self.to_local(p).abs();
        let h = self.size * 0.5;
        q.x <= h.x && q.y <= h.y && q.z <= h.z
    }

    /// The eight corners in world coordinates; bit k of the index picks the
    /// + side of axis k.
    pub fn corners(&self) -> [Point3<f64>; 8] {
        let h = self.size * 0.5;
        std::array::from_fn(|i| {
            let s = Vector3::new(
                if i & 1 != 0 { h.x } else { -h.x },
                if i & 2 != 0 { h.y } else { -h.y },
                if i & 4 != 0 { h.z } else { -h.z },
            );
            self.center + self.rotation * s
        })
    }
}

/// The boxes of one file and their categories.
#[derive(Clone, Debug, PartialEq)]
pub struct BoxSet {
    pub boxes: Vec<Box3>,
    /// Unique labels in order of first appearance; category id = index + 1.
    pub categories: Vec<String>,
}

impl BoxSet {
    /// A set from boxes (categories derived from their labels).
    pub fn from_boxes(boxes: Vec<Box3>) -> BoxSet {
        let mut categories: Vec<String> = Vec::new();
        for b in &boxes {
            if !categories.contains(&b.label) {
                categories.push(b.label.clone());
            }
        }
        BoxSet { boxes, categories }
    }

    /// Category id (1-based) of a label.
    pub fn category_id(&self, label: &str) -> Option<u32> {
        self.categories.iter().position(|c| c == label).map(|i| i as u32 + 1)
    }

    /// The box with an instance id.
    pub fn by_instance(&self, instance_id: u32) -> Option<&Box3> {
        self.position(instance_id).map(|i| &self.boxes[i])
    }

    /// Index in `boxes` of the box with an instance id (box k of a boxes
    /// file has id k; objects of given masks keep their own ids).
    pub fn position(&self, instance_id: u32) -> Option<usize> {
        let i = (instance_id as usize).checked_sub(1)?;
        if self.boxes.get(i).is_some_and(|b| b.instance_id == instance_id) {
            return Some(i);
        }
        self.boxes.iter().position(|b| b.instance_id == instance_id)
    }

    /// The largest instance id (0 when empty).
    pub fn max_instance_id(&self) -> u32 {
        self.boxes.iter().map(|b| b.instance_id).max().unwrap_or(0)
    }

    /// Non-fatal findings: boxes with zero volume (they can contain nothing).
    pub fn warnings(&self) -> Vec<String> {
        self.boxes
            .iter()
            .filter(|b| b.volume() == 0.0)
            .map(|b| {
                format!(
                    "box {} (`{}`) has zero volume (size {:?}): it can contain nothing",
                    b.instance_id,
                    b.label,
                    <[f64; 3]>::from(b.size)
                )
            })
            .collect()
    }
}

/// Why a boxes file was rejected.
#[derive(Debug, thiserror::Error)]
pub enum BoxError {
    #[error("{path}: cannot read the boxes file: {source}")]
    Read { path: PathBuf, source: std::io::Error },
    #[error("{path}: {bytes} bytes is larger than any boxes file (at most {MAX_FILE_BYTES})")]
    TooLarge { path: PathBuf, bytes: u64 },
    #[error("{path}: not valid JSON: {source}")]
    Json { path: PathBuf, source: serde_json::Error },
    #[error("{path}: {problem}")]
    Format { path: PathBuf, problem: String },
    /// `index` is 1-based (the instance id).
    #[error("{path}: box {index} (boxes[{}]), field `{field}`: {problem}", .index - 1)]
    Box {
        path: PathBuf,
        index: usize,
        field: String,
        problem: String,
    },
}

/// Read and validate a boxes file.
pub fn read_boxes(path: &Path) -> Result<BoxSet, BoxError> {
    parse_boxes(&read_text(path)?, path)
}

/// A text file of at most [`MAX_FILE_BYTES`] (also for devices and pipes,
/// which report no length), as UTF-8.
pub(crate) fn read_text(path: &Path) -> Result<String, BoxError> {
    let read_err = |source| BoxError::Read {
        path: path.to_path_buf(),
        source,
    };
    let bytes = std::fs::metadata(path).map_err(read_err)?.len();
    if bytes > MAX_FILE_BYTES {
        return Err(BoxError::TooLarge {
            path: path.to_path_buf(),
            bytes,
        });
    }
    // Devices and pipes report no length: read at most one byte past the cap.
    let mut raw = Vec::new();
    std::io::Read::read_to_end(
        &mut std::io::Read::take(std::fs::File::open(path).map_err(read_err)?, MAX_FILE_BYTES + 1),
        &mut raw,
    )
    .map_err(read_err)?;
    if raw.len() as u64 > MAX_FILE_BYTES {
        return Err(BoxError::TooLarge {
            path: path.to_path_buf(),
            bytes: raw.len() as u64,
        });
    }
    String::from_utf8(raw).map_err(|_| BoxError::Format {
        path: path.to_path_buf(),
        problem: "not UTF-8 text".into(),
    })
}

/// Parse and validate boxes JSON; `source` only names the file in errors.
pub fn parse_boxes(text: &str, source: &Path) -> Result<BoxSet, BoxError> {
    let format = |problem: String| BoxError::Format {
        path: source.to_path_buf(),
        problem,
    };
    if text.len() as u64 > MAX_FILE_BYTES {
        return Err(BoxError::TooLarge {
            path: source.to_path_buf(),
            bytes: text.len() as u64,
        });
    }
    // Editors on Windows may start the file with a byte-order mark.
    let text = text.strip_prefix('\u{feff}').unwrap_or(text);
    let root: Value = serde_json::from_str(text).map_err(|e| BoxError::Json {
        path: source.to_path_buf(),
        source: e,
    })?;
    let root = root
        .as_object()
        .ok_or_else(|| format("expected a JSON object with a `boxes` array".into()))?;
    if let Some(key) = root.keys().find(|k| k.as_str() != "boxes") {
        return Err(format(format!(
            "unknown key `{key}` at the top level (expected only `boxes`)"
        )));
    }
    let list = match root.get("boxes") {
        None => return Err(format("missing the `boxes` array".into())),
        Some(Value::Array(list)) => list,
        Some(other) => return Err(format(format!("`boxes` must be an array, found {}", kind(other)))),
    };
    if list.is_empty() {
        return Err(format("`boxes` is empty: nothing to label".into()));
    }
    if list.len() > MAX_BOXES {
        return Err(format(format!(
            "{} boxes is more than the {MAX_BOXES} a 16-bit mask can hold",
            list.len()
        )));
    }
    let boxes = list
        .iter()
        .enumerate()
        .map(|(i, v)| {
            parse_box(v, i + 1).map_err(|(field, problem)| BoxError::Box {
                path: source.to_path_buf(),
                index: i + 1,
                field,
                problem,
            })
        })
        .collect::<Result<Vec<_>, _>>()?;
    Ok(BoxSet::from_boxes(boxes))
}

/// A field name and what is wrong with it.
pub(crate) type FieldError = (String, String);

fn field_err(field: &str, problem: impl Into<String>) -> FieldError {
    (field.to_string(), problem.into())
}

fn kind(v: &Value) -> &'static str {
    match v {
        Value::Null => "null",
        Value::Bool(_) => "a boolean",
        Value::Number(_) => "a number",
        Value::String(_) => "a string",
        Value::Array(_) => "an array",
        Value::Object(_) => "an object",
    }
}

/// One box entry; `id` is its 1-based index.
pub(crate) fn parse_box(v: &Value, id: usize) -> Result<Box3, FieldError> {
    let obj: &Map<String, Value> = v
        .as_object()
        .ok_or_else(|| field_err("", format!("expected an object, found {}", kind(v))))?;
    if let Some(key) = obj.keys().find(|k| !BOX_KEYS.contains(&k.as_str())) {
        return Err(field_err(
            key,
            format!("unknown key (expected {})", BOX_KEYS.join(", ")),
        ));
    }
    let label = match obj.get("label") {
        None => return Err(field_err("label", "missing")),
        Some(Value::String(s)) if s.trim().is_empty() => return Err(field_err("label", "must not be empty")),
        Some(Value::String(s)) if s.len() > MAX_LABEL_BYTES => {
            return Err(field_err(
                "label",
                format!("{} bytes is longer than {MAX_LABEL_BYTES}", s.len()),
            ))
        }
        Some(Value::String(s)) if s.chars().any(char::is_control) => {
            return Err(field_err("label", "must not contain control characters"))
        }
        Some(Value::String(s)) => s.clone(),
        Some(other) => return Err(field_err("label", format!("expected a string, found {}", kind(other)))),
    };
    let center = Point3::from(numbers::<3>(obj, "center")?);
    let size = Vector3::from(numbers::<3>(obj, "size")?);
    if let Some(axis) = (0..3).find(|&a| size[a] < 0.0) {
        return Err(field_err(
            "size",
            format!(
                "edge {} is {}; sizes must not be negative",
                ["x", "y", "z"][axis],
                size[axis]
            ),
        ));
    }
    // Volume and corners must be finite numbers (a size of 1e307 overflows both).
    let corner = center.coords.abs() + size * 0.5;
    if !(size.x * size.y * size.z).is_finite() || !corner.iter().all(|x| x.is_finite()) {
        return Err(field_err(
            "size",
            format!(
                "{:?} with centre {:?} is too large: its volume or corners are not finite numbers",
                <[f64; 3]>::from(size),
                <[f64; 3]>::from(center.coords)
            ),
        ));
    }
    let rotation = match (obj.get("rotation"), obj.get("quaternion")) {
        (Some(_), Some(_)) => {
            return Err(field_err(
                "quaternion",
                "give either `rotation` or `quaternion`, not both",
            ))
        }
        (Some(r), None) => rotation_matrix(r)?,
        (None, Some(q)) => rotation_quaternion(q)?,
        (None, None) => Rotation3::identity(),
    };
    Ok(Box3 {
        label,
        instance_id: id as u32,
        center,
        size,
        rotation,
    })
}

/// A finite number.
fn number(v: &Value, field: &str, at: &str) -> Result<f64, FieldError> {
    match v.as_f64() {
        Some(x) if x.is_finite() => Ok(x),
        Some(x) => Err(field_err(field, format!("{at} is {x}; expected a finite number"))),
        None => Err(field_err(field, format!("{at} must be a number, found {}", kind(v)))),
    }
}

/// An array of exactly N finite numbers.
fn number_array<const N: usize>(v: &Value, field: &str) -> Result<[f64; N], FieldError> {
    let list = v
        .as_array()
        .ok_or_else(|| field_err(field, format!("expected an array of {N} numbers, found {}", kind(v))))?;
    if list.len() != N {
        return Err(field_err(field, format!("expected {N} numbers, found {}", list.len())));
    }
    let mut out = [0.0; N];
    for (i, (x, item)) in out.iter_mut().zip(list).enumerate() {
        *x = number(item, field, &format!("element {i}"))?;
    }
    Ok(out)
}

/// Required key holding N finite numbers.
fn numbers<const N: usize>(obj: &Map<String, Value>, field: &str) -> Result<[f64; N], FieldError> {
    let v = obj.get(field).ok_or_else(|| field_err(field, "missing"))?;
    number_array::<N>(v, field)
}

/// Row-major 3x3 rotation, checked orthonormal with determinant +1, then
/// re-orthonormalised so containment tests are exact.
fn rotation_matrix(v: &Value) -> Result<Rotation3<f64>, FieldError> {
    let rows = v
        .as_array()
        .ok_or_else(|| field_err("rotation", format!("expected 3 rows of 3 numbers, found {}", kind(v))))?;
    if rows.len() != 3 {
        return Err(field_err("rotation", format!("expected 3 rows, found {}", rows.len())));
    }
    let mut m = [[0.0; 3]; 3];
    for (r, row) in rows.iter().enumerate() {
        let values = row.as_array().ok_or_else(|| {
            field_err(
                "rotation",
                format!("row {r} must be an array of 3 numbers, found {}", kind(row)),
            )
        })?;
        if values.len() != 3 {
            return Err(field_err(
                "rotation",
                format!("row {r} has {} numbers, expected 3", values.len()),
            ));
        }
        for (c, x) in values.iter().enumerate() {
            m[r][c] = number(x, "rotation", &format!("row {r} column {c}"))?;
        }
    }
    let mat = Matrix3::from_fn(|r, c| m[r][c]);
    let gram = mat.transpose() * mat;
    let off = (gram - Matrix3::identity()).iter().fold(0.0f64, |a, x| a.max(x.abs()));
    if off > ROTATION_TOLERANCE {
        return Err(field_err(
            "rotation",
            format!("not orthonormal (R^T R differs from identity by {off:.2e}, tolerance {ROTATION_TOLERANCE})"),
        ));
    }
    let det = mat.determinant();
    if (det - 1.0).abs() > ROTATION_TOLERANCE {
        return Err(field_err(
            "rotation",
            format!("determinant is {det:.4}, expected +1 (a reflection is not a rotation)"),
        ));
    }
    Ok(orthonormalised(&mat))
}

/// The rotation a nearly orthonormal matrix (checked by the caller) stands
/// for, made exactly orthonormal through a unit quaternion (closed form:
/// nalgebra's iterative `Rotation3::from_matrix` can give the identity for
/// a half turn, or never return).
pub(crate) fn orthonormalised(m: &Matrix3<f64>) -> Rotation3<f64> {
    let q = UnitQuaternion::from_rotation_matrix(&Rotation3::from_matrix_unchecked(*m));
    UnitQuaternion::new_normalize(q.into_inner()).to_rotation_matrix()
}

/// `[x, y, z, w]` quaternion, normalised; zero length is an error.
fn rotation_quaternion(v: &Value) -> Result<Rotation3<f64>, FieldError> {
    let [x, y, z, w] = number_array::<4>(v, "quaternion")?;
    let q = Quaternion::new(w, x, y, z);
    let len = q.norm();
    if !(len > 1e-9 && len.is_finite()) {
        return Err(field_err(
            "quaternion",
            format!("length is {len}; a rotation quaternion must not be zero"),
        ));
    }
    Ok(UnitQuaternion::from_quaternion(q).to_rotation_matrix())
}

#[cfg(test)]
mod tests {
    use super::*;

    fn parse(text: &str) -> Result<BoxSet, BoxError> {
        parse_boxes(text, Path::new("boxes.json"))
    }

    #[test]
    fn valid_file_with_rotation_quaternion_and_identity() {
        let c = std::f64::consts::FRAC_1_SQRT_2;
        let text = format!(
            r#"{{"boxes": [
                {{"label": "mug", "center": [0.41, -0.12, 0.05], "size": [0.10, 0.12, 0.11],
                  "rotation": [[{c}, -{c}, 0], [{c}, {c}, 0], [0, 0, 1]]}},
                {{"label": "book", "center": [1, 2, 3], "size": [0.2, 0.3, 0.05], "quaternion": [0, 0, 0.3826834323650898, 0.9238795325112867]}},
                {{"label": "mug", "center": [0, 0, 0], "size": [1, 2, 3]}}
            ]}}"#
        );
        let set = parse(&text).unwrap();
        assert_eq!(set.boxes.len(), 3);
        assert_eq!(set.categories, vec!["mug".to_string(), "book".to_string()]);
        assert_eq!(
            (set.category_id("mug"), set.category_id("book"), set.category_id("cup")),
            (Some(1), Some(2), None)
        );
        assert_eq!(
            set.boxes.iter().map(|b| b.instance_id).collect::<Vec<_>>(),
            vec![1, 2, 3]
        );
        let yaw45 = Rotation3::from_axis_angle(&Vector3::z_axis(), std::f64::consts::FRAC_PI_4);
        assert!((set.boxes[0].rotation.matrix() - yaw45.matrix()).amax() < 1e-12);
        assert!((set.boxes[1].rotation.matrix() - yaw45.matrix()).amax() < 1e-9);
        assert_eq!(set.boxes[2].rotation, Rotation3::identity());
        let b = &set.boxes[0];
        assert!((b.volume() - 0.10 * 0.12 * 0.11).abs() < 1e-15);
        // The box's x axis is world (1, 1, 0)/sqrt 2.
        // Along world (1, -1) the box is 0.12 wide, along (1, 1) only 0.10.
        assert!(b.contains(&(b.center + Vector3::new(0.04, -0.04, 0.0))));
        assert!(!b.contains(&(b.center + Vector3::new(0.04, 0.04, 0.0))));
        assert!(b.contains(&(b.center + Vector3::new(0.03, 0.03, 0.054))));
        assert!(!b.contains(&(b.center + Vector3::new(0.03, 0.03, 0.056))));
        let m = b.object_to_world();
        let x_axis = b.rotation.matrix().column(0).into_owned();
        assert!((m * Point3::new(1.0, 0.0, 0.0) - (b.center + x_axis)).norm() < 1e-12);
        for corner in b.corners() {
            let local = b.to_local(&corner).abs();
            assert!((local - b.size * 0.5).norm() < 1e-12);
        }
        assert!(set.warnings().is_empty());
        assert_eq!(set.by_instance(2).map(|b| b.label.as_str()), Some("book"));
        assert!(set.by_instance(0).is_none() && set.by_instance(4).is_none());
    }

    #[test]
    fn zero_volume_box_is_accepted_with_a_warning() {
        let set = parse(r#"{"boxes": [{"label": "sheet", "center": [0, 0, 0], "size": [1, 1, 0]}]}"#).unwrap();
        let w = set.warnings();
        assert_eq!(w.len(), 1);
        assert!(w[0].contains("box 1") && w[0].contains("zero volume"), "{}", w[0]);
    }

    /// Every invalid box: (entry JSON, field named, words in the message).
    #[test]
    fn every_invalid_box_names_its_index_and_field() {
        let good = r#"{"label": "a", "center": [0, 0, 0], "size": [1, 1, 1]}"#;
        let cases: &[(&str, &str, &str)] = &[
            (r#"[1, 2]"#, "", "expected an object"),
            (r#"{"center": [0, 0, 0], "size": [1, 1, 1]}"#, "label", "missing"),
            (
                r#"{"label": "", "center": [0, 0, 0], "size": [1, 1, 1]}"#,
                "label",
                "empty",
            ),
            (
                r#"{"label": "  ", "center": [0, 0, 0], "size": [1, 1, 1]}"#,
                "label",
                "empty",
            ),
            (
                r#"{"label": 3, "center": [0, 0, 0], "size": [1, 1, 1]}"#,
                "label",
                "expected a string",
            ),
            (
                r#"{"label": "a\u0007", "center": [0, 0, 0], "size": [1, 1, 1]}"#,
                "label",
                "control",
            ),
            (r#"{"label": "a", "size": [1, 1, 1]}"#, "center", "missing"),
            (
                r#"{"label": "a", "center": [0, 0], "size": [1, 1, 1]}"#,
                "center",
                "expected 3 numbers",
            ),
            (
                r#"{"label": "a", "center": "here", "size": [1, 1, 1]}"#,
                "center",
                "expected an array",
            ),
            (
                r#"{"label": "a", "center": [0, "x", 0], "size": [1, 1, 1]}"#,
                "center",
                "element 1 must be a number",
            ),
            (r#"{"label": "a", "center": [0, 0, 0]}"#, "size", "missing"),
            (
                r#"{"label": "a", "center": [0, 0, 0], "size": [1, -1, 1]}"#,
                "size",
                "edge y is -1",
            ),
            (
                r#"{"label": "a", "center": [0, 0, 0], "size": [1e307, 1e307, 1]}"#,
                "size",
                "too large",
            ),
            (
                r#"{"label": "a", "center": [1.7e308, 0, 0], "size": [1e308, 1, 1]}"#,
                "size",
                "too large",
            ),
            (
                r#"{"label": "a", "center": [0, 0, 0], "size": [1, 1, null]}"#,
                "size",
                "element 2 must be a number",
            ),
            (
                r#"{"label": "a", "center": [0, 0, 0], "size": [1, 1, 1, 1]}"#,
                "size",
                "expected 3 numbers, found 4",
            ),
            (
                r#"{"label": "a", "center": [0, 0, 0], "size": [1, 1, 1], "colour": "red"}"#,
                "colour",
                "unknown key",
            ),
            (
                r#"{"label": "a", "center": [0, 0, 0], "size": [1, 1, 1], "rotation": [[1, 0, 0], [0, 1, 0]]}"#,
                "rotation",
                "expected 3 rows",
            ),
            (
                r#"{"label": "a", "center": [0, 0, 0], "size": [1, 1, 1], "rotation": [[1, 0, 0], [0, 1], [0, 0, 1]]}"#,
                "rotation",
                "row 1 has 2",
            ),
            (
                r#"{"label": "a", "center": [0, 0, 0], "size": [1, 1, 1], "rotation": [[1, 0, 0], 5, [0, 0, 1]]}"#,
                "rotation",
                "row 1 must be an array",
            ),
            (
                r#"{"label": "a", "center": [0, 0, 0], "size": [1, 1, 1], "rotation": [[1, 0, 0], [0, 1, 0], [0, 0, "z"]]}"#,
                "rotation",
                "row 2 column 2",
            ),
            (
                r#"{"label": "a", "center": [0, 0, 0], "size": [1, 1, 1], "rotation": [[1, 0, 0], [0, 1, 0], [0, 0, 2]]}"#,
                "rotation",
                "not orthonormal",
            ),
            (
                r#"{"label": "a", "center": [0, 0, 0], "size": [1, 1, 1], "rotation": [[1, 0.01, 0], [0, 1, 0], [0, 0, 1]]}"#,
                "rotation",
                "not orthonormal",
            ),
            (
                r#"{"label": "a", "center": [0, 0, 0], "size": [1, 1, 1], "rotation": [[1, 0, 0], [0, 1, 0], [0, 0, -1]]}"#,
                "rotation",
                "determinant",
            ),
            (
                r#"{"label": "a", "center": [0, 0, 0], "size": [1, 1, 1], "rotation": "I"}"#,
                "rotation",
                "expected 3 rows of 3 numbers",
            ),
            (
                r#"{"label": "a", "center": [0, 0, 0], "size": [1, 1, 1], "quaternion": [0, 0, 0, 0]}"#,
                "quaternion",
                "must not be zero",
            ),
            (
                r#"{"label": "a", "center": [0, 0, 0], "size": [1, 1, 1], "quaternion": [0, 0, 1]}"#,
                "quaternion",
                "expected 4 numbers",
            ),
            (
                r#"{"label": "a", "center": [0, 0, 0], "size": [1, 1, 1], "quaternion": [0, 0, 0, 1], "rotation": [[1, 0, 0], [0, 1, 0], [0, 0, 1]]}"#,
                "quaternion",
                "not both",
            ),
        ];
        for (entry, field, words) in cases {
            // The bad box is the third: the message must say box 3 (boxes[2]).
            let text = format!(r#"{{"boxes": [{good}, {good}, {entry}]}}"#);
            let err = parse(&text).expect_err(entry);
            let msg = err.to_string();
            match &err {
                BoxError::Box { index, field: f, .. } => {
                    assert_eq!((*index, f.as_str()), (3, *field), "{entry}: {msg}");
                }
                other => panic!("{entry}: expected a box error, got {other:?}"),
            }
            assert!(msg.starts_with("boxes.json: box 3 (boxes[2])"), "{msg}");
            assert!(msg.contains(&format!("`{field}`")), "{msg}");
            assert!(msg.contains(words), "{entry}: `{msg}` lacks `{words}`");
        }
    }

    #[test]
    fn file_level_errors() {
        let cases: &[(&str, &str)] = &[
            ("{", "not valid JSON"),
            // JSON cannot hold NaN or infinity; an overflowing number is a JSON error with its position.
            (
                r#"{"boxes": [{"label": "a", "center": [0, 1e999, 0], "size": [1, 1, 1]}]}"#,
                "number out of range",
            ),
            ("[]", "expected a JSON object"),
            (r#"{}"#, "missing the `boxes` array"),
            (r#"{"boxes": {}}"#, "must be an array"),
            (r#"{"boxes": []}"#, "empty"),
            (r#"{"boxes": [], "version": 1}"#, "unknown key `version`"),
        ];
        for (text, words) in cases {
            let msg = parse(text).expect_err(text).to_string();
            assert!(msg.starts_with("boxes.json: "), "{msg}");
            assert!(msg.contains(words), "{text}: `{msg}` lacks `{words}`");
        }
        let entry = r#"{"label": "a", "center": [0, 0, 0], "size": [1, 1, 1]}"#;
        let many = format!(r#"{{"boxes": [{}]}}"#, vec![entry; MAX_BOXES + 1].join(","));
        let msg = parse(&many).expect_err("too many").to_string();
        assert!(msg.contains("65536 boxes"), "{msg}");
        let missing = read_boxes(Path::new("/nonexistent/boxes.json"))
            .expect_err("missing file")
            .to_string();
        assert!(missing.starts_with("/nonexistent/boxes.json: cannot read"), "{missing}");
    }

    #[test]
    fn nearly_orthonormal_rotation_is_cleaned_up() {
        let text = r#"{"boxes": [{"label": "a", "center": [0, 0, 0], "size": [1, 1, 1], "rotation": [[1, 0.0004, 0], [-0.0004, 1, 0], [0, 0, 1.0002]]}]}"#;
        let r = parse(text).unwrap().boxes[0].rotation;
        let r = r.matrix();
        assert!((r.transpose() * r - Matrix3::identity()).amax() < 1e-12);
        assert!((r.determinant() - 1.0).abs() < 1e-12);
    }

    /// nalgebra's iterative `Rotation3::from_matrix` gives the identity for a half turn.
    #[test]
    fn a_half_turn_stays_a_half_turn() {
        let text = r#"{"boxes": [{"label": "a", "center": [0, 0, 0], "size": [1, 1, 1], "rotation": [[-1, 0, 0], [0, -1, 0], [0, 0, 1]]}]}"#;
        let r = parse(text).unwrap().boxes[0].rotation;
        let half_turn = Matrix3::from_diagonal(&Vector3::new(-1.0, -1.0, 1.0));
        assert!((r.matrix() - half_turn).amax() < 1e-15, "{r:?}");
    }

    #[test]
    fn byte_order_mark_is_accepted_and_dev_zero_is_capped() {
        // Regression: a BOM gave a bare "line 1 column 1".
        let set =
            parse("\u{feff}{\"boxes\": [{\"label\": \"a\", \"center\": [0, 0, 0], \"size\": [1, 1, 1]}]}").unwrap();
        assert_eq!(set.boxes.len(), 1);
        // Regression: /dev/zero (no length) was read past the size cap.
        if Path::new("/dev/zero").exists() {
            let err = read_boxes(Path::new("/dev/zero")).unwrap_err().to_string();
            assert!(
                err.starts_with("/dev/zero") && err.contains("larger than any boxes file"),
                "{err}"
            );
        }
    }
}
