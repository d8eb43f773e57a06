//! Summary of a loaded scan for `nerflabel info`.

use super::Scan;

/// What `nerflabel info` reports about a scan.
#[derive(Clone, Debug)]
pub struct ScanSummary {
    pub frames: usize,
}

/// Summarise a loaded scan.
pub fn summarize(scan: &Scan) -> ScanSummary {
    ScanSummary { frames: scan.frames.len() }
}
