//! The HTTP API's handlers as plain functions of the session and the
//! request body (no sockets: tests call them directly).
//!
//! - `GET /api/info`: scan, boxes file, preview depth source, up axis.
//! - `GET /api/boxes`: the boxes.json document (`{"boxes": []}` before the first save).
//! - `PUT /api/boxes`: a boxes.json document; 200 and the file replaced
//!   atomically, or 400 `{"error": ...}` naming the box and field (file untouched).
//! - `POST /api/fit`: `{"polygon": [[x, y, z], ...]}` (world points, taken
//!   along the up axis), `{"seed": [x, y, z]}` or `{"shrink": BOX}`, with an
//!   optional `"label"` -> `{"box": BOX, "points": N}`.
//! - `GET /api/frames`: stems, sizes and camera positions.
//! - `GET|POST /api/frames/{stem}/preview.png`: the frame with the labels the
//!   saved boxes (GET) or the posted boxes.json document (POST) produce.
//! - `GET /api/cloud.bin`: the page's point cloud ([`super::cloud_bin`]).

use super::fit_box::{FitError, Region, MAX_POLYGON_VERTICES};
use super::preview::render_preview;
use super::session::Session;
use crate::boxes::{parse_boxes, Box3, BoxError, BoxSet};
use nalgebra::{Point3, Rotation3, Vector3};
use serde_json::{json, Value};

/// Largest request body accepted, bytes (a boxes file's own cap).
pub const MAX_BODY_BYTES: u64 = crate::boxes::parse::MAX_FILE_BYTES;

/// A response: status, content type and body.
#[derive(Clone, Debug, PartialEq)]
pub struct Reply {
    pub status: u16,
    pub content_type: &'static str,
    pub body: Vec<u8>,
}

impl Reply {
    /// 200 with a JSON body.
    pub fn json(value: &Value) -> Reply {
        Reply::json_status(200, value)
    }

    fn json_status(status: u16, value: &Value) -> Reply {
        Reply {
            status,
            content_type: "application/json",
            body: value.to_string().into_bytes(),
        }
    }

    /// A JSON `{"error": message}` with `status`.
    pub fn error(status: u16, message: impl Into<String>) -> Reply {
        Reply::json_status(status, &json!({ "error": message.into() }))
    }

    /// The body parsed as JSON (tests).
    pub fn body_json(&self) -> Option<Value> {
        serde_json::from_slice(&self.body).ok()
    }
}

/// A box as a boxes.json entry (FORMATS.md section 2).
pub fn box_json(label: &str, center: &Point3<f64>, size: &Vector3<f64>, rotation: &Rotation3<f64>) -> Value {
    let m = rotation.matrix();
    let rows: [[f64; 3]; 3] = std::array::from_fn(|r| std::array::from_fn(|c| m[(r, c)]));
    json!({
        "label": label,
        "center": <[f64; 3]>::from(center.coords),
        "size": <[f64; 3]>::from(*size),
        "rotation": rows,
    })
}

/// A box set as a boxes.json document.
pub fn boxes_document(set: &BoxSet) -> Value {
    let boxes: Vec<Value> = (set.boxes.iter())
        .map(|b| box_json(&b.label, &b.center, &b.size, &b.rotation))
        .collect();
    json!({ "boxes": boxes })
}

/// `GET /api/info`.
pub fn info(session: &Session) -> Reply {
    Reply::json(&json!({
        "scan": session.scan_dir.display().to_string(),
        "boxes_file": session.boxes_path.display().to_string(),
        "source": session.source_name(),
        "up": <[f64; 3]>::from(session.fit.ground.up),
        "frames": session.scan.frames.len(),
        "surface_points": session.fit.len(),
        "model_surface_points": session.fit.unseen(),
    }))
}

/// `GET /api/boxes`.
pub fn get_boxes(session: &Session) -> Reply {
    match session.saved_boxes() {
        Ok(set) => Reply::json(&boxes_document(&set)),
        Err(e) => Reply::error(500, e.to_string()),
    }
}

/// A posted boxes.json document, validated as `label` would read the file;
/// an empty list is no boxes. The error names the box, its label and the field.
pub fn parse_document(session: &Session, body: &[u8]) -> Result<BoxSet, String> {
    let text = std::str::from_utf8(body).map_err(|_| "the request body is not UTF-8 text".to_string())?;
    let raw: Option<Value> = serde_json::from_str(text).ok();
    if let Some(list) = raw.as_ref().and_then(|v| v.get("boxes")).and_then(Value::as_array) {
        let only_boxes = raw.as_ref().and_then(Value::as_object).is_some_and(|o| o.len() == 1);
        if list.is_empty() && only_boxes {
            return Ok(BoxSet::from_boxes(Vec::new()));
        }
    }
    parse_boxes(text, &session.boxes_path).map_err(|e| match e {
        BoxError::Box {
            index, field, problem, ..
        } => {
            let label = (raw.as_ref()).and_then(|v| {
                v.get("boxes")?
                    .get(index.checked_sub(1)?)?
                    .get("label")?
                    .as_str()
                    .map(String::from)
            });
            let named = label.map(|l| format!(" (`{l}`)")).unwrap_or_default();
            format!("box {index}{named}, field `{field}`: {problem}")
        }
        other => other.to_string(),
    })
}

/// `PUT /api/boxes`: validate, then replace the file atomically.
pub fn put_boxes(session: &Session, body: &[u8]) -> Reply {
    let set = match parse_document(session, body) {
        Ok(set) => set,
        Err(message) => return Reply::error(400, message),
    };
    let document = boxes_document(&set);
    let text = match serde_json::to_string_pretty(&document) {
        Ok(t) => t + "\n",
        Err(e) => return Reply::error(500, e.to_string()),
    };
    let _guard = session.writing.lock().unwrap_or_else(|p| p.into_inner());
    match crate::atomic::write_file(&session.boxes_path, text.as_bytes()) {
        Ok(()) => Reply::json(&json!({ "saved": set.boxes.len(), "file": session.boxes_path.display().to_string() })),
        Err(e) => Reply::error(500, format!("{}: cannot write: {e}", session.boxes_path.display())),
    }
}

fn point(v: &Value, what: &str) -> Result<Point3<f64>, String> {
    let a = v
        .as_array()
        .filter(|a| a.len() == 3)
        .ok_or(format!("{what}: expected [x, y, z]"))?;
    let c: Vec<f64> = a.iter().filter_map(Value::as_f64).collect();
    match c[..] {
        [x, y, z] if c.iter().all(|x| x.is_finite()) => Ok(Point3::new(x, y, z)),
        _ => Err(format!("{what}: expected three finite numbers")),
    }
}

/// The region of a fit request.
fn region(request: &Value, session: &Session) -> Result<Region, String> {
    if let Some(poly) = request.get("polygon") {
        let list = poly
            .as_array()
            .ok_or("`polygon`: expected a list of [x, y, z] points")?;
        if list.len() > MAX_POLYGON_VERTICES {
            return Err(format!("`polygon`: more than {MAX_POLYGON_VERTICES} vertices"));
        }
        let pts = (list.iter().enumerate())
            .map(|(i, v)| point(v, &format!("`polygon[{i}]`")))
            .collect::<Result<Vec<_>, _>>()?;
        return Ok(Region::Polygon(pts));
    }
    if let Some(seed) = request.get("seed") {
        return Ok(Region::Seed(point(seed, "`seed`")?));
    }
    if let Some(b) = request.get("shrink") {
        let doc = json!({ "boxes": [b] });
        let set = parse_document(session, doc.to_string().as_bytes())?;
        let one: Option<Box3> = set.boxes.into_iter().next();
        return one.map(Region::Shrink).ok_or_else(|| "`shrink`: expected a box".into());
    }
    Err("expected `polygon`, `seed` or `shrink`".into())
}

/// `POST /api/fit`.
pub fn fit(session: &Session, body: &[u8]) -> Reply {
    let request: Value = match serde_json::from_slice(body) {
        Ok(v) => v,
        Err(e) => return Reply::error(400, format!("the fit request is not JSON: {e}")),
    };
    let region = match region(&request, session) {
        Ok(r) => r,
        Err(message) => return Reply::error(400, message),
    };
    let label = match (&region, request.get("label").and_then(Value::as_str)) {
        (_, Some(l)) if !l.trim().is_empty() => l.trim().to_string(),
        (Region::Shrink(b), _) => b.label.clone(),
        _ => "object".to_string(),
    };
    match session.fit.fit(&region) {
        Ok(b) => Reply::json(&json!({
            "box": box_json(&label, &b.center, &b.size, &b.rotation),
            "points": b.points,
            "support_height": b.support_height,
        })),
        Err(e @ (FitError::Empty | FitError::NoObject { .. })) => Reply::error(422, e.to_string()),
        Err(e) => Reply::error(400, e.to_string()),
    }
}

/// `GET /api/frames`.
pub fn frames(session: &Session) -> Reply {
    let frames: Vec<Value> = (session.scan.frames.iter())
        .map(|f| {
            let m = &f.camera_to_world;
            json!({
                "stem": f.name,
                "id": f.id,
                "width": f.rgb.width(),
                "height": f.rgb.height(),
                "position": <[f64; 3]>::from(m.translation.vector),
                "forward": <[f64; 3]>::from(m.rotation.matrix().column(2).into_owned()),
            })
        })
        .collect();
    Reply::json(&json!({ "frames": frames }))
}

/// `GET|POST /api/frames/{stem}/preview.png`: `body` holds the current
/// boxes (POST) or is `None` for the saved ones.
pub fn preview(session: &Session, stem: &str, body: Option<&[u8]>) -> Reply {
    let Some(frame) = session.scan.frames.iter().find(|f| f.name == stem) else {
        return Reply::error(404, format!("no frame `{stem}` in the scan"));
    };
    let set = match body {
        Some(body) => match parse_document(session, body) {
            Ok(set) => set,
            Err(message) => return Reply::error(400, message),
        },
        None => match session.saved_boxes() {
            Ok(set) => set,
            Err(e) => return Reply::error(500, e.to_string()),
        },
    };
    let image = match render_preview(frame, &set, session.model.as_ref(), &session.surface, &session.cameras) {
        Ok(img) => img,
        Err(e) => return Reply::error(500, format!("frame {stem}: {e}")),
    };
    match crate::png_encode::encode_rgb(image.as_raw(), image.width(), image.height()) {
        Ok(png) => Reply {
            status: 200,
            content_type: "image/png",
            body: png,
        },
        Err(e) => Reply::error(500, format!("frame {stem}: cannot encode the preview: {e}")),
    }
}

/// `GET /api/cloud.bin`.
pub fn cloud(session: &Session) -> Reply {
    Reply {
        status: 200,
        content_type: "application/octet-stream",
        body: session.cloud_bin.clone(),
    }
}
