//! The annotation server's HTTP API, called without sockets on generated
//! scenes: saving valid and invalid boxes, fitting a box from a top-view
//! gesture, and the masks such boxes give against the exact ones.

mod common;

use common::annotate::{call, gesture};

use nalgebra::{distance, Matrix3, Point3, Rotation3, Vector3};
use nerflabel::annotate::{route, Session};
use nerflabel::boxes::{read_boxes, BoxSet, DepthSource, LabelOptions};
use nerflabel::evaluate::{evaluate_labels, fixture_truth};
use nerflabel::fixture::{generate, FixtureOptions, SceneKind};
use nerflabel::scan::{load, LoadOptions};
use serde_json::{json, Value};
use std::path::Path;

/// A tabletop scan (every object with sensor depth, so each can be fitted) and its session.
fn tabletop(dir: &Path, frames: usize) -> Session {
    let mut o = FixtureOptions::new(SceneKind::Tabletop);
    (o.width, o.height, o.frames, o.holdout) = (240, 180, Some(frames), Some(0));
    o.corruptions.no_depth_objects = false;
    generate(dir, &o).unwrap();
    let scan = load(dir, &LoadOptions::default()).unwrap();
    Session::open(scan, dir.to_path_buf(), dir.join("annotated.json"), None).unwrap()
}

fn parse_box(v: &Value) -> (Point3<f64>, Vector3<f64>, Matrix3<f64>) {
    let vec3 = |k: &str| Vector3::from(serde_json::from_value::<[f64; 3]>(v[k].clone()).unwrap());
    let rows: [[f64; 3]; 3] = serde_json::from_value(v["rotation"].clone()).unwrap();
    (
        Point3::from(vec3("center")),
        vec3("size"),
        Matrix3::from_fn(|r, c| rows[r][c]),
    )
}

#[test]
fn put_saves_valid_boxes_and_refuses_an_invalid_one_naming_box_and_field() {
    let dir = tempfile::tempdir().unwrap();
    let session = tabletop(dir.path(), 12);
    let file = dir.path().join("annotated.json");
    assert_eq!(
        call(&session, "GET", "/api/boxes", &Value::Null),
        (200, json!({"boxes": []}))
    );

    let valid = json!({"boxes": [
        {"label": "mug", "center": [0.1, 0.2, 0.8], "size": [0.1, 0.1, 0.12], "rotation": [[1,0,0],[0,1,0],[0,0,1]]},
        {"label": "book", "center": [-0.2, 0.0, 0.78], "size": [0.2, 0.15, 0.04]}
    ]});
    let (status, body) = call(&session, "PUT", "/api/boxes", &valid);
    assert_eq!(status, 200, "{body}");
    let saved = read_boxes(&file).unwrap();
    assert_eq!(saved.boxes.len(), 2);
    assert_eq!(saved.boxes[1].label, "book");
    assert_eq!(saved.boxes[1].rotation, Rotation3::identity());
    let (_, got) = call(&session, "GET", "/api/boxes", &Value::Null);
    assert_eq!(got["boxes"][0]["size"], json!([0.1, 0.1, 0.12]));
    let before = std::fs::read(&file).unwrap();

    let mut invalid = valid.clone();
    invalid["boxes"][1]["size"] = json!([0.2, -0.15, 0.04]);
    let (status, body) = call(&session, "PUT", "/api/boxes", &invalid);
    assert_eq!(status, 400);
    let message = body["error"].as_str().unwrap();
    assert!(
        message.contains("box 2") && message.contains("`book`") && message.contains("`size`"),
        "{message}"
    );
    assert_eq!(std::fs::read(&file).unwrap(), before, "the file is untouched");

    let (status, body) = call(
        &session,
        "PUT",
        "/api/boxes",
        &json!({"boxes": [{"label": "x", "centre": [0, 0, 0]}]}),
    );
    assert_eq!(status, 400);
    assert!(body["error"].as_str().unwrap().contains("box 1"), "{body}");
    let reply = route(&session, "PUT", "/api/boxes", b"{\"boxes\": [");
    assert_eq!(reply.status, 400);
    assert_eq!(std::fs::read(&file).unwrap(), before);
    let leftovers = std::fs::read_dir(dir.path()).unwrap().filter_map(Result::ok);
    assert!(leftovers
        .into_iter()
        .all(|e| !e.file_name().to_string_lossy().contains(".tmp")));

    // Everything deleted and saved: an empty list, read back as no boxes.
    assert_eq!(call(&session, "PUT", "/api/boxes", &json!({"boxes": []})).0, 200);
    assert_eq!(
        call(&session, "GET", "/api/boxes", &Value::Null).1,
        json!({"boxes": []})
    );
}

#[test]
fn frames_cloud_and_preview_answer() {
    let dir = tempfile::tempdir().unwrap();
    let session = tabletop(dir.path(), 12);
    let (status, frames) = call(&session, "GET", "/api/frames", &Value::Null);
    assert_eq!(status, 200);
    let list = frames["frames"].as_array().unwrap();
    assert_eq!(list.len(), 12);
    let stem = list[3]["stem"].as_str().unwrap().to_string();

    let cloud = route(&session, "GET", "/api/cloud.bin", b"");
    assert_eq!(&cloud.body[..8], b"NLCLOUD1");
    let n = u32::from_le_bytes(cloud.body[8..12].try_into().unwrap()) as usize;
    assert!(n > 10_000, "{n} points");
    assert_eq!(cloud.body.len(), 32 + 15 * n);

    let truth = read_boxes(&dir.path().join("gt/boxes_tight.json")).unwrap();
    let doc = nerflabel::annotate::api::boxes_document(&truth);
    let plain = route(
        &session,
        "POST",
        &format!("/api/frames/{stem}/preview.png"),
        b"{\"boxes\": []}",
    );
    let labelled = route(
        &session,
        "POST",
        &format!("/api/frames/{stem}/preview.png"),
        doc.to_string().as_bytes(),
    );
    assert_eq!((plain.status, labelled.status), (200, 200));
    let plain = image::load_from_memory(&plain.body).unwrap().to_rgb8();
    let labelled = image::load_from_memory(&labelled.body).unwrap().to_rgb8();
    assert_eq!(plain.dimensions(), (240, 180));
    let changed = plain.pixels().zip(labelled.pixels()).filter(|(a, b)| a != b).count();
    let share = changed as f64 / (240.0 * 180.0);
    assert!(share > 0.02 && share < 0.6, "the boxes tint {share:.3} of the frame");
    assert_eq!(route(&session, "GET", "/api/frames/nope/preview.png", b"").status, 404);
    assert_eq!(route(&session, "GET", "/api/nothing", b"").status, 404);
    assert!(route(&session, "GET", "/", b"").body.starts_with(b"<!DOCTYPE html>"));
}

#[test]
fn fit_from_a_top_view_rectangle_recovers_the_true_box() {
    let dir = tempfile::tempdir().unwrap();
    let session = tabletop(dir.path(), 30);
    let truth = read_boxes(&dir.path().join("gt/boxes_tight.json")).unwrap();
    let cuboid = truth.boxes.iter().find(|b| b.label == "box").unwrap();
    let (status, body) = call(&session, "POST", "/api/fit", &gesture(cuboid, 0.06));
    assert_eq!(status, 200, "{body}");
    let (center, size, rotation) = parse_box(&body["box"]);
    assert_eq!(body["box"]["label"], "box");
    let centre_err = distance(&center, &cuboid.center);
    // Box axes are defined up to a half turn (and x is the longer edge): compare the long axes.
    let (long_fit, long_true) = (
        rotation.column(0),
        cuboid
            .rotation
            .matrix()
            .column(if cuboid.size.x >= cuboid.size.y { 0 } else { 1 }),
    );
    let angle = long_fit.dot(&long_true).abs().min(1.0).acos().to_degrees();
    let mut true_size = cuboid.size;
    if true_size.y > true_size.x {
        true_size = Vector3::new(true_size.y, true_size.x, true_size.z);
    }
    let size_err = (size - true_size).abs().max();
    eprintln!(
        "fit: centre {:.1} mm, size {:.1} mm, yaw {angle:.2}°",
        centre_err * 1e3,
        size_err * 1e3
    );
    assert!(centre_err < 0.01, "centre off by {centre_err} m");
    assert!(size_err < 0.01, "size {size} vs {true_size}");
    assert!(angle < 3.0, "yaw off by {angle}°");

    // A seed click on the top face finds the same object.
    let top = cuboid.center + Vector3::z() * cuboid.size.z * 0.5;
    let (status, body) = call(&session, "POST", "/api/fit", &json!({"seed": [top.x, top.y, top.z]}));
    assert_eq!(status, 200, "{body}");
    assert!(distance(&parse_box(&body["box"]).0, &cuboid.center) < 0.02);

    // A region of bare table holds no object.
    let far = json!({"polygon": [[5.0, 5.0, 0.0], [5.1, 5.0, 0.0], [5.1, 5.1, 0.0]]});
    let (status, body) = call(&session, "POST", "/api/fit", &far);
    assert_eq!(status, 422, "{body}");
    assert_eq!(call(&session, "POST", "/api/fit", &json!({"polygon": 3})).0, 400);
}

/// Done-criterion of issue 17: boxes made by one gesture each (a top-view
/// rectangle 5 cm around every object) label the objects at >= 0.95 of the
/// mIoU of the true boxes.
#[test]
fn one_gesture_boxes_label_nearly_as_well_as_the_true_boxes() {
    let dir = tempfile::tempdir().unwrap();
    let session = tabletop(dir.path(), 30);
    let truth = read_boxes(&dir.path().join("gt/boxes_tight.json")).unwrap();
    let fitted: Vec<Value> = (truth.boxes.iter())
        .map(|b| {
            let (status, body) = call(&session, "POST", "/api/fit", &gesture(b, 0.05));
            assert_eq!(status, 200, "{}: {body}", b.label);
            body["box"].clone()
        })
        .collect();
    let (status, body) = call(&session, "PUT", "/api/boxes", &json!({ "boxes": fitted }));
    assert_eq!(status, 200, "{body}");
    let made: BoxSet = read_boxes(&dir.path().join("annotated.json")).unwrap();
    let scan = &session.scan;
    let gt = fixture_truth(dir.path(), scan, 3).unwrap();
    let options = LabelOptions {
        source: DepthSource::Sensor,
        ..LabelOptions::default()
    };
    let miou = |set: &BoxSet| {
        evaluate_labels(scan, set, None, &gt, options)
            .unwrap()
            .scores
            .mean_object_iou()
    };
    let (fitted, true_boxes) = (miou(&made), miou(&truth));
    let drawn = miou(&read_boxes(&dir.path().join("boxes.json")).unwrap());
    eprintln!(
        "mIoU: one-gesture boxes {fitted:.4}, true (tight) boxes {true_boxes:.4}, the fixture's drawn boxes {drawn:.4}; ratio {:.4}",
        fitted / true_boxes
    );
    // The tight boxes cut off the noisy rim of each object's sensor depth;
    // the fixture's drawn boxes (snug, with a margin) are the harder bar.
    let bar = true_boxes.max(drawn);
    assert!(fitted >= 0.95 * bar, "{fitted} < 0.95 x {bar}");
}

/// The real cabinet scan (TUM fr3/cabinet, Kinect depth; `../shared/data`,
/// skipped when absent): a rectangle 10 cm around the measured box fits a
/// box on it (measured: centre 1.4 cm, yaw 0.9°, edges 2.8-4.3 cm longer
/// than the tight reference, from the Kinect's centimetre noise).
#[test]
fn a_real_cabinet_is_fitted_from_a_rectangle_around_it() {
    let data = std::env::var_os("NERFLABEL_SHARED_DATA")
        .map(std::path::PathBuf::from)
        .unwrap_or_else(|| Path::new(env!("CARGO_MANIFEST_DIR")).join("../shared/data"));
    let root = data.join("scans/cabinet");
    if !root.join("reference_box.json").exists() {
        eprintln!("skipping: {} is absent", root.display());
        return;
    }
    let scan = load(&root, &LoadOptions::default()).unwrap();
    let dir = tempfile::tempdir().unwrap();
    let session = Session::open(scan, root.clone(), dir.path().join("boxes.json"), None).unwrap();
    assert!(
        (session.fit.ground.up - Vector3::z()).norm() < 1e-9,
        "the floor sets up: {}",
        session.fit.ground.up
    );
    let reference = read_boxes(&root.join("reference_box.json")).unwrap();
    let cabinet = &reference.boxes[0];
    let (status, body) = call(&session, "POST", "/api/fit", &gesture(cabinet, 0.1));
    assert_eq!(status, 200, "{body}");
    let (center, size, rotation) = parse_box(&body["box"]);
    let angle = rotation
        .column(0)
        .dot(&cabinet.rotation.matrix().column(0))
        .abs()
        .min(1.0)
        .acos()
        .to_degrees();
    let grown = size - cabinet.size;
    eprintln!(
        "cabinet: centre {:.1} cm, yaw {angle:.2}°, edges {:.1} {:.1} {:.1} cm longer",
        distance(&center, &cabinet.center) * 100.0,
        grown.x * 100.0,
        grown.y * 100.0,
        grown.z * 100.0
    );
    assert!(distance(&center, &cabinet.center) < 0.025);
    assert!(angle < 2.0, "yaw off by {angle}°");
    assert!(
        grown.min() > -0.01 && grown.max() < 0.06,
        "size {size} vs {}",
        cabinet.size
    );
}

/// With a model, the live check renders depth from it (a model of a few
/// steps: this checks the path, not the masks' quality).
#[test]
fn previews_render_from_the_model_when_there_is_one() {
    use nerflabel::nerf::train::fit::{fit, FitOptions};
    use nerflabel::nerf::train::settings::{FitSettings, Preset};
    let dir = tempfile::tempdir().unwrap();
    let mut o = FixtureOptions::new(SceneKind::Small);
    (o.width, o.height, o.frames, o.holdout) = (96, 72, Some(8), Some(0));
    generate(dir.path(), &o).unwrap();
    let mut scan = load(dir.path(), &LoadOptions::default()).unwrap();
    let options = FitOptions {
        settings: FitSettings {
            holdout_every: 0,
            preset: Preset::Fast,
            ..FitSettings::default()
        },
        steps: Some(20),
        time: None,
        ..FitOptions::default()
    };
    let stop = std::sync::atomic::AtomicBool::new(false);
    let model = fit(&mut scan, &options, &stop, &mut |_| {}).unwrap().model;
    let session = Session::open(
        scan,
        dir.path().to_path_buf(),
        dir.path().join("boxes.json"),
        Some(model),
    )
    .unwrap();
    assert_eq!(call(&session, "GET", "/api/info", &Value::Null).1["source"], "nerf");
    let stem = session.scan.frames[2].name.clone();
    let doc = std::fs::read(dir.path().join("boxes.json")).unwrap();
    let reply = route(&session, "POST", &format!("/api/frames/{stem}/preview.png"), &doc);
    assert_eq!(reply.status, 200, "{:?}", reply.body_json());
    let img = image::load_from_memory(&reply.body).unwrap();
    assert_eq!((img.width(), img.height()), (96, 72));
    let saved = route(&session, "GET", &format!("/api/frames/{stem}/preview.png"), b"");
    assert_eq!(saved.status, 200, "GET previews the saved boxes.json");
}

/// An existing boxes file that `label` would refuse stops `annotate` before
/// it serves, with the message naming the file, the box and the field.
#[test]
fn annotate_refuses_an_invalid_boxes_file_before_serving() {
    let dir = tempfile::tempdir().unwrap();
    let scan = common::small_scan(dir.path());
    let bad = dir.path().join("bad.json");
    std::fs::write(
        &bad,
        r#"{"boxes": [{"label": "cup", "center": [0, 0, 0], "size": [0.1, "x", 0.1]}]}"#,
    )
    .unwrap();
    let out = common::run(&["annotate", common::s(&scan), "--boxes", common::s(&bad)]);
    assert!(!out.status.success());
    let err = common::stderr(&out);
    assert!(
        err.contains("bad.json") && err.contains("box 1") && err.contains("`size`"),
        "{err}"
    );
    assert!(out.stdout.is_empty(), "no URL is printed");
}
