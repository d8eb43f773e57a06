//! The `--poses FILE.json` input (FORMATS.md section 4): views to render
//! instead of sampled ones, checked like every outside input.

use super::error::PosesFileError;
use crate::scan::{check_intrinsics, check_pose, Intrinsics, MAX_FRAMES, MAX_IMAGE_SIDE};
use nalgebra::{IsometryMatrix3, Matrix4};
use serde_json::Value;
use std::path::{Path, PathBuf};

/// Largest accepted poses file (about 200 bytes per view).
pub const MAX_POSES_FILE_BYTES: u64 = 64 << 20;
/// Most views in one poses file.
pub const MAX_VIEWS: usize = MAX_FRAMES;
/// Most pixels of one view (8192 x 8192).
pub const MAX_VIEW_PIXELS: u64 = 1 << 26;

/// One view to render: pose, pinhole intrinsics and image size.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ViewSpec {
    /// Camera-to-world pose, OpenCV axes, scan world frame (metres).
    pub camera_to_world: IsometryMatrix3<f64>,
    pub intrinsics: Intrinsics,
    pub width: u32,
    pub height: u32,
}

/// Read and check a poses file.
pub fn read_poses(path: &Path) -> Result<Vec<ViewSpec>, PosesFileError> {
    let io = |source| PosesFileError::Io {
        path: path.to_path_buf(),
        source,
    };
    let len = std::fs::metadata(path).map_err(io)?.len();
    if len > MAX_POSES_FILE_BYTES {
        return Err(PosesFileError::File {
            path: path.to_path_buf(),
            problem: format!("{len} bytes is larger than the {MAX_POSES_FILE_BYTES} accepted for a poses file"),
        });
    }
    let text = std::fs::read_to_string(path).map_err(io)?;
    parse_poses(&text, path)
}

/// Parse and check the text of a poses file; `path` names it in errors.
pub fn parse_poses(text: &str, path: &Path) -> Result<Vec<ViewSpec>, PosesFileError> {
    let file_err = |problem: String| PosesFileError::File {
        path: path.to_path_buf(),
        problem,
    };
    let root: Value = serde_json::from_str(text).map_err(|e| file_err(format!("not valid JSON: {e}")))?;
    let views = root
        .get("views")
        .ok_or_else(|| file_err("expected an object with a `views` list".into()))?
        .as_array()
        .ok_or_else(|| file_err("`views` must be a list".into()))?;
    if views.is_empty() {
        return Err(file_err("`views` is empty".into()));
    }
    if views.len() > MAX_VIEWS {
        return Err(file_err(format!(
            "{} views, at most {MAX_VIEWS} are accepted",
            views.len()
        )));
    }
    views
        .iter()
        .enumerate()
        .map(|(i, v)| parse_view(v, ViewCtx { path, view: i }))
        .collect()
}

/// Where a value sits, for error messages.
#[derive(Clone, Copy)]
struct ViewCtx<'a> {
    path: &'a Path,
    view: usize,
}

impl ViewCtx<'_> {
    fn err(&self, field: &'static str, problem: impl Into<String>) -> PosesFileError {
        PosesFileError::View {
            path: PathBuf::from(self.path),
            view: self.view,
            field,
            problem: problem.into(),
        }
    }

    fn field<'v>(&self, v: &'v Value, field: &'static str) -> Result<&'v Value, PosesFileError> {
        v.get(field).ok_or_else(|| self.err(field, "missing"))
    }

    /// A list of exactly `n` finite numbers.
    fn numbers(&self, v: &Value, field: &'static str, n: usize, what: &str) -> Result<Vec<f64>, PosesFileError> {
        let list = v
            .as_array()
            .ok_or_else(|| self.err(field, format!("expected a list of {n} numbers {what}")))?;
        if list.len() != n {
            return Err(self.err(field, format!("expected {n} numbers {what}, found {}", list.len())));
        }
        list.iter()
            .enumerate()
            .map(|(j, x)| match x.as_f64() {
                Some(f) if f.is_finite() => Ok(f),
                _ => Err(self.err(field, format!("entry {j} is {x}, expected a finite number"))),
            })
            .collect()
    }

    /// A positive integer image side up to the cap.
    fn side(&self, v: &Value, field: &'static str) -> Result<u32, PosesFileError> {
        let raw = self.field(v, field)?;
        match raw.as_u64() {
            Some(n) if (1..=u64::from(MAX_IMAGE_SIDE)).contains(&n) => Ok(n as u32),
            _ => Err(self.err(field, format!("{raw} is not an integer in 1..={MAX_IMAGE_SIDE}"))),
        }
    }
}

/// One entry of `views`.
fn parse_view(v: &Value, ctx: ViewCtx) -> Result<ViewSpec, PosesFileError> {
    if !v.is_object() {
        return Err(ctx.err("views", format!("expected an object, found {v}")));
    }
    let width = ctx.side(v, "width")?;
    let height = ctx.side(v, "height")?;
    if u64::from(width) * u64::from(height) > MAX_VIEW_PIXELS {
        return Err(ctx.err(
            "width",
            format!("{width}x{height} has more than {MAX_VIEW_PIXELS} pixels"),
        ));
    }

    let field = "camera_to_world";
    let rows = ctx
        .field(v, field)?
        .as_array()
        .ok_or_else(|| ctx.err(field, "expected a list of 4 rows of 4 numbers"))?;
    if rows.len() != 4 {
        return Err(ctx.err(field, format!("expected 4 rows, found {}", rows.len())));
    }
    let mut m = [[0.0f64; 4]; 4];
    for (r, row) in rows.iter().enumerate() {
        let values = ctx.numbers(row, field, 4, &format!("in row {r}"))?;
        m[r].copy_from_slice(&values);
    }
    let matrix = Matrix4::from_fn(|r, c| m[r][c]);
    if let Some(problem) = check_pose(&matrix).problem() {
        return Err(ctx.err(field, problem));
    }
    let camera_to_world = crate::scan::isometry(&matrix);

    let field = "intrinsics";
    let k = ctx.numbers(ctx.field(v, field)?, field, 4, "[fx, fy, cx, cy]")?;
    let intrinsics = Intrinsics {
        fx: k[0],
        fy: k[1],
        cx: k[2],
        cy: k[3],
    };
    check_intrinsics(&intrinsics, width, height).map_err(|problem| ctx.err(field, problem))?;
    Ok(ViewSpec {
        camera_to_world,
        intrinsics,
        width,
        height,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::{Rotation3, Vector3};
    use serde_json::json;

    fn good_view() -> Value {
        json!({
            "camera_to_world": [[0.0, -1.0, 0.0, 0.5], [1.0, 0.0, 0.0, -0.25], [0.0, 0.0, 1.0, 1.5], [0, 0, 0, 1]],
            "intrinsics": [500.0, 510.0, 320.0, 240.0],
            "width": 640,
            "height": 480
        })
    }

    fn parse(views: Vec<Value>) -> Result<Vec<ViewSpec>, PosesFileError> {
        parse_poses(&json!({ "views": views }).to_string(), Path::new("poses.json"))
    }

    #[test]
    fn good_file_parses_rows_as_rows() {
        let views = parse(vec![good_view(), good_view()]).unwrap();
        assert_eq!(views.len(), 2);
        let v = views[0];
        assert_eq!((v.width, v.height), (640, 480));
        assert_eq!(
            v.intrinsics,
            Intrinsics {
                fx: 500.0,
                fy: 510.0,
                cx: 320.0,
                cy: 240.0
            }
        );
        assert_eq!(v.camera_to_world.translation.vector, Vector3::new(0.5, -0.25, 1.5));
        // Row 0 is (0, -1, 0): the camera's y axis maps to world -x.
        assert_eq!(v.camera_to_world * Vector3::y(), Vector3::new(-1.0, 0.0, 0.0));
        assert!((v.camera_to_world.rotation.matrix().determinant() - 1.0).abs() < 1e-12);
    }

    /// Replace `field` of the good view by `value`; `None` removes it.
    fn with(field: &str, value: Option<Value>) -> Value {
        let mut v = good_view();
        let obj = v.as_object_mut().unwrap();
        match value {
            Some(x) => obj.insert(field.into(), x),
            None => obj.remove(field),
        };
        v
    }

    #[test]
    fn every_invalid_view_names_file_view_and_field() {
        let rot = |angle: f64| {
            let m = Rotation3::from_axis_angle(&Vector3::z_axis(), angle);
            let r = |i: usize| [m[(i, 0)], m[(i, 1)], m[(i, 2)], 0.0];
            json!([r(0), r(1), r(2), [0, 0, 0, 1]])
        };
        let cases: Vec<(&str, Option<Value>, &str)> = vec![
            ("width", None, "missing"),
            ("width", Some(json!(0)), "not an integer"),
            ("width", Some(json!(-4)), "not an integer"),
            ("width", Some(json!(64.5)), "not an integer"),
            ("width", Some(json!("640")), "not an integer"),
            ("height", Some(json!(100_000)), "not an integer"),
            ("camera_to_world", None, "missing"),
            ("camera_to_world", Some(json!("identity")), "4 rows"),
            (
                "camera_to_world",
                Some(json!([[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0]])),
                "expected 4 rows",
            ),
            (
                "camera_to_world",
                Some(json!([[1, 0, 0], [0, 1, 0], [0, 0, 1], [0, 0, 0]])),
                "expected 4 numbers in row 0",
            ),
            (
                "camera_to_world",
                Some(json!([[1, 0, 0, "x"], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]])),
                "entry 3",
            ),
            (
                "camera_to_world",
                Some(json!([[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 1, 1]])),
                "last row",
            ),
            (
                "camera_to_world",
                Some(json!([[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, -1, 0], [0, 0, 0, 1]])),
                "reflection",
            ),
            (
                "camera_to_world",
                Some(json!([[1.01, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]])),
                "orthonormal",
            ),
            (
                "camera_to_world",
                Some(json!([[2, 0, 0, 0], [0, 2, 0, 0], [0, 0, 2, 0], [0, 0, 0, 1]])),
                "orthonormal",
            ),
            ("intrinsics", None, "missing"),
            ("intrinsics", Some(json!([500, 500, 320])), "found 3"),
            ("intrinsics", Some(json!({"fx": 500})), "list of 4 numbers"),
            ("intrinsics", Some(json!([500, null, 320, 240])), "entry 1"),
            ("intrinsics", Some(json!([0, 500, 320, 240])), "positive"),
            ("intrinsics", Some(json!([-500, 500, 320, 240])), "positive"),
            ("intrinsics", Some(json!([500, 500, 5000, 240])), "principal point"),
        ];
        for (field, value, expect) in cases {
            let shown = format!("{value:?}");
            let err = parse(vec![good_view(), with(field, value)]).unwrap_err();
            let msg = err.to_string();
            assert!(
                matches!(&err, PosesFileError::View { view: 1, field: f, .. } if *f == field),
                "{field} = {shown}: {msg}"
            );
            assert!(msg.starts_with("poses.json: view 1: `"), "{msg}");
            assert!(msg.contains(expect), "{field} = {shown}: expected `{expect}` in: {msg}");
        }
        let mut huge = with("width", Some(json!(16_000)));
        huge["height"] = json!(16_000);
        let msg = parse(vec![huge]).unwrap_err().to_string();
        assert!(msg.contains("view 0: `width`: 16000x16000 has more than"), "{msg}");
        // Any proper rotation is accepted.
        assert!(parse(vec![with("camera_to_world", Some(rot(0.3)))]).is_ok());
    }

    #[test]
    fn invalid_files_are_errors_that_name_the_file() {
        let cases = [
            ("", "not valid JSON"),
            ("{\"views\": [", "not valid JSON"),
            ("[]", "`views` list"),
            ("{\"frames\": []}", "`views` list"),
            ("{\"views\": {}}", "must be a list"),
            ("{\"views\": []}", "empty"),
            ("{\"views\": [3]}", "expected an object"),
        ];
        for (text, expect) in cases {
            let msg = parse_poses(text, Path::new("dir/p.json")).unwrap_err().to_string();
            assert!(msg.starts_with("dir/p.json: "), "{msg}");
            assert!(msg.contains(expect), "{text}: expected `{expect}` in: {msg}");
        }
        let missing = read_poses(Path::new("/nonexistent/poses.json")).unwrap_err();
        assert!(matches!(missing, PosesFileError::Io { .. }), "{missing}");
    }

    #[test]
    fn too_many_views_are_refused_without_parsing_them() {
        let text = format!("{{\"views\": [{}]}}", vec!["0"; MAX_VIEWS + 1].join(","));
        let msg = parse_poses(&text, Path::new("p.json")).unwrap_err().to_string();
        assert!(msg.contains("at most"), "{msg}");
    }
}
