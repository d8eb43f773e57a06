//! `batch MANIFEST --merge OUT`: the finished scans as one dataset.
//!
//! - `OUT/synth/scan=<id>/part-0.parquet`: each scan's synthetic views with
//!   every column synth wrote, a `scan` column added (hive partitioning
//!   gives the same value from the path) and the file metadata kept, the
//!   `huggingface` features included (with `scan` added);
//! - `OUT/coco/<split>.json`: the labels of the scans of each split (scans
//!   drawn into train/val/test with a seed), ids renumbered, categories
//!   joined by name, `file_name` and `mask_file` relative to OUT;
//! - `OUT/splits.json` (the scan ids of each split) and `OUT/summary.csv`
//!   (one row a scan: state, frames, fit figures, labels, views, error).
//!
//! Every file is written atomically; OUT carries the marker `.nerflabel-merge`
//! and a merge never writes into a non-empty folder without it.

use super::coco_merge::merge_coco;
use super::error::BatchError;
use super::manifest::{Entry, Manifest};
use super::partition::{copy_partition, remove_stale_partitions};
use super::stages::{parquet_rows, ScanOutputs};
use super::status::{ScanStatus, StageState};
use crate::outputs::{lock_output, resolve};
use crate::rng::Rng;
use serde_json::{json, Value};
use std::collections::{BTreeSet, HashMap};
use std::path::{Path, PathBuf};

/// Marker file of a merged dataset folder.
pub const MERGE_MARKER: &str = ".nerflabel-merge";
/// Name of the id column and of the hive partition key.
pub const ID_COLUMN: &str = "scan";
/// Largest COCO file read, bytes.
const MAX_COCO_BYTES: u64 = 4 << 30;
/// RNG stream of the split (separate from every other use of a seed).
const SPLIT_STREAM: u64 = 0x5_9117;

/// How the scans are split.
#[derive(Clone, Copy, Debug)]
pub struct MergeOptions {
    /// Share of the scans in the validation split.
    pub val: f64,
    /// Share of the scans in the test split (no test file when 0).
    pub test: f64,
    pub seed: u64,
}

impl Default for MergeOptions {
    fn default() -> Self {
        MergeOptions {
            val: 0.2,
            test: 0.0,
            seed: 0,
        }
    }
}

/// One scan's row of the summary.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct ScanRow {
    pub id: String,
    pub scan: String,
    /// done, failed, running, interrupted, not run, no scan folder.
    pub state: String,
    pub split: Option<String>,
    pub frames: Option<u64>,
    pub fit_steps: Option<u64>,
    pub fit_seconds: Option<f64>,
    pub psnr_db: Option<f64>,
    pub ssim: Option<f64>,
    pub depth_mae_mm: Option<f64>,
    pub labelled_frames: Option<u64>,
    pub annotations: Option<u64>,
    pub synth_views: Option<u64>,
    pub error: Option<String>,
}

/// What a merge wrote.
#[derive(Clone, Debug)]
pub struct MergeSummary {
    pub out: PathBuf,
    pub rows: Vec<ScanRow>,
    /// Split name and scan ids, in file order.
    pub splits: Vec<(String, Vec<String>)>,
}

impl MergeSummary {
    /// Scans merged (state done).
    pub fn merged(&self) -> usize {
        self.rows.iter().filter(|r| r.state == "done").count()
    }
}

/// Merge the finished scans of `manifest` into `out`.
pub fn merge(manifest: &Manifest, out: &Path, options: &MergeOptions) -> Result<MergeSummary, BatchError> {
    for (name, share) in [("--val", options.val), ("--test", options.test)] {
        if !(0.0..1.0).contains(&share) {
            return Err(BatchError::Output {
                path: out.to_path_buf(),
                what: format!("{name} {share}: expected a share of the scans, at least 0 and below 1"),
            });
        }
    }
    if options.val + options.test >= 1.0 {
        return Err(BatchError::Output {
            path: out.to_path_buf(),
            what: format!(
                "--val {} and --test {} leave no scan for training",
                options.val, options.test
            ),
        });
    }
    prepare_out(manifest, out)?;
    let _lock = lock_output(out, "this merged dataset")?;
    let out_abs = resolve(out);

    let mut rows: Vec<ScanRow> = Vec::new();
    let mut done: Vec<&Entry> = Vec::new();
    for entry in &manifest.entries {
        let (row, finished) = scan_row(entry)?;
        if finished {
            done.push(entry);
        }
        rows.push(row);
    }
    let splits = split(&done, options);
    let split_of: HashMap<&str, &str> = splits
        .iter()
        .flat_map(|(name, ids)| ids.iter().map(move |id| (id.as_str(), name.as_str())))
        .collect();
    for row in &mut rows {
        row.split = split_of.get(row.id.as_str()).map(|s| s.to_string());
    }

    // Synthetic views, one partition a scan; partitions of scans no longer finished go.
    let synth_root = out.join("synth");
    let mut partitions = BTreeSet::new();
    for entry in &done {
        let src = ScanOutputs::of(entry).synth;
        if entry.synth_views == 0 || parquet_rows(&src).is_none() {
            continue;
        }
        let dir = synth_root.join(format!("{ID_COLUMN}={}", entry.id));
        let views = copy_partition(&src, &dir.join("part-0.parquet"), &entry.id)?;
        if let Some(row) = rows.iter_mut().find(|r| r.id == entry.id) {
            row.synth_views = Some(views);
        }
        partitions.insert(dir.file_name().map(|n| n.to_os_string()).unwrap_or_default());
    }
    remove_stale_partitions(&synth_root, &partitions)?;

    // COCO per split.
    let coco_dir = out.join("coco");
    for (name, ids) in &splits {
        let scans: Vec<&Entry> = ids
            .iter()
            .filter_map(|id| done.iter().find(|e| &e.id == id).copied())
            .filter(|e| e.labels())
            .collect();
        let coco = merge_coco(&scans, &out_abs, name)?;
        let path = coco_dir.join(format!("{name}.json"));
        write_json(&path, &coco)?;
    }
    if options.test == 0.0 {
        remove_file_if_there(&coco_dir.join("test.json"))?;
    }
    let splits_json: serde_json::Map<String, Value> =
        splits.iter().map(|(name, ids)| (name.clone(), json!(ids))).collect();
    write_json(&out.join("splits.json"), &Value::Object(splits_json))?;
    let csv = summary_csv(&rows);
    let path = out.join("summary.csv");
    crate::atomic::write_file(&path, csv.as_bytes()).map_err(BatchError::io(&path, "write the summary"))?;
    Ok(MergeSummary {
        out: out.to_path_buf(),
        rows,
        splits,
    })
}

/// Create OUT with its marker; refuse a non-empty folder without it and an
/// OUT inside a scan folder.
fn prepare_out(manifest: &Manifest, out: &Path) -> Result<(), BatchError> {
    if out.exists() && !out.is_dir() {
        return Err(BatchError::Output {
            path: out.to_path_buf(),
            what: "is a file, expected a folder for the merged dataset".into(),
        });
    }
    let out_abs = resolve(out);
    for entry in &manifest.entries {
        let scan = resolve(&entry.scan);
        if out_abs.starts_with(&scan) || scan.starts_with(&out_abs) {
            return Err(BatchError::Output {
                path: out.to_path_buf(),
                what: format!(
                    "the merged dataset must lie outside every scan folder, and contain none ({})",
                    entry.scan.display()
                ),
            });
        }
    }
    let marker = out.join(MERGE_MARKER);
    if out.is_dir() && !marker.exists() {
        let mut items = std::fs::read_dir(out).map_err(BatchError::io(out, "list the output folder"))?;
        if items.next().is_some() {
            return Err(BatchError::Output {
                path: out.to_path_buf(),
                what: format!("not empty and not an earlier merge (no {MERGE_MARKER}); choose an empty or new folder"),
            });
        }
    }
    std::fs::create_dir_all(out).map_err(BatchError::io(out, "create the output folder"))?;
    crate::atomic::write_file(&marker, b"nerflabel merged dataset\n")
        .map_err(BatchError::io(&marker, "write the marker"))
}

/// A scan's summary row and whether it finished.
fn scan_row(entry: &Entry) -> Result<(ScanRow, bool), BatchError> {
    let mut row = ScanRow {
        id: entry.id.clone(),
        scan: entry.scan.display().to_string(),
        ..ScanRow::default()
    };
    if !entry.scan.is_dir() {
        row.state = "no scan folder".into();
        return Ok((row, false));
    }
    let out = ScanOutputs::of(entry);
    let Some(status) = ScanStatus::read(&out.status)? else {
        row.state = "not run".into();
        return Ok((row, false));
    };
    row.state = state_name(status.state).into();
    row.error = status.error.clone();
    if status.fit.state == StageState::Done {
        if let Some(report) = read_json(&out.report) {
            let holdout = report["holdout_frames"].as_array().map_or(0, |a| a.len() as u64);
            row.frames = report["train_frames"].as_u64().map(|t| t + holdout);
            row.fit_steps = report["counters"]["steps"].as_u64();
            row.fit_seconds = report["timings"]["train_s"].as_f64();
            let last = report["curve"]
                .as_array()
                .and_then(|c| c.last())
                .cloned()
                .unwrap_or_default();
            row.psnr_db = last["psnr"].as_f64();
            row.ssim = last["ssim"].as_f64();
            row.depth_mae_mm = last["depth_mae_m"].as_f64().map(|m| m * 1e3);
        }
    }
    let finished = status.state == StageState::Done;
    if finished && status.label.state == StageState::Done {
        if let Some(coco) = read_json(&out.labels.join("coco.json")) {
            row.labelled_frames = coco["images"].as_array().map(|a| a.len() as u64);
            row.annotations = coco["annotations"].as_array().map(|a| a.len() as u64);
        }
    }
    Ok((row, finished))
}

fn state_name(state: StageState) -> &'static str {
    match state {
        StageState::Pending => "pending",
        StageState::Running => "running",
        StageState::Done => "done",
        StageState::Failed => "failed",
        StageState::Interrupted => "interrupted",
        StageState::Skipped => "skipped",
    }
}

pub(super) fn read_json(path: &Path) -> Option<Value> {
    let len = std::fs::metadata(path).ok()?.len();
    if len > MAX_COCO_BYTES {
        return None;
    }
    serde_json::from_slice(&std::fs::read(path).ok()?).ok()
}

/// The finished scans drawn into train, val (and test), by scan: ids
/// sorted, shuffled with the seed, val and test take their rounded shares
/// (at least one scan each when the share is above 0 and a scan is left for
/// training), train the rest.
fn split(done: &[&Entry], options: &MergeOptions) -> Vec<(String, Vec<String>)> {
    let mut ids: Vec<String> = done.iter().map(|e| e.id.clone()).collect();
    ids.sort();
    let mut rng = Rng::new(options.seed, SPLIT_STREAM);
    for i in (1..ids.len()).rev() {
        let j = rng.below(i as u64 + 1) as usize;
        ids.swap(i, j);
    }
    let n = ids.len();
    let share = |f: f64, left: usize| -> usize {
        if f <= 0.0 || left <= 1 {
            return 0;
        }
        ((n as f64 * f).round() as usize).clamp(1, left - 1)
    };
    let n_val = share(options.val, n);
    let n_test = share(options.test, n - n_val);
    let val = ids.drain(..n_val).collect::<Vec<_>>();
    let test = ids.drain(..n_test).collect::<Vec<_>>();
    let mut splits = vec![("train".to_string(), sorted(ids)), ("val".to_string(), sorted(val))];
    if options.test > 0.0 {
        splits.push(("test".to_string(), sorted(test)));
    }
    splits
}

fn sorted(mut v: Vec<String>) -> Vec<String> {
    v.sort();
    v
}

fn remove_file_if_there(path: &Path) -> Result<(), BatchError> {
    match std::fs::remove_file(path) {
        Err(e) if e.kind() != std::io::ErrorKind::NotFound => Err(BatchError::io(path, "remove a stale file")(e)),
        _ => Ok(()),
    }
}

fn write_json(path: &Path, value: &Value) -> Result<(), BatchError> {
    let bytes = serde_json::to_vec(value).map_err(|e| BatchError::Invalid {
        path: path.to_path_buf(),
        problem: format!("cannot serialise: {e}"),
    })?;
    crate::atomic::write_file(path, &bytes).map_err(BatchError::io(path, "write"))
}

/// The summary table as CSV (RFC 4180 quoting).
fn summary_csv(rows: &[ScanRow]) -> String {
    let mut s = String::from(
        "scan_id,scan,state,split,frames,fit_steps,fit_seconds,psnr_db,ssim,depth_mae_mm,labelled_frames,annotations,synth_views,error\n",
    );
    let num = |v: Option<u64>| v.map(|v| v.to_string()).unwrap_or_default();
    let float = |v: Option<f64>, digits: usize| v.map(|v| format!("{v:.digits$}")).unwrap_or_default();
    for r in rows {
        let fields = [
            quote(&r.id),
            quote(&r.scan),
            quote(&r.state),
            quote(r.split.as_deref().unwrap_or("")),
            num(r.frames),
            num(r.fit_steps),
            float(r.fit_seconds, 1),
            float(r.psnr_db, 2),
            float(r.ssim, 3),
            float(r.depth_mae_mm, 1),
            num(r.labelled_frames),
            num(r.annotations),
            num(r.synth_views),
            quote(r.error.as_deref().unwrap_or("")),
        ];
        s.push_str(&fields.join(","));
        s.push('\n');
    }
    s
}

fn quote(text: &str) -> String {
    if text.contains([',', '"', '\n', '\r']) {
        format!("\"{}\"", text.replace('"', "\"\""))
    } else {
        text.to_string()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::batch::manifest::parse_manifest;

    fn entries(n: usize) -> Vec<Entry> {
        let text: String = (0..n).map(|i| format!("{{\"scan\": \"s{i}\"}}\n")).collect();
        parse_manifest(&text, Path::new("m.jsonl"), Path::new("/d"))
            .unwrap()
            .entries
    }

    #[test]
    fn the_split_is_by_scan_seeded_and_keeps_a_training_scan() {
        let e = entries(10);
        let refs: Vec<&Entry> = e.iter().collect();
        let options = MergeOptions {
            val: 0.2,
            test: 0.1,
            seed: 3,
        };
        let a = split(&refs, &options);
        assert_eq!(a, split(&refs, &options), "same seed, same split");
        let sizes: Vec<usize> = a.iter().map(|(_, ids)| ids.len()).collect();
        assert_eq!(sizes, vec![7, 2, 1]);
        let all: BTreeSet<&String> = a.iter().flat_map(|(_, ids)| ids).collect();
        assert_eq!(all.len(), 10, "each scan in exactly one split");
        let other = split(&refs, &MergeOptions { seed: 4, ..options });
        assert_ne!(a, other, "another seed draws other scans");
        // Two scans: one trains, one validates; one scan only trains.
        let two = split(&refs[..2], &MergeOptions::default());
        assert_eq!((two[0].1.len(), two[1].1.len()), (1, 1));
        let one = split(&refs[..1], &MergeOptions::default());
        assert_eq!((one[0].1.len(), one[1].1.len()), (1, 0));
    }

    /// A finished scan `name` under `root` whose labels have `categories`
    /// (id, name) and one image with one annotation of each.
    fn labelled_scan(root: &Path, name: &str, categories: &[(u64, &str)]) {
        let scan = root.join(name);
        let labels = scan.join("nerflabel/labels");
        std::fs::create_dir_all(labels.join("masks")).unwrap();
        std::fs::create_dir_all(scan.join("rgb")).unwrap();
        std::fs::write(scan.join("rgb/000000.png"), b"png").unwrap();
        std::fs::write(labels.join("masks/000000.png"), b"png").unwrap();
        let annotations: Vec<Value> = categories
            .iter()
            .enumerate()
            .map(|(i, (id, _))| json!({"id": i + 1, "image_id": 7, "category_id": id, "bbox": [0, 0, 1, 1]}))
            .collect();
        let coco = json!({
            "info": {"image_root": resolve(&scan).display().to_string()},
            "images": [{"id": 7, "file_name": "rgb/000000.png", "mask_file": "masks/000000.png", "width": 4, "height": 3}],
            "categories": categories.iter().map(|(id, n)| json!({"id": id, "name": n})).collect::<Vec<_>>(),
            "annotations": annotations,
        });
        std::fs::write(labels.join("coco.json"), coco.to_string()).unwrap();
        let mut status = ScanStatus {
            state: StageState::Done,
            ..ScanStatus::default()
        };
        status.label.state = StageState::Done;
        status
            .write(&crate::batch::status::status_path(&scan.join("nerflabel")))
            .unwrap();
    }

    #[test]
    fn coco_files_join_categories_by_name_renumber_ids_and_resolve_paths_from_out() {
        let dir = tempfile::tempdir().unwrap();
        labelled_scan(dir.path(), "s0", &[(1, "mug"), (2, "ball")]);
        labelled_scan(dir.path(), "s1", &[(1, "ball"), (2, "can")]);
        let text = "{\"scan\": \"s0\", \"boxes\": \"b.json\", \"synth_views\": 0}\n{\"scan\": \"s1\", \"boxes\": \"b.json\", \"synth_views\": 0}\n{\"scan\": \"gone\"}\n";
        let manifest = parse_manifest(text, &dir.path().join("m.jsonl"), dir.path()).unwrap();
        let out = dir.path().join("out");
        let options = MergeOptions {
            val: 0.0,
            ..MergeOptions::default()
        };
        let summary = merge(&manifest, &out, &options).unwrap();
        assert_eq!(summary.merged(), 2);
        assert_eq!(summary.rows[2].state, "no scan folder");
        let train: Value = serde_json::from_slice(&std::fs::read(out.join("coco/train.json")).unwrap()).unwrap();
        let names: Vec<&str> = train["categories"]
            .as_array()
            .unwrap()
            .iter()
            .map(|c| c["name"].as_str().unwrap())
            .collect();
        assert_eq!(names, ["ball", "can", "mug"]);
        let images = train["images"].as_array().unwrap();
        assert_eq!(
            images.iter().map(|i| i["id"].as_u64().unwrap()).collect::<Vec<_>>(),
            [1, 2]
        );
        assert_eq!(images[1]["scan"], "s1");
        for image in images {
            assert!(out.join(image["file_name"].as_str().unwrap()).is_file(), "{image}");
            assert!(out.join(image["mask_file"].as_str().unwrap()).is_file(), "{image}");
        }
        // s1's `ball` (its category 1) and `can` (2) are ball = 1 and can = 2 in the merged file;
        // s0's `mug` (1) is 3.
        let pairs: Vec<(u64, u64)> = train["annotations"]
            .as_array()
            .unwrap()
            .iter()
            .map(|a| (a["image_id"].as_u64().unwrap(), a["category_id"].as_u64().unwrap()))
            .collect();
        assert_eq!(pairs, [(1, 3), (1, 1), (2, 1), (2, 2)]);
        let val: Value = serde_json::from_slice(&std::fs::read(out.join("coco/val.json")).unwrap()).unwrap();
        assert!(val["images"].as_array().unwrap().is_empty());

        // A folder that is not an earlier merge is refused; an earlier merge is updated.
        let other = dir.path().join("other");
        std::fs::create_dir_all(&other).unwrap();
        std::fs::write(other.join("keep.txt"), b"x").unwrap();
        let err = merge(&manifest, &other, &options).unwrap_err().to_string();
        assert!(err.contains("not empty and not an earlier merge"), "{err}");
        merge(&manifest, &out, &options).unwrap();
    }

    #[test]
    fn csv_fields_with_commas_or_quotes_are_quoted() {
        let rows = [ScanRow {
            id: "a".into(),
            state: "failed".into(),
            error: Some("fit: bad \"depth\", frame 3".into()),
            psnr_db: Some(27.456),
            ..ScanRow::default()
        }];
        let csv = summary_csv(&rows);
        assert!(
            csv.ends_with("a,,failed,,,,,27.46,,,,,,\"fit: bad \"\"depth\"\", frame 3\"\n"),
            "{csv}"
        );
    }
}
