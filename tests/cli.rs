//! The real binary: help text, bad input, `info` on the shared real scan,
//! and the committed fixture staying reproducible.

use nalgebra::Point3;
use std::path::{Path, PathBuf};
use std::process::{Command, Output};

fn nerflabel(args: &[&str]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_nerflabel"))
        .args(args)
        .output()
        .expect("the binary runs")
}

fn shared_data() -> Option<PathBuf> {
    let dir = std::env::var_os("NERFLABEL_SHARED_DATA")
        .map(PathBuf::from)
        .unwrap_or_else(|| Path::new(env!("CARGO_MANIFEST_DIR")).join("../shared/data"));
    if dir.exists() {
        Some(dir)
    } else {
        eprintln!("skipping: {} is absent", dir.display());
        None
    }
}

#[test]
fn help_lists_every_subcommand() {
    let out = nerflabel(&["--help"]);
    assert!(out.status.success());
    let text = String::from_utf8_lossy(&out.stdout).to_string();
    insta::assert_snapshot!("help", text);
    for cmd in [
        "info", "cloud", "fixture", "demo", "fit", "report", "label", "synth", "boxes", "batch",
    ] {
        assert!(text.contains(cmd), "{cmd} missing from --help");
    }
}

#[test]
fn missing_scan_folder_is_one_clear_error_with_nonzero_exit() {
    let out = nerflabel(&["info", "/definitely/not/here"]);
    assert!(!out.status.success());
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(err.contains("/definitely/not/here"), "{err}");
    assert!(err.contains("does not exist"), "{err}");
    assert!(!err.contains("panicked"), "{err}");
}

#[test]
fn threads_sets_the_worker_count_and_zero_is_refused() {
    let fixture = Path::new(env!("CARGO_MANIFEST_DIR")).join("fixtures/small");
    let dir = tempfile::tempdir().unwrap();
    let model = dir.path().join("model.nlf");
    let fit = |threads: &str| {
        let args = [
            "--threads",
            threads,
            "fit",
            fixture.to_str().unwrap(),
            "--steps",
            "2",
            "--holdout",
            "0",
        ];
        Command::new(env!("CARGO_BIN_EXE_nerflabel"))
            .args(args)
            .arg("--model")
            .arg(&model)
            .output()
            .unwrap()
    };
    let out = fit("1");
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    let report: serde_json::Value =
        serde_json::from_slice(&std::fs::read(dir.path().join("model.report.json")).unwrap()).unwrap();
    assert_eq!(report["threads"], 1);
    let out = fit("0");
    assert!(!out.status.success());
    assert!(String::from_utf8_lossy(&out.stderr).contains("--threads must be at least 1"));
}

/// `-q` leaves warnings and errors only; `-v` adds every held-out evaluation.
#[test]
fn quiet_silences_progress_and_summaries_and_verbose_adds_evaluations() {
    let fixture = Path::new(env!("CARGO_MANIFEST_DIR")).join("fixtures/small");
    let dir = tempfile::tempdir().unwrap();
    let model = dir.path().join("model.nlf");
    let fit = |flag: Option<&str>| {
        let mut cmd = Command::new(env!("CARGO_BIN_EXE_nerflabel"));
        cmd.args(flag)
            .args(["fit", fixture.to_str().unwrap(), "--steps", "3", "--model"])
            .arg(&model)
            .env("NERFLABEL_PROGRESS_EVERY", "0.001");
        let out = cmd.output().unwrap();
        assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
        (
            String::from_utf8_lossy(&out.stdout).to_string(),
            String::from_utf8_lossy(&out.stderr).to_string(),
        )
    };
    let (stdout, stderr) = fit(None);
    assert!(stdout.contains("trained 3 steps"), "{stdout}");
    assert!(stderr.contains("fitting"), "{stderr}");
    // Three steps end inside the warm-up: the model is not one to label from.
    assert!(
        stderr.contains("warning: training stopped after 3 steps, inside the"),
        "{stderr}"
    );
    assert!(
        !stderr.contains("held-out PSNR") || !stderr.contains("step 3, "),
        "{stderr}"
    );
    let (stdout, stderr) = fit(Some("-q"));
    assert_eq!(stdout, "", "-q prints no summary");
    let lines: Vec<&str> = stderr.lines().filter(|l| !l.starts_with("warning:")).collect();
    assert!(lines.is_empty(), "-q prints only warnings: {lines:?}");
    let (_, stderr) = fit(Some("-v"));
    assert!(
        stderr
            .lines()
            .any(|l| l.contains("held-out PSNR") && l.starts_with("step ")),
        "-v prints each evaluation: {stderr}"
    );
    let out = nerflabel(&["-q", "-v", "info", fixture.to_str().unwrap()]);
    assert!(!out.status.success(), "-q and -v together are refused");
}

#[test]
fn unknown_format_and_bad_budget_are_rejected_before_work() {
    let out = nerflabel(&["info", ".", "--format", "meshroom"]);
    assert!(!out.status.success());
    assert!(String::from_utf8_lossy(&out.stderr).contains("meshroom"));
    let fixture = Path::new(env!("CARGO_MANIFEST_DIR")).join("fixtures/small");
    let out = nerflabel(&["fit", fixture.to_str().unwrap(), "--time=-3"]);
    assert!(!out.status.success());
    assert!(String::from_utf8_lossy(&out.stderr).contains("--time"));
}

#[test]
fn info_on_the_real_cabinet_scan_reports_58_frames_and_bounds_around_its_box() {
    let Some(data) = shared_data() else { return };
    let scan_dir = data.join("scans/cabinet");
    let out = nerflabel(&["info", scan_dir.to_str().unwrap()]);
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    let text = String::from_utf8_lossy(&out.stdout);
    assert!(text.contains("58 (58 with depth)"), "{text}");
    // The printed bounds enclose every corner of boxes.json's box.
    let line = text
        .lines()
        .find(|l| l.starts_with("scene bounds:"))
        .expect("bounds line");
    let nums: Vec<f64> = line
        .split(|c: char| !(c.is_ascii_digit() || c == '.' || c == '-'))
        .filter_map(|s| s.parse().ok())
        .collect();
    assert!(nums.len() >= 6, "{line}");
    let (lo, hi) = (&nums[0..3], &nums[3..6]);
    let boxes: serde_json::Value =
        serde_json::from_slice(&std::fs::read(scan_dir.join("boxes.json")).unwrap()).unwrap();
    let b = &boxes["boxes"][0];
    let c: Vec<f64> = (0..3).map(|i| b["center"][i].as_f64().unwrap()).collect();
    let s: Vec<f64> = (0..3).map(|i| b["size"][i].as_f64().unwrap()).collect();
    let r: Vec<Vec<f64>> = (0..3)
        .map(|i| (0..3).map(|j| b["rotation"][i][j].as_f64().unwrap()).collect())
        .collect();
    for corner in 0..8 {
        let sign = [
            (corner & 1) as f64 * 2.0 - 1.0,
            ((corner >> 1) & 1) as f64 * 2.0 - 1.0,
            ((corner >> 2) & 1) as f64 * 2.0 - 1.0,
        ];
        for axis in 0..3 {
            let p = c[axis] + (0..3).map(|k| r[axis][k] * sign[k] * s[k] / 2.0).sum::<f64>();
            assert!(
                p >= lo[axis] - 1e-3 && p <= hi[axis] + 1e-3,
                "corner {corner} axis {axis}: {p} outside {line}"
            );
        }
    }
}

#[test]
fn committed_fixture_matches_its_regeneration_and_reprojects_within_millimetres() {
    let root = Path::new(env!("CARGO_MANIFEST_DIR"));
    let committed = root.join("fixtures/small");
    let dir = tempfile::tempdir().unwrap();
    let fresh = dir.path().join("small");
    // The command recorded in fixtures/README.md.
    let out = nerflabel(&[
        "fixture",
        "--scene",
        "small",
        fresh.to_str().unwrap(),
        "--width",
        "160",
        "--height",
        "120",
    ]);
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    for rel in [
        "rgb/000003.png",
        "depth/000003.png",
        "pose/000003.txt",
        "intrinsics.txt",
        "boxes.json",
        "gt/masks/000003.png",
    ] {
        assert_eq!(
            std::fs::read(committed.join(rel)).unwrap(),
            std::fs::read(fresh.join(rel)).unwrap(),
            "{rel} differs"
        );
    }
    // A depth point of frame A projected into frame B lands on B's depth.
    let scan = nerflabel::scan::load(&committed, &Default::default()).unwrap();
    let (a, b) = (&scan.frames[3], &scan.frames[5]);
    let (da, db) = (a.depth.as_ref().unwrap(), b.depth.as_ref().unwrap());
    let world_to_b = b.camera_to_world.inverse();
    let mut errors = Vec::new();
    let (w, h) = a.size();
    for v in (4..h - 4).step_by(3) {
        for u in (4..w - 4).step_by(3) {
            let z = da.get(u, v) as f64;
            if z <= 0.0 {
                continue;
            }
            let p_world = a.camera_to_world * Point3::from(a.intrinsics.unproject(u as f64, v as f64) * z);
            let p_b = world_to_b * p_world;
            let Some((ub, vb)) = b.intrinsics.project(&p_b) else {
                continue;
            };
            let (ui, vi) = (ub.round(), vb.round());
            if ui < 0.0 || vi < 0.0 || ui >= w as f64 || vi >= h as f64 {
                continue;
            }
            let zb = db.get(ui as u32, vi as u32) as f64;
            if zb > 0.0 && (zb - p_b.z).abs() < 0.05 {
                errors.push((zb - p_b.z).abs());
            }
        }
    }
    errors.sort_by(|x, y| x.total_cmp(y));
    assert!(errors.len() > 200, "too few overlapping pixels: {}", errors.len());
    let median = errors[errors.len() / 2];
    // Sensor noise (1.5 mm at 1 m, growing with z^2) plus nearest-pixel lookup at 160x120.
    assert!(median < 0.006, "median reprojection disagreement {median} m");
}

#[test]
fn cloud_writes_a_binary_ply_of_the_fixture_inside_its_bounds() {
    let fixture = Path::new(env!("CARGO_MANIFEST_DIR")).join("fixtures/small");
    let dir = tempfile::tempdir().unwrap();
    let ply = dir.path().join("cloud.ply");
    let out = nerflabel(&["cloud", fixture.to_str().unwrap(), "-o", ply.to_str().unwrap()]);
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    let bytes = std::fs::read(&ply).unwrap();
    let header_end = bytes
        .windows(11)
        .position(|w| w == b"end_header\n")
        .expect("PLY header")
        + 11;
    let header = String::from_utf8_lossy(&bytes[..header_end]);
    assert!(header.starts_with("ply\nformat binary_little_endian 1.0\n"), "{header}");
    let count: usize = header
        .lines()
        .find_map(|l| l.strip_prefix("element vertex "))
        .and_then(|n| n.trim().parse().ok())
        .expect("vertex count");
    assert!(count > 1000, "only {count} points");
    // x y z float + r g b uchar per vertex.
    assert_eq!(bytes.len() - header_end, count * 15);
    // Every point lies inside the small scene (a few metres around the origin).
    for rec in bytes[header_end..].chunks_exact(15) {
        for a in 0..3 {
            let v = f32::from_le_bytes([rec[4 * a], rec[4 * a + 1], rec[4 * a + 2], rec[4 * a + 3]]);
            assert!(v.is_finite() && v.abs() < 10.0, "coordinate {v}");
        }
    }
}

/// Output into a closed pipe (`nerflabel info | head -1`) ends quietly, without a panic.
#[cfg(unix)]
#[test]
fn output_into_a_closed_pipe_does_not_panic() {
    let small = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("fixtures/small");
    // `true` exits before the scan is read, so every line goes into a closed pipe.
    let script = format!(
        "'{}' info '{}' | true",
        env!("CARGO_BIN_EXE_nerflabel"),
        small.display()
    );
    let out = std::process::Command::new("sh").args(["-c", &script]).output().unwrap();
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(
        !stderr.contains("panicked") && !stderr.contains("Broken pipe"),
        "{stderr}"
    );
}
