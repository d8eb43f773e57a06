//! Helpers shared by the subcommands: loading a scan with its warnings,
//! default output paths, progress bars, Ctrl-C and SIGTERM.

use super::ScanArgs;
use anyhow::Context;
use indicatif::{ProgressBar, ProgressStyle};
use nerflabel::nerf::model_file::{Model, ScanMatch};
use nerflabel::scan::Scan;
use signal_hook::consts::{SIGINT, SIGTERM};
use signal_hook::iterator::Signals;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, AtomicI32, Ordering};
use std::time::Duration;

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
    let bar = ProgressBar::new(len);
    let style = ProgressStyle::with_template(template).unwrap_or_else(|_| ProgressStyle::default_bar());
    bar.set_style(style.progress_chars("=> "));
    bar.enable_steady_tick(Duration::from_millis(250));
    bar
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
