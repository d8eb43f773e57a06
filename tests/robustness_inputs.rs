//! Issue 6 through the real binary: degenerate scans (no depth, zero,
//! saturated and 1 mm depth, one frame, duplicate poses, pure rotation,
//! extreme intrinsics), extreme scene scales (same depth error relative to
//! the scene, same label masks), labelling without any depth, and nothing
//! lost (corrupted model files are rejected, a failed fit leaves an existing
//! model intact).
//!
//! The no-depth labelling test needs 1000 training steps and is ignored:
//! `cargo test --release --test robustness_inputs -- --ignored`
//!
//! Each degenerate scan must give either a clean refusal (non-zero exit, one
//! `error:` message, no panic) or a model whose every parameter is finite.

use nerflabel::boxes::metrics::MaskScores;
use nerflabel::evaluate::score_holdout;
use nerflabel::nerf::model_file::Model;
use nerflabel::rng::Rng;
use std::path::{Path, PathBuf};
use std::process::{Command, Output};
use std::sync::OnceLock;

fn bin() -> Command {
    Command::new(env!("CARGO_BIN_EXE_nerflabel"))
}

/// A small clean fixture scan `dir/name` (80x60, `frames` frames).
fn fixture(dir: &Path, name: &str, frames: u32, extra: &[&str]) -> PathBuf {
    let out = dir.join(name);
    let frames = frames.to_string();
    let o = bin()
        .args([
            "fixture", "--scene", "small", "--width", "80", "--height", "60", "--frames", &frames, "--clean",
        ])
        .args(extra)
        .arg(&out)
        .output()
        .unwrap();
    assert!(o.status.success(), "fixture: {}", String::from_utf8_lossy(&o.stderr));
    out
}

fn fit(scan: &Path, model: &Path, steps: u32) -> Output {
    bin()
        .arg("fit")
        .arg(scan)
        .args([
            "--steps",
            &steps.to_string(),
            "--holdout",
            "0",
            "--seed",
            "1",
            "--model",
        ])
        .arg(model)
        .output()
        .unwrap()
}

/// Every parameter and occupancy density of the model is finite.
fn assert_model_finite(model: &Model, what: &str) {
    let f = &model.field;
    let sections: [(&str, &[f32]); 4] = [
        ("grid", &f.grid.params),
        ("density MLP", &f.density.params),
        ("colour MLP", &f.color.params),
        ("occupancy", model.occupancy.densities()),
    ];
    for (name, params) in sections {
        assert!(!params.is_empty() || name == "occupancy", "{what}: empty {name}");
        if let Some(bad) = params.iter().find(|v| !v.is_finite()) {
            panic!("{what}: {name} holds {bad}");
        }
    }
}

/// Every number in a JSON report is finite (serde_json writes NaN as null).
fn assert_report_finite(path: &Path, what: &str) {
    let text = std::fs::read_to_string(path).unwrap();
    let json: serde_json::Value = serde_json::from_str(&text).unwrap();
    fn walk(v: &serde_json::Value, at: &str, what: &str) {
        match v {
            serde_json::Value::Number(n) => assert!(n.as_f64().is_some_and(f64::is_finite), "{what}: {at} = {n}"),
            serde_json::Value::Null => panic!("{what}: {at} is null (NaN?)"),
            serde_json::Value::Array(a) => a
                .iter()
                .enumerate()
                .for_each(|(i, x)| walk(x, &format!("{at}[{i}]"), what)),
            serde_json::Value::Object(o) => o.iter().for_each(|(k, x)| walk(x, &format!("{at}.{k}"), what)),
            _ => {}
        }
    }
    walk(&json, "report", what);
}

/// What a fit on a degenerate scan did.
#[derive(Debug)]
enum Outcome {
    Fitted,
    /// The error message (printed with --nocapture for the docs).
    Refused(#[allow(dead_code)] String),
}

/// Fit `scan`; accept a clean refusal or a finite model, fail on anything else.
fn fit_degenerate(scan: &Path, steps: u32, what: &str) -> Outcome {
    let model_path = scan.join("model.nlf");
    let o = fit(scan, &model_path, steps);
    let stderr = String::from_utf8_lossy(&o.stderr).to_string();
    assert!(!stderr.contains("panicked"), "{what}: panic\n{stderr}");
    if o.status.success() {
        let model = Model::load(&model_path).unwrap_or_else(|e| panic!("{what}: model does not load: {e}"));
        assert_model_finite(&model, what);
        assert_report_finite(&model_path.with_extension("report.json"), what);
        Outcome::Fitted
    } else {
        assert_ne!(o.status.code(), Some(101), "{what}: exit code of a panic\n{stderr}");
        assert!(
            stderr.trim_start().starts_with("error:"),
            "{what}: no error message\n{stderr}"
        );
        assert_eq!(
            stderr.matches("error:").count(),
            1,
            "{what}: more than one message\n{stderr}"
        );
        assert!(!model_path.exists(), "{what}: a refused fit left a model behind");
        Outcome::Refused(stderr)
    }
}

fn frame_files(dir: &Path) -> Vec<PathBuf> {
    let mut v: Vec<PathBuf> = std::fs::read_dir(dir).unwrap().map(|e| e.unwrap().path()).collect();
    v.sort();
    v
}

/// Rewrite every depth PNG of a native scan with `f(old value)`.
fn map_depth(scan: &Path, f: impl Fn(u16) -> u16) {
    for p in frame_files(&scan.join("depth")) {
        let mut img = image::open(&p).unwrap().to_luma16();
        for px in img.pixels_mut() {
            px.0[0] = f(px.0[0]);
        }
        img.save(&p).unwrap();
    }
}

fn read_pose(p: &Path) -> [[f64; 4]; 4] {
    let nums: Vec<f64> = std::fs::read_to_string(p)
        .unwrap()
        .split_whitespace()
        .map(|s| s.parse().unwrap())
        .collect();
    let mut m = [[0.0; 4]; 4];
    for (i, v) in nums.iter().enumerate().take(16) {
        m[i / 4][i % 4] = *v;
    }
    m
}

fn write_pose(p: &Path, m: &[[f64; 4]; 4]) {
    let text: String = m
        .iter()
        .map(|r| format!("{:.17} {:.17} {:.17} {:.17}\n", r[0], r[1], r[2], r[3]))
        .collect();
    std::fs::write(p, text).unwrap();
}

fn write_intrinsics(scan: &Path, fx: f64, fy: f64, cx: f64, cy: f64) {
    std::fs::write(
        scan.join("intrinsics.txt"),
        format!("{fx} 0 {cx}\n0 {fy} {cy}\n0 0 1\n"),
    )
    .unwrap();
}

#[test]
fn scan_without_any_depth_fits_photometrically() {
    let dir = tempfile::tempdir().unwrap();
    let scan = fixture(dir.path(), "nodepth", 6, &[]);
    std::fs::remove_dir_all(scan.join("depth")).unwrap();
    let model_path = scan.join("model.nlf");
    let o = fit(&scan, &model_path, 30);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let model = Model::load(&model_path).unwrap();
    assert_model_finite(&model, "no depth");
    assert_report_finite(&scan.join("model.report.json"), "no depth");
}

#[test]
fn all_zero_depth_is_refused_or_fits_finite() {
    let dir = tempfile::tempdir().unwrap();
    let scan = fixture(dir.path(), "zero", 6, &[]);
    map_depth(&scan, |_| 0);
    eprintln!("{:?}", fit_degenerate(&scan, 20, "all-zero depth"));
}

#[test]
fn saturated_65535_depth_is_refused_or_fits_finite() {
    let dir = tempfile::tempdir().unwrap();
    let scan = fixture(dir.path(), "sat", 6, &[]);
    map_depth(&scan, |d| if d > 0 { 65535 } else { 0 });
    eprintln!("{:?}", fit_degenerate(&scan, 20, "65535 depth"));
}

#[test]
fn one_millimetre_depth_is_refused_or_fits_finite() {
    let dir = tempfile::tempdir().unwrap();
    let scan = fixture(dir.path(), "mm", 6, &[]);
    map_depth(&scan, |d| if d > 0 { 1 } else { 0 });
    eprintln!("{:?}", fit_degenerate(&scan, 20, "1 mm depth"));
}

#[test]
fn single_frame_is_refused_or_fits_finite() {
    let dir = tempfile::tempdir().unwrap();
    let scan = fixture(dir.path(), "one", 3, &[]);
    for sub in ["rgb", "depth", "pose"] {
        for p in frame_files(&scan.join(sub)).into_iter().skip(1) {
            std::fs::remove_file(p).unwrap();
        }
    }
    eprintln!("{:?}", fit_degenerate(&scan, 20, "single frame"));
}

#[test]
fn duplicate_poses_are_refused_or_fit_finite() {
    let dir = tempfile::tempdir().unwrap();
    let scan = fixture(dir.path(), "dup", 6, &[]);
    let poses = frame_files(&scan.join("pose"));
    let first = std::fs::read(&poses[0]).unwrap();
    for p in &poses[1..] {
        std::fs::write(p, &first).unwrap();
    }
    eprintln!("{:?}", fit_degenerate(&scan, 20, "duplicate poses"));
}

#[test]
#[allow(clippy::needless_range_loop)] // row-by-row matrix arithmetic
fn pure_rotation_is_refused_or_fits_finite() {
    let dir = tempfile::tempdir().unwrap();
    let scan = fixture(dir.path(), "rot", 6, &[]);
    let poses = frame_files(&scan.join("pose"));
    // World-to-camera [R | t]: centre C = -R^T t; keep R, set t = -R C0.
    let m0 = read_pose(&poses[0]);
    let c0: [f64; 3] = std::array::from_fn(|j| -(0..3).map(|i| m0[i][j] * m0[i][3]).sum::<f64>());
    for p in &poses {
        let mut m = read_pose(p);
        for i in 0..3 {
            m[i][3] = -(0..3).map(|j| m[i][j] * c0[j]).sum::<f64>();
        }
        write_pose(p, &m);
    }
    // Check the edit: every centre is now c0.
    for p in &poses {
        let m = read_pose(p);
        for j in 0..3 {
            let c = -(0..3).map(|i| m[i][j] * m[i][3]).sum::<f64>();
            assert!((c - c0[j]).abs() < 1e-9);
        }
    }
    eprintln!("{:?}", fit_degenerate(&scan, 20, "pure rotation"));
}

#[test]
fn extreme_intrinsics_are_refused_or_fit_finite() {
    let dir = tempfile::tempdir().unwrap();
    let (w, h) = (80.0, 60.0);
    let cases = [
        ("wide fx = 0.2 w", 0.2 * w, 0.2 * w, 40.0, 30.0),
        ("narrow fx = 20 w", 20.0 * w, 20.0 * w, 40.0, 30.0),
        ("fx != fy", 60.0, 140.0, 40.0, 30.0),
        ("principal point off centre", 67.0, 67.0, 1.45 * w, -0.45 * h),
    ];
    for (i, (what, fx, fy, cx, cy)) in cases.into_iter().enumerate() {
        let scan = fixture(dir.path(), &format!("k{i}"), 4, &[]);
        write_intrinsics(&scan, fx, fy, cx, cy);
        eprintln!("{what}: {:?}", fit_degenerate(&scan, 20, what));
    }
}

/// An instance-id PNG as u16 values (8-bit files are widened).
fn read_ids(path: &Path) -> Vec<u16> {
    match image::open(path).unwrap_or_else(|e| panic!("{}: {e}", path.display())) {
        image::DynamicImage::ImageLuma8(m) => m.into_raw().into_iter().map(u16::from).collect(),
        image::DynamicImage::ImageLuma16(m) => m.into_raw(),
        other => panic!("{}: colour type {:?}", path.display(), other.color()),
    }
}

/// Run `label` with the nerf depth source into `out` and return the masks by frame name.
fn label_masks(scan: &Path, model: &Path, boxes: &Path, out: &Path) -> Vec<(String, Vec<u16>)> {
    let o = bin()
        .arg("label")
        .arg(scan)
        .arg("--boxes")
        .arg(boxes)
        .args(["--source", "nerf", "--model"])
        .arg(model)
        .arg("--out")
        .arg(out)
        .output()
        .unwrap();
    assert!(
        o.status.success(),
        "label {}: {}",
        scan.display(),
        String::from_utf8_lossy(&o.stderr)
    );
    frame_files(&out.join("masks"))
        .into_iter()
        .map(|p| (p.file_stem().unwrap().to_string_lossy().into_owned(), read_ids(&p)))
        .collect()
}

/// Masks scored against the fixture's exact instance masks.
fn scores_against_truth(scan: &Path, masks: &[(String, Vec<u16>)], width: usize) -> MaskScores {
    let mut s = MaskScores::default();
    for (name, mask) in masks {
        s.add(
            mask,
            &read_ids(&scan.join("gt/masks").join(format!("{name}.png"))),
            width,
        );
    }
    s
}

/// The small scene at scales 0.01 and 100 (nerfstudio layout so depth keeps
/// its units), each fitted 150 steps at the fast preset, shared by the tests.
struct Scaled {
    _dir: tempfile::TempDir,
    /// (scale, scan folder, model path)
    fits: Vec<(f64, PathBuf, PathBuf)>,
}

fn scaled_fits() -> &'static Scaled {
    static SCALED: OnceLock<Scaled> = OnceLock::new();
    SCALED.get_or_init(|| {
        let dir = tempfile::tempdir().unwrap();
        let fits = ["0.01", "100"]
            .into_iter()
            .map(|scale| {
                let scan = bin_fixture(dir.path(), &format!("scale{scale}"), scale);
                let model_path = scan.join("model.nlf");
                let o = bin()
                    .arg("fit")
                    .arg(&scan)
                    .args([
                        "--steps",
                        "150",
                        "--preset",
                        "fast",
                        "--holdout",
                        "0",
                        "--seed",
                        "1",
                        "--model",
                    ])
                    .arg(&model_path)
                    .output()
                    .unwrap();
                assert!(
                    o.status.success(),
                    "scale {scale}: {}",
                    String::from_utf8_lossy(&o.stderr)
                );
                (scale.parse().unwrap(), scan, model_path)
            })
            .collect();
        Scaled { _dir: dir, fits }
    })
}

/// A clean 160x120 fixture of the small scene at `scale`, 12 frames, 2 held-out views.
fn bin_fixture(dir: &Path, name: &str, scale: &str) -> PathBuf {
    let out = dir.join(name);
    let o = bin()
        .args([
            "fixture",
            "--scene",
            "small",
            "--width",
            "160",
            "--height",
            "120",
            "--frames",
            "12",
            "--holdout",
            "2",
            "--clean",
        ])
        .args(["--scale", scale, "--layout", "nerfstudio"])
        .arg(&out)
        .output()
        .unwrap();
    assert!(o.status.success(), "fixture: {}", String::from_utf8_lossy(&o.stderr));
    out
}

#[test]
fn tiny_and_huge_scene_scales_fit_without_nan_and_agree() {
    let mut relative = Vec::new();
    for (scale, scan, model_path) in &scaled_fits().fits {
        let model = Model::load(model_path).unwrap();
        assert_model_finite(&model, &format!("scale {scale}"));
        assert_report_finite(&scan.join("model.report.json"), &format!("scale {scale}"));
        let score = score_holdout(&model, scan).unwrap();
        eprintln!("scale {scale}: {score:?}");
        assert!(
            score.psnr.is_finite() && score.depth_mae_m.is_finite(),
            "scale {scale}: {score:?}"
        );
        relative.push(score.depth_mae_m / scale);
    }
    let (small, large) = (relative[0], relative[1]);
    eprintln!("relative depth MAE: scale 0.01 {small:.6}, scale 100 {large:.6}");
    // Bounds, steps and loss widths follow the scale: the same scene gives the
    // same error relative to its size (the fit is scale-invariant up to rounding).
    let (lo, hi) = (small.min(large), small.max(large));
    assert!(
        hi <= 1.02 * lo,
        "relative depth MAE differs: 0.01 -> {small}, 100 -> {large}"
    );
    assert!(
        hi < 0.05,
        "150 steps must place the surface within 5 % of the scene size: {hi}"
    );
}

#[test]
fn tiny_and_huge_scene_scales_give_the_same_label_masks() {
    let dir = tempfile::tempdir().unwrap();
    let mut runs = Vec::new();
    for (scale, scan, model_path) in &scaled_fits().fits {
        // The generator writes boxes.json in the scaled world frame.
        let boxes = nerflabel::boxes::read_boxes(&scan.join("boxes.json")).unwrap();
        let masks = label_masks(
            scan,
            model_path,
            &scan.join("boxes.json"),
            &dir.path().join(format!("labels{scale}")),
        );
        let truth = scores_against_truth(scan, &masks, 160);
        eprintln!(
            "scale {scale}: per object {:?}, mean {:.3}",
            truth.per_object(),
            truth.mean_object_iou()
        );
        runs.push((boxes, masks, truth));
    }
    let (b0, b1) = (&runs[0].0.boxes, &runs[1].0.boxes);
    for (a, b) in b0.iter().zip(b1) {
        assert!(
            (b.center - a.center * 1e4).norm() <= 1e-9 * b.center.coords.norm().max(1.0),
            "box {} centre not scaled",
            a.instance_id
        );
        assert!(
            (b.size - a.size * 1e4).norm() <= 1e-9 * b.size.norm(),
            "box {} size not scaled",
            a.instance_id
        );
    }
    // The masks of the two scales, compared with each other.
    let mut agreement = MaskScores::default();
    let mut labelled = 0;
    assert_eq!(runs[0].1.len(), runs[1].1.len());
    for ((n0, m0), (n1, m1)) in runs[0].1.iter().zip(&runs[1].1) {
        assert_eq!(n0, n1);
        agreement.add(m1, m0, 160);
        labelled += m0.iter().filter(|&&v| v != 0).count();
    }
    let objects = agreement.per_object();
    eprintln!("scale 100 against scale 0.01: per object {objects:?}; {labelled} labelled pixels");
    assert!(
        labelled > 12 * 160 * 120 / 50,
        "masks must not be (nearly) empty: {labelled} pixels"
    );
    for (id, iou) in &objects {
        assert!(
            *iou >= 0.97,
            "instance {id}: masks at scales 0.01 and 100 differ (IoU {iou})"
        );
    }
    // Both are real labels, not the same garbage.
    for (_, _, truth) in &runs {
        assert!(
            truth.mean_object_iou() > 0.5,
            "IoU against the ground truth {}",
            truth.mean_object_iou()
        );
    }
}

/// Photometric geometry needs many more steps than depth-supervised:
/// measured mean object IoU 0.0004 after 300 steps, 0.30 after 600, 0.44
/// after 1000 (box 0.67, ball 0.07, can 0.58), hence ignored in the suite.
#[test]
#[ignore = "1000 training steps (~25 s with --release)"]
fn scan_without_any_depth_still_labels() {
    let dir = tempfile::tempdir().unwrap();
    let scan = dir.path().join("scan");
    let o = bin()
        .args([
            "fixture",
            "--scene",
            "small",
            "--width",
            "160",
            "--height",
            "120",
            "--frames",
            "24",
            "--holdout",
            "0",
            "--clean",
        ])
        .arg(&scan)
        .output()
        .unwrap();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    std::fs::remove_dir_all(scan.join("depth")).unwrap();
    let model_path = dir.path().join("model.nlf");
    let o = bin()
        .arg("fit")
        .arg(&scan)
        .args([
            "--steps",
            "1000",
            "--preset",
            "fast",
            "--holdout",
            "0",
            "--seed",
            "1",
            "--model",
        ])
        .arg(&model_path)
        .output()
        .unwrap();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    assert_model_finite(&Model::load(&model_path).unwrap(), "no depth");
    let masks = label_masks(&scan, &model_path, &scan.join("boxes.json"), &dir.path().join("labels"));
    assert_eq!(masks.len(), 24);
    let s = scores_against_truth(&scan, &masks, 160);
    eprintln!(
        "no depth: per object {:?}, mean {:.3}, frame mIoU {:.3}",
        s.per_object(),
        s.mean_object_iou(),
        s.mean_frame_iou()
    );
    // A broken model (no surface, or floaters in front of everything) scores near 0.
    // Measured 0.49 (box 0.66, ball 0.18, can 0.64); coarse, capped rays
    // without depth (right for the few holes of a scan with depth) gave 0.19.
    assert!(s.mean_object_iou() > 0.4, "no-depth labels IoU {}", s.mean_object_iou());
    assert!(
        s.per_object().values().filter(|&&v| v > 0.5).count() >= 2,
        "{:?}",
        s.per_object()
    );
}

/// A real model file, fitted for a few steps.
fn small_model(dir: &Path) -> (PathBuf, Vec<u8>) {
    let scan = fixture(dir, "m", 4, &[]);
    let model_path = dir.join("model.nlf");
    let o = fit(&scan, &model_path, 3);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let bytes = std::fs::read(&model_path).unwrap();
    (model_path, bytes)
}

#[test]
fn truncated_or_bit_flipped_model_is_rejected_naming_the_file() {
    let dir = tempfile::tempdir().unwrap();
    let (_, bytes) = small_model(dir.path());
    let bad = dir.path().join("damaged.nlf");
    let mut rng = Rng::new(21, 0);
    let mut cuts: Vec<usize> = vec![0, 1, 7, 8, 12, 16, 19, 20, 21, bytes.len() - 4, bytes.len() - 1];
    cuts.extend((0..40).map(|_| rng.below(bytes.len() as u64) as usize));
    for cut in cuts {
        std::fs::write(&bad, &bytes[..cut]).unwrap();
        let err = match std::panic::catch_unwind(|| Model::load(&bad)) {
            Ok(Err(e)) => e.to_string(),
            Ok(Ok(_)) => panic!("truncated at {cut} of {} bytes: accepted", bytes.len()),
            Err(_) => panic!("truncated at {cut}: Model::load panicked"),
        };
        assert!(err.contains("damaged.nlf") && !err.contains('\n'), "cut {cut}: {err}");
    }
    for _ in 0..60 {
        let mut b = bytes.clone();
        let i = rng.below(b.len() as u64) as usize;
        b[i] ^= 1 << rng.below(8);
        std::fs::write(&bad, &b).unwrap();
        let err = match std::panic::catch_unwind(|| Model::load(&bad)) {
            Ok(Err(e)) => e.to_string(),
            Ok(Ok(_)) => panic!("bit flip at byte {i}: accepted"),
            Err(_) => panic!("bit flip at byte {i}: Model::load panicked"),
        };
        assert!(err.contains("damaged.nlf") && !err.contains('\n'), "flip {i}: {err}");
    }
}

#[test]
fn failed_fit_leaves_the_existing_model_untouched() {
    let dir = tempfile::tempdir().unwrap();
    let (model_path, before) = small_model(dir.path());
    let checkpoint = model_path.with_extension("checkpoint");
    let checkpoint_before = std::fs::read(&checkpoint).unwrap();
    // A scan that fails to load: a pose file that is not a matrix.
    let broken = fixture(dir.path(), "broken", 4, &[]);
    std::fs::write(frame_files(&broken.join("pose"))[1].as_path(), "not a pose\n").unwrap();
    let o = fit(&broken, &model_path, 5);
    assert!(!o.status.success(), "the broken scan fitted");
    let stderr = String::from_utf8_lossy(&o.stderr);
    assert!(!stderr.contains("panicked") && stderr.contains("000001"), "{stderr}");
    assert!(
        std::fs::read(&model_path).unwrap() == before,
        "the old model bytes changed"
    );
    // A scan whose intrinsics are invalid (zero focal length).
    let bad_k = fixture(dir.path(), "badk", 4, &[]);
    write_intrinsics(&bad_k, 0.0, 0.0, 40.0, 30.0);
    let o = fit(&bad_k, &model_path, 5);
    assert!(!o.status.success(), "zero focal length fitted");
    assert!(
        std::fs::read(&model_path).unwrap() == before,
        "the old model bytes changed"
    );
    assert!(
        std::fs::read(&checkpoint).unwrap() == checkpoint_before,
        "the old checkpoint changed"
    );
    // No temp files left beside the model.
    let leftovers: Vec<_> = frame_files(dir.path())
        .into_iter()
        .filter(|p| {
            p.is_file()
                && p.extension()
                    .is_none_or(|e| e != "nlf" && e != "json" && e != "checkpoint" && e != "lock")
        })
        .collect();
    assert!(leftovers.is_empty(), "{leftovers:?}");
}
