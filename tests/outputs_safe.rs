//! Outputs never destroy inputs or earlier work: `--out`/`--model` over a
//! scan's input folders and files is refused before any work, a label swap
//! only replaces what `label` wrote, partial re-labelling keeps every other
//! frame, each model has its own report, `synth` never replaces a file
//! silently, and two fits of one model cannot run at once.

mod common;

use common::{copy_dir, one_view_poses, run, s, small_scan, stderr};
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::process::Command;

/// Every file under `dir` with its bytes.
fn contents(dir: &Path) -> BTreeMap<PathBuf, Vec<u8>> {
    let mut out = BTreeMap::new();
    let mut stack = vec![dir.to_path_buf()];
    while let Some(d) = stack.pop() {
        for entry in std::fs::read_dir(&d).unwrap() {
            let path = entry.unwrap().path();
            if path.is_dir() {
                stack.push(path);
            } else {
                out.insert(
                    path.strip_prefix(dir).unwrap().to_path_buf(),
                    std::fs::read(&path).unwrap(),
                );
            }
        }
    }
    out
}

/// The scan's input files (everything but the work folder `nerflabel/`).
fn inputs(scan: &Path) -> BTreeMap<PathBuf, Vec<u8>> {
    contents(scan)
        .into_iter()
        .filter(|(p, _)| !p.starts_with("nerflabel"))
        .collect()
}

#[test]
fn label_fit_and_synth_outputs_over_the_scans_inputs_are_refused_and_change_nothing() {
    let dir = tempfile::tempdir().unwrap();
    let scan = small_scan(dir.path());
    // A real model so label and synth reach their output handling.
    let fit = run(&["fit", s(&scan), "--steps", "2", "--preset", "fast", "--holdout", "0"]);
    assert!(fit.status.success(), "{}", stderr(&fit));
    let before = inputs(&scan);
    let boxes = scan.join("boxes.json");
    let targets = [
        scan.clone(),
        scan.join("rgb"),
        scan.join("depth"),
        scan.join("pose"),
        scan.join("rgb/new"),
        scan.join("depth/000001.png"),
        scan.join("rgb/000000.png"),
        scan.join("pose/000003.txt"),
        scan.join("intrinsics.txt"),
        scan.join("boxes.json.d/../rgb"),
    ];
    for target in &targets {
        let t = s(target);
        for args in [
            vec![
                "label",
                s(&scan),
                "--boxes",
                s(&boxes),
                "--source",
                "sensor",
                "--out",
                t,
            ],
            vec!["label", s(&scan), "--boxes", s(&boxes), "--depth", "--out", t],
            vec!["fit", s(&scan), "--steps", "2", "--preset", "fast", "--model", t],
            vec![
                "synth",
                s(&scan),
                "--n",
                "1",
                "--width",
                "16",
                "--height",
                "12",
                "--out",
                t,
            ],
        ] {
            let o = run(&args);
            assert!(!o.status.success(), "{args:?} must be refused");
            let msg = stderr(&o);
            assert!(
                msg.contains("refusing") || msg.contains("is a directory") || msg.contains("is a file"),
                "{args:?}: the message says why: {msg}"
            );
            assert!(!msg.contains("panicked"), "{args:?}: {msg}");
        }
    }
    assert!(inputs(&scan) == before, "no input file of the scan changed or appeared");
}

#[test]
fn label_out_at_the_scan_root_no_longer_deletes_its_depth() {
    // Regression: the staging swap replaced SCAN/depth with label outputs.
    let dir = tempfile::tempdir().unwrap();
    let scan = small_scan(dir.path());
    let o = run(&[
        "label",
        s(&scan),
        "--boxes",
        s(&scan.join("boxes.json")),
        "--source",
        "sensor",
        "--out",
        s(&scan),
    ]);
    assert!(!o.status.success());
    let info = run(&["info", s(&scan)]);
    let summary = String::from_utf8_lossy(&info.stdout);
    assert!(summary.contains("(24 with depth)"), "depth still there: {summary}");
}

#[test]
fn label_refuses_a_folder_it_did_not_write_that_holds_its_output_names() {
    // Another scan (or any folder with depth/ or coco.json) is not ours to replace.
    let dir = tempfile::tempdir().unwrap();
    let scan = small_scan(dir.path());
    let other = dir.path().join("other");
    copy_dir(&scan.join("depth"), &other.join("depth"));
    let before = contents(&other);
    let o = run(&[
        "label",
        s(&scan),
        "--boxes",
        s(&scan.join("boxes.json")),
        "--source",
        "sensor",
        "--out",
        s(&other),
    ]);
    assert!(!o.status.success());
    assert!(
        stderr(&o).contains("was not written by `nerflabel label`"),
        "{}",
        stderr(&o)
    );
    assert!(contents(&other) == before);
    // A folder label wrote is replaced on the next run.
    let out = dir.path().join("labels");
    for _ in 0..2 {
        let o = run(&[
            "label",
            s(&scan),
            "--boxes",
            s(&scan.join("boxes.json")),
            "--source",
            "sensor",
            "--out",
            s(&out),
        ]);
        assert!(o.status.success(), "{}", stderr(&o));
    }
}

#[test]
fn model_paths_that_cannot_be_written_fail_before_training() {
    let dir = tempfile::tempdir().unwrap();
    let scan = small_scan(dir.path());
    let existing_dir = dir.path().join("adir");
    std::fs::create_dir(&existing_dir).unwrap();
    // Many steps: a check made after training would take far longer than the test allows to notice.
    let o = run(&["fit", s(&scan), "--steps", "100000", "--model", s(&existing_dir)]);
    assert!(!o.status.success());
    assert!(stderr(&o).contains("is a directory"), "{}", stderr(&o));
    assert!(
        !dir.path().join("adir.checkpoint").exists(),
        "nothing written beside it"
    );
    let file = dir.path().join("afile");
    std::fs::write(&file, "x").unwrap();
    let o = run(&["fit", s(&scan), "--steps", "100000", "--model", s(&file.join("m.nlf"))]);
    assert!(stderr(&o).contains("is a file, not a folder"), "{}", stderr(&o));
    let o = run(&["synth", s(&scan), "--n", "100000", "--out", s(&existing_dir)]);
    assert!(!o.status.success());
    assert!(stderr(&o).contains("is a directory"), "{}", stderr(&o));
}

#[test]
fn each_model_keeps_its_own_report_and_a_model_named_like_a_report_survives() {
    let dir = tempfile::tempdir().unwrap();
    let scan = small_scan(dir.path());
    let models = dir.path().join("models");
    for (name, seed) in [("a.nlf", "1"), ("b.nlf", "2"), ("fit_report.json", "3")] {
        let m = models.join(name);
        let o = run(&[
            "fit",
            s(&scan),
            "--steps",
            "2",
            "--preset",
            "fast",
            "--holdout",
            "0",
            "--seed",
            seed,
            "--model",
            s(&m),
        ]);
        assert!(o.status.success(), "{}", stderr(&o));
    }
    for (name, seed) in [("a", 1), ("b", 2), ("fit_report", 3)] {
        let report: serde_json::Value =
            serde_json::from_slice(&std::fs::read(models.join(format!("{name}.report.json"))).unwrap()).unwrap();
        assert_eq!(report["seed"], seed, "{name}'s report is its own");
    }
    // Regression: the report used to overwrite a model called fit_report.json.
    let o = run(&[
        "label",
        s(&scan),
        "--boxes",
        s(&scan.join("boxes.json")),
        "--model",
        s(&models.join("fit_report.json")),
        "--out",
        s(&dir.path().join("l")),
    ]);
    assert!(o.status.success(), "the model is still a model: {}", stderr(&o));
    let o = run(&["report", s(&scan), "--model", s(&models.join("a.nlf"))]);
    assert!(
        String::from_utf8_lossy(&o.stdout).contains("seed 1"),
        "{}",
        String::from_utf8_lossy(&o.stdout)
    );
    // Reports of earlier versions (fit_report.json beside the model) are still read.
    let legacy = dir.path().join("legacy");
    std::fs::create_dir(&legacy).unwrap();
    std::fs::copy(models.join("b.nlf"), legacy.join("model.nlf")).unwrap();
    std::fs::copy(models.join("b.report.json"), legacy.join("fit_report.json")).unwrap();
    let o = run(&["report", s(&scan), "--model", s(&legacy.join("model.nlf"))]);
    assert!(String::from_utf8_lossy(&o.stdout).contains("seed 2"), "{}", stderr(&o));
}

#[test]
fn relabelling_three_frames_keeps_every_other_frames_files_byte_identical() {
    let dir = tempfile::tempdir().unwrap();
    let scan = small_scan(dir.path());
    let out = dir.path().join("labels");
    let boxes = s(&scan.join("boxes.json")).to_string();
    let full = run(&[
        "label",
        s(&scan),
        "--boxes",
        &boxes,
        "--source",
        "sensor",
        "--yolo",
        "--out",
        s(&out),
    ]);
    assert!(full.status.success(), "{}", stderr(&full));
    let before = contents(&out);
    // Relabel frames 3, 4 and 5 with a box moved, so their masks change.
    let mut doc: serde_json::Value = serde_json::from_slice(&std::fs::read(&boxes).unwrap()).unwrap();
    let c = doc["boxes"][0]["center"][0].as_f64().unwrap();
    doc["boxes"][0]["center"][0] = (c + 0.02).into();
    let moved = dir.path().join("moved.json");
    std::fs::write(&moved, serde_json::to_vec(&doc).unwrap()).unwrap();
    let part = run(&[
        "label",
        s(&scan),
        "--boxes",
        s(&moved),
        "--source",
        "sensor",
        "--yolo",
        "--frames",
        "3..6",
        "--out",
        s(&out),
    ]);
    assert!(part.status.success(), "{}", stderr(&part));
    let after = contents(&out);
    let relabelled = |p: &Path| {
        ["000003", "000004", "000005"]
            .iter()
            .any(|f| p.file_stem().is_some_and(|s| s == *f))
    };
    let mut changed = 0;
    for (path, bytes) in &before {
        // Files of the whole folder: the COCO file and the score against the fixture's exact masks.
        if path == Path::new("coco.json") || path == Path::new("evaluation.json") {
            continue;
        }
        let now = after
            .get(path)
            .unwrap_or_else(|| panic!("{} was deleted", path.display()));
        if relabelled(path) {
            changed += (now != bytes) as usize;
        } else {
            assert!(now == bytes, "{} changed", path.display());
        }
    }
    assert!(changed > 0, "the relabelled frames' masks changed with the box");
    assert_eq!(
        before.keys().collect::<Vec<_>>(),
        after.keys().collect::<Vec<_>>(),
        "same files"
    );
    let coco: serde_json::Value = serde_json::from_slice(&after[Path::new("coco.json")]).unwrap();
    let old: serde_json::Value = serde_json::from_slice(&before[Path::new("coco.json")]).unwrap();
    let frames: Vec<u64> = coco["images"]
        .as_array()
        .unwrap()
        .iter()
        .map(|i| i["frame_id"].as_u64().unwrap())
        .collect();
    assert_eq!(frames, (0..24).collect::<Vec<u64>>(), "every frame, in order");
    // Other frames' annotations are the old ones (ids renumbered only).
    let strip = |doc: &serde_json::Value, frame: u64| -> Vec<serde_json::Value> {
        let image = doc["images"]
            .as_array()
            .unwrap()
            .iter()
            .find(|i| i["frame_id"] == frame)
            .unwrap();
        doc["annotations"]
            .as_array()
            .unwrap()
            .iter()
            .filter(|a| a["image_id"] == image["id"])
            .map(|a| {
                let mut a = a.clone();
                a["id"] = 0.into();
                a["image_id"] = 0.into();
                a
            })
            .collect()
    };
    for frame in [0u64, 2, 6, 23] {
        assert_eq!(strip(&coco, frame), strip(&old, frame), "frame {frame}");
    }
    assert_ne!(strip(&coco, 4), strip(&old, 4), "frame 4 relabelled");
    let ids: Vec<u64> = coco["annotations"]
        .as_array()
        .unwrap()
        .iter()
        .map(|a| a["id"].as_u64().unwrap())
        .collect();
    assert_eq!(
        ids,
        (1..=ids.len() as u64).collect::<Vec<_>>(),
        "annotation ids renumbered 1.."
    );
}

#[test]
fn synth_refuses_to_replace_a_file_without_overwrite_or_while_another_run_writes_it() {
    let dir = tempfile::tempdir().unwrap();
    let scan = small_scan(dir.path());
    let fit = run(&["fit", s(&scan), "--steps", "2", "--preset", "fast", "--holdout", "0"]);
    assert!(fit.status.success(), "{}", stderr(&fit));
    let out = dir.path().join("views.parquet");
    std::fs::write(&out, b"precious").unwrap();
    // One given view: a two-step model has no geometry to sample views around.
    let poses = dir.path().join("poses.json");
    one_view_poses(&poses);
    let synth = |extra: &[&str]| {
        let mut args = vec!["synth", s(&scan), "--poses", s(&poses), "--out", s(&out)];
        args.extend_from_slice(extra);
        run(&args)
    };
    let o = synth(&[]);
    assert!(!o.status.success());
    assert!(stderr(&o).contains("--overwrite"), "{}", stderr(&o));
    assert_eq!(std::fs::read(&out).unwrap(), b"precious");
    // Another process writing the same file (here: this test holding its lock).
    let held = std::fs::File::create(dir.path().join(".views.parquet.lock")).unwrap();
    held.try_lock().unwrap();
    let o = synth(&["--overwrite"]);
    assert!(!o.status.success());
    assert!(stderr(&o).contains("another nerflabel process"), "{}", stderr(&o));
    assert_eq!(std::fs::read(&out).unwrap(), b"precious");
    drop(held);
    let o = synth(&["--overwrite"]);
    assert!(o.status.success(), "{}", stderr(&o));
    assert_eq!(&std::fs::read(&out).unwrap()[..4], b"PAR1");
}

#[test]
fn a_second_fit_of_the_same_model_stops_at_once_naming_the_first() {
    let dir = tempfile::tempdir().unwrap();
    let scan = small_scan(dir.path());
    let model = dir.path().join("m.nlf");
    let mut first = Command::new(env!("CARGO_BIN_EXE_nerflabel"))
        .args([
            "fit",
            s(&scan),
            "--steps",
            "100000",
            "--preset",
            "fast",
            "--model",
            s(&model),
        ])
        .stdout(std::process::Stdio::null())
        .stderr(std::process::Stdio::null())
        .spawn()
        .unwrap();
    let lock = dir.path().join(".m.nlf.lock");
    let pid = first.id().to_string();
    for _ in 0..600 {
        if std::fs::read_to_string(&lock).is_ok_and(|t| t == pid) {
            break;
        }
        std::thread::sleep(std::time::Duration::from_millis(50));
    }
    let second = run(&[
        "fit",
        s(&scan),
        "--steps",
        "2",
        "--preset",
        "fast",
        "--model",
        s(&model),
    ]);
    let _ = first.kill();
    let _ = first.wait();
    assert!(!second.status.success());
    assert!(stderr(&second).contains(&format!("pid {pid}")), "{}", stderr(&second));
    // The lock dies with its holder.
    let third = run(&[
        "fit",
        s(&scan),
        "--steps",
        "2",
        "--preset",
        "fast",
        "--holdout",
        "0",
        "--model",
        s(&model),
    ]);
    assert!(third.status.success(), "{}", stderr(&third));
}
