//! `nerflabel batch` end to end on three small generated scans, one broken:
//! every stage runs, a second run on a scan is refused, a run killed with
//! SIGKILL mid-fit is completed by a rerun that resumes the fit and leaves
//! the finished scan's outputs alone, the broken scan's error is in its
//! status file, and the merged dataset has what it should (and loads in
//! pyarrow, polars and `datasets` where Python has them).

mod common;

use common::batch::{batch, bin, python_loads, stamp, status, three_scans};
use common::{s, stderr};
use serde_json::Value;
use std::path::Path;
use std::process::Stdio;
use std::time::{Duration, Instant};

#[test]
fn batch_runs_refuses_twins_resumes_after_kill_9_and_merges_the_finished_scans() {
    let dir = tempfile::tempdir().unwrap();
    // b fits by steps (a time budget would leave a resumed fit on a loaded
    // machine too few steps to sample views): long enough that its first
    // checkpoint (after 10 s of training) comes well before the end.
    let (manifest, [a, b, c]) = three_scans(dir.path(), r#""steps": 800"#);

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
    // synth declares its columns to `datasets`; the merge declares `scan` too.
    let hf: Value = serde_json::from_str(&get("huggingface").expect("the huggingface features kept")).unwrap();
    assert_eq!(hf["info"]["features"]["scan"]["dtype"], "string", "{hf}");
    assert_eq!(hf["info"]["features"]["rgb"]["_type"], "Image", "{hf}");
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
