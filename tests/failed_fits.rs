//! Fits that cannot train anything fail up front or at the end with a
//! message, never exit 0 with a useless model.

use std::path::{Path, PathBuf};
use std::process::{Command, Output};

fn run(args: &[&str]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_nerflabel"))
        .args(args)
        .output()
        .expect("the binary runs")
}

fn stderr(o: &Output) -> String {
    String::from_utf8_lossy(&o.stderr).into_owned()
}

fn small_scan(dir: &Path) -> PathBuf {
    let scan = dir.join("scan");
    std::fs::create_dir_all(&scan).unwrap();
    let from = Path::new(env!("CARGO_MANIFEST_DIR")).join("fixtures/small");
    for sub in ["rgb", "depth", "pose"] {
        std::fs::create_dir_all(scan.join(sub)).unwrap();
        for entry in std::fs::read_dir(from.join(sub)).unwrap() {
            let entry = entry.unwrap();
            std::fs::copy(entry.path(), scan.join(sub).join(entry.file_name())).unwrap();
        }
    }
    std::fs::copy(from.join("intrinsics.txt"), scan.join("intrinsics.txt")).unwrap();
    scan
}

#[test]
fn non_finite_or_negative_depth_weights_are_refused_before_work() {
    let dir = tempfile::tempdir().unwrap();
    let scan = small_scan(dir.path());
    let model = dir.path().join("m.nlf");
    for bad in ["nan", "inf", "-1"] {
        let flag = format!("--lambda-depth={bad}");
        let o = run(&[
            "fit",
            scan.to_str().unwrap(),
            "--steps",
            "2",
            &flag,
            "--model",
            model.to_str().unwrap(),
        ]);
        assert!(!o.status.success(), "--lambda-depth {bad} must be refused");
        assert!(
            stderr(&o).contains("--lambda-depth must be a finite number >= 0"),
            "{}",
            stderr(&o)
        );
        assert!(!model.exists());
    }
}

#[test]
fn bounds_away_from_the_scene_are_refused_naming_bbox_txt() {
    // Regression: bbox.txt 100 m away from the scene gave a fit of 30
    // skipped batches that exited 0 and wrote a model.
    let dir = tempfile::tempdir().unwrap();
    let scan = small_scan(dir.path());
    std::fs::write(scan.join("bbox.txt"), "100 100 100 101 101 101\n").unwrap();
    let model = dir.path().join("m.nlf");
    let o = run(&[
        "fit",
        scan.to_str().unwrap(),
        "--steps",
        "2",
        "--model",
        model.to_str().unwrap(),
    ]);
    assert!(!o.status.success());
    let msg = stderr(&o);
    assert!(msg.contains("bbox.txt") && msg.contains("miss the scene"), "{msg}");
    assert!(!model.exists());
    // Bounds around the scene are fine.
    std::fs::write(scan.join("bbox.txt"), "-3 -3 -3 3 3 3\n").unwrap();
    let o = run(&[
        "fit",
        scan.to_str().unwrap(),
        "--steps",
        "2",
        "--preset",
        "fast",
        "--model",
        model.to_str().unwrap(),
    ]);
    assert!(o.status.success(), "{}", stderr(&o));
}
