//! Nothing lost on interruption, through the real binary on a copy of
//! `fixtures/small`: Ctrl-C (SIGINT) during `fit` saves a usable model
//! marked interrupted and `fit --resume` finishes it; SIGKILL at random
//! moments of `fit`, `label` and `synth` (and at the moment a temp file
//! appears, i.e. while an output is being written) leaves every output path
//! holding either the previous complete output or a complete new one.
//!
//! The only leftovers a SIGKILL may leave are the documented hidden temp
//! entries of the killed process (`.NAME.tmpPID` beside a file,
//! `.staging-PID` / `.replaced-PID` in a label folder); later runs ignore
//! them.

use arrow_array::RecordBatch;
use nerflabel::nerf::model_file::Model;
use nerflabel::nerf::train::checkpoint::Checkpoint;
use nerflabel::rng::Rng;
use parquet::arrow::arrow_reader::ParquetRecordBatchReaderBuilder;
use std::collections::BTreeSet;
use std::io::{BufRead, BufReader};
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

fn bin() -> Command {
    Command::new(env!("CARGO_BIN_EXE_nerflabel"))
}

fn copy_dir(from: &Path, to: &Path) {
    std::fs::create_dir_all(to).unwrap();
    for e in std::fs::read_dir(from).unwrap() {
        let e = e.unwrap();
        let target = to.join(e.file_name());
        if e.file_type().unwrap().is_dir() {
            copy_dir(&e.path(), &target);
        } else {
            std::fs::copy(e.path(), target).unwrap();
        }
    }
}

/// A private copy of the committed 160x120, 24-frame fixture.
fn work_scan(dir: &Path) -> PathBuf {
    let scan = dir.join("scan");
    copy_dir(&Path::new(env!("CARGO_MANIFEST_DIR")).join("fixtures/small"), &scan);
    scan
}

fn names(dir: &Path) -> BTreeSet<String> {
    match std::fs::read_dir(dir) {
        Ok(rd) => rd
            .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
            .collect(),
        Err(_) => BTreeSet::new(),
    }
}

fn run_ok(cmd: &mut Command) -> Duration {
    let t = Instant::now();
    let o = cmd.output().unwrap();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    t.elapsed()
}

/// SIGKILL `child` after `delay` or as soon as `trigger` holds, whichever
/// comes first; `false` when it finished before (then it must have succeeded).
fn kill_when(child: &mut Child, delay: Duration, trigger: &dyn Fn(u32) -> bool) -> bool {
    let start = Instant::now();
    let pid = child.id();
    loop {
        if let Some(status) = child.try_wait().unwrap() {
            assert!(status.success(), "the run failed on its own: {status}");
            return false;
        }
        if start.elapsed() >= delay || trigger(pid) {
            child.kill().unwrap();
            child.wait().unwrap();
            return true;
        }
        std::thread::sleep(Duration::from_micros(300));
    }
}

/// When to kill run `i`: at the first sign of a write for the first few,
/// at random moments of a full run's duration for the rest.
fn plan(i: usize, full: Duration, rng: &mut Rng, writes: usize) -> (Duration, usize) {
    if i < writes {
        (full * 3, i)
    } else {
        (full.mul_f64(rng.range(0.05, 1.1)), usize::MAX)
    }
}

fn report_run(i: usize, killed: bool, delay: Duration, write: usize) {
    let when = if write == usize::MAX {
        format!("at {delay:.2?}")
    } else {
        format!("at write trigger {write}")
    };
    eprintln!(
        "run {i}: {} {when}",
        if killed { "killed" } else { "finished before the kill" }
    );
}

/// Leftovers in `dir` besides `expected` must be temp entries of killed processes.
fn assert_only_documented_leftovers(dir: &Path, expected: &[&str], killed: &[u32], patterns: &[&str]) {
    for name in names(dir) {
        if expected.contains(&name.as_str()) {
            continue;
        }
        let ok = patterns
            .iter()
            .any(|p| killed.iter().any(|pid| name == p.replace("PID", &pid.to_string())));
        assert!(ok, "{}: unexpected leftover `{name}`", dir.display());
    }
}

/// Start a long fit of `scan`, send `signal` once training runs, and
/// return its exit status and stderr.
fn fit_until_signal(fit: &mut Command, signal: &str) -> (std::process::ExitStatus, String) {
    let mut child = fit
        .args(["--steps", "100000"])
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    let stderr = child.stderr.take().unwrap();
    let (tx, rx) = std::sync::mpsc::channel();
    let reader = std::thread::spawn(move || {
        let mut all = String::new();
        for line in BufReader::new(stderr).lines() {
            let line = line.unwrap();
            let _ = tx.send(line.clone());
            all.push_str(&line);
            all.push('\n');
        }
        all
    });
    // Training has started once the set-up line is printed; let it run a few steps.
    let deadline = Instant::now() + Duration::from_secs(120);
    while !rx
        .recv_timeout(Duration::from_secs(120))
        .unwrap()
        .contains("training views")
    {
        assert!(Instant::now() < deadline, "fit never started training");
    }
    std::thread::sleep(Duration::from_millis(1500));
    let k = Command::new("kill")
        .args([&format!("-{signal}"), &child.id().to_string()])
        .status()
        .unwrap();
    assert!(k.success());
    let status = child.wait().unwrap();
    (status, reader.join().unwrap())
}

/// After a signal: the model, report and checkpoint are all of the stopped
/// run, at the same step; returns that step.
fn assert_saved_when_stopped(out: &Path) -> u64 {
    let model = Model::load(&out.join("model.nlf")).unwrap();
    let report: serde_json::Value =
        serde_json::from_slice(&std::fs::read(out.join("model.report.json")).unwrap()).unwrap();
    assert_eq!(report["interrupted"], true);
    let steps = report["counters"]["steps"].as_u64().unwrap();
    assert!((1..100_000).contains(&steps), "{steps}");
    assert_eq!(model.header.steps, steps);
    assert_eq!(
        Checkpoint::load(&out.join("model.checkpoint")).unwrap().steps(),
        steps,
        "checkpoint saved when stopped"
    );
    steps
}

#[test]
fn sigterm_during_fit_saves_like_ctrl_c_and_exits_143() {
    // Regression: SIGTERM (timeout, Docker, Slurm) killed the run, leaving a
    // checkpoint of the killed run beside the old model and report.
    let dir = tempfile::tempdir().unwrap();
    let scan = work_scan(dir.path());
    let (status, stderr) = fit_until_signal(
        bin()
            .arg("fit")
            .arg(&scan)
            .args(["--preset", "fast", "--holdout", "12"]),
        "TERM",
    );
    assert_eq!(status.code(), Some(143), "{stderr}");
    assert!(stderr.contains("interrupted: saved the model"), "{stderr}");
    assert_saved_when_stopped(&scan.join("nerflabel"));
}

#[test]
fn sigint_during_fit_saves_an_interrupted_model_and_resume_finishes_it() {
    let dir = tempfile::tempdir().unwrap();
    let scan = work_scan(dir.path());
    let out = scan.join("nerflabel");
    let fit = |extra: &[&str]| {
        let mut c = bin();
        c.arg("fit")
            .arg(&scan)
            .args(["--preset", "fast", "--holdout", "12", "--seed", "1"])
            .args(extra);
        c
    };
    let (status, stderr) = fit_until_signal(&mut fit(&[]), "INT");
    assert_eq!(
        status.code(),
        Some(130),
        "Ctrl-C saves, then exits 130 so scripts can tell: {stderr}"
    );
    assert!(stderr.contains("interrupted: saved the model"), "{stderr}");
    assert_eq!(
        names(&out),
        [".model.nlf.lock", "model.report.json", "model.checkpoint", "model.nlf"]
            .map(String::from)
            .into(),
        "only the outputs, no temp file"
    );
    let steps = assert_saved_when_stopped(&out);

    let model = Model::load(&out.join("model.nlf")).unwrap();
    assert!(model
        .field
        .grid
        .params
        .iter()
        .chain(&model.field.density.params)
        .all(|v| v.is_finite()));
    let report: serde_json::Value =
        serde_json::from_slice(&std::fs::read(out.join("model.report.json")).unwrap()).unwrap();
    assert_eq!(
        report["curve"].as_array().unwrap().last().unwrap()["step"].as_u64(),
        Some(steps),
        "evaluated when stopped"
    );

    // Resuming with another seed is refused and leaves everything alone.
    let before = std::fs::read(out.join("model.nlf")).unwrap();
    let o = bin()
        .arg("fit")
        .arg(&scan)
        .args(["--preset", "fast", "--holdout", "12", "--seed", "2", "--resume"])
        .output()
        .unwrap();
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(
        !o.status.success() && err.contains("--seed 1 (this run: 2)") && !err.contains("panicked"),
        "{err}"
    );
    assert!(std::fs::read(out.join("model.nlf")).unwrap() == before);
    // Without a checkpoint, --resume says so.
    let o = fit(&["--resume", "--model"])
        .arg(dir.path().join("elsewhere/model.nlf"))
        .output()
        .unwrap();
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(
        !o.status.success() && err.contains("no checkpoint to resume from"),
        "{err}"
    );

    // Resume to 15 more steps: counters add up, the curve continues.
    let total = steps + 15;
    run_ok(fit(&["--resume", "--steps", &total.to_string()]).stdout(Stdio::null()));
    let resumed: serde_json::Value =
        serde_json::from_slice(&std::fs::read(out.join("model.report.json")).unwrap()).unwrap();
    assert_eq!(resumed["interrupted"], false);
    assert_eq!(resumed["counters"]["steps"].as_u64(), Some(total));
    assert_eq!(resumed["resumed_from"], serde_json::json!([steps]));
    assert!(resumed["counters"]["samples"].as_u64().unwrap() > report["counters"]["samples"].as_u64().unwrap());
    assert!(resumed["timings"]["train_s"].as_f64().unwrap() > report["timings"]["train_s"].as_f64().unwrap());
    let curve: Vec<u64> = resumed["curve"]
        .as_array()
        .unwrap()
        .iter()
        .map(|p| p["step"].as_u64().unwrap())
        .collect();
    let old: Vec<u64> = report["curve"]
        .as_array()
        .unwrap()
        .iter()
        .map(|p| p["step"].as_u64().unwrap())
        .collect();
    assert_eq!(curve[..old.len()], old[..], "the old curve is kept");
    assert_eq!(curve.last(), Some(&total), "{curve:?}");
    assert_eq!(Model::load(&out.join("model.nlf")).unwrap().header.steps, total);
}

#[test]
fn sigkill_during_fit_leaves_the_previous_or_a_complete_new_model() {
    let dir = tempfile::tempdir().unwrap();
    let scan = work_scan(dir.path());
    let out = scan.join("nerflabel");
    let fit = |seed: usize| {
        let mut c = bin();
        c.arg("fit").arg(&scan).args([
            "--steps",
            "8",
            "--preset",
            "fast",
            "--holdout",
            "0",
            "--seed",
            &seed.to_string(),
        ]);
        c.stdout(Stdio::null()).stderr(Stdio::null());
        c
    };
    let full = run_ok(&mut fit(0));
    let mut model = std::fs::read(out.join("model.nlf")).unwrap();
    let mut rng = Rng::new(61, 0);
    let mut killed = Vec::new();
    let watch = [
        ".model.nlf.tmpPID",
        ".model.checkpoint.tmpPID",
        ".model.report.json.tmpPID",
    ];
    for i in 0..7 {
        let seed = i + 1;
        let (delay, write) = plan(i, full, &mut rng, 3);
        let mut child = fit(seed).spawn().unwrap();
        let trigger =
            |pid: u32| write < watch.len() && out.join(watch[write].replace("PID", &pid.to_string())).exists();
        let was_killed = kill_when(&mut child, delay, &trigger);
        if was_killed {
            killed.push(child.id());
        }
        report_run(i, was_killed, delay, write);
        // The model path holds the previous model or a complete new one.
        let bytes = std::fs::read(out.join("model.nlf")).unwrap();
        let m = Model::load(&out.join("model.nlf")).unwrap_or_else(|e| panic!("run {i}: {e}"));
        assert_eq!(m.header.steps, 8);
        if bytes != model {
            assert_eq!(
                m.header.seed, seed as u64,
                "run {i}: a new model must come from this run"
            );
            model = bytes;
        } else {
            assert!(was_killed, "run {i} finished but the model did not change");
        }
        let ckpt = Checkpoint::load(&out.join("model.checkpoint")).unwrap_or_else(|e| panic!("run {i}: {e}"));
        assert_eq!(ckpt.steps(), 8);
        let report: serde_json::Value = serde_json::from_slice(&std::fs::read(out.join("model.report.json")).unwrap())
            .unwrap_or_else(|e| panic!("run {i}: model.report.json: {e}"));
        assert_eq!(report["counters"]["steps"], 8);
        assert_only_documented_leftovers(
            &out,
            &["model.nlf", "model.checkpoint", "model.report.json", ".model.nlf.lock"],
            &killed,
            &watch,
        );
    }
    assert!(killed.len() >= 3, "most runs must be killed: {killed:?}");
    // Leftover temp files do not disturb a later fit.
    run_ok(&mut fit(99));
    assert_eq!(Model::load(&out.join("model.nlf")).unwrap().header.seed, 99);
}

/// Check a label folder: when `coco.json` is there, its images are exactly
/// the mask files, all decodable; returns the image count.
fn check_labels(out: &Path) -> Option<usize> {
    let text = std::fs::read(out.join("coco.json")).ok()?;
    let coco: serde_json::Value =
        serde_json::from_slice(&text).unwrap_or_else(|e| panic!("coco.json does not parse: {e}"));
    let images: BTreeSet<String> = coco["images"]
        .as_array()
        .unwrap()
        .iter()
        .map(|i| format!("{:06}.png", i["frame_id"].as_u64().unwrap()))
        .collect();
    for sub in ["masks"] {
        assert_eq!(
            names(&out.join(sub)),
            images,
            "{sub}/ must hold exactly the images of coco.json"
        );
        for name in &images {
            let img = image::open(out.join(sub).join(name)).unwrap_or_else(|e| panic!("{sub}/{name}: {e}"));
            assert_eq!((img.width(), img.height()), (160, 120));
        }
    }
    Some(images.len())
}

#[test]
fn sigkill_during_label_leaves_the_previous_or_a_complete_new_labelling() {
    let dir = tempfile::tempdir().unwrap();
    let scan = work_scan(dir.path());
    run_ok(
        bin()
            .arg("fit")
            .arg(&scan)
            .args(["--steps", "8", "--preset", "fast", "--holdout", "0"])
            .stdout(Stdio::null()),
    );
    let out = scan.join("nerflabel/labels");
    // Each run relabels a different range of frames (recorded in coco.json's
    // info), so old and new are told apart; the other frames are kept.
    let label = |frames: usize| {
        let mut c = bin();
        c.arg("label").arg(&scan).arg("--boxes").arg(scan.join("boxes.json"));
        c.args(["--source", "nerf", "--frames", &format!("0..{frames}")]);
        c.stdout(Stdio::null()).stderr(Stdio::null());
        c
    };
    let full = run_ok(&mut label(24));
    assert_eq!(check_labels(&out), Some(24));
    let mut rng = Rng::new(62, 0);
    let mut killed = Vec::new();
    // The last complete labelling: its range and its image count.
    let mut complete = Some(("0..24".to_string(), 24));
    for i in 0..7 {
        let frames = 23 - i;
        let range = format!("0..{frames}");
        let (delay, write) = plan(i, full, &mut rng, 3);
        let mut child = label(frames).spawn().unwrap();
        let trigger = |pid: u32| match write {
            0 => out.join(format!(".staging-{pid}/masks")).exists(),
            1 => out.join(format!(".staging-{pid}/coco.json")).exists(),
            2 => out.join(format!(".replaced-{pid}")).exists(),
            _ => false,
        };
        let was_killed = kill_when(&mut child, delay, &trigger);
        let pid = child.id();
        if was_killed {
            killed.push(pid);
        }
        report_run(i, was_killed, delay, write);
        match check_labels(&out) {
            Some(n) => {
                // A partial run keeps the other frames of a complete labelling; after a
                // kill between the swap's renames there is none (it sits in .replaced-PID),
                // so the next run writes only its own frames.
                let old = complete.as_ref().map(|(_, count)| *count);
                let new = old.map_or(frames, |count| count.max(frames));
                assert!(
                    n == new || Some(n) == old,
                    "run {i}: {n} images, expected {new} (new) or {old:?} (old)"
                );
                let labelled = labelled_range(&out);
                assert!(
                    labelled == range || Some(&labelled) == complete.as_ref().map(|(r, _)| r),
                    "run {i}: range {labelled} is neither the old nor the new labelling"
                );
                assert!(
                    was_killed || labelled == range,
                    "run {i} finished but left the old labels"
                );
                complete = Some((labelled, n));
            }
            None => {
                // Killed between the renames of the swap: the previous run sits complete beside it.
                assert!(was_killed, "run {i} finished without coco.json");
                if complete.is_some() {
                    assert!(
                        out.join(format!(".replaced-{pid}/coco.json")).exists(),
                        "run {i}: the previous labels are lost"
                    );
                }
                complete = None;
            }
        }
        assert_only_documented_leftovers(
            &out,
            // evaluation.json: the fixture has exact masks, so label scores against them.
            &["coco.json", "masks", ".nerflabel-labels", "evaluation.json"],
            &killed,
            &[".staging-PID", ".replaced-PID", ".evaluation.json.tmpPID"],
        );
    }
    assert!(killed.len() >= 3, "most runs must be killed: {killed:?}");
    run_ok(&mut label(24));
    assert_eq!(check_labels(&out), Some(24));
}

/// The frame range the last run over a label folder relabelled.
fn labelled_range(out: &Path) -> String {
    let coco: serde_json::Value = serde_json::from_slice(&std::fs::read(out.join("coco.json")).unwrap()).unwrap();
    coco["info"]["frames"].as_str().unwrap_or_default().to_string()
}

/// Rows of a Parquet file, panicking on anything unreadable.
fn parquet_rows(path: &Path) -> usize {
    let file = std::fs::File::open(path).unwrap();
    let reader = ParquetRecordBatchReaderBuilder::try_new(file)
        .unwrap_or_else(|e| panic!("{}: {e}", path.display()))
        .build()
        .unwrap();
    let batches: Vec<RecordBatch> = reader
        .map(|b| b.unwrap_or_else(|e| panic!("{}: {e}", path.display())))
        .collect();
    batches.iter().map(|b| b.num_rows()).sum()
}

#[test]
fn sigkill_during_synth_leaves_the_previous_or_a_complete_new_parquet() {
    let dir = tempfile::tempdir().unwrap();
    let scan_dir = work_scan(dir.path());
    run_ok(
        bin()
            .arg("fit")
            .arg(&scan_dir)
            .args(["--steps", "8", "--preset", "fast", "--holdout", "0"])
            .stdout(Stdio::null()),
    );
    let scan = nerflabel::scan::load(&scan_dir, &Default::default()).unwrap();
    // Poses files of the first n training frames at half size (views of known content, no sampling).
    let poses = |n: usize| {
        let views: Vec<serde_json::Value> = scan.frames[..n]
            .iter()
            .map(|f| {
                let h = f.camera_to_world.to_homogeneous();
                let m: [[f64; 4]; 4] = std::array::from_fn(|r| std::array::from_fn(|c| h[(r, c)]));
                let k = f.intrinsics.scaled((160, 120), (80, 60));
                serde_json::json!({"camera_to_world": m, "intrinsics": [k.fx, k.fy, k.cx, k.cy], "width": 80, "height": 60})
            })
            .collect();
        let path = dir.path().join(format!("poses{n}.json"));
        std::fs::write(&path, serde_json::json!({ "views": views }).to_string()).unwrap();
        path
    };
    let out = dir.path().join("synth");
    let synth = |n: usize| {
        let mut c = bin();
        c.arg("synth")
            .arg(&scan_dir)
            .arg("--poses")
            .arg(poses(n))
            .arg("--out")
            .arg(out.join("views.parquet"))
            .arg("--overwrite");
        c.stdout(Stdio::null()).stderr(Stdio::null());
        c
    };
    let full = run_ok(&mut synth(8));
    assert_eq!(parquet_rows(&out.join("views.parquet")), 8);
    let mut rng = Rng::new(63, 0);
    let mut killed = Vec::new();
    let mut rows = 8;
    for i in 0..7 {
        let n = 7 - i % 2;
        let (delay, write) = plan(i, full, &mut rng, 2);
        let mut child = synth(n).spawn().unwrap();
        let trigger = |pid: u32| {
            let tmp = out.join(format!(".views.parquet.tmp{pid}"));
            // 0: as soon as the temp file exists; 1: once row groups are in it.
            match write {
                0 => tmp.exists(),
                1 => std::fs::metadata(&tmp).is_ok_and(|m| m.len() > 4096),
                _ => false,
            }
        };
        let was_killed = kill_when(&mut child, delay, &trigger);
        if was_killed {
            killed.push(child.id());
        }
        report_run(i, was_killed, delay, write);
        let now = parquet_rows(&out.join("views.parquet"));
        assert!(
            now == rows || now == n,
            "run {i}: {now} rows is neither the old ({rows}) nor the new ({n}) file"
        );
        assert!(was_killed || now == n, "run {i} finished but left the old file");
        rows = now;
        assert_only_documented_leftovers(
            &out,
            &["views.parquet", ".views.parquet.lock"],
            &killed,
            &[".views.parquet.tmpPID"],
        );
    }
    assert!(killed.len() >= 3, "most runs must be killed: {killed:?}");
    run_ok(&mut synth(8));
    assert_eq!(parquet_rows(&out.join("views.parquet")), 8);
}
