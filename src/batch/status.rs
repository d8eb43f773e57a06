//! The per-scan status file `SCAN/nerflabel/batch.status.json`: the state of
//! each stage, what its outputs were made from (so a rerun can tell whether
//! they are still valid), timings and the error of a failed run. Written
//! atomically at every change.

use super::error::BatchError;
use serde::{Deserialize, Serialize};
use std::path::{Path, PathBuf};

/// Largest status file read, bytes.
const MAX_STATUS_BYTES: u64 = 16 * 1024 * 1024;

/// Where a scan's batch status is kept.
pub fn status_path(work_dir: &Path) -> PathBuf {
    work_dir.join("batch.status.json")
}

/// Where a stage, or a scan's whole run, stands.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize, Default)]
#[serde(rename_all = "lowercase")]
pub enum StageState {
    /// Not started yet.
    #[default]
    Pending,
    /// Started and not finished (a killed run leaves this).
    Running,
    /// Finished; its outputs were complete.
    Done,
    /// Failed; `error` says why.
    Failed,
    /// Stopped by SIGTERM or Ctrl-C after saving (a rerun resumes).
    Interrupted,
    /// The manifest line asks for nothing here (no boxes, `synth_views` 0).
    Skipped,
}

/// One stage's record.
#[derive(Clone, Debug, Default, Serialize, Deserialize, PartialEq)]
pub struct StageRecord {
    pub state: StageState,
    /// What the outputs were made from (settings, input checksums); a rerun
    /// redoes the stage when it changed.
    #[serde(default)]
    pub made_from: String,
    /// CRC-32 of the model file once written (fit only), 8 hex digits.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub model_crc32: Option<String>,
    /// Wall time of the last run of the stage, seconds.
    #[serde(default)]
    pub seconds: f64,
    /// How often the stage was started.
    #[serde(default)]
    pub runs: u32,
    /// Whether the last run resumed from a checkpoint (fit only).
    #[serde(default)]
    pub resumed: bool,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub error: Option<String>,
}

/// The status file's content.
#[derive(Clone, Debug, Default, Serialize, Deserialize, PartialEq)]
pub struct ScanStatus {
    pub nerflabel_version: String,
    pub id: String,
    pub scan: String,
    /// Manifest line the run was started from.
    pub line: usize,
    pub state: StageState,
    /// The failed stage's error, `fit: ...`.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub error: Option<String>,
    /// Unix seconds.
    #[serde(default)]
    pub started: u64,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub finished: Option<u64>,
    #[serde(default)]
    pub host: String,
    #[serde(default)]
    pub pid: u32,
    /// `JOBID_TASK` under Slurm.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub slurm_job: Option<String>,
    #[serde(default)]
    pub fit: StageRecord,
    #[serde(default)]
    pub label: StageRecord,
    #[serde(default)]
    pub synth: StageRecord,
}

impl ScanStatus {
    /// Read `path`; `None` when there is none.
    pub fn read(path: &Path) -> Result<Option<ScanStatus>, BatchError> {
        let len = match std::fs::metadata(path) {
            Ok(m) => m.len(),
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(None),
            Err(e) => return Err(BatchError::io(path, "read the batch status")(e)),
        };
        if len > MAX_STATUS_BYTES {
            return Err(BatchError::Invalid {
                path: path.to_path_buf(),
                problem: format!("{len} bytes, more than a status file holds"),
            });
        }
        let bytes = std::fs::read(path).map_err(BatchError::io(path, "read the batch status"))?;
        serde_json::from_slice(&bytes)
            .map(Some)
            .map_err(|e| BatchError::Invalid {
                path: path.to_path_buf(),
                problem: format!("not a batch status file ({e})"),
            })
    }

    /// Write to `path` atomically.
    pub fn write(&self, path: &Path) -> Result<(), BatchError> {
        let json = serde_json::to_vec_pretty(self).map_err(|e| BatchError::Invalid {
            path: path.to_path_buf(),
            problem: format!("cannot serialise the status: {e}"),
        })?;
        crate::atomic::write_file(path, &json).map_err(BatchError::io(path, "write the batch status"))
    }
}

/// Seconds since the Unix epoch (0 if the clock is before it).
pub fn now_unix() -> u64 {
    std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map_or(0, |d| d.as_secs())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_status_round_trips_and_a_missing_one_is_none() {
        let dir = tempfile::tempdir().unwrap();
        let path = status_path(dir.path());
        assert_eq!(ScanStatus::read(&path).unwrap(), None);
        let mut s = ScanStatus {
            id: "a".into(),
            state: StageState::Failed,
            error: Some("fit: boom".into()),
            ..ScanStatus::default()
        };
        s.fit.state = StageState::Done;
        s.fit.model_crc32 = Some("0badf00d".into());
        s.write(&path).unwrap();
        assert_eq!(ScanStatus::read(&path).unwrap(), Some(s));
        std::fs::write(&path, "{").unwrap();
        let e = ScanStatus::read(&path).unwrap_err().to_string();
        assert!(
            e.contains("batch.status.json") && e.contains("not a batch status file"),
            "{e}"
        );
    }
}
