//! Helpers shared by the subcommands: loading a scan with its warnings,
//! default output paths, progress bars, Ctrl-C.

use super::ScanArgs;
use anyhow::Context;
use indicatif::{ProgressBar, ProgressStyle};
use nerflabel::scan::Scan;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, Ordering};
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

/// Flag set by the first Ctrl-C; a second Ctrl-C exits at once (outputs
/// are written atomically, so nothing half-written is left behind).
pub fn stop_flag() -> &'static AtomicBool {
    static INSTALLED: std::sync::Once = std::sync::Once::new();
    INSTALLED.call_once(|| {
        let _ = ctrlc::set_handler(|| {
            if STOP.swap(true, Ordering::SeqCst) {
                std::process::exit(130);
            }
            eprintln!("\ninterrupted: finishing the current step and saving (Ctrl-C again to abort)");
        });
    });
    &STOP
}
