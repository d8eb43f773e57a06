//! Helpers shared by the end-to-end tests: copies of the committed fixture
//! and running the binary.
#![allow(dead_code)]

pub mod annotate;
pub mod batch;

use std::path::{Path, PathBuf};
use std::process::{Command, Output};

/// Copy a folder tree.
pub fn copy_dir(from: &Path, to: &Path) {
    std::fs::create_dir_all(to).unwrap();
    for entry in std::fs::read_dir(from).unwrap() {
        let entry = entry.unwrap();
        let target = to.join(entry.file_name());
        if entry.file_type().unwrap().is_dir() {
            copy_dir(&entry.path(), &target);
        } else {
            std::fs::copy(entry.path(), target).unwrap();
        }
    }
}

/// The committed small fixture (24 frames, 160x120, exact masks in gt/).
pub fn small_fixture() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("fixtures/small")
}

/// A copy of the small fixture at `dir/scan`.
pub fn small_scan(dir: &Path) -> PathBuf {
    let scan = dir.join("scan");
    copy_dir(&small_fixture(), &scan);
    scan
}

/// A copy of the small fixture at `dir/scan` with the model of `fit SCAN
/// --steps 300 --seed 1` and its report in SCAN/nerflabel/. The fit runs
/// once per build of the binary and state of the fixture (their sizes and
/// time stamps name the cache in the target's test folder) and every test that needs it copies it: the
/// fit is deterministic, so each would have made the same model.
pub fn small_scan_fitted(dir: &Path) -> PathBuf {
    let scan = small_scan(dir);
    let stamp = |path: &Path| {
        let meta = std::fs::metadata(path).unwrap();
        let modified = meta
            .modified()
            .ok()
            .and_then(|t| t.duration_since(std::time::UNIX_EPOCH).ok());
        format!("{}-{}", meta.len(), modified.map_or(0, |d| d.as_nanos()))
    };
    let key = format!(
        "small-300-steps-{}-{}",
        stamp(Path::new(env!("CARGO_BIN_EXE_nerflabel"))),
        stamp(&small_fixture().join("gt/meta.json"))
    );
    let cache = Path::new(env!("CARGO_TARGET_TMPDIR")).join(key);
    let files = ["model.nlf", "model.report.json"];
    if !cache.join(files[1]).is_file() {
        // Fit in a scan copy of its own, then move the files into place
        // (a concurrent test doing the same only wastes its time).
        let work = tempfile::tempdir_in(env!("CARGO_TARGET_TMPDIR")).unwrap();
        let fresh = small_scan(work.path());
        let fit = run(&["fit", s(&fresh), "--steps", "300", "--seed", "1"]);
        assert!(fit.status.success(), "{}", stderr(&fit));
        let staged = work.path().join("cache");
        std::fs::create_dir_all(&staged).unwrap();
        for f in files {
            std::fs::copy(fresh.join("nerflabel").join(f), staged.join(f)).unwrap();
        }
        let _ = std::fs::rename(&staged, &cache);
    }
    std::fs::create_dir_all(scan.join("nerflabel")).unwrap();
    for f in files {
        std::fs::copy(cache.join(f), scan.join("nerflabel").join(f)).unwrap();
    }
    scan
}

/// Run the binary with `args`.
pub fn run(args: &[&str]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_nerflabel"))
        .args(args)
        .output()
        .expect("the binary runs")
}

/// `label SCAN --boxes SCAN/boxes.json --source sensor --out OUT EXTRA...`.
pub fn label_sensor(scan: &Path, out: &Path, extra: &[&str]) -> Output {
    let boxes = scan.join("boxes.json");
    let mut args = vec![
        "label",
        s(scan),
        "--boxes",
        s(&boxes),
        "--source",
        "sensor",
        "--out",
        s(out),
    ];
    args.extend_from_slice(extra);
    run(&args)
}

pub fn stderr(o: &Output) -> String {
    String::from_utf8_lossy(&o.stderr).into_owned()
}

pub fn s(p: &Path) -> &str {
    p.to_str().unwrap()
}

/// A `--poses` file with one 16x12 view from the identity pose (a model of
/// a few steps has no geometry to sample views around).
pub fn one_view_poses(path: &Path) {
    let identity = [
        [1.0, 0.0, 0.0, 0.0],
        [0.0, 1.0, 0.0, 0.0],
        [0.0, 0.0, 1.0, 0.0],
        [0.0, 0.0, 0.0, 1.0],
    ];
    let view = serde_json::json!({"views": [{"camera_to_world": identity, "intrinsics": [20.0, 20.0, 7.5, 5.5], "width": 16, "height": 12}]});
    std::fs::write(path, view.to_string()).unwrap();
}
