//! Many scans (`nerflabel batch`): a JSON Lines manifest of independent
//! scans, each run through fit, label and synth as one task (a Slurm array
//! task, a Kubernetes indexed job, or in turn), with a per-scan lock and
//! status file so that reruns skip finished stages and resume a killed fit;
//! the sbatch script of a job array over the manifest; and the merge of the
//! finished scans into one dataset (hive-partitioned Parquet, COCO per
//! split, a summary table).
//!
//! Runs the stages only through the [`stages::Stages`] trait the CLI
//! implements: never depends on the CLI, and never prints.

mod coco_merge;
pub mod error;
pub mod hf_json;
pub mod manifest;
pub mod merge;
mod partition;
pub mod sbatch;
pub mod stages;
pub mod status;

pub use error::BatchError;
pub use manifest::{read_manifest, Entry, Manifest};
pub use merge::{merge, MergeOptions, MergeSummary};
pub use sbatch::{sbatch_script, SbatchOptions};
pub use stages::{run_entry, EntryOutcome, Stage, Stages};
pub use status::{ScanStatus, StageState};
