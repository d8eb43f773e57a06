//! Helpers of the `annotate` API tests: a request through the router, and
//! the top-view rectangle a user drags around an object.

use nalgebra::Vector3;
use nerflabel::annotate::{route, Session};
use nerflabel::boxes::Box3;
use serde_json::{json, Value};

/// Status and JSON body of one request answered by the router (no socket).
pub fn call(session: &Session, method: &str, url: &str, body: &Value) -> (u16, Value) {
    let reply = route(session, method, url, body.to_string().as_bytes());
    (reply.status, reply.body_json().unwrap_or(Value::Null))
}

/// A top-view rectangle around the box's footprint, `margin` metres wider on each side.
pub fn gesture(b: &Box3, margin: f64) -> Value {
    let h = b.size * 0.5 + Vector3::repeat(margin);
    let (x_axis, y_axis) = (b.rotation * Vector3::x(), b.rotation * Vector3::y());
    let corners: Vec<[f64; 3]> = [(-1.0, -1.0), (1.0, -1.0), (1.0, 1.0), (-1.0, 1.0)]
        .iter()
        .map(|&(sx, sy)| (b.center + x_axis * (sx * h.x) + y_axis * (sy * h.y)).coords.into())
        .collect();
    json!({ "polygon": corners, "label": b.label })
}
