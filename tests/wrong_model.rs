//! A model is only used with the scan it was fitted to: `label` and
//! `synth` refuse a model whose scan fingerprint (frames, names, sizes,
//! intrinsics, poses) differs from the scan's, unless `--force`.

mod common;

use common::{copy_dir, one_view_poses, run, s, stderr};
use std::path::{Path, PathBuf};

/// Move every camera of a native scan by 0.3 m along x (world-to-camera files).
fn shift_poses(scan: &Path) {
    for entry in std::fs::read_dir(scan.join("pose")).unwrap() {
        let path = entry.unwrap().path();
        let text = std::fs::read_to_string(&path).unwrap();
        let mut rows: Vec<Vec<f64>> = text
            .lines()
            .filter(|l| !l.trim().is_empty())
            .map(|l| l.split_whitespace().map(|v| v.parse().unwrap()).collect())
            .collect();
        rows[0][3] += 0.3;
        let text: String = rows
            .iter()
            .map(|r| r.iter().map(|v| format!("{v:.17e}")).collect::<Vec<_>>().join(" ") + "\n")
            .collect();
        std::fs::write(&path, text).unwrap();
    }
}

#[test]
fn a_model_of_the_scan_before_its_poses_moved_is_refused_unless_forced() {
    // Regression: after shifting every pose by 0.3 m, label exited 0 and mask IoU fell from 0.615 to 0.29.
    let dir = tempfile::tempdir().unwrap();
    let scan: PathBuf = dir.path().join("scan");
    copy_dir(&Path::new(env!("CARGO_MANIFEST_DIR")).join("fixtures/small"), &scan);
    let fit = run(&["fit", s(&scan), "--steps", "2", "--preset", "fast", "--holdout", "0"]);
    assert!(fit.status.success(), "{}", stderr(&fit));
    let boxes = scan.join("boxes.json");
    let out = dir.path().join("labels");
    let label = |extra: &[&str]| {
        let mut args = vec!["label", s(&scan), "--boxes", s(&boxes), "--out", s(&out)];
        args.extend_from_slice(extra);
        run(&args)
    };
    assert!(label(&[]).status.success(), "the model of this scan is accepted");

    shift_poses(&scan);
    let o = label(&[]);
    assert!(!o.status.success());
    let msg = stderr(&o);
    assert!(
        msg.contains("fitted to another scan") && msg.contains("other poses") && msg.contains("--force"),
        "{msg}"
    );
    let poses = dir.path().join("poses.json");
    one_view_poses(&poses);
    let views = dir.path().join("v.parquet");
    let synth = |extra: &[&str]| {
        let mut args = vec![
            "synth",
            s(&scan),
            "--poses",
            s(&poses),
            "--out",
            s(&views),
            "--overwrite",
        ];
        args.extend_from_slice(extra);
        run(&args)
    };
    let o = synth(&[]);
    assert!(
        !o.status.success() && stderr(&o).contains("fitted to another scan"),
        "{}",
        stderr(&o)
    );

    // --force uses it with a warning; the sensor source needs no model at all.
    let o = label(&["--force"]);
    assert!(
        o.status.success() && stderr(&o).contains("using it anyway"),
        "{}",
        stderr(&o)
    );
    let o = synth(&["--force"]);
    assert!(
        o.status.success() && stderr(&o).contains("using it anyway"),
        "{}",
        stderr(&o)
    );
    let o = label(&["--source", "sensor"]);
    assert!(o.status.success(), "{}", stderr(&o));

    // A scan with another frame count says so.
    std::fs::remove_file(scan.join("rgb/000023.png")).unwrap();
    std::fs::remove_file(scan.join("pose/000023.txt")).unwrap();
    std::fs::remove_file(scan.join("depth/000023.png")).unwrap();
    let o = label(&[]);
    assert!(
        stderr(&o).contains("fitted to 24 frames, this scan has 23"),
        "{}",
        stderr(&o)
    );
}

#[test]
fn messages_say_what_is_true_for_corrupt_models_missing_boxes_and_the_sensor_source() {
    let dir = tempfile::tempdir().unwrap();
    let scan: PathBuf = dir.path().join("scan");
    copy_dir(&Path::new(env!("CARGO_MANIFEST_DIR")).join("fixtures/small"), &scan);
    let boxes = scan.join("boxes.json");
    let out = dir.path().join("labels");
    // Regression: the first line said "run nerflabel fit first", the cause was on the second.
    let model = dir.path().join("corrupt.nlf");
    std::fs::write(&model, b"NERFLBL\0garbage").unwrap();
    let o = run(&[
        "label",
        s(&scan),
        "--boxes",
        s(&boxes),
        "--model",
        s(&model),
        "--out",
        s(&out),
    ]);
    let first = stderr(&o).lines().next().unwrap_or_default().to_string();
    assert!(
        !o.status.success() && first.contains("corrupt.nlf") && !first.contains("fit` first"),
        "{}",
        stderr(&o)
    );
    let o = run(&[
        "label",
        s(&scan),
        "--boxes",
        s(&boxes),
        "--model",
        s(&dir.path().join("none.nlf")),
        "--out",
        s(&out),
    ]);
    assert!(
        stderr(&o).contains("no model here: run `nerflabel fit` first"),
        "{}",
        stderr(&o)
    );
    // Regression: the sensor source printed "rendered 16.1 % of the pixels".
    let o = run(&[
        "label",
        s(&scan),
        "--boxes",
        s(&boxes),
        "--source",
        "sensor",
        "--out",
        s(&out),
    ]);
    let stdout = String::from_utf8_lossy(&o.stdout);
    assert!(
        o.status.success() && stdout.contains("classified") && !stdout.contains("rendered"),
        "{stdout}"
    );
    // Regression: synth without any boxes wrote empty masks without a word.
    std::fs::remove_file(&boxes).unwrap();
    let fit = run(&["fit", s(&scan), "--steps", "2", "--preset", "fast", "--holdout", "0"]);
    assert!(fit.status.success(), "{}", stderr(&fit));
    let poses = dir.path().join("poses.json");
    one_view_poses(&poses);
    let o = run(&[
        "synth",
        s(&scan),
        "--poses",
        s(&poses),
        "--out",
        s(&dir.path().join("v.parquet")),
    ]);
    assert!(
        o.status.success() && stderr(&o).contains("every mask will be empty"),
        "{}",
        stderr(&o)
    );
}
