//! Helpers shared by the subcommands: loading a scan with its warnings,
//! default output paths, progress bars, Ctrl-C and SIGTERM.

use super::ScanArgs;
use anyhow::Context;
use indicatif::{ProgressBar, ProgressStyle};
use nerflabel::nerf::model_file::{Model, ScanMatch};
use nerflabel::scan::Scan;
use signal_hook::consts::{SIGINT, SIGTERM};
use signal_hook::iterator::Signals;
use std::io::IsTerminal;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, AtomicI32, Ordering};
use std::sync::Mutex;
use std::time::{Duration, Instant};

/// Load and validate a scan, printing its warnings to stderr.
pub fn load_scan(args: &ScanArgs) -> anyhow::Result<Scan> {
    let scan = nerflabel::scan::load(&args.scan, &args.load_options())
        .with_context(|| format!("cannot read the scan {}", args.scan.display()))?;
    for warning in &scan.warnings {
        eprintln!("warning: {warning}");
    }
    Ok(scan)
}

/// Read a model and the CRC32 of its file. A missing file suggests fitting;
/// any other problem is reported as it is (it names the file first).
pub fn read_model(path: &Path) -> anyhow::Result<(Model, u32)> {
    if !path.exists() {
        anyhow::bail!(
            "{}: no model here: run `nerflabel fit` first, or give its path with --model (label can also use --source sensor)",
            path.display()
        );
    }
    let bytes = std::fs::read(path).with_context(|| format!("{}: cannot read the model", path.display()))?;
    let checksum = crc32fast::hash(&bytes);
    Ok((Model::from_bytes(&bytes, path)?, checksum))
}

/// Refuse a model fitted to another scan (or to this one before its poses
/// changed) unless `force`, which only warns; then give the scan the poses
/// the model was fitted with (refined from the captured ones).
pub fn check_model_scan(model: &Model, path: &Path, scan: &mut Scan, force: bool) -> anyhow::Result<()> {
    match model.matches_scan(scan) {
        ScanMatch::Same => {}
        ScanMatch::Unknown => eprintln!(
            "warning: {}: the model does not record which scan it was fitted to (an earlier version wrote it); make sure it belongs to this scan",
            path.display()
        ),
        ScanMatch::Other(what) if force => {
            eprintln!("warning: {}: the model belongs to another scan ({what}); using it anyway (--force)", path.display())
        }
        ScanMatch::Other(what) => anyhow::bail!(
            "{}: the model was fitted to another scan, or to this one before it changed ({what}); refit with `nerflabel fit`, or pass --force to use it anyway",
            path.display()
        ),
    }
    model.apply_fitted_poses(scan);
    Ok(())
}

/// SCAN/nerflabel, where outputs go by default.
pub fn work_dir(scan: &Path) -> PathBuf {
    scan.join("nerflabel")
}

/// The model path: `--model` or SCAN/nerflabel/model.nlf.
pub fn model_path(scan: &Path, model: Option<&PathBuf>) -> PathBuf {
    model.cloned().unwrap_or_else(|| work_dir(scan).join("model.nlf"))
}

/// A progress bar on stderr (hidden when stderr is not a terminal).
pub fn progress_bar(len: u64, template: &str) -> ProgressBar {
    if super::verbosity::quiet() {
        return ProgressBar::hidden();
    }
    let bar = ProgressBar::new(len);
    let style = ProgressStyle::with_template(template).unwrap_or_else(|_| ProgressStyle::default_bar());
    bar.set_style(style.progress_chars("=> "));
    bar.enable_steady_tick(Duration::from_millis(250));
    bar
}

/// Seconds between plain progress lines when stderr is not a terminal;
/// `NERFLABEL_PROGRESS_EVERY` (seconds) overrides it.
const PLAIN_PROGRESS_EVERY_S: f64 = 10.0;

/// Progress for logs. The bar draws only on a terminal; under nohup, CI
/// or a cluster scheduler this prints a plain line instead, at a steady
/// pace: how far, elapsed, ETA and what the caller adds.
pub struct PlainProgress {
    started: Instant,
    every: Option<Duration>,
    last: Mutex<Instant>,
}

impl PlainProgress {
    /// Silent when stderr is a terminal (the bar shows progress there).
    pub fn new() -> Self {
        let seconds = std::env::var("NERFLABEL_PROGRESS_EVERY")
            .ok()
            .and_then(|v| v.parse::<f64>().ok())
            .filter(|s| s.is_finite() && *s > 0.0)
            .unwrap_or(PLAIN_PROGRESS_EVERY_S);
        let now = Instant::now();
        PlainProgress {
            started: now,
            every: (!std::io::stderr().is_terminal() && !super::verbosity::quiet())
                .then(|| Duration::from_secs_f64(seconds)),
            last: Mutex::new(now),
        }
    }

    /// Print a line when the last one (or the start) is a period ago;
    /// `fraction` of the work is done, `detail` describes where it stands.
    pub fn tick(&self, fraction: f64, detail: impl FnOnce() -> String) {
        let Some(every) = self.every else { return };
        let Ok(mut last) = self.last.try_lock() else { return };
        if last.elapsed() < every {
            return;
        }
        *last = Instant::now();
        let elapsed = self.started.elapsed().as_secs_f64();
        let fraction = fraction.clamp(0.0, 1.0);
        let eta = if fraction > 0.0 {
            clock(elapsed * (1.0 - fraction) / fraction)
        } else {
            "?".into()
        };
        eprintln!(
            "progress {:.0} %, {} elapsed, ETA {eta}: {}",
            fraction * 100.0,
            clock(elapsed),
            detail()
        );
    }
}

/// `h:mm:ss` of a number of seconds.
fn clock(seconds: f64) -> String {
    let s = seconds.max(0.0).round() as u64;
    format!("{}:{:02}:{:02}", s / 3600, (s / 60) % 60, s % 60)
}

static STOP: AtomicBool = AtomicBool::new(false);
/// The signal that set [`STOP`] (0 = none).
static SIGNAL: AtomicI32 = AtomicI32::new(0);

/// Flag set by the first Ctrl-C (SIGINT) or SIGTERM; a second signal exits at
/// once (outputs are written atomically, so nothing half-written is left).
pub fn stop_flag() -> &'static AtomicBool {
    static INSTALLED: std::sync::Once = std::sync::Once::new();
    INSTALLED.call_once(|| match Signals::new([SIGINT, SIGTERM]) {
        Ok(mut signals) => {
            std::thread::spawn(move || {
                for signal in signals.forever() {
                    if STOP.swap(true, Ordering::SeqCst) {
                        std::process::exit(128 + signal);
                    }
                    SIGNAL.store(signal, Ordering::SeqCst);
                    let name = if signal == SIGTERM { "SIGTERM" } else { "Ctrl-C" };
                    eprintln!("\ninterrupted ({name}): finishing the current step and saving (signal again to abort)");
                }
            });
        }
        Err(e) => eprintln!("warning: cannot catch Ctrl-C or SIGTERM ({e}): an interrupted run will not save its work"),
    });
    &STOP
}

/// Exit status of a run that a signal stopped after saving its work:
/// 128 + the signal's number (130 for Ctrl-C, 143 for SIGTERM), as shells do.
pub fn interrupted_status() -> Option<u8> {
    match SIGNAL.load(Ordering::SeqCst) {
        0 => None,
        signal => u8::try_from(128 + signal).ok(),
    }
}
