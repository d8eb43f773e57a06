//! Seeded byte-mutation fuzzing of every parser that reads outside text or
//! bytes: native `intrinsics.txt` and pose files, nerfstudio
//! `transforms.json`, TUM `rgb.txt` / `depth.txt` / `groundtruth.txt`, COLMAP `cameras.txt` / `images.txt`,
//! `boxes.json`, the box files `boxes import` reads (labelCloud, KITTI,
//! CVAT and the KITTI calibration), and model files.
//!
//! Each iteration mutates a valid file (bit flips, random bytes, inserted
//! tokens such as `nan` or `1e400`, deleted or duplicated ranges,
//! truncation), loads it, and asserts: no panic, and an error (if any) is one
//! non-empty line. The normal suite runs `ITERS` iterations per parser; the
//! ignored `*_long` variants run `NERFLABEL_FUZZ_ITERS` (default 20 000):
//!
//! `NERFLABEL_FUZZ_ITERS=100000 cargo test --release --test fuzz_parsers -- --ignored`

use nerflabel::boxes::interop::{import_boxes, ImportFormat};
use nerflabel::boxes::{read_boxes, BoxClassifier};
use nerflabel::nerf::model_file::Model;
use nerflabel::rng::Rng;
use nerflabel::scan::{load, Layout, LoadOptions};
use std::panic::{catch_unwind, AssertUnwindSafe};
use std::path::{Path, PathBuf};
use std::process::Command;

/// Iterations per parser in the normal suite.
const ITERS: usize = 300;

fn long_iters() -> usize {
    std::env::var("NERFLABEL_FUZZ_ITERS")
        .ok()
        .and_then(|s| s.parse().ok())
        .unwrap_or(20_000)
}

/// Tokens that tend to reach edge cases of number and JSON parsing.
const TOKENS: &[&str] = &[
    "nan",
    "NaN",
    "inf",
    "-inf",
    "1e400",
    "-1e400",
    "0",
    "-0",
    "-1",
    "1e-320",
    "18446744073709551616",
    "99999999999999999999",
    "\n",
    " ",
    "\t",
    "\0",
    "#",
    "\"",
    "{",
    "}",
    "[",
    "]",
    ",",
    ":",
    "null",
    "true",
    "\u{feff}",
    "é",
    "\r\n",
    "0x10",
    "4294967296",
    "[[1,0,0,0],[0,1,0,0],[0,0,1,0],[0,0,0,1]]",
];

/// Apply 1-4 random mutations to `bytes`.
fn mutate(bytes: &[u8], rng: &mut Rng) -> Vec<u8> {
    let mut b = bytes.to_vec();
    for _ in 0..1 + rng.below(4) {
        let len = b.len() as u64;
        let at = if len == 0 { 0 } else { rng.below(len) as usize };
        match rng.below(8) {
            0 if len > 0 => b[at] ^= 1 << rng.below(8),
            1 if len > 0 => b[at] = rng.below(256) as u8,
            2 => {
                let tok = TOKENS[rng.below(TOKENS.len() as u64) as usize].as_bytes();
                b.splice(at..at, tok.iter().copied());
            }
            3 if len > 0 => {
                let end = (at + 1 + rng.below(16) as usize).min(b.len());
                b.drain(at..end);
            }
            4 => b.truncate(at),
            5 if len > 0 => {
                let end = (at + 1 + rng.below(64) as usize).min(b.len());
                let chunk: Vec<u8> = b[at..end].to_vec();
                let to = rng.below(b.len() as u64 + 1) as usize;
                b.splice(to..to, chunk);
            }
            6 if len > 0 && b[at].is_ascii_digit() => b[at] = b'0' + rng.below(10) as u8,
            _ => {
                // Replace a digit run with a random token (keeps the structure).
                let tok = TOKENS[rng.below(TOKENS.len() as u64) as usize].as_bytes();
                let end = (at..b.len()).find(|&i| !b[i].is_ascii_digit()).unwrap_or(b.len());
                b.splice(at..end.max(at), tok.iter().copied());
            }
        }
    }
    b
}

/// Run `f`; fail on a panic or a multi-line or empty error message.
fn no_panic_one_line<T, E: std::fmt::Display>(what: &str, f: impl FnOnce() -> Result<T, E>) -> bool {
    match catch_unwind(AssertUnwindSafe(f)) {
        Err(_) => panic!("{what}: parser panicked"),
        Ok(Ok(_)) => true,
        Ok(Err(e)) => {
            let msg = e.to_string();
            assert!(!msg.trim().is_empty(), "{what}: empty error");
            assert!(!msg.contains('\n'), "{what}: multi-line error:\n{msg}");
            false
        }
    }
}

fn fixture(dir: &Path, name: &str, extra: &[&str]) -> PathBuf {
    let out = dir.join(name);
    let o = Command::new(env!("CARGO_BIN_EXE_nerflabel"))
        .args([
            "fixture",
            "--scene",
            "small",
            "--width",
            "16",
            "--height",
            "12",
            "--frames",
            "3",
            "--holdout",
            "0",
            "--clean",
        ])
        .args(extra)
        .arg(&out)
        .output()
        .unwrap();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    out
}

/// Mutate `file` inside the scan `root` `iters` times, loading the scan each
/// time with `layout`; the original file is restored afterwards.
fn fuzz_scan_file(root: &Path, file: &Path, layout: Layout, iters: usize, seed: u64) {
    let options = LoadOptions {
        layout: Some(layout),
        fix_poses: false,
    };
    assert!(
        load(root, &options).is_ok(),
        "the unmutated scan must load: {:?}",
        load(root, &options).err().map(|e| e.to_string())
    );
    let original = std::fs::read(file).unwrap();
    let mut rng = Rng::new(seed, 0);
    let mut accepted = 0;
    for i in 0..iters {
        let bytes = mutate(&original, &mut rng);
        std::fs::write(file, &bytes).unwrap();
        let what = format!(
            "{} iteration {i}: {:?}",
            file.display(),
            String::from_utf8_lossy(&bytes)
        );
        if no_panic_one_line(&what, || load(root, &options)) {
            accepted += 1;
        }
    }
    std::fs::write(file, &original).unwrap();
    eprintln!("{}: {accepted} of {iters} mutations still loaded", file.display());
    assert!(
        accepted < iters,
        "{}: no mutation was ever rejected; the fuzzer does not reach the parser",
        file.display()
    );
}

fn fuzz_native(iters: usize) {
    let dir = tempfile::tempdir().unwrap();
    let scan = fixture(dir.path(), "native", &[]);
    fuzz_scan_file(&scan, &scan.join("intrinsics.txt"), Layout::Native, iters, 1);
    fuzz_scan_file(&scan, &scan.join("pose/000001.txt"), Layout::Native, iters, 2);
}

fn fuzz_nerfstudio(iters: usize) {
    let dir = tempfile::tempdir().unwrap();
    let scan = fixture(dir.path(), "ns", &["--layout", "nerfstudio"]);
    fuzz_scan_file(&scan, &scan.join("transforms.json"), Layout::Nerfstudio, iters, 3);
}

/// A TUM scan built from a native fixture: the same images, timestamps 0.1 s
/// apart, camera-to-world translations along x, identity rotations.
fn tum_scan(dir: &Path) -> PathBuf {
    let scan = fixture(dir, "tum", &[]);
    let (mut rgb, mut depth, mut gt) = (
        String::from("# colour images\n"),
        String::from("# depth\n"),
        String::from("# ground truth\n"),
    );
    for i in 0..3 {
        let t = 1305031102.0 + 0.1 * i as f64;
        rgb.push_str(&format!("{t:.6} rgb/{i:06}.png\n"));
        depth.push_str(&format!("{:.6} depth/{i:06}.png\n", t + 0.004));
        gt.push_str(&format!(
            "{:.4} {} 0.0 -1.5 0.0 0.0 0.0 1.0\n",
            t - 0.002,
            0.1 * i as f64
        ));
    }
    std::fs::write(scan.join("rgb.txt"), rgb).unwrap();
    std::fs::write(scan.join("depth.txt"), depth).unwrap();
    std::fs::write(scan.join("groundtruth.txt"), gt).unwrap();
    std::fs::remove_dir_all(scan.join("pose")).unwrap();
    scan
}

fn fuzz_tum(iters: usize) {
    let dir = tempfile::tempdir().unwrap();
    let scan = tum_scan(dir.path());
    fuzz_scan_file(&scan, &scan.join("rgb.txt"), Layout::Tum, iters, 4);
    fuzz_scan_file(&scan, &scan.join("groundtruth.txt"), Layout::Tum, iters, 5);
}

/// A COLMAP text model built from a native fixture: images renamed into
/// `images/`, world-to-camera poses as quaternions, one PINHOLE camera.
fn colmap_scan(dir: &Path) -> PathBuf {
    let scan = fixture(dir, "colmap", &[]);
    let k = std::fs::read_to_string(scan.join("intrinsics.txt")).unwrap();
    let k: Vec<f64> = k.split_whitespace().map(|v| v.parse().unwrap()).collect();
    std::fs::create_dir_all(scan.join("sparse/0")).unwrap();
    std::fs::write(
        scan.join("sparse/0/cameras.txt"),
        format!("# cameras\n1 PINHOLE 16 12 {} {} {} {}\n", k[0], k[4], k[2], k[5]),
    )
    .unwrap();
    std::fs::rename(scan.join("rgb"), scan.join("images")).unwrap();
    let mut images = String::from("# images\n");
    for i in 0..3 {
        images.push_str(&format!("{} 1 0 0 0 {} 0 1.5 1 {i:06}.png\n\n", 3 - i, -0.1 * i as f64));
    }
    std::fs::write(scan.join("sparse/0/images.txt"), images).unwrap();
    std::fs::remove_dir_all(scan.join("pose")).unwrap();
    scan
}

fn fuzz_colmap(iters: usize) {
    let dir = tempfile::tempdir().unwrap();
    let scan = colmap_scan(dir.path());
    fuzz_scan_file(&scan, &scan.join("sparse/0/cameras.txt"), Layout::Colmap, iters, 8);
    fuzz_scan_file(&scan, &scan.join("sparse/0/images.txt"), Layout::Colmap, iters, 9);
}

fn fuzz_tum_depth(iters: usize) {
    let dir = tempfile::tempdir().unwrap();
    let scan = tum_scan(dir.path());
    fuzz_scan_file(&scan, &scan.join("depth.txt"), Layout::Tum, iters, 7);
}

/// The committed fixture's boxes.json (rotation matrices) plus boxes given
/// by a quaternion and by nothing (identity), as one file.
fn boxes_text() -> String {
    let path = Path::new(env!("CARGO_MANIFEST_DIR")).join("fixtures/small/boxes.json");
    let mut json: serde_json::Value = serde_json::from_slice(&std::fs::read(path).unwrap()).unwrap();
    let list = json["boxes"].as_array_mut().unwrap();
    list.push(serde_json::json!({"label": "mug", "center": [0.41, -0.12, 0.05], "size": [0.1, 0.12, 0.11], "quaternion": [0, 0, 0.38268343, 0.92387953]}));
    list.push(serde_json::json!({"label": "sheet", "center": [0, 0, 0], "size": [1, 1, 0]}));
    serde_json::to_string_pretty(&json).unwrap()
}

fn fuzz_boxes(iters: usize) {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("boxes.json");
    let original = boxes_text().into_bytes();
    std::fs::write(&path, &original).unwrap();
    assert_eq!(read_boxes(&path).unwrap().boxes.len(), 5);
    let mut rng = Rng::new(8, 0);
    let mut accepted = 0;
    for i in 0..iters {
        let bytes = mutate(&original, &mut rng);
        std::fs::write(&path, &bytes).unwrap();
        let what = format!("boxes.json iteration {i}: {:?}", String::from_utf8_lossy(&bytes));
        let result =
            catch_unwind(AssertUnwindSafe(|| read_boxes(&path))).unwrap_or_else(|_| panic!("{what}: parser panicked"));
        match result {
            Err(e) => {
                let msg = e.to_string();
                assert!(
                    msg.starts_with(&path.display().to_string()) && !msg.contains('\n'),
                    "{what}: {msg}"
                );
            }
            Ok(set) => {
                accepted += 1;
                // An accepted file holds usable boxes: finite, non-negative
                // sizes, proper rotations, ids 1..n, known categories.
                for (k, b) in set.boxes.iter().enumerate() {
                    assert_eq!(b.instance_id as usize, k + 1, "{what}");
                    assert!(
                        b.center.iter().all(|x| x.is_finite())
                            && b.size.iter().all(|x| x.is_finite())
                            && b.size.min() >= 0.0,
                        "{what}: {b:?}"
                    );
                    let r = b.rotation.matrix();
                    assert!(
                        (r.transpose() * r - nalgebra::Matrix3::identity()).amax() <= 1e-9,
                        "{what}: {r:?}"
                    );
                    assert!((r.determinant() - 1.0).abs() < 1e-9, "{what}: {r:?}");
                    assert!(
                        !b.label.trim().is_empty() && set.category_id(&b.label).is_some(),
                        "{what}"
                    );
                }
                // The classifier puts each box centre into some box (its own or a smaller one).
                let classifier = catch_unwind(AssertUnwindSafe(|| BoxClassifier::new(&set)))
                    .unwrap_or_else(|_| panic!("{what}: classifier panicked"));
                for b in &set.boxes {
                    assert_ne!(
                        classifier.classify(&b.center),
                        0,
                        "{what}: centre of box {} in no box",
                        b.instance_id
                    );
                }
            }
        }
    }
    eprintln!("boxes.json: {accepted} of {iters} mutations still parsed");
    assert!(
        accepted < iters,
        "no mutation was ever rejected; the fuzzer does not reach the parser"
    );
}

/// A real model file from a 2-step fit of a tiny fixture.
fn model_bytes(dir: &Path) -> Vec<u8> {
    let scan = fixture(dir, "m", &[]);
    let path = dir.join("model.nlf");
    let o = Command::new(env!("CARGO_BIN_EXE_nerflabel"))
        .arg("fit")
        .arg(&scan)
        .args(["--steps", "2", "--holdout", "0", "--model"])
        .arg(&path)
        .output()
        .unwrap();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    std::fs::read(path).unwrap()
}

fn fuzz_model(iters: usize) {
    let dir = tempfile::tempdir().unwrap();
    let original = model_bytes(dir.path());
    let path = Path::new("fuzzed.nlf");
    assert!(Model::from_bytes(&original, path).is_ok());
    let mut rng = Rng::new(6, 0);
    let (mut accepted_raw, mut accepted_fixed) = (0, 0);
    for i in 0..iters {
        // Mutations of the whole file (caught by magic, version or checksum)...
        let raw = mutate(&original, &mut rng);
        if no_panic_one_line(&format!("model iteration {i} (raw)"), || Model::from_bytes(&raw, path)) && raw != original
        {
            accepted_raw += 1;
        }
        // ...and of the header and sections with the checksum recomputed, so
        // the header JSON and section lengths are parsed.
        let header_end = 16 + u32::from_le_bytes([original[12], original[13], original[14], original[15]]) as usize;
        let mut body = original[..original.len() - 4].to_vec();
        let focus = if rng.below(2) == 0 {
            0..header_end.min(body.len())
        } else {
            0..body.len()
        };
        let mutated = mutate(&body[focus.clone()], &mut rng);
        body.splice(focus, mutated);
        if rng.below(4) == 0 {
            // Also a wrong header length now and then.
            let n = rng.below(body.len() as u64 * 2 + 1) as u32;
            if body.len() >= 16 {
                body[12..16].copy_from_slice(&n.to_le_bytes());
            }
        }
        let crc = crc32fast::hash(&body);
        body.extend_from_slice(&crc.to_le_bytes());
        let what = format!("model iteration {i} (checksum fixed)");
        let ok = match catch_unwind(AssertUnwindSafe(|| Model::from_bytes(&body, path))) {
            Err(_) => panic!("{what}: Model::from_bytes panicked"),
            Ok(Ok(model)) => {
                // Accepted files must hold a usable, consistent model.
                let bytes = model.to_bytes();
                assert!(
                    Model::from_bytes(&bytes, path).is_ok(),
                    "{what}: accepted model does not round-trip"
                );
                true
            }
            Ok(Err(e)) => {
                let msg = e.to_string();
                assert!(msg.contains("fuzzed.nlf") && !msg.contains('\n'), "{what}: {msg}");
                false
            }
        };
        accepted_fixed += ok as usize;
    }
    eprintln!("model: {accepted_raw} raw and {accepted_fixed} checksum-fixed mutations of {iters} accepted");
    assert_eq!(accepted_raw, 0, "a mutated model passed the checksum");
}

#[test]
fn fuzz_native_intrinsics_and_pose_files() {
    fuzz_native(ITERS);
}

#[test]
fn fuzz_nerfstudio_transforms_json() {
    fuzz_nerfstudio(ITERS);
}

#[test]
fn fuzz_tum_rgb_and_groundtruth_lists() {
    fuzz_tum(ITERS);
}

#[test]
fn fuzz_colmap_cameras_and_images() {
    fuzz_colmap(ITERS);
}

#[test]
fn fuzz_tum_depth_list() {
    fuzz_tum_depth(ITERS);
}

#[test]
fn fuzz_boxes_json() {
    fuzz_boxes(ITERS);
}

/// Valid files of each `boxes import` format (and a KITTI calibration).
const IMPORTS: [(&str, ImportFormat, &str); 4] = [
    (
        "cloud.json",
        ImportFormat::Labelcloud,
        r#"{"folder": "p", "filename": "cloud.ply", "path": "p/cloud.ply", "objects": [
            {"name": "box", "centroid": {"x": -0.2, "y": 0.15, "z": 0.08}, "dimensions": {"length": 0.31, "width": 0.21, "height": 0.15}, "rotations": {"x": 0, "y": 0.1, "z": 0.52}},
            {"name": "can", "centroid": {"x": 0, "y": -0.25, "z": 0.13}, "dimensions": {"length": 0.17, "width": 0.17, "height": 0.25}, "rotations": {"x": 0, "y": 0, "z": -3.1}}]}"#,
    ),
    (
        "000001.txt",
        ImportFormat::Kitti,
        "Car 0.00 0 1.85 387.63 181.54 423.81 203.12 1.67 1.87 3.69 -16.53 2.39 58.49 1.57\n\
         DontCare -1 -1 -10 503.89 169.71 590.61 190.13 -1 -1 -1 -1000 -1000 -1000 -10\n\
         Pedestrian 0.00 0 -0.20 712.40 143.00 810.73 307.92 1.89 0.48 1.20 1.84 1.47 8.41 0.01 0.98\n",
    ),
    (
        "c.pcd.json",
        ImportFormat::Cvat,
        r#"{"description": "", "key": "k", "tags": [], "objects": [{"key": "o1", "classTitle": "chair", "tags": []}],
            "figures": [{"key": "f1", "objectKey": "o1", "geometryType": "cuboid_3d", "geometry": {
              "position": {"x": 1, "y": 2, "z": 0.5}, "rotation": {"x": 0, "y": 0, "z": 1.57}, "dimensions": {"x": 0.5, "y": 0.6, "z": 0.9}}}]}"#,
    ),
    (
        "calib.txt",
        ImportFormat::Kitti,
        "0 0 1 1\n-1 0 0 2\n0 -1 0 3\n0 0 0 1\n",
    ),
];

fn fuzz_imports(iters: usize) {
    let dir = tempfile::tempdir().unwrap();
    let kitti = dir.path().join("intact.txt");
    std::fs::write(&kitti, IMPORTS[1].2).unwrap();
    for (k, (name, format, text)) in IMPORTS.iter().enumerate() {
        let path = dir.path().join(name);
        std::fs::write(&path, text).unwrap();
        let calib = *name == "calib.txt";
        // The calibration is fuzzed beside an intact KITTI file.
        let run = || {
            if calib {
                import_boxes(&kitti, *format, Some(&path))
            } else {
                import_boxes(&path, *format, None)
            }
        };
        assert!(run().is_ok(), "{name}: the valid file imports");
        let mut rng = Rng::new(21 + k as u64, 0);
        for i in 0..iters {
            let bytes = mutate(text.as_bytes(), &mut rng);
            std::fs::write(&path, &bytes).unwrap();
            let what = format!("{name} iteration {i}: {:?}", String::from_utf8_lossy(&bytes));
            if let Ok(imported) = catch_unwind(AssertUnwindSafe(run)).unwrap_or_else(|_| panic!("{what}: panicked")) {
                for b in &imported.boxes.boxes {
                    let r = b.rotation.matrix();
                    assert!(b.center.iter().all(|x| x.is_finite()) && b.size.min() >= 0.0, "{what}");
                    assert!(
                        (r.transpose() * r - nalgebra::Matrix3::identity()).amax() <= 1e-9,
                        "{what}"
                    );
                }
            } else {
                no_panic_one_line(&what, run);
            }
        }
    }
}

#[test]
fn fuzz_box_imports_and_kitti_calibration() {
    fuzz_imports(ITERS);
}

#[test]
fn fuzz_model_file_bytes() {
    fuzz_model(ITERS);
}

#[test]
#[ignore = "long fuzz run; iterations from NERFLABEL_FUZZ_ITERS"]
fn fuzz_native_long() {
    fuzz_native(long_iters());
}

#[test]
#[ignore = "long fuzz run; iterations from NERFLABEL_FUZZ_ITERS"]
fn fuzz_nerfstudio_long() {
    fuzz_nerfstudio(long_iters());
}

#[test]
#[ignore = "long fuzz run; iterations from NERFLABEL_FUZZ_ITERS"]
fn fuzz_tum_long() {
    fuzz_tum(long_iters());
}

#[test]
#[ignore = "long fuzz run; iterations from NERFLABEL_FUZZ_ITERS"]
fn fuzz_model_long() {
    fuzz_model(long_iters());
}

#[test]
#[ignore = "long fuzz run; iterations from NERFLABEL_FUZZ_ITERS"]
fn fuzz_tum_depth_long() {
    fuzz_tum_depth(long_iters());
}

#[test]
#[ignore = "long fuzz run; iterations from NERFLABEL_FUZZ_ITERS"]
fn fuzz_box_imports_long() {
    fuzz_imports(long_iters());
}

#[test]
#[ignore = "long fuzz run; iterations from NERFLABEL_FUZZ_ITERS"]
fn fuzz_boxes_long() {
    fuzz_boxes(long_iters());
}
