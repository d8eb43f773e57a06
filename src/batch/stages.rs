//! One scan's batch run: take the scan's lock, then run fit, label and synth
//! in turn, skipping a stage whose outputs are complete and were made from
//! what the manifest asks now, resuming a fit a killed or stopped run left
//! behind, and recording every step in the scan's status file.

use super::error::BatchError;
use super::manifest::Entry;
use super::status::{now_unix, status_path, ScanStatus, StageRecord, StageState};
use crate::nerf::train::checkpoint::checkpoint_path;
use crate::nerf::train::report::report_path;
use crate::outputs::{lock_output, OutputError};
use std::path::{Path, PathBuf};
use std::time::Instant;

/// A stage of a scan's run.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Stage {
    Fit,
    Label,
    Synth,
}

impl Stage {
    pub fn name(self) -> &'static str {
        match self {
            Stage::Fit => "fit",
            Stage::Label => "label",
            Stage::Synth => "synth",
        }
    }
}

/// What runs the stages (the CLI's `fit`, `label` and `synth`). Each writes
/// its outputs atomically to the default places under SCAN/nerflabel; an
/// error is returned as its full message.
pub trait Stages {
    /// Fit the scan's model; `resume` continues from the checkpoint beside it.
    fn fit(&mut self, entry: &Entry, resume: bool) -> Result<(), String>;
    /// Label the scan's boxes and/or masks into SCAN/nerflabel/labels.
    fn label(&mut self, entry: &Entry) -> Result<(), String>;
    /// Render the scan's synthetic views into SCAN/nerflabel/synth.parquet, replacing an older file.
    fn synth(&mut self, entry: &Entry) -> Result<(), String>;
    /// Whether a signal asked the run to stop (a stage then saved what it had).
    fn interrupted(&self) -> bool;
    /// Told before a stage starts (`resumed` for a fit from its checkpoint) or is skipped.
    fn note(&mut self, _entry: &Entry, _stage: Stage, _what: StageNote) {}
}

/// What happens to a stage.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum StageNote {
    /// Outputs complete and current: not run again.
    Complete,
    /// Not asked for by the manifest line.
    NotAsked,
    Start,
    Resume,
}

/// How a scan's run ended.
#[derive(Clone, Debug, PartialEq)]
pub enum EntryOutcome {
    /// Every stage done; `ran` were run now, the others were complete already or not asked for.
    Done {
        ran: Vec<Stage>,
    },
    Failed {
        stage: Stage,
        error: String,
    },
    /// A signal stopped the run after `stage` saved its work.
    Interrupted {
        stage: Stage,
    },
}

/// The default output paths of a scan.
pub struct ScanOutputs {
    pub model: PathBuf,
    pub report: PathBuf,
    pub checkpoint: PathBuf,
    pub labels: PathBuf,
    pub synth: PathBuf,
    pub status: PathBuf,
}

impl ScanOutputs {
    pub fn of(entry: &Entry) -> ScanOutputs {
        let work = entry.work_dir();
        let model = work.join("model.nlf");
        ScanOutputs {
            report: report_path(&model),
            checkpoint: checkpoint_path(&model),
            labels: work.join("labels"),
            synth: work.join("synth.parquet"),
            status: status_path(&work),
            model,
        }
    }
}

/// Run one scan: lock it, run or skip each stage, keep its status file.
/// A stage's failure is recorded and returned as [`EntryOutcome::Failed`];
/// `Err` means the run could not start (no scan folder, a second run, a
/// status file that cannot be written).
pub fn run_entry(entry: &Entry, stages: &mut dyn Stages) -> Result<EntryOutcome, BatchError> {
    if !entry.scan.is_dir() {
        return Err(BatchError::ScanMissing {
            scan: entry.scan.clone(),
            line: entry.line,
        });
    }
    let work = entry.work_dir();
    let _lock = lock_output(&work.join("batch"), "this scan").map_err(|e| match e {
        OutputError::Locked { holder, .. } => BatchError::Output {
            path: entry.scan.clone(),
            what: format!(
                "another nerflabel batch run{holder} is working on this scan (manifest line {}, id {}); refusing to run it twice at once",
                entry.line, entry.id
            ),
        },
        other => BatchError::Busy {
            scan: entry.scan.clone(),
            source: other,
        },
    })?;
    let out = ScanOutputs::of(entry);
    // An unreadable status (hand-edited, another tool's) is started afresh.
    let before = ScanStatus::read(&out.status).ok().flatten().unwrap_or_default();
    let mut status = ScanStatus {
        nerflabel_version: env!("CARGO_PKG_VERSION").into(),
        id: entry.id.clone(),
        scan: crate::outputs::resolve(&entry.scan).display().to_string(),
        line: entry.line,
        state: StageState::Running,
        error: None,
        started: now_unix(),
        finished: None,
        host: host_name(),
        pid: std::process::id(),
        slurm_job: slurm_job(),
        ..before
    };
    status.write(&out.status)?;

    let mut ran = Vec::new();
    for stage in [Stage::Fit, Stage::Label, Stage::Synth] {
        let plan = plan(stage, entry, &out, &status);
        let record = record_mut(&mut status, stage);
        match plan {
            Plan::NotAsked => {
                *record = StageRecord {
                    state: StageState::Skipped,
                    ..StageRecord::default()
                };
                stages.note(entry, stage, StageNote::NotAsked);
                continue;
            }
            Plan::Complete => {
                stages.note(entry, stage, StageNote::Complete);
                continue;
            }
            Plan::Run { made_from, resume } => {
                record.state = StageState::Running;
                record.made_from = made_from;
                record.runs = record.runs.saturating_add(1);
                record.resumed = resume;
                record.error = None;
                record.model_crc32 = None;
                status.write(&out.status)?;
                stages.note(entry, stage, if resume { StageNote::Resume } else { StageNote::Start });
                let started = Instant::now();
                let result = match stage {
                    Stage::Fit => stages.fit(entry, resume),
                    Stage::Label => stages.label(entry),
                    Stage::Synth => stages.synth(entry),
                };
                let record = record_mut(&mut status, stage);
                record.seconds = started.elapsed().as_secs_f64();
                if stages.interrupted() {
                    record.state = StageState::Interrupted;
                    status.state = StageState::Interrupted;
                    status.finished = Some(now_unix());
                    status.write(&out.status)?;
                    return Ok(EntryOutcome::Interrupted { stage });
                }
                let result = result.and_then(|()| check_made(stage, &out));
                match result {
                    Ok(crc) => {
                        record.state = StageState::Done;
                        record.model_crc32 = crc;
                        status.write(&out.status)?;
                        ran.push(stage);
                    }
                    Err(error) => {
                        record.state = StageState::Failed;
                        record.error = Some(error.clone());
                        status.state = StageState::Failed;
                        status.error = Some(format!("{}: {error}", stage.name()));
                        status.finished = Some(now_unix());
                        status.write(&out.status)?;
                        return Ok(EntryOutcome::Failed { stage, error });
                    }
                }
            }
        }
    }
    status.state = StageState::Done;
    status.finished = Some(now_unix());
    status.write(&out.status)?;
    Ok(EntryOutcome::Done { ran })
}

fn record_mut(status: &mut ScanStatus, stage: Stage) -> &mut StageRecord {
    match stage {
        Stage::Fit => &mut status.fit,
        Stage::Label => &mut status.label,
        Stage::Synth => &mut status.synth,
    }
}

/// What to do with a stage.
#[derive(Debug, PartialEq)]
enum Plan {
    NotAsked,
    Complete,
    Run { made_from: String, resume: bool },
}

fn plan(stage: Stage, entry: &Entry, out: &ScanOutputs, status: &ScanStatus) -> Plan {
    let model_crc = || file_crc32(&out.model).map(hex).unwrap_or_else(|| "none".into());
    match stage {
        Stage::Fit => {
            let made_from = format!(
                "time={:?} steps={:?} seed={} preset={}",
                entry.time, entry.steps, entry.seed, entry.preset
            );
            let rec = &status.fit;
            let same = rec.made_from == made_from;
            if same && rec.state == StageState::Done && fit_complete(out, rec) {
                return Plan::Complete;
            }
            // A fit a killed or stopped run left behind goes on from its checkpoint.
            let resume =
                same && matches!(rec.state, StageState::Running | StageState::Interrupted) && out.checkpoint.is_file();
            Plan::Run { made_from, resume }
        }
        Stage::Label => {
            if !entry.labels() {
                return Plan::NotAsked;
            }
            let made_from = format!(
                "model={} boxes={} masks={}",
                model_crc(),
                input_tag(entry.boxes.as_deref()),
                entry.masks.as_ref().map_or("none".into(), |m| m.display().to_string())
            );
            let rec = &status.label;
            if rec.state == StageState::Done && rec.made_from == made_from && out.labels.join("coco.json").is_file() {
                return Plan::Complete;
            }
            Plan::Run {
                made_from,
                resume: false,
            }
        }
        Stage::Synth => {
            if entry.synth_views == 0 {
                return Plan::NotAsked;
            }
            let made_from = format!(
                "model={} views={} size={}x{} seed={} boxes={} masks={}",
                model_crc(),
                entry.synth_views,
                entry.synth_width.map_or("scan".into(), |w| w.to_string()),
                entry.synth_height.map_or("scan".into(), |h| h.to_string()),
                entry.seed,
                input_tag(entry.boxes.as_deref()),
                entry.masks.as_ref().map_or("none".into(), |m| m.display().to_string())
            );
            let rec = &status.synth;
            if rec.state == StageState::Done && rec.made_from == made_from && parquet_rows(&out.synth).is_some() {
                return Plan::Complete;
            }
            Plan::Run {
                made_from,
                resume: false,
            }
        }
    }
}

/// The model is the one the finished fit wrote and its report says it finished.
fn fit_complete(out: &ScanOutputs, rec: &StageRecord) -> bool {
    let crc = file_crc32(&out.model).map(hex);
    crc.is_some() && crc == rec.model_crc32 && read_report(&out.report).is_some_and(|r| !r.interrupted)
}

/// After a stage returned: its outputs are there; the fit's model CRC-32.
fn check_made(stage: Stage, out: &ScanOutputs) -> Result<Option<String>, String> {
    match stage {
        Stage::Fit => {
            let report = read_report(&out.report)
                .ok_or_else(|| format!("{}: no readable fit report after the fit", out.report.display()))?;
            if report.interrupted {
                return Err(format!(
                    "{}: the fit stopped before its budget (interrupted)",
                    out.report.display()
                ));
            }
            let crc =
                file_crc32(&out.model).ok_or_else(|| format!("{}: no model after the fit", out.model.display()))?;
            Ok(Some(hex(crc)))
        }
        Stage::Label => {
            let coco = out.labels.join("coco.json");
            if coco.is_file() {
                Ok(None)
            } else {
                Err(format!("{}: no COCO file after labelling", coco.display()))
            }
        }
        Stage::Synth => match parquet_rows(&out.synth) {
            Some(_) => Ok(None),
            None => Err(format!("{}: no readable Parquet file after synth", out.synth.display())),
        },
    }
}

/// A boxes file as path and CRC-32 (a changed file relabels).
fn input_tag(path: Option<&Path>) -> String {
    match path {
        None => "none".into(),
        Some(p) => format!(
            "{}:{}",
            p.display(),
            file_crc32(p).map(hex).unwrap_or_else(|| "missing".into())
        ),
    }
}

pub(crate) fn hex(crc: u32) -> String {
    format!("{crc:08x}")
}

/// CRC-32 of a file's bytes, `None` when it cannot be read.
pub(crate) fn file_crc32(path: &Path) -> Option<u32> {
    use std::io::Read;
    let mut file = std::fs::File::open(path).ok()?;
    let mut hasher = crc32fast::Hasher::new();
    let mut buf = vec![0u8; 1 << 20];
    loop {
        let n = file.read(&mut buf).ok()?;
        if n == 0 {
            break;
        }
        hasher.update(buf.get(..n)?);
    }
    Some(hasher.finalize())
}

/// The part of a fit report the batch reads.
#[derive(serde::Deserialize)]
pub(crate) struct ReportState {
    pub interrupted: bool,
}

pub(crate) fn read_report(path: &Path) -> Option<ReportState> {
    let bytes = std::fs::read(path).ok()?;
    serde_json::from_slice(&bytes).ok()
}

/// Rows of a Parquet file whose footer reads, `None` otherwise.
pub(crate) fn parquet_rows(path: &Path) -> Option<i64> {
    use parquet::file::reader::{FileReader, SerializedFileReader};
    let file = std::fs::File::open(path).ok()?;
    let reader = SerializedFileReader::new(file).ok()?;
    let rows = reader.metadata().file_metadata().num_rows();
    (rows > 0).then_some(rows)
}

fn host_name() -> String {
    std::fs::read_to_string("/proc/sys/kernel/hostname")
        .map(|h| h.trim().to_string())
        .or_else(|_| std::env::var("HOSTNAME"))
        .unwrap_or_default()
}

/// `ARRAYJOB_TASK` (or the job id) when running under Slurm.
fn slurm_job() -> Option<String> {
    let var = |name| std::env::var(name).ok().filter(|v: &String| !v.is_empty());
    match (var("SLURM_ARRAY_JOB_ID"), var("SLURM_ARRAY_TASK_ID")) {
        (Some(job), Some(task)) => Some(format!("{job}_{task}")),
        _ => var("SLURM_JOB_ID"),
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::batch::manifest::parse_manifest;

    /// Stages that write stand-in outputs, count calls and fail on demand.
    struct Fake {
        calls: Vec<(Stage, bool)>,
        fail: Option<Stage>,
        /// A signal arrives during this stage (it saves and returns Ok).
        signal: Option<Stage>,
    }

    fn report(interrupted: bool) -> String {
        format!("{{\"steps\": 3, \"interrupted\": {interrupted}}}")
    }

    impl Stages for Fake {
        fn fit(&mut self, entry: &Entry, resume: bool) -> Result<(), String> {
            self.calls.push((Stage::Fit, resume));
            if self.signal == Some(Stage::Fit) {
                let out = ScanOutputs::of(entry);
                std::fs::create_dir_all(entry.work_dir()).unwrap();
                std::fs::write(&out.checkpoint, b"ckpt").unwrap();
                std::fs::write(&out.report, report(true)).unwrap();
                return Ok(());
            }
            if self.fail == Some(Stage::Fit) {
                return Err("cannot read the scan".into());
            }
            let out = ScanOutputs::of(entry);
            std::fs::create_dir_all(entry.work_dir()).unwrap();
            // Every fit writes another model.
            let fits = self.calls.iter().filter(|(s, _)| *s == Stage::Fit).count();
            std::fs::write(&out.model, format!("model {fits}")).unwrap();
            std::fs::write(&out.report, report(false)).unwrap();
            Ok(())
        }
        fn label(&mut self, entry: &Entry) -> Result<(), String> {
            self.calls.push((Stage::Label, false));
            let out = ScanOutputs::of(entry);
            std::fs::create_dir_all(&out.labels).unwrap();
            std::fs::write(out.labels.join("coco.json"), b"{}").unwrap();
            Ok(())
        }
        fn synth(&mut self, _entry: &Entry) -> Result<(), String> {
            self.calls.push((Stage::Synth, false));
            Ok(())
        }
        fn interrupted(&self) -> bool {
            self.signal
                .is_some_and(|stage| self.calls.iter().any(|(s, _)| *s == stage))
        }
    }

    fn entry(dir: &Path, line: &str) -> Entry {
        std::fs::create_dir_all(dir.join("scan")).unwrap();
        let m = parse_manifest(line, Path::new("m.jsonl"), dir).unwrap();
        m.entries[0].clone()
    }

    #[test]
    fn a_rerun_skips_complete_stages_and_redoes_what_a_changed_input_invalidates() {
        let dir = tempfile::tempdir().unwrap();
        std::fs::write(dir.path().join("boxes.json"), b"[1]").unwrap();
        let e = entry(
            dir.path(),
            "{\"scan\": \"scan\", \"boxes\": \"boxes.json\", \"synth_views\": 0}",
        );
        let mut fake = Fake {
            calls: vec![],
            fail: None,
            signal: None,
        };
        let outcome = run_entry(&e, &mut fake).unwrap();
        assert_eq!(
            outcome,
            EntryOutcome::Done {
                ran: vec![Stage::Fit, Stage::Label]
            }
        );
        let status = ScanStatus::read(&ScanOutputs::of(&e).status).unwrap().unwrap();
        assert_eq!(
            (status.state, status.fit.state, status.label.state, status.synth.state),
            (
                StageState::Done,
                StageState::Done,
                StageState::Done,
                StageState::Skipped
            )
        );
        assert_eq!(status.fit.model_crc32, Some(hex(crc32fast::hash(b"model 1"))));

        fake.calls.clear();
        assert_eq!(run_entry(&e, &mut fake).unwrap(), EntryOutcome::Done { ran: vec![] });
        assert!(fake.calls.is_empty(), "{:?}", fake.calls);

        // New boxes: only the labels are redone.
        std::fs::write(dir.path().join("boxes.json"), b"[2]").unwrap();
        run_entry(&e, &mut fake).unwrap();
        assert_eq!(fake.calls, vec![(Stage::Label, false)]);

        // A model changed behind the batch's back: refit, then relabel.
        fake.calls = vec![(Stage::Fit, false)];
        std::fs::write(ScanOutputs::of(&e).model, b"other").unwrap();
        run_entry(&e, &mut fake).unwrap();
        assert_eq!(fake.calls[1..], [(Stage::Fit, false), (Stage::Label, false)]);
    }

    #[test]
    fn a_fit_a_killed_run_left_resumes_from_its_checkpoint() {
        let dir = tempfile::tempdir().unwrap();
        let e = entry(dir.path(), "{\"scan\": \"scan\", \"synth_views\": 0, \"time\": 5}");
        let out = ScanOutputs::of(&e);
        // What a run killed mid-fit leaves: status `running`, a checkpoint.
        let mut status = ScanStatus::default();
        status.fit.state = StageState::Running;
        status.fit.made_from = "time=Some(5.0) steps=None seed=0 preset=default".into();
        status.write(&out.status).unwrap();
        std::fs::write(&out.checkpoint, b"ckpt").unwrap();
        let mut fake = Fake {
            calls: vec![],
            fail: None,
            signal: None,
        };
        run_entry(&e, &mut fake).unwrap();
        assert_eq!(fake.calls, vec![(Stage::Fit, true)]);
        let status = ScanStatus::read(&out.status).unwrap().unwrap();
        assert!(status.fit.resumed && status.fit.runs == 1 && status.state == StageState::Done);
    }

    #[test]
    fn a_fit_stopped_by_sigterm_is_recorded_interrupted_and_resumed_by_the_next_run() {
        let dir = tempfile::tempdir().unwrap();
        let e = entry(dir.path(), "{\"scan\": \"scan\", \"synth_views\": 0}");
        let mut stopped = Fake {
            calls: vec![],
            fail: None,
            signal: Some(Stage::Fit),
        };
        assert_eq!(
            run_entry(&e, &mut stopped).unwrap(),
            EntryOutcome::Interrupted { stage: Stage::Fit }
        );
        let status = ScanStatus::read(&ScanOutputs::of(&e).status).unwrap().unwrap();
        assert_eq!(
            (status.state, status.fit.state),
            (StageState::Interrupted, StageState::Interrupted)
        );
        let mut next = Fake {
            calls: vec![],
            fail: None,
            signal: None,
        };
        assert_eq!(
            run_entry(&e, &mut next).unwrap(),
            EntryOutcome::Done { ran: vec![Stage::Fit] }
        );
        assert_eq!(next.calls, vec![(Stage::Fit, true)]);
    }

    #[test]
    fn a_failing_stage_records_its_error_and_a_second_run_is_refused() {
        let dir = tempfile::tempdir().unwrap();
        let e = entry(dir.path(), "{\"scan\": \"scan\", \"id\": \"s1\"}");
        let mut fake = Fake {
            calls: vec![],
            fail: Some(Stage::Fit),
            signal: None,
        };
        let outcome = run_entry(&e, &mut fake).unwrap();
        assert!(matches!(outcome, EntryOutcome::Failed { stage: Stage::Fit, .. }));
        let status = ScanStatus::read(&ScanOutputs::of(&e).status).unwrap().unwrap();
        assert_eq!(status.state, StageState::Failed);
        assert_eq!(status.error.as_deref(), Some("fit: cannot read the scan"));

        let _held = lock_output(&e.work_dir().join("batch"), "this scan").unwrap();
        let err = run_entry(&e, &mut fake).unwrap_err().to_string();
        assert!(
            err.contains("another nerflabel batch run") && err.contains(&format!("pid {}", std::process::id())),
            "{err}"
        );

        let gone = entry(dir.path(), "{\"scan\": \"nowhere\"}");
        let err = run_entry(&gone, &mut fake).unwrap_err().to_string();
        assert!(err.contains("nowhere") && err.contains("does not exist"), "{err}");
        assert!(
            !dir.path().join("nowhere").exists(),
            "nothing created for a missing scan"
        );
    }
}
