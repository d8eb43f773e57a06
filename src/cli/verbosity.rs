//! How much the commands say (`-q`, `-v`): warnings and errors always;
//! progress, what is being done and the summary lines unless `-q`; details
//! (every held-out evaluation, every checkpoint) only with `-v`. The output
//! a command exists to print (`info`, `report`, `batch --sbatch`, the
//! `annotate` URL) is printed whatever the level.

use std::sync::atomic::{AtomicU8, Ordering};

/// Progress and summaries off.
pub const QUIET: u8 = 0;
/// Progress and summaries.
pub const NORMAL: u8 = 1;
/// Also details.
pub const VERBOSE: u8 = 2;

static LEVEL: AtomicU8 = AtomicU8::new(NORMAL);

/// Set the level for the rest of the run.
pub fn set(level: u8) {
    LEVEL.store(level, Ordering::Relaxed);
}

/// Whether progress and summaries are silenced (`-q`).
pub fn quiet() -> bool {
    LEVEL.load(Ordering::Relaxed) == QUIET
}

/// Whether details are wanted (`-v`).
pub fn verbose() -> bool {
    LEVEL.load(Ordering::Relaxed) >= VERBOSE
}

/// A summary line on stdout, unless `-q`.
macro_rules! say {
    ($($arg:tt)*) => {
        if !$crate::cli::verbosity::quiet() {
            println!($($arg)*);
        }
    };
}

/// What is being done, on stderr, unless `-q`.
macro_rules! note {
    ($($arg:tt)*) => {
        if !$crate::cli::verbosity::quiet() {
            eprintln!($($arg)*);
        }
    };
}

/// A detail on stderr, only with `-v`.
macro_rules! detail {
    ($($arg:tt)*) => {
        if $crate::cli::verbosity::verbose() {
            eprintln!($($arg)*);
        }
    };
}

pub(crate) use {detail, note, say};
