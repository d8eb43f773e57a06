//! The `nerflabel` command line: parse, call the library, print.

mod cli;

use clap::Parser;
use std::process::ExitCode;

fn main() -> ExitCode {
    restore_default_sigpipe();
    let args = cli::Cli::parse();
    match cli::run(args) {
        // A run stopped by Ctrl-C or SIGTERM saved its work; its status says it was stopped.
        Ok(()) => cli::interrupted_status().map_or(ExitCode::SUCCESS, ExitCode::from),
        Err(err) => {
            // One clear message: the outermost context, then each cause.
            eprintln!("error: {err}");
            for cause in err.chain().skip(1) {
                eprintln!("  caused by: {cause}");
            }
            // A run stopped by a signal (synth gives up its views) still says so.
            cli::interrupted_status().map_or(ExitCode::FAILURE, ExitCode::from)
        }
    }
}

/// Rust ignores SIGPIPE, so printing into a closed pipe (`nerflabel info |
/// head`) panics; end quietly as other command-line tools do instead.
fn restore_default_sigpipe() {
    #[cfg(unix)]
    // SAFETY: called first thing in main, before any thread exists; only
    // resets one signal's disposition to the system default.
    unsafe {
        libc::signal(libc::SIGPIPE, libc::SIG_DFL);
    }
}
