//! End-to-end checks of the fixture generator: the files it writes parse,
//! match the scene's exact ground truth, and are deterministic for a seed.

use nalgebra::{IsometryMatrix3, Matrix3, Matrix4, Point3, Rotation3, Translation3, Vector3, Vector4};
use nerflabel::fixture::{
    generate, read_meta, trajectory, Corruptions, FixtureError, FixtureLayout, FixtureOptions, Scene, SceneKind,
};
use nerflabel::scan::Intrinsics;
use serde_json::Value;
use std::fs;
use std::path::Path;

fn small_options(frames: usize, holdout: usize) -> FixtureOptions {
    let mut o = FixtureOptions::new(SceneKind::Small);
    o.width = 80;
    o.height = 60;
    o.frames = Some(frames);
    o.holdout = Some(holdout);
    o.seed = 11;
    o
}

fn read_matrix(path: &Path) -> Vec<Vec<f64>> {
    let text = fs::read_to_string(path).unwrap();
    text.lines()
        .filter(|l| !l.trim().is_empty())
        .map(|l| l.split_whitespace().map(|v| v.parse::<f64>().unwrap()).collect())
        .collect()
}

fn mat4(rows: &[Vec<f64>]) -> Matrix4<f64> {
    assert_eq!(rows.len(), 4);
    Matrix4::from_fn(|r, c| rows[r][c])
}

/// The rigid transform in the top three rows of `m`.
fn rigid(m: &Matrix4<f64>) -> IsometryMatrix3<f64> {
    IsometryMatrix3::from_parts(
        Translation3::new(m[(0, 3)], m[(1, 3)], m[(2, 3)]),
        Rotation3::from_matrix_unchecked(m.fixed_view::<3, 3>(0, 0).into_owned()),
    )
}

fn json_mat4(v: &Value) -> Matrix4<f64> {
    let rows: Vec<Vec<f64>> = v
        .as_array()
        .unwrap()
        .iter()
        .map(|r| r.as_array().unwrap().iter().map(|x| x.as_f64().unwrap()).collect())
        .collect();
    mat4(&rows)
}

fn max_abs_diff(a: &Matrix4<f64>, b: &IsometryMatrix3<f64>) -> f64 {
    (a - b.to_homogeneous()).amax()
}

fn read_json(path: &Path) -> Value {
    serde_json::from_str(&fs::read_to_string(path).unwrap()).unwrap()
}

fn gray16(path: &Path) -> image::ImageBuffer<image::Luma<u16>, Vec<u16>> {
    match image::open(path).unwrap() {
        image::DynamicImage::ImageLuma16(img) => img,
        other => panic!("{}: expected 16-bit gray, found {:?}", path.display(), other.color()),
    }
}

fn gray8(path: &Path) -> image::GrayImage {
    match image::open(path).unwrap() {
        image::DynamicImage::ImageLuma8(img) => img,
        other => panic!("{}: expected 8-bit gray, found {:?}", path.display(), other.color()),
    }
}

#[test]
fn native_scan_parses_and_matches_exact_ground_truth() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("small");
    let options = small_options(6, 2);
    let summary = generate(&out, &options).unwrap();
    assert_eq!((summary.frames, summary.holdout, summary.depth_size), (6, 2, (32, 24)));
    assert!(summary.warnings.is_empty(), "{:?}", summary.warnings);

    let scene = Scene::new(SceneKind::Small, 1.0);
    let path = trajectory(&scene, 6, 2, 11);
    let k = options.intrinsics();

    // intrinsics.txt round-trips exactly.
    let km = read_matrix(&out.join("intrinsics.txt"));
    let parsed = Intrinsics {
        fx: km[0][0],
        fy: km[1][1],
        cx: km[0][2],
        cy: km[1][2],
    };
    assert_eq!(parsed, k);
    assert_eq!((km[0][1], km[1][0], km[2][2]), (0.0, 0.0, 1.0));

    let gt_unit = read_json(&out.join("gt/meta.json"))["gt_depth_unit_m"]
        .as_f64()
        .unwrap();
    let glass = scene.labelled().find(|o| o.no_sensor_depth).unwrap().instance_id;
    for (i, c2w) in path.scan.iter().enumerate() {
        let name = format!("{i:06}");
        // pose/ holds world-to-camera; its inverse is the render pose.
        let w2c = mat4(&read_matrix(&out.join(format!("pose/{name}.txt"))));
        let back = rigid(&w2c).inverse();
        assert!(
            max_abs_diff(&back.to_homogeneous(), c2w) < 1e-9,
            "frame {i}: pose off by {}",
            max_abs_diff(&back.to_homogeneous(), c2w)
        );

        let rgb = image::open(out.join(format!("rgb/{name}.png"))).unwrap();
        assert_eq!(
            (rgb.width(), rgb.height(), rgb.color()),
            (80, 60, image::ColorType::Rgb8)
        );
        let depth = gray16(&out.join(format!("depth/{name}.png")));
        assert_eq!(depth.dimensions(), (32, 24));

        // Ground truth equals a fresh render from the parsed pose.
        let render = scene.render(&back, &parsed, 80, 60);
        let gt = gray16(&out.join(format!("gt/depth/{name}.png")));
        for (q, &z) in gt.as_raw().iter().zip(&render.depth) {
            assert!((*q as f64 * gt_unit - z as f64).abs() <= gt_unit * 0.5 + 1e-9);
        }
        let mask = gray8(&out.join(format!("gt/masks/{name}.png")));
        assert!(mask
            .as_raw()
            .iter()
            .zip(&render.instance)
            .all(|(&m, &id)| m as u16 == id));

        // The glass-like object reads 0 in the sensor depth.
        let low_k = parsed.scaled((80, 60), (32, 24));
        let low = scene.render(&back, &low_k, 32, 24);
        for (d, id) in depth.as_raw().iter().zip(&low.instance) {
            if *id == glass {
                assert_eq!(*d, 0);
            }
        }
    }
    for (i, c2w) in path.holdout.iter().enumerate() {
        let name = format!("{i:06}");
        let w2c = mat4(&read_matrix(&out.join(format!("gt/holdout/pose/{name}.txt"))));
        assert!(max_abs_diff(&rigid(&w2c).inverse().to_homogeneous(), c2w) < 1e-9);
        let rgb = image::open(out.join(format!("gt/holdout/rgb/{name}.png")))
            .unwrap()
            .to_rgb8();
        assert_eq!(rgb, scene.render(c2w, &k, 80, 60).rgb, "held-out colour is clean");
        assert_eq!(
            gray16(&out.join(format!("gt/holdout/depth/{name}.png"))).dimensions(),
            (80, 60)
        );
        assert_eq!(
            gray8(&out.join(format!("gt/holdout/masks/{name}.png"))).dimensions(),
            (80, 60)
        );
    }
    assert!(!out.join("gt/holdout/rgb/000002.png").exists());
    assert!(!out.join("rgb/000006.png").exists());

    // boxes.json: one user box per object, each holding the tight box with a small margin.
    let boxes = read_json(&out.join("boxes.json"));
    let tight = read_json(&out.join("gt/boxes_tight.json"));
    let objects = read_json(&out.join("gt/objects.json"));
    let list = boxes["boxes"].as_array().unwrap();
    assert_eq!(list.len(), scene.labelled().count());
    for (o, (b, t)) in scene
        .labelled()
        .zip(list.iter().zip(tight["boxes"].as_array().unwrap()))
    {
        assert_eq!(b["label"], o.label.as_str());
        let v3 = |v: &Value| Vector3::new(v[0].as_f64().unwrap(), v[1].as_f64().unwrap(), v[2].as_f64().unwrap());
        let rot = match b.get("rotation") {
            Some(r) => Matrix3::from_rows(&[v3(&r[0]).transpose(), v3(&r[1]).transpose(), v3(&r[2]).transpose()]),
            None => Matrix3::identity(),
        };
        let (center, size) = (v3(&b["center"]), v3(&b["size"]));
        assert!((v3(&t["size"]) - o.size).norm() < 1e-12 && (v3(&t["center"]) - o.center()).norm() < 1e-12);
        for c in 0..8 {
            let s = Vector3::new(
                (c & 1) as f64 - 0.5,
                ((c >> 1) & 1) as f64 - 0.5,
                ((c >> 2) & 1) as f64 - 0.5,
            );
            let corner = (o.object_to_world * Point3::from(s.component_mul(&o.size))).coords;
            let local = rot.transpose() * (corner - center);
            let slack = (local.abs() - size * 0.5).max();
            // Inside, except the bottom face, which sits just above the support.
            assert!(
                slack <= 0.01 * o.size.max(),
                "{}: corner {c} outside by {slack}",
                o.label
            );
        }
        assert!((size - o.size).max() < 0.04 * o.size.max());
    }
    let objs = objects["objects"].as_array().unwrap();
    for (o, j) in scene.labelled().zip(objs) {
        assert_eq!(j["instance_id"].as_u64().unwrap(), o.instance_id as u64);
        let object_to_world = o.object_to_world.to_homogeneous();
        assert!((json_mat4(&j["object_to_world"]) - object_to_world).amax() < 1e-15);
        assert_eq!(j["no_sensor_depth"].as_bool().unwrap(), o.no_sensor_depth);
    }

    let parsed_meta = read_meta(&out).unwrap();
    assert_eq!(
        (parsed_meta.scene, parsed_meta.scale, parsed_meta.seed),
        (SceneKind::Small, 1.0, 11)
    );
    assert_eq!(
        (
            parsed_meta.width,
            parsed_meta.height,
            parsed_meta.frames,
            parsed_meta.holdout
        ),
        (80, 60, 6, 2)
    );
    assert_eq!((parsed_meta.intrinsics, parsed_meta.gt_depth_unit), (k, gt_unit));
    assert_eq!(parsed_meta.build_scene(), scene);
    let meta = read_json(&out.join("gt/meta.json"));
    assert_eq!(meta["scene"], "small");
    assert_eq!(meta["seed"].as_u64(), Some(11));
    assert_eq!(meta["scan_depth"]["unit_m"].as_f64(), Some(0.001));
    let cmd = meta["command"].as_str().unwrap();
    assert!(
        cmd.starts_with("nerflabel fixture --scene small ") && cmd.contains("--frames 6") && cmd.contains("--seed 11")
    );
}

#[test]
fn broken_meta_is_reported_with_its_path() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("fx");
    generate(&out, &small_options(1, 0)).unwrap();
    let meta_path = out.join("gt/meta.json");
    let text = fs::read_to_string(&meta_path)
        .unwrap()
        .replace("\"small\"", "\"kitchen\"");
    fs::write(&meta_path, text).unwrap();
    let err = read_meta(&out).unwrap_err().to_string();
    assert!(err.contains("gt/meta.json") && err.contains("kitchen"), "{err}");
    fs::write(&meta_path, "{").unwrap();
    assert!(read_meta(&out).unwrap_err().to_string().contains("not valid JSON"));
}

/// Every file under `root`, relative path -> bytes, sorted.
fn tree(root: &Path) -> Vec<(String, Vec<u8>)> {
    let mut files = Vec::new();
    let mut stack = vec![root.to_path_buf()];
    while let Some(dir) = stack.pop() {
        for entry in fs::read_dir(&dir).unwrap() {
            let p = entry.unwrap().path();
            if p.is_dir() {
                stack.push(p);
            } else {
                let rel = p.strip_prefix(root).unwrap().to_string_lossy().into_owned();
                files.push((rel, fs::read(&p).unwrap()));
            }
        }
    }
    files.sort();
    files
}

#[test]
fn same_seed_gives_identical_bytes_and_another_seed_other_noise() {
    let dir = tempfile::tempdir().unwrap();
    let options = small_options(4, 1);
    for name in ["a", "b"] {
        generate(&dir.path().join(name), &options).unwrap();
    }
    let mut other = options.clone();
    other.seed = 12;
    generate(&dir.path().join("c"), &other).unwrap();
    let (a, b, c) = (
        tree(&dir.path().join("a")),
        tree(&dir.path().join("b")),
        tree(&dir.path().join("c")),
    );
    // Scan frames (rgb, depth, pose), their masks and depth, held-out files, JSON documents, drawn boxes.
    assert_eq!(a.len(), 4 * 3 + 4 * 2 + 4 + 5 + 2);
    for ((pa, da), (pb, db)) in a.iter().zip(&b) {
        assert_eq!(pa, pb);
        if pa.ends_with("meta.json") {
            // Only the output path in the recorded command differs.
            let text = |d: &[u8], n: &str| {
                String::from_utf8(d.to_vec())
                    .unwrap()
                    .replace(&format!("/{n} "), "/OUT ")
            };
            assert_eq!(text(da, "a"), text(db, "b"));
        } else {
            assert!(da == db, "{pa} differs between runs with the same seed");
        }
    }
    let differ = |prefix: &str| {
        a.iter()
            .zip(&c)
            .filter(|((p, x), (_, y))| p.starts_with(prefix) && x != y)
            .count()
    };
    assert_eq!(differ("depth/"), 4, "another seed must change the sensor noise");
    assert_eq!(differ("rgb/"), 4);
    assert_eq!(differ("boxes.json"), 0, "the scene itself does not depend on the seed");
}

#[test]
fn nerfstudio_layout_at_large_scale_keeps_depth_in_range() {
    let dir = tempfile::tempdir().unwrap();
    let mut options = small_options(3, 0);
    options.scale = 100.0;
    options.corruptions = Corruptions::none();
    // Native millimetres overflow at 100x: the summary says so.
    let native = generate(&dir.path().join("native"), &options).unwrap();
    assert!(
        native.warnings.iter().any(|w| w.contains("exceed 65535")),
        "{:?}",
        native.warnings
    );

    options.layout = FixtureLayout::Nerfstudio;
    let out = dir.path().join("ns");
    let summary = generate(&out, &options).unwrap();
    assert!(summary.warnings.is_empty(), "{:?}", summary.warnings);
    assert!(!out.join("pose").exists() && !out.join("intrinsics.txt").exists());
    let t = read_json(&out.join("transforms.json"));
    let k = options.intrinsics();
    assert_eq!(t["fl_x"].as_f64(), Some(k.fx));
    assert_eq!(
        t["cx"].as_f64(),
        Some(k.cx + 0.5),
        "nerfstudio puts pixel centres at +0.5"
    );
    assert_eq!((t["w"].as_u64(), t["h"].as_u64()), (Some(80), Some(60)));
    let unit = t["depth_unit_scale_factor"].as_f64().unwrap();
    assert!((unit - 0.1).abs() < 1e-12);
    let scene = Scene::new(SceneKind::Small, 100.0);
    let path = trajectory(&scene, 3, 0, 11);
    let flip = Matrix4::from_diagonal(&Vector4::new(1.0, -1.0, -1.0, 1.0));
    let frames = t["frames"].as_array().unwrap();
    assert_eq!(frames.len(), 3);
    for (f, c2w) in frames.iter().zip(&path.scan) {
        let gl = json_mat4(&f["transform_matrix"]);
        assert!(max_abs_diff(&(gl * flip), c2w) < 1e-9);
        let rgb = image::open(out.join(f["file_path"].as_str().unwrap())).unwrap();
        assert_eq!((rgb.width(), rgb.height()), (80, 60));
        let depth = gray16(&out.join(f["depth_file_path"].as_str().unwrap()));
        let exact = scene.render(c2w, &k, 80, 60).depth;
        for (q, z) in depth.as_raw().iter().zip(exact) {
            assert!((*q as f64 * unit - z as f64).abs() <= 0.5 * unit + 1e-6);
        }
    }
}

#[test]
fn tiny_scale_in_native_layout_warns_about_millimetres() {
    let dir = tempfile::tempdir().unwrap();
    let mut options = small_options(2, 0);
    options.scale = 0.01;
    let summary = generate(&dir.path().join("tiny"), &options).unwrap();
    assert!(
        summary.warnings.iter().any(|w| w.contains("nerfstudio")),
        "{:?}",
        summary.warnings
    );
    assert!((summary.gt_depth_unit - 2e-6).abs() < 1e-18);
}

#[test]
fn refuses_foreign_folder_and_replaces_own_fixture_only_when_asked() {
    let dir = tempfile::tempdir().unwrap();
    let foreign = dir.path().join("foreign");
    fs::create_dir_all(&foreign).unwrap();
    fs::write(foreign.join("notes.txt"), "mine").unwrap();
    let options = small_options(2, 0);
    assert!(matches!(generate(&foreign, &options), Err(FixtureError::NotEmpty(_))));
    assert_eq!(fs::read_to_string(foreign.join("notes.txt")).unwrap(), "mine");

    let out = dir.path().join("fx");
    let mut bigger = small_options(3, 0);
    generate(&out, &bigger).unwrap();
    fs::write(out.join("README.txt"), "keep").unwrap();
    assert!(matches!(generate(&out, &options), Err(FixtureError::Exists(_))));
    bigger.frames = Some(2);
    bigger.overwrite = true;
    generate(&out, &bigger).unwrap();
    assert!(
        !out.join("rgb/000002.png").exists(),
        "stale frames of the earlier fixture are removed"
    );
    assert_eq!(fs::read_to_string(out.join("README.txt")).unwrap(), "keep");

    let mut bad = small_options(2, 3);
    assert!(matches!(
        generate(&dir.path().join("bad"), &bad),
        Err(FixtureError::Option(_))
    ));
    bad.holdout = Some(0);
    bad.scale = f64::NAN;
    assert!(matches!(
        generate(&dir.path().join("bad"), &bad),
        Err(FixtureError::Option(_))
    ));
}

/// Full-size run (120 frames, 640x480): prints the time taken.
/// `cargo test --release --test fixture_gen -- --ignored --nocapture`
#[test]
#[ignore]
fn full_tabletop_fixture_prints_timing() {
    let dir = tempfile::tempdir().unwrap();
    let options = FixtureOptions::new(SceneKind::Tabletop);
    let start = std::time::Instant::now();
    let summary = generate(&dir.path().join("tabletop"), &options).unwrap();
    eprintln!(
        "tabletop {} + {} frames at {}x{} in {:.1} s ({} rayon threads), valid depth {:.3}",
        summary.frames,
        summary.holdout,
        summary.size.0,
        summary.size.1,
        start.elapsed().as_secs_f64(),
        rayon::current_num_threads(),
        summary.valid_depth_fraction
    );
    assert_eq!(
        (summary.frames, summary.holdout, summary.depth_size),
        (120, 12, (256, 192))
    );
    assert!(summary.valid_depth_fraction > 0.6 && summary.valid_depth_fraction < 0.95);
    assert!(summary.warnings.is_empty(), "{:?}", summary.warnings);
}

#[test]
fn realistic_scans_have_jpeg_colour_pose_error_and_drawn_boxes() {
    let dir = tempfile::tempdir().unwrap();
    let mut o = FixtureOptions::new(SceneKind::Clutter);
    (o.width, o.height, o.frames, o.holdout, o.seed) = (96, 72, Some(6), Some(0), 5);
    o.corruptions = Corruptions::realistic();
    generate(dir.path(), &o).unwrap();
    let scan = nerflabel::scan::load(dir.path(), &Default::default()).unwrap();
    assert_eq!(scan.frames.len(), 6);
    assert!(dir.path().join("rgb/000000.jpg").is_file());
    assert!(!dir.path().join("rgb/000000.png").exists());

    // Written poses differ from the exact ones by about the configured error, never more than 5 sigma.
    let (mut shift, mut turn) = (Vec::new(), Vec::new());
    for i in 0..6 {
        let name = format!("{i:06}.txt");
        let written = mat4(&read_matrix(&dir.path().join("pose").join(&name)));
        let exact = mat4(&read_matrix(&dir.path().join("gt/pose").join(&name)));
        let error = rigid(&written) * rigid(&exact).inverse();
        shift.push(error.translation.vector.norm());
        let r: Matrix3<f64> = *error.rotation.matrix();
        turn.push(((r.trace() - 1.0) / 2.0).clamp(-1.0, 1.0).acos().to_degrees());
    }
    let c = Corruptions::realistic();
    assert!(turn.iter().all(|&t| t > 0.0 && t < 4.0 * c.pose_sigma_deg), "{turn:?}");
    assert!(turn.iter().sum::<f64>() / 6.0 > 0.3 * c.pose_sigma_deg, "{turn:?}");
    // World-to-camera translation error also carries the rotation error times the distance (about 1 m).
    assert!(shift.iter().all(|&s| s > 1e-5 && s < 0.05), "{shift:?}");

    // Drawn boxes: snug ones hold the tight box, loose ones hold the snug ones and reach 2 cm below.
    let boxes = |name: &str| {
        nerflabel::boxes::read_boxes(&dir.path().join("gt").join(name))
            .unwrap()
            .boxes
    };
    let (tight, snug, loose) = (
        boxes("boxes_tight.json"),
        boxes("boxes_user.json"),
        boxes("boxes_loose.json"),
    );
    assert_eq!((tight.len(), snug.len(), loose.len()), (6, 6, 6));
    for ((t, s), l) in tight.iter().zip(&snug).zip(&loose) {
        let bottom = |b: &nerflabel::boxes::Box3| b.center.z - b.size.z / 2.0;
        assert!(
            (s.size - t.size - nalgebra::Vector3::new(0.02, 0.02, 0.009))
                .abs()
                .max()
                < 1e-9
        );
        assert!((bottom(s) - bottom(t) - 0.001).abs() < 1e-9);
        assert!(
            (l.size - t.size - nalgebra::Vector3::new(0.05, 0.05, 0.045))
                .abs()
                .max()
                < 1e-9
        );
        assert!((bottom(t) - bottom(l) - 0.02).abs() < 1e-9);
    }
}
