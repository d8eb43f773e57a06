//! `nerflabel batch`: run a manifest's scans (one by index, the Slurm or
//! Kubernetes array task's, or all in turn), write its sbatch script, or
//! merge the finished scans into one dataset.

use super::verbosity::{note, say};
use super::{fit, label, synth, BatchArgs, FitArgs, LabelArgs, ScanArgs, SynthArgs};
use anyhow::{bail, Context};
use nerflabel::batch::stages::StageNote;
use nerflabel::batch::{
    merge, read_manifest, run_entry, sbatch_script, BatchError, Entry, EntryOutcome, Manifest, MergeOptions,
    SbatchOptions, Stage, Stages,
};
use nerflabel::boxes::{Overlap, DEFAULT_SOURCE};
use nerflabel::nerf::train::settings::FitSettings;
use std::path::{Path, PathBuf};

/// Environment variables that give an array task's index, in order.
const INDEX_VARS: [&str; 2] = ["SLURM_ARRAY_TASK_ID", "JOB_COMPLETION_INDEX"];

pub fn run(args: &BatchArgs) -> anyhow::Result<()> {
    let manifest = read_manifest(&args.manifest)?;
    if args.sbatch {
        return write_sbatch(args, &manifest);
    }
    if let Some(out) = &args.merge {
        return run_merge(args, &manifest, out);
    }
    let selected: Vec<&Entry> = match task_index(args.index)? {
        Some((index, from)) => {
            let entry = manifest.entries.get(index).ok_or(BatchError::IndexOutOfRange {
                index,
                entries: manifest.entries.len(),
                from,
            })?;
            vec![entry]
        }
        None => manifest.entries.iter().collect(),
    };
    let mut stages = CliStages;
    let mut failures: Vec<String> = Vec::new();
    for entry in &selected {
        note!(
            "== scan {} ({}), manifest line {}",
            entry.id,
            entry.scan.display(),
            entry.line
        );
        let status = nerflabel::batch::status::status_path(&entry.work_dir());
        match run_entry(entry, &mut stages) {
            Ok(EntryOutcome::Done { ran }) => {
                let ran: Vec<&str> = ran.iter().map(|s| s.name()).collect();
                say!(
                    "scan {}: done ({}); status: {}",
                    entry.id,
                    if ran.is_empty() {
                        "every stage was complete already".to_string()
                    } else {
                        format!("ran {}", ran.join(", "))
                    },
                    status.display()
                );
            }
            Ok(EntryOutcome::Failed { stage, error }) => failures.push(format!(
                "scan {} ({}): {} failed: {error} (recorded in {})",
                entry.id,
                entry.scan.display(),
                stage.name(),
                status.display()
            )),
            Ok(EntryOutcome::Interrupted { stage }) => {
                // main turns the signal into exit status 130 / 143.
                eprintln!(
                    "scan {}: stopped by a signal during {}; its work is saved and a rerun resumes it",
                    entry.id,
                    stage.name()
                );
                return Ok(());
            }
            Err(e) => failures.push(format!("scan {}: {e}", entry.id)),
        }
    }
    match failures.len() {
        0 => Ok(()),
        1 if selected.len() == 1 => bail!("{}", failures.remove(0)),
        n => {
            for f in &failures {
                eprintln!("error: {f}");
            }
            bail!(
                "{n} of {} scans failed (the others' outputs are complete)",
                selected.len()
            )
        }
    }
}

/// `--index`, else the array task's index from the environment, else `None` (every entry).
fn task_index(index: Option<usize>) -> Result<Option<(usize, String)>, BatchError> {
    if let Some(i) = index {
        return Ok(Some((i, " (--index)".into())));
    }
    for var in INDEX_VARS {
        if let Ok(value) = std::env::var(var) {
            let i = value.trim().parse::<usize>().map_err(|_| BatchError::BadIndexVar {
                var: var.into(),
                value: value.clone(),
            })?;
            return Ok(Some((i, format!(" (from {var})"))));
        }
    }
    Ok(None)
}

/// The stages as the `fit`, `label` and `synth` commands run them, with their defaults.
struct CliStages;

fn scan_args(entry: &Entry) -> ScanArgs {
    ScanArgs {
        scan: entry.scan.clone(),
        format: None,
        fix_poses: false,
    }
}

/// An error with its causes, on one line.
fn message(err: anyhow::Error) -> String {
    err.chain().map(|c| c.to_string()).collect::<Vec<_>>().join(": ")
}

impl Stages for CliStages {
    fn fit(&mut self, entry: &Entry, resume: bool) -> Result<(), String> {
        let args = FitArgs {
            scan: scan_args(entry),
            time: entry.time,
            steps: entry.steps,
            model: None,
            settings: FitSettings {
                seed: entry.seed,
                preset: entry.preset,
                ..FitSettings::default()
            },
            resume,
        };
        fit::run(&args).map_err(message)
    }

    fn label(&mut self, entry: &Entry) -> Result<(), String> {
        let args = LabelArgs {
            scan: scan_args(entry),
            boxes: entry.boxes.clone(),
            masks: entry.masks.clone(),
            out: None,
            image_root: None,
            depth: false,
            model: None,
            frames: None,
            source: DEFAULT_SOURCE,
            yolo: false,
            yolo_seg: false,
            yolo_images: None,
            yolo_val: None,
            seed: entry.seed,
            force: false,
            exact_boxes: false,
            overlap: Overlap::Smallest,
            no_colour_snap: false,
        };
        label::run(&args).map_err(message)
    }

    fn synth(&mut self, entry: &Entry) -> Result<(), String> {
        let args = SynthArgs {
            scan: scan_args(entry),
            boxes: entry.boxes.clone(),
            masks: entry.masks.clone(),
            exact_boxes: false,
            n: entry.synth_views,
            width: entry.synth_width,
            height: entry.synth_height,
            seed: entry.seed,
            poses: None,
            out: None,
            overwrite: true,
            force: false,
            model: None,
            clearance: None,
            appearance: "neutral".into(),
        };
        synth::run(&args).map_err(message)
    }

    fn interrupted(&self) -> bool {
        super::interrupted_status().is_some()
    }

    fn note(&mut self, entry: &Entry, stage: Stage, what: StageNote) {
        let what = match what {
            StageNote::Complete => "outputs complete, skipped",
            StageNote::NotAsked => "not asked for by the manifest line",
            StageNote::Start => "starting",
            StageNote::Resume => "resuming from the checkpoint a stopped run left",
        };
        note!("[{}] {}: {what}", entry.id, stage.name());
    }
}

/// `--sbatch`: the job array script on stdout; its log folder is created.
fn write_sbatch(args: &BatchArgs, manifest: &Manifest) -> anyhow::Result<()> {
    let manifest_abs = std::fs::canonicalize(&args.manifest)
        .with_context(|| format!("{}: cannot resolve the manifest's path", args.manifest.display()))?;
    let binary = std::env::current_exe().context("cannot find the nerflabel binary's own path")?;
    let log_dir = manifest_abs
        .parent()
        .map_or_else(|| PathBuf::from("slurm-logs"), |d| d.join("slurm-logs"));
    std::fs::create_dir_all(&log_dir)
        .with_context(|| format!("{}: cannot create the folder of the tasks' logs", log_dir.display()))?;
    let options = SbatchOptions {
        binary,
        manifest: manifest_abs,
        log_dir: log_dir.clone(),
        cpus: args.cpus,
        mem_mb: args.mem.as_deref().map(parse_mem).transpose()?,
        time_limit_s: args.time_limit.as_deref().map(parse_time_limit).transpose()?,
        parallel: args.parallel,
        partition: args.partition.clone(),
    };
    print!("{}", sbatch_script(manifest, &options));
    note!(
        "{} array tasks; submit with `sbatch FILE` (logs in {})",
        manifest.entries.len(),
        log_dir.display()
    );
    Ok(())
}

/// `--mem`: megabytes, or a number with `M`, `G` or `T`.
fn parse_mem(text: &str) -> anyhow::Result<u64> {
    let t = text.trim();
    let (number, unit) = match t.char_indices().last() {
        Some((i, c)) if c.is_ascii_alphabetic() => (&t[..i], c.to_ascii_uppercase()),
        _ => (t, 'M'),
    };
    let value: u64 = number
        .parse()
        .map_err(|_| anyhow::anyhow!("--mem {text}: expected megabytes or a size such as 8G"))?;
    let mb = match unit {
        'M' => Some(value),
        'G' => value.checked_mul(1024),
        'T' => value.checked_mul(1024 * 1024),
        _ => None,
    };
    match mb {
        Some(mb) if mb > 0 => Ok(mb),
        _ => bail!("--mem {text}: expected megabytes or a size such as 8G (units M, G, T)"),
    }
}

/// `--time-limit`: seconds, `H:MM:SS` or `D-HH:MM:SS`.
fn parse_time_limit(text: &str) -> anyhow::Result<u64> {
    let bad = || anyhow::anyhow!("--time-limit {text}: expected seconds, H:MM:SS or D-HH:MM:SS");
    let t = text.trim();
    let (days, clock) = match t.split_once('-') {
        Some((d, rest)) => (d.parse::<u64>().map_err(|_| bad())?, rest),
        None => (0, t),
    };
    let parts: Vec<u64> = clock
        .split(':')
        .map(|p| p.parse::<u64>().map_err(|_| bad()))
        .collect::<Result<_, _>>()?;
    let seconds = match parts.as_slice() {
        [s] if days == 0 => *s,
        [h, m, s] if *m < 60 && *s < 60 => h * 3600 + m * 60 + s,
        _ => return Err(bad()),
    };
    let total = days
        .checked_mul(86_400)
        .and_then(|d| d.checked_add(seconds))
        .ok_or_else(bad)?;
    if total == 0 {
        return Err(bad());
    }
    Ok(total)
}

/// `--merge OUT`: gather the finished scans, print the summary table.
fn run_merge(args: &BatchArgs, manifest: &Manifest, out: &Path) -> anyhow::Result<()> {
    let defaults = MergeOptions::default();
    let options = MergeOptions {
        val: args.val.unwrap_or(defaults.val),
        test: args.test.unwrap_or(defaults.test),
        seed: args.seed.unwrap_or(defaults.seed),
    };
    let summary = merge(manifest, out, &options)?;
    println!(
        "{:<20} {:<12} {:<6} {:>6} {:>6} {:>8} {:>11} {:>6}  error",
        "scan", "state", "split", "frames", "steps", "PSNR dB", "annotations", "views"
    );
    let opt = |v: Option<u64>| v.map_or("-".into(), |v| v.to_string());
    for r in &summary.rows {
        println!(
            "{:<20} {:<12} {:<6} {:>6} {:>6} {:>8} {:>11} {:>6}  {}",
            r.id,
            r.state,
            r.split.as_deref().unwrap_or("-"),
            opt(r.frames),
            opt(r.fit_steps),
            r.psnr_db.map_or("-".into(), |p| format!("{p:.2}")),
            opt(r.annotations),
            opt(r.synth_views),
            r.error.as_deref().unwrap_or("")
        );
    }
    let sizes: Vec<String> = summary
        .splits
        .iter()
        .map(|(name, ids)| format!("{} {name}", ids.len()))
        .collect();
    say!(
        "merged {} of {} scans into {} ({}): synth/scan=<id>/part-0.parquet, coco/<split>.json, splits.json, summary.csv",
        summary.merged(),
        summary.rows.len(),
        summary.out.display(),
        sizes.join(", ")
    );
    let unfinished = summary.rows.len() - summary.merged();
    if unfinished > 0 {
        eprintln!("warning: {unfinished} scan(s) not finished are left out (see summary.csv)");
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn memory_and_time_limits_parse_as_sbatch_takes_them() {
        assert_eq!(parse_mem("8000").unwrap(), 8000);
        assert_eq!(parse_mem("8G").unwrap(), 8192);
        assert!(parse_mem("8X").is_err() && parse_mem("0").is_err() && parse_mem("G").is_err());
        assert_eq!(parse_time_limit("90").unwrap(), 90);
        assert_eq!(parse_time_limit("1:30:00").unwrap(), 5400);
        assert_eq!(parse_time_limit("2-00:00:10").unwrap(), 172_810);
        assert!(parse_time_limit("1:75:00").is_err() && parse_time_limit("x").is_err());
    }
}
