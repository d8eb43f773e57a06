//! `nerflabel batch` end to end on three small generated scans, one broken:
//! every stage runs, a second run on a scan is refused, a run killed with
//! SIGKILL mid-fit is completed by a rerun that resumes the fit and leaves
//! the finished scan's outputs alone, the broken scan's error is in its
//! status file, and the merged dataset has what it should (and loads in
//! pyarrow, polars and `datasets` where Python has them).

mod common;

use common::{s, stderr};
use serde_json::Value;
use std::path::{Path, PathBuf};
use std::process::{Command, Output, Stdio};
use std::time::{Duration, Instant, SystemTime};

fn bin() -> Command {
    let mut c = Command::new(env!("CARGO_BIN_EXE_nerflabel"));
    // An array task's index from the environment would select one line.
    c.env_remove("SLURM_ARRAY_TASK_ID").env_remove("JOB_COMPLETION_INDEX");
    c
}

fn batch(manifest: &Path, extra: &[&str]) -> Output {
    bin().arg("batch").arg(manifest).args(extra).output().unwrap()
}

/// A small clean scan at `dir/name` (clean depth: a short fit is enough to sample views).
fn scan(dir: &Path, name: &str) -> PathBuf {
    let path = dir.join(name);
    let o = bin()
        .args([
            "fixture", "--scene", "small", "--width", "160", "--height", "120", "--clean",
        ])
        .arg(&path)
        .output()
        .unwrap();
    assert!(o.status.success(), "{}", stderr(&o));
    path
}

fn status(scan: &Path) -> Value {
    let path = scan.join("nerflabel/batch.status.json");
    serde_json::from_slice(&std::fs::read(&path).unwrap()).unwrap()
}

/// Modification time and bytes of a scan's outputs (finished outputs must not be redone).
fn stamp(scan: &Path) -> Vec<(SystemTime, Vec<u8>)> {
    ["model.nlf", "model.report.json", "labels/coco.json", "synth.parquet"]
        .iter()
        .map(|f| {
            let p = scan.join("nerflabel").join(f);
            (
                std::fs::metadata(&p).unwrap().modified().unwrap(),
                std::fs::read(&p).unwrap(),
            )
        })
        .collect()
}

#[test]
fn batch_runs_refuses_twins_resumes_after_kill_9_and_merges_the_finished_scans() {
    let dir = tempfile::tempdir().unwrap();
    let (a, b) = (scan(dir.path(), "a"), scan(dir.path(), "b"));
    let c = scan(dir.path(), "c");
    // The broken scan: a colour frame that is not an image.
    std::fs::write(c.join("rgb/000002.png"), b"garbage").unwrap();
    let manifest = dir.path().join("scans.jsonl");
    let small = r#""preset": "fast", "synth_views": 3, "synth_width": 80, "synth_height": 60"#;
    std::fs::write(
        &manifest,
        format!(
            "{{\"scan\": \"a\", \"boxes\": \"a/boxes.json\", \"steps\": 150, {small}}}\n\
             {{\"scan\": \"b\", \"boxes\": \"b/boxes.json\", \"time\": 24, {small}}}\n\
             \n\
             {{\"scan\": \"c\", \"id\": \"broken\", \"steps\": 20, {small}}}\n"
        ),
    )
    .unwrap();

    // Line 0 through Kubernetes' index variable.
    let o = bin()
        .arg("batch")
        .arg(&manifest)
        .env("JOB_COMPLETION_INDEX", "0")
        .output()
        .unwrap();
    assert!(o.status.success(), "{}", stderr(&o));
    let st = status(&a);
    assert_eq!(st["state"], "done", "{st}");
    for stage in ["fit", "label", "synth"] {
        assert_eq!(st[stage]["state"], "done", "{stage}: {st}");
    }
    assert!(!b.join("nerflabel").exists(), "only line 0 ran");
    let a_done = stamp(&a);

    // The broken scan (index 2: the blank line is not counted) through Slurm's variable.
    let o = bin()
        .arg("batch")
        .arg(&manifest)
        .env("SLURM_ARRAY_TASK_ID", "2")
        .output()
        .unwrap();
    assert!(!o.status.success());
    let err = stderr(&o);
    assert!(err.contains("scan broken") && err.contains("000002.png"), "{err}");
    let st = status(&c);
    assert_eq!(
        (&st["state"], &st["fit"]["state"]),
        (&"failed".into(), &"failed".into())
    );
    let recorded = st["error"].as_str().unwrap();
    assert!(
        recorded.starts_with("fit: ") && recorded.contains("000002.png"),
        "{recorded}"
    );

    // Scan b: a second run while the first fits is refused; the first is
    // killed with SIGKILL once its fit has saved a checkpoint.
    let mut first = bin()
        .args(["batch", "--index", "1"])
        .arg(&manifest)
        .stdout(Stdio::null())
        .stderr(Stdio::null())
        .spawn()
        .unwrap();
    let checkpoint = b.join("nerflabel/model.checkpoint");
    let started = Instant::now();
    while !checkpoint.exists() {
        assert!(
            first.try_wait().unwrap().is_none(),
            "the fit ended before its first checkpoint"
        );
        assert!(
            started.elapsed() < Duration::from_secs(120),
            "no checkpoint after 120 s"
        );
        std::thread::sleep(Duration::from_millis(100));
    }
    let twin = batch(&manifest, &["--index", "1"]);
    let err = stderr(&twin);
    assert!(
        !twin.status.success()
            && err.contains("refusing to run it twice")
            && err.contains(&format!("pid {}", first.id())),
        "{err}"
    );
    first.kill().unwrap(); // SIGKILL
    first.wait().unwrap();
    assert_eq!(
        status(&b)["fit"]["state"],
        "running",
        "a killed run leaves its fit running"
    );

    // Rerun every line in turn: b resumes and finishes, a is left as it was,
    // the broken scan fails again and the run exits non-zero.
    let o = batch(&manifest, &[]);
    let err = stderr(&o);
    assert!(!o.status.success() && err.contains("1 of 3 scans failed"), "{err}");
    assert!(err.contains("[a] fit: outputs complete, skipped"), "{err}");
    let st = status(&b);
    assert_eq!(st["state"], "done", "{st}");
    assert_eq!(st["fit"]["resumed"], true, "{st}");
    let report: Value = serde_json::from_slice(&std::fs::read(b.join("nerflabel/model.report.json")).unwrap()).unwrap();
    assert_eq!(report["interrupted"], false);
    assert_eq!(report["resumed_from"].as_array().map(Vec::len), Some(1), "{report}");
    assert!(a_done == stamp(&a), "the finished scan's outputs were rewritten");

    // Merge: two scans, one per split with --val 0.5.
    let out = dir.path().join("dataset");
    let o = batch(&manifest, &["--merge", s(&out), "--val", "0.5", "--seed", "1"]);
    assert!(o.status.success(), "{}", stderr(&o));
    for id in ["a", "b"] {
        assert!(out.join(format!("synth/scan={id}/part-0.parquet")).is_file());
    }
    assert!(!out.join("synth/scan=broken").exists());
    let splits: Value = serde_json::from_slice(&std::fs::read(out.join("splits.json")).unwrap()).unwrap();
    let mut both: Vec<&str> = ["train", "val"]
        .iter()
        .flat_map(|k| splits[*k].as_array().unwrap().iter().map(|v| v.as_str().unwrap()))
        .collect();
    both.sort();
    assert_eq!(both, ["a", "b"], "{splits}");
    assert_eq!(splits["val"].as_array().unwrap().len(), 1);
    let mut images = 0;
    for split in ["train", "val"] {
        let coco: Value =
            serde_json::from_slice(&std::fs::read(out.join(format!("coco/{split}.json"))).unwrap()).unwrap();
        for image in coco["images"].as_array().unwrap() {
            let file = out.join(image["file_name"].as_str().unwrap());
            assert!(file.is_file(), "{} does not resolve from OUT", file.display());
            assert!(out.join(image["mask_file"].as_str().unwrap()).is_file());
        }
        images += coco["images"].as_array().unwrap().len();
        assert!(!coco["annotations"].as_array().unwrap().is_empty(), "{split}");
    }
    assert_eq!(images, 48, "24 frames of each finished scan");
    let summary = std::fs::read_to_string(out.join("summary.csv")).unwrap();
    let rows: Vec<&str> = summary.lines().collect();
    assert_eq!(rows.len(), 4, "{summary}");
    assert!(
        rows[1].starts_with("a,") && rows[1].contains(",done,") && rows[1].contains(",24,150,"),
        "{summary}"
    );
    assert!(rows[2].starts_with("b,") && rows[2].contains(",done,"), "{summary}");
    assert!(
        rows[3].starts_with("broken,") && rows[3].contains(",failed,") && rows[3].contains("000002.png"),
        "{summary}"
    );
    check_parquet(&out, "a", 3);
    python_loads(&out, &["a", "b"]);
}

/// The partition keeps synth's columns and metadata and adds `scan`.
fn check_parquet(out: &Path, id: &str, views: usize) {
    use arrow_array::{Array, StringArray};
    use parquet::arrow::arrow_reader::ParquetRecordBatchReaderBuilder;
    let path = out.join(format!("synth/scan={id}/part-0.parquet"));
    let builder = ParquetRecordBatchReaderBuilder::try_new(std::fs::File::open(&path).unwrap()).unwrap();
    let kv = builder.metadata().file_metadata().key_value_metadata().unwrap().clone();
    let get = |k: &str| kv.iter().find(|e| e.key == k).and_then(|e| e.value.clone());
    assert!(
        get("model_crc32").is_some() && get("seed").is_some(),
        "synth's metadata kept"
    );
    if let Some(hf) = get("huggingface") {
        let hf: Value = serde_json::from_str(&hf).unwrap();
        assert_eq!(hf["info"]["features"]["scan"]["dtype"], "string", "{hf}");
    }
    let schema = builder.schema().clone();
    let reader = builder.build().unwrap();
    let mut rows = 0;
    for batch in reader {
        let batch = batch.unwrap();
        let ids = batch.column_by_name("scan").unwrap();
        let ids = ids.as_any().downcast_ref::<StringArray>().unwrap();
        assert!((0..ids.len()).all(|i| ids.value(i) == id));
        rows += batch.num_rows();
    }
    assert_eq!(rows, views);
    assert_eq!(schema.fields().last().unwrap().name(), "scan");
    assert!(schema.field_with_name("view_id").is_ok());
}

/// pyarrow (hive partitioning), polars and `datasets` load the merged dataset; each skips when missing.
pub fn python_loads(out: &Path, ids: &[&str]) {
    let script = Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/batch/check_merged.py");
    let o = match Command::new("python3").arg(&script).arg(out).args(ids).output() {
        Ok(o) => o,
        Err(e) => {
            eprintln!("skipped the Python loads: no python3 ({e})");
            return;
        }
    };
    let text = String::from_utf8_lossy(&o.stdout);
    eprintln!("{text}");
    assert!(o.status.success(), "{text}\n{}", stderr(&o));
    assert!(text.contains("ok coco paths resolve from OUT"), "{text}");
}
