//! `nerflabel boxes import|export` through the binary: a labelCloud file
//! and a KITTI label file describing the committed fixture's boxes import
//! to boxes that label the scan exactly as the fixture's own boxes.json
//! does; export -> import gives the same boxes; bad files fail with one
//! message naming file, entry and field, and write nothing.

mod common;

use common::{run, s, small_scan, stderr};
use nalgebra::{IsometryMatrix3, Matrix3, Rotation3, Translation3, Vector3};
use nerflabel::boxes::{read_boxes, Box3, BoxSet};
use std::path::Path;

fn ok(args: &[&str]) -> String {
    let o = run(args);
    assert!(o.status.success(), "{args:?}: {}", stderr(&o));
    String::from_utf8_lossy(&o.stdout).into_owned()
}

/// Label the scan with the sensor source and return every mask file's bytes.
fn masks(scan: &Path, boxes: &Path, out: &Path) -> Vec<(String, Vec<u8>)> {
    ok(&[
        "label",
        s(scan),
        "--boxes",
        s(boxes),
        "--source",
        "sensor",
        "--out",
        s(out),
    ]);
    let mut files: Vec<(String, Vec<u8>)> = std::fs::read_dir(out.join("masks"))
        .unwrap()
        .map(|e| {
            let e = e.unwrap();
            (
                e.file_name().to_string_lossy().into_owned(),
                std::fs::read(e.path()).unwrap(),
            )
        })
        .collect();
    files.sort();
    files
}

fn assert_same_boxes(a: &BoxSet, b: &BoxSet, tolerance: f64) {
    assert_eq!(a.boxes.len(), b.boxes.len());
    for (x, y) in a.boxes.iter().zip(&b.boxes) {
        assert_eq!((&x.label, x.instance_id), (&y.label, y.instance_id));
        assert!((x.center - y.center).abs().max() <= tolerance, "{x:?}\n{y:?}");
        assert!((x.size - y.size).abs().max() <= tolerance, "{x:?}\n{y:?}");
        assert!(
            (x.rotation.matrix() - y.rotation.matrix()).amax() <= tolerance,
            "{x:?}\n{y:?}"
        );
    }
}

/// The same solid: every corner of one box is a corner of the other.
fn assert_same_solids(a: &Box3, b: &Box3, tolerance: f64) {
    assert_eq!(a.label, b.label);
    for p in a.corners() {
        let nearest = b.corners().iter().map(|q| (p - q).norm()).fold(f64::INFINITY, f64::min);
        assert!(nearest <= tolerance, "corner {p:?} of {a:?} is {nearest} from {b:?}");
    }
}

/// The fixture's three boxes (a box turned 30 degrees about z, a ball, a
/// can) as labelCloud's centroid_abs export writes them (json.dump with
/// tab indent; degrees).
const FIXTURE_CENTROID_ABS: &str = "{\n\t\"folder\": \"small\",\n\t\"filename\": \"cloud.ply\",\n\t\"path\": \"small/cloud.ply\",\n\t\"objects\": [\n\
\t\t{\n\t\t\t\"name\": \"box\",\n\t\t\t\"centroid\": {\"x\": -0.2, \"y\": 0.15, \"z\": 0.078375},\n\t\t\t\"dimensions\": {\"length\": 0.309, \"width\": 0.209, \"height\": 0.15225},\n\t\t\t\"rotations\": {\"x\": 0.0, \"y\": 0.0, \"z\": 30.0}\n\t\t},\n\
\t\t{\n\t\t\t\"name\": \"ball\",\n\t\t\t\"centroid\": {\"x\": 0.25, \"y\": 0.1, \"z\": 0.1227},\n\t\t\t\"dimensions\": {\"length\": 0.2472, \"width\": 0.2472, \"height\": 0.2418},\n\t\t\t\"rotations\": {\"x\": 0.0, \"y\": 0.0, \"z\": 0.0}\n\t\t},\n\
\t\t{\n\t\t\t\"name\": \"can\",\n\t\t\t\"centroid\": {\"x\": 0.0, \"y\": -0.25, \"z\": 0.1278125},\n\t\t\t\"dimensions\": {\"length\": 0.1675, \"width\": 0.1675, \"height\": 0.251875},\n\t\t\t\"rotations\": {\"x\": 0.0, \"y\": 0.0, \"z\": 0.0}\n\t\t}\n\t]\n}\n";

#[test]
fn labelcloud_file_of_the_fixture_boxes_labels_as_the_fixture_boxes_do() {
    let dir = tempfile::tempdir().unwrap();
    let scan = small_scan(dir.path());
    let original = read_boxes(&scan.join("boxes.json")).unwrap();
    // centroid_abs (degrees, as written above) and centroid_rel (radians
    // rounded to labelCloud's default 8 decimals).
    let abs = dir.path().join("cloud_abs.json");
    std::fs::write(&abs, FIXTURE_CENTROID_ABS).unwrap();
    let rel = dir.path().join("cloud_rel.json");
    std::fs::write(&rel, FIXTURE_CENTROID_ABS.replace("\"z\": 30.0}", "\"z\": 0.52359878}")).unwrap();
    let want = masks(&scan, &scan.join("boxes.json"), &dir.path().join("labels_original"));
    assert!(
        want.iter().any(|(_, png)| png.len() > 200),
        "the fixture's objects are labelled"
    );
    for (file, from, tolerance) in [(&abs, "labelcloud-abs", 1e-9), (&rel, "labelcloud", 1e-8)] {
        let out = dir.path().join(format!("{from}.boxes.json"));
        let said = ok(&["boxes", "import", s(file), "--from", from, "--out", s(&out)]);
        assert!(said.contains("imported 3 boxes (3 labels)"), "{said}");
        let imported = read_boxes(&out).unwrap();
        assert_same_boxes(&imported, &original, tolerance);
        let got = masks(&scan, &out, &dir.path().join(format!("labels_{from}")));
        assert!(
            got == want,
            "{from}: the imported boxes label other pixels than the fixture's boxes"
        );
    }
}

#[test]
fn kitti_file_of_the_fixture_boxes_labels_as_the_fixture_boxes_do() {
    let dir = tempfile::tempdir().unwrap();
    let scan = small_scan(dir.path());
    let original = read_boxes(&scan.join("boxes.json")).unwrap();
    // A KITTI camera looking along world +y from (0.1, -1.2, 0.4), its y axis
    // down (world -z): x right = world x, z forward = world y.
    let rotation = Matrix3::from_columns(&[Vector3::x(), -Vector3::z(), Vector3::y()]);
    let camera_to_world = IsometryMatrix3::from_parts(
        Translation3::new(0.1, -1.2, 0.4),
        Rotation3::from_matrix_unchecked(rotation),
    )
    .to_homogeneous();
    let calib = dir.path().join("calib.txt");
    let rows: Vec<String> = (0..4)
        .map(|r| {
            let row = camera_to_world.row(r);
            format!("{:?} {:?} {:?} {:?}", row[0], row[1], row[2], row[3])
        })
        .collect();
    std::fs::write(&calib, rows.join("\n") + "\n").unwrap();
    // Each box as a KITTI line: height along camera y (world z), length along
    // the box's own x, width along its y; rotation_y = -yaw (camera y points down).
    let world_to_camera = IsometryMatrix3::from_parts(
        Translation3::new(0.1, -1.2, 0.4),
        Rotation3::from_matrix_unchecked(rotation),
    )
    .inverse();
    let mut lines = String::new();
    for b in &original.boxes {
        let x_axis = b.rotation * Vector3::x();
        let yaw = x_axis.y.atan2(x_axis.x);
        let bottom = world_to_camera * (b.center - Vector3::new(0.0, 0.0, b.size.z / 2.0));
        lines.push_str(&format!(
            "{} 0.00 0 {:?} 10.00 20.00 60.00 80.00 {:?} {:?} {:?} {:?} {:?} {:?} {:?}\n",
            b.label, -yaw, b.size.z, b.size.y, b.size.x, bottom.x, bottom.y, bottom.z, -yaw
        ));
    }
    lines.push_str("DontCare -1 -1 -10 503.89 169.71 590.61 190.13 -1 -1 -1 -1000 -1000 -1000 -10\n");
    let label_file = dir.path().join("000000.txt");
    std::fs::write(&label_file, &lines).unwrap();
    let out = dir.path().join("kitti.boxes.json");
    let o = run(&[
        "boxes",
        "import",
        s(&label_file),
        "--from",
        "kitti",
        "--calib",
        s(&calib),
        "--out",
        s(&out),
    ]);
    assert!(o.status.success(), "{}", stderr(&o));
    assert!(stderr(&o).contains("skipped 1 DontCare"), "{}", stderr(&o));
    let imported = read_boxes(&out).unwrap();
    assert_eq!(imported.boxes.len(), original.boxes.len());
    for (a, b) in imported.boxes.iter().zip(&original.boxes) {
        assert_same_solids(a, b, 1e-9);
        assert!((a.center - b.center).norm() < 1e-9 && (a.volume() - b.volume()).abs() < 1e-12);
    }
    let want = masks(&scan, &scan.join("boxes.json"), &dir.path().join("labels_original"));
    let got = masks(&scan, &out, &dir.path().join("labels_kitti"));
    assert!(
        got == want,
        "the KITTI boxes label other pixels than the fixture's boxes"
    );
}

#[test]
fn export_to_labelcloud_and_back_gives_the_same_boxes() {
    let dir = tempfile::tempdir().unwrap();
    let boxes = common::small_fixture().join("boxes.json");
    let original = read_boxes(&boxes).unwrap();
    for format in ["labelcloud", "labelcloud-abs"] {
        let exported = dir.path().join(format!("{format}.json"));
        let cloud = dir.path().join("pointclouds/scan.ply");
        ok(&[
            "boxes",
            "export",
            s(&boxes),
            "--to",
            format,
            "--cloud",
            s(&cloud),
            "--out",
            s(&exported),
        ]);
        let doc: serde_json::Value = serde_json::from_slice(&std::fs::read(&exported).unwrap()).unwrap();
        assert_eq!(
            (doc["folder"].as_str(), doc["filename"].as_str()),
            (Some("pointclouds"), Some("scan.ply"))
        );
        assert_eq!(doc["objects"].as_array().unwrap().len(), 3);
        let back = dir.path().join(format!("{format}.boxes.json"));
        ok(&["boxes", "import", s(&exported), "--from", format, "--out", s(&back)]);
        assert_same_boxes(&read_boxes(&back).unwrap(), &original, 1e-9);
    }
    // The default output is <cloud stem>.json in the current folder.
    let o = std::process::Command::new(env!("CARGO_BIN_EXE_nerflabel"))
        .args([
            "boxes",
            "export",
            s(&boxes),
            "--to",
            "labelcloud",
            "--cloud",
            "room.pcd",
        ])
        .current_dir(dir.path())
        .output()
        .unwrap();
    assert!(o.status.success(), "{}", stderr(&o));
    assert!(dir.path().join("room.json").is_file());
}

#[test]
fn bad_files_fail_with_file_entry_and_field_and_write_nothing() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("boxes.json");
    let write = |name: &str, text: &str| {
        let p = dir.path().join(name);
        std::fs::write(&p, text).unwrap();
        p
    };
    let lc = write(
        "lc.json",
        r#"{"objects": [{"name": "a", "centroid": {"x": 0, "y": 0, "z": 0}, "dimensions": {"length": 1, "width": 1, "height": 1}, "rotations": {"x": 0, "y": 0, "z": 0}},
                        {"name": "b", "centroid": {"x": 0, "y": 0}, "dimensions": {"length": 1, "width": 1, "height": 1}, "rotations": {"x": 0, "y": 0, "z": 0}}]}"#,
    );
    let kitti = write(
        "k.txt",
        "Car 0 0 0 0 0 1 1 1 1 1 0 0 5 0\nCar 0 0 0 0 0 1 1 1 1 1 0 0 five 0\n",
    );
    let cvat = write(
        "c.pcd.json",
        r#"{"objects": [], "figures": [{"objectKey": "x", "geometryType": "cuboid_3d", "geometry": {}}]}"#,
    );
    let not_json = write("n.json", "{\"objects\": [");
    let calib = write("calib.txt", "1 0 0 0\n0 1 0 0\n0 0 1 0\n");
    let cases: Vec<(Vec<&str>, &str)> = vec![
        (
            vec![s(&lc), "--from", "labelcloud"],
            "lc.json: object 2 (objects[1]), field `centroid.z`: missing",
        ),
        (
            vec![s(&kitti), "--from", "kitti"],
            "k.txt: line 2, field `z`: `five` is not a finite number",
        ),
        (
            vec![s(&cvat), "--from", "cvat"],
            "c.pcd.json: figure 1 (figures[0]), field `objectKey`",
        ),
        (vec![s(&not_json), "--from", "labelcloud"], "n.json: not valid JSON"),
        (
            vec![s(&lc), "--from", "labelcloud", "--calib", s(&calib)],
            "--calib places KITTI",
        ),
        (
            vec!["/no/such/file.json", "--from", "cvat"],
            "/no/such/file.json: cannot read",
        ),
        (
            vec![s(&lc), "--from", "labelcloud", "--out", s(&lc)],
            "is also an input",
        ),
    ];
    for (args, words) in cases {
        let mut all = vec!["boxes", "import"];
        all.extend(&args);
        if !args.contains(&"--out") {
            all.extend(["--out", s(&out)]);
        }
        let o = run(&all);
        assert_eq!(
            o.status.code(),
            Some(1),
            "{all:?}: a clean failure, not a panic: {}",
            stderr(&o)
        );
        let message = stderr(&o);
        let first = message.lines().next().unwrap_or("");
        assert!(
            first.starts_with("error: ") && first.contains(words),
            "{all:?}: {message}"
        );
        assert!(!out.exists(), "{all:?} wrote {}", out.display());
    }
    // An existing output is kept unless --overwrite.
    std::fs::write(&out, "mine").unwrap();
    let good = write("good.json", FIXTURE_CENTROID_ABS);
    let o = run(&[
        "boxes",
        "import",
        s(&good),
        "--from",
        "labelcloud-abs",
        "--out",
        s(&out),
    ]);
    assert!(
        !o.status.success() && stderr(&o).contains("--overwrite"),
        "{}",
        stderr(&o)
    );
    assert_eq!(std::fs::read_to_string(&out).unwrap(), "mine");
    ok(&[
        "boxes",
        "import",
        s(&good),
        "--from",
        "labelcloud-abs",
        "--out",
        s(&out),
        "--overwrite",
    ]);
    assert_eq!(read_boxes(&out).unwrap().boxes.len(), 3);
}

/// `--help` of a subcommand without the global options (they change with other work).
fn own_help(args: &[&str]) -> String {
    let text = String::from_utf8_lossy(&run(args).stdout).into_owned();
    let top = String::from_utf8_lossy(&run(&["--help"]).stdout).into_owned();
    let global: Vec<String> = top
        .lines()
        .filter_map(|l| {
            l.trim_start()
                .strip_prefix("--")
                .map(|o| o.split([' ', ',']).next().unwrap_or("").to_string())
        })
        .filter(|o| o != "help" && o != "version")
        .collect();
    let mut out = String::new();
    let mut skipping = false;
    for line in text.lines() {
        let option = line.trim_start().starts_with('-') && line.starts_with("  ");
        if option {
            skipping = global.iter().any(|g| line.trim_start().starts_with(&format!("--{g}")));
        }
        if !skipping {
            out.push_str(line);
            out.push('\n');
        }
    }
    out
}

#[test]
fn boxes_help_names_the_formats_and_their_conventions() {
    let import = own_help(&["boxes", "import", "--help"]);
    for words in [
        "labelcloud-abs",
        "centroid_rel",
        "label_2",
        "Sly Point Cloud",
        "--calib",
        "camera-to-world",
    ] {
        assert!(import.contains(words), "{words} missing from boxes import --help");
    }
    insta::assert_snapshot!("boxes_import_help", import);
    insta::assert_snapshot!("boxes_export_help", own_help(&["boxes", "export", "--help"]));
}
