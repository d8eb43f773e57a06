//! The sbatch script of a Slurm job array over a manifest: one array task
//! per scan, its CPU, memory and time limits derived from the largest scan
//! (frames and resolution read from the scan folders without decoding) and
//! overridable.

use super::manifest::{Entry, Manifest};
use crate::nerf::train::fit::DEFAULT_TIME_S;
use std::fmt::Write as _;
use std::path::{Path, PathBuf};

/// Frames and resolution assumed for a scan whose folder cannot be probed.
const GUESS_FRAMES: u64 = 300;
const GUESS_PIXELS: u64 = 640 * 480;
/// Default CPUs per task and tasks running at once.
pub const DEFAULT_CPUS: u32 = 4;
pub const DEFAULT_PARALLEL: usize = 8;

/// What the script runs and the limits given on the command line.
#[derive(Clone, Debug, Default)]
pub struct SbatchOptions {
    /// The nerflabel binary (absolute).
    pub binary: PathBuf,
    /// The manifest (absolute).
    pub manifest: PathBuf,
    /// Folder of the tasks' logs (must exist when the job starts).
    pub log_dir: PathBuf,
    pub cpus: Option<u32>,
    pub mem_mb: Option<u64>,
    pub time_limit_s: Option<u64>,
    /// Most tasks running at once (`%K`).
    pub parallel: Option<usize>,
    pub partition: Option<String>,
}

/// What was read of one scan to size the job.
#[derive(Clone, Debug, PartialEq)]
pub struct ScanSize {
    pub frames: u64,
    pub pixels: u64,
    /// The frames and resolution were read (not guessed).
    pub probed: bool,
}

/// Frames and resolution of a scan from its colour folder (`rgb/`,
/// `images/`, `color/`): the files counted, the first image's header read.
pub fn probe_scan(scan: &Path) -> ScanSize {
    for folder in ["rgb", "images", "color"] {
        let Ok(read) = std::fs::read_dir(scan.join(folder)) else {
            continue;
        };
        let mut images: Vec<PathBuf> = read
            .filter_map(Result::ok)
            .map(|e| e.path())
            .filter(|p| {
                p.extension()
                    .and_then(|e| e.to_str())
                    .is_some_and(|e| matches!(e.to_ascii_lowercase().as_str(), "png" | "jpg" | "jpeg"))
            })
            .collect();
        images.sort();
        let Some(first) = images.first() else { continue };
        if let Ok((w, h)) = image::image_dimensions(first) {
            return ScanSize {
                frames: images.len() as u64,
                pixels: u64::from(w) * u64::from(h),
                probed: true,
            };
        }
    }
    ScanSize {
        frames: GUESS_FRAMES,
        pixels: GUESS_PIXELS,
        probed: false,
    }
}

/// Seconds one scan's task may take: fit budget, scan loading, labelling and
/// synthesis estimated generously, times 1.5, plus 5 minutes.
pub fn task_seconds(entry: &Entry, size: &ScanSize) -> u64 {
    let fit = match (entry.time, entry.steps) {
        (Some(t), _) => t,
        // A step of the default preset takes well under 0.2 s on 4 cores.
        (None, Some(steps)) => steps as f64 * 0.2,
        (None, None) => DEFAULT_TIME_S,
    };
    let megapixels = size.pixels as f64 / 1e6;
    let load = size.frames as f64 * megapixels * 0.2;
    let label = if entry.labels() {
        size.frames as f64 * megapixels * 2.0
    } else {
        0.0
    };
    let width_height = match (entry.synth_width, entry.synth_height) {
        (Some(w), Some(h)) => f64::from(w) * f64::from(h) / 1e6,
        _ => megapixels,
    };
    let synth = entry.synth_views as f64 * width_height * 5.0;
    ((fit + load + label + synth) * 1.5 + 300.0).ceil() as u64
}

/// Memory of one scan's task, MB: the decoded scan and the training rays
/// (about 40 bytes a pixel) over a 1.5 GB base, in steps of 512 MB.
pub fn task_mem_mb(size: &ScanSize) -> u64 {
    let bytes = size.frames.saturating_mul(size.pixels).saturating_mul(40);
    let mb = 1536 + bytes / (1024 * 1024);
    mb.div_ceil(512) * 512
}

/// `D-HH:MM:SS`, as sbatch's `--time` takes it.
pub fn slurm_time(seconds: u64) -> String {
    let (d, rest) = (seconds / 86_400, seconds % 86_400);
    format!("{d}-{:02}:{:02}:{:02}", rest / 3600, (rest / 60) % 60, rest % 60)
}

/// Quote for the shell: single quotes, an inner one closed and escaped.
fn shell_quote(text: &str) -> String {
    format!("'{}'", text.replace('\'', "'\\''"))
}

/// The sbatch script for `manifest` (sizes probed from its scan folders).
pub fn sbatch_script(manifest: &Manifest, options: &SbatchOptions) -> String {
    let sizes: Vec<ScanSize> = manifest.entries.iter().map(|e| probe_scan(&e.scan)).collect();
    script_for(manifest, &sizes, options)
}

fn script_for(manifest: &Manifest, sizes: &[ScanSize], options: &SbatchOptions) -> String {
    let n = manifest.entries.len();
    let derived_time = manifest
        .entries
        .iter()
        .zip(sizes)
        .map(|(e, s)| task_seconds(e, s))
        .max()
        .unwrap_or(600);
    let derived_mem = sizes.iter().map(task_mem_mb).max().unwrap_or(2048);
    let largest = sizes.iter().max_by_key(|s| s.frames.saturating_mul(s.pixels));
    let guessed = sizes.iter().filter(|s| !s.probed).count();
    let cpus = options.cpus.unwrap_or(DEFAULT_CPUS).max(1);
    let mem = options.mem_mb.unwrap_or(derived_mem);
    let time = options.time_limit_s.unwrap_or(derived_time);
    let parallel = options.parallel.unwrap_or(DEFAULT_PARALLEL).clamp(1, n.max(1));
    let name = manifest
        .path
        .file_stem()
        .map(|s| s.to_string_lossy().into_owned())
        .unwrap_or_else(|| "manifest".into())
        .replace(|c: char| !(c.is_ascii_alphanumeric() || c == '-' || c == '_'), "_");
    let mut s = String::new();
    let _ = writeln!(s, "#!/bin/bash");
    let _ = writeln!(
        s,
        "# Slurm job array over {} ({n} scans), written by `nerflabel batch MANIFEST --sbatch` (nerflabel {}).",
        manifest.path.display(),
        env!("CARGO_PKG_VERSION")
    );
    let _ = writeln!(
        s,
        "# Submit with `sbatch THIS_FILE`. Submitting it again after a failure, a time-out or a killed"
    );
    let _ = writeln!(
        s,
        "# task redoes only what is missing: finished stages are skipped, a killed fit resumes."
    );
    if let Some(l) = largest {
        let _ = writeln!(
            s,
            "# Limits derived from the scans (largest: {} frames of {:.2} MP{}); override them with",
            l.frames,
            l.pixels as f64 / 1e6,
            if guessed > 0 {
                format!("; {guessed} scan(s) not probed, sized as {GUESS_FRAMES} frames of 640x480")
            } else {
                String::new()
            }
        );
    }
    let _ = writeln!(s, "# --cpus, --mem, --time-limit and --parallel.");
    let _ = writeln!(s, "#SBATCH --job-name=nerflabel-{name}");
    let _ = writeln!(s, "#SBATCH --array=0-{}%{parallel}", n.saturating_sub(1));
    let _ = writeln!(s, "#SBATCH --cpus-per-task={cpus}");
    let _ = writeln!(s, "#SBATCH --mem={mem}M");
    let _ = writeln!(s, "#SBATCH --time={}", slurm_time(time));
    let _ = writeln!(s, "#SBATCH --output={}/%x-%A_%a.log", options.log_dir.display());
    if let Some(p) = &options.partition {
        let _ = writeln!(s, "#SBATCH --partition={p}");
    }
    let _ = writeln!(s, "set -u");
    let _ = writeln!(
        s,
        "# Each task runs line SLURM_ARRAY_TASK_ID; SIGTERM at the time limit saves the fit for the rerun."
    );
    let _ = writeln!(
        s,
        "exec {} --threads \"${{SLURM_CPUS_PER_TASK:-{cpus}}}\" batch {}",
        shell_quote(&options.binary.display().to_string()),
        shell_quote(&options.manifest.display().to_string())
    );
    s
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::batch::manifest::parse_manifest;

    #[test]
    fn the_array_covers_every_line_and_limits_follow_the_largest_scan_unless_overridden() {
        let m = parse_manifest(
            "{\"scan\": \"a\", \"time\": 600, \"boxes\": \"b.json\"}\n{\"scan\": \"b\", \"steps\": 100, \"synth_views\": 0}\n{\"scan\": \"c it's\", \"id\": \"c\"}\n",
            Path::new("/m/run.jsonl"),
            Path::new("/m"),
        )
        .unwrap();
        let small = ScanSize {
            frames: 24,
            pixels: 160 * 120,
            probed: true,
        };
        let big = ScanSize {
            frames: 1000,
            pixels: 1920 * 1440,
            probed: true,
        };
        let options = SbatchOptions {
            binary: "/opt/bin/nerflabel".into(),
            manifest: "/m/run.jsonl".into(),
            log_dir: "/m/slurm-logs".into(),
            ..SbatchOptions::default()
        };
        let script = script_for(&m, &[small.clone(), big.clone(), small.clone()], &options);
        assert!(script.starts_with("#!/bin/bash\n"));
        assert!(script.contains("#SBATCH --array=0-2%3\n"), "{script}");
        assert!(script.contains("#SBATCH --cpus-per-task=4\n"));
        // Memory from the 1000 x 2.8 MP scan: 1.5 GB + 40 B/pixel.
        let mem = task_mem_mb(&big);
        assert!((100_000..115_000).contains(&mem), "{mem}");
        assert!(script.contains(&format!("#SBATCH --mem={mem}M\n")));
        // Time from the 600 s fit with labels: at least the budget, under a day.
        let t = task_seconds(&m.entries[0], &small);
        assert!((900..86_400).contains(&t), "{t}");
        let longest = (0..3)
            .map(|i| task_seconds(&m.entries[i], [&small, &big, &small][i]))
            .max()
            .unwrap();
        assert!(script.contains(&format!("#SBATCH --time={}\n", slurm_time(longest))));
        assert!(script.contains("batch '/m/run.jsonl'"), "{script}");
        assert!(script.contains("exec '/opt/bin/nerflabel' --threads \"${SLURM_CPUS_PER_TASK:-4}\""));

        let script = script_for(
            &m,
            &[small.clone(), small.clone(), small],
            &SbatchOptions {
                cpus: Some(2),
                mem_mb: Some(3000),
                time_limit_s: Some(90_061),
                parallel: Some(1),
                partition: Some("cpu".into()),
                ..options
            },
        );
        for line in [
            "--array=0-2%1\n",
            "--cpus-per-task=2\n",
            "--mem=3000M\n",
            "--time=1-01:01:01\n",
            "--partition=cpu\n",
        ] {
            assert!(script.contains(line), "{line} in {script}");
        }
        assert_eq!(shell_quote("c it's"), "'c it'\\''s'");
    }
}
