//! Helpers of the `nerflabel batch` tests: generated scans, status files,
//! output stamps and the Python loads of a merged dataset.

use super::stderr;
use serde_json::Value;
use std::path::{Path, PathBuf};
use std::process::{Command, Output};
use std::time::SystemTime;

pub fn bin() -> Command {
    let mut c = Command::new(env!("CARGO_BIN_EXE_nerflabel"));
    // An array task's index from the environment would select one line.
    c.env_remove("SLURM_ARRAY_TASK_ID").env_remove("JOB_COMPLETION_INDEX");
    c
}

pub fn batch(manifest: &Path, extra: &[&str]) -> Output {
    bin().arg("batch").arg(manifest).args(extra).output().unwrap()
}

/// A small clean scan at `dir/name` (clean depth: a short fit is enough to sample views).
pub fn scan(dir: &Path, name: &str) -> PathBuf {
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

pub fn status(scan: &Path) -> Value {
    let path = scan.join("nerflabel/batch.status.json");
    serde_json::from_slice(&std::fs::read(&path).unwrap()).unwrap()
}

/// Modification time and bytes of a scan's outputs (finished outputs must not be redone).
pub fn stamp(scan: &Path) -> Vec<(SystemTime, Vec<u8>)> {
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
    if text.contains("ok datasets") {
        assert!(
            text.contains("image columns ['rgb', 'depth', 'mask']"),
            "datasets decodes the image columns: {text}"
        );
    }
}

/// Three generated scans `a`, `b` and `c` under `dir` (`c` broken: a colour
/// frame that is not an image, id `broken`) and their manifest
/// `dir/scans.jsonl` (a blank line before `c`); `b_budget` is b's fit budget
/// (e.g. `"steps": 150`). Returns the manifest and the three scans.
pub fn three_scans(dir: &Path, b_budget: &str) -> (PathBuf, [PathBuf; 3]) {
    let (a, b, c) = (scan(dir, "a"), scan(dir, "b"), scan(dir, "c"));
    std::fs::write(c.join("rgb/000002.png"), b"garbage").unwrap();
    let manifest = dir.join("scans.jsonl");
    let small = r#""preset": "fast", "synth_views": 3, "synth_width": 80, "synth_height": 60"#;
    std::fs::write(
        &manifest,
        format!(
            "{{\"scan\": \"a\", \"boxes\": \"a/boxes.json\", \"steps\": 150, {small}}}\n\
             {{\"scan\": \"b\", \"boxes\": \"b/boxes.json\", {b_budget}, {small}}}\n\
             \n\
             {{\"scan\": \"c\", \"id\": \"broken\", \"steps\": 20, {small}}}\n"
        ),
    )
    .unwrap();
    (manifest, [a, b, c])
}
