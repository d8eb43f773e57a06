//! Summary of a loaded scan for `nerflabel info`: sizes, depth coverage and
//! range, trajectory length and the loader's warnings.

use super::{Layout, Scan};
use rayon::prelude::*;
use std::collections::BTreeMap;
use std::fmt;
use std::path::PathBuf;

/// At most this many depth values are kept for the median.
const MEDIAN_SAMPLES: usize = 1 << 20;

/// What `nerflabel info` reports about a scan.
#[derive(Clone, Debug, PartialEq)]
pub struct ScanSummary {
    /// Folder the scan was read from.
    pub root: PathBuf,
    /// Layout it was read as.
    pub layout: Layout,
    /// Number of frames.
    pub frames: usize,
    /// Colour resolutions with their frame counts, sorted.
    pub rgb_sizes: Vec<((u32, u32), usize)>,
    /// Depth resolutions as stored on disk, with their frame counts, sorted.
    pub depth_sizes: Vec<((u32, u32), usize)>,
    /// Frames that have a depth image.
    pub frames_with_depth: usize,
    /// Fraction (0..=1) of all frames' colour pixels that have a depth measurement.
    pub depth_coverage: f64,
    /// Smallest, median (from a sample when large) and largest valid depth, metres.
    pub depth_range: Option<DepthRange>,
    /// Sum of the distances between consecutive camera centres, metres.
    pub trajectory_length: f64,
    /// Non-fatal findings of the loader.
    pub warnings: Vec<String>,
}

/// Range of valid depth values, metres.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct DepthRange {
    pub min: f32,
    pub median: f32,
    pub max: f32,
}

/// Summarise a loaded scan.
pub fn summarize(scan: &Scan) -> ScanSummary {
    let mut rgb_sizes = BTreeMap::new();
    let mut depth_sizes = BTreeMap::new();
    for frame in &scan.frames {
        *rgb_sizes.entry(frame.size()).or_insert(0usize) += 1;
        if let Some(size) = frame.depth_size {
            *depth_sizes.entry(size).or_insert(0usize) += 1;
        }
    }
    let total_pixels: usize = scan
        .frames
        .iter()
        .map(|f| f.rgb.width() as usize * f.rgb.height() as usize)
        .sum();
    let depth_pixels: usize = scan
        .frames
        .iter()
        .filter_map(|f| f.depth.as_ref())
        .map(|d| d.metres.len())
        .sum();
    // Sample every `stride`-th pixel for the median so memory stays bounded.
    let stride = depth_pixels.div_ceil(MEDIAN_SAMPLES).max(1);
    let stats: Vec<(usize, f32, f32, Vec<f32>)> = scan
        .frames
        .par_iter()
        .filter_map(|f| f.depth.as_ref())
        .map(|d| {
            let (mut count, mut lo, mut hi) = (0usize, f32::INFINITY, 0.0f32);
            for &z in d.metres.iter().filter(|&&z| z > 0.0) {
                count += 1;
                lo = lo.min(z);
                hi = hi.max(z);
            }
            let sample = d.metres.iter().step_by(stride).copied().filter(|&z| z > 0.0).collect();
            (count, lo, hi, sample)
        })
        .collect();
    let valid: usize = stats.iter().map(|s| s.0).sum();
    let mut samples: Vec<f32> = stats.iter().flat_map(|s| s.3.iter().copied()).collect();
    let depth_range = (valid > 0 && !samples.is_empty()).then(|| {
        let mid = samples.len() / 2;
        let (_, median, _) = samples.select_nth_unstable_by(mid, f32::total_cmp);
        DepthRange {
            min: stats.iter().map(|s| s.1).fold(f32::INFINITY, f32::min),
            median: *median,
            max: stats.iter().map(|s| s.2).fold(0.0, f32::max),
        }
    });
    let trajectory_length = scan
        .frames
        .windows(2)
        .map(|w| match w {
            [a, b] => (b.camera_center() - a.camera_center()).norm(),
            _ => 0.0,
        })
        .sum();
    ScanSummary {
        root: scan.root.clone(),
        layout: scan.layout,
        frames: scan.frames.len(),
        rgb_sizes: rgb_sizes.into_iter().collect(),
        depth_sizes: depth_sizes.into_iter().collect(),
        frames_with_depth: scan.frames.iter().filter(|f| f.depth.is_some()).count(),
        depth_coverage: if total_pixels > 0 {
            valid as f64 / total_pixels as f64
        } else {
            0.0
        },
        depth_range,
        trajectory_length,
        warnings: scan.warnings.clone(),
    }
}

fn sizes(list: &[((u32, u32), usize)], frames: usize) -> String {
    let parts: Vec<String> = list
        .iter()
        .map(|((w, h), n)| {
            if *n == frames {
                format!("{w}x{h}")
            } else {
                format!("{w}x{h} ({n} frames)")
            }
        })
        .collect();
    parts.join(", ")
}

impl fmt::Display for ScanSummary {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        writeln!(f, "scan        {} ({})", self.root.display(), self.layout)?;
        writeln!(f, "frames      {} ({} with depth)", self.frames, self.frames_with_depth)?;
        writeln!(f, "rgb         {}", sizes(&self.rgb_sizes, self.frames))?;
        if self.depth_sizes.is_empty() {
            writeln!(f, "depth       none")?;
        } else {
            let resampled = self
                .depth_sizes
                .iter()
                .any(|(s, _)| !self.rgb_sizes.iter().any(|(r, _)| r == s));
            let note = if resampled { ", resampled to the rgb grid" } else { "" };
            writeln!(
                f,
                "depth       {} on disk{note}",
                sizes(&self.depth_sizes, self.frames_with_depth)
            )?;
        }
        write!(
            f,
            "coverage    {:.1}% of pixels have depth",
            self.depth_coverage * 100.0
        )?;
        match self.depth_range {
            Some(r) => writeln!(
                f,
                "; {:.2} / {:.2} / {:.2} m (min / median / max)",
                r.min, r.median, r.max
            )?,
            None => writeln!(f)?,
        }
        writeln!(f, "trajectory  {:.2} m", self.trajectory_length)?;
        if self.warnings.is_empty() {
            write!(f, "warnings    none")
        } else {
            write!(f, "warnings    {}", self.warnings.len())?;
            for w in &self.warnings {
                write!(f, "\n  - {w}")?;
            }
            Ok(())
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::scan::{DepthMap, Frame, Intrinsics, RgbImage};
    use nalgebra::IsometryMatrix3;

    fn frame(id: u64, x: f64, depth: Option<Vec<f32>>) -> Frame {
        let k = Intrinsics {
            fx: 2.0,
            fy: 2.0,
            cx: 1.0,
            cy: 0.5,
        };
        let depth = depth.map(|metres| DepthMap {
            width: 2,
            height: 2,
            metres,
        });
        let mut f = Frame::new(
            id,
            format!("{id:06}"),
            RgbImage::new(2, 2),
            depth,
            IsometryMatrix3::translation(x, 0.0, 0.0),
            k,
        );
        f.depth_size = f.depth_size.map(|_| (1, 1));
        f
    }

    #[test]
    fn summary_counts_coverage_range_and_path() {
        let scan = Scan {
            root: PathBuf::from("/s"),
            layout: Layout::Native,
            frames: vec![
                frame(0, 0.0, Some(vec![1.0, 2.0, 0.0, 3.0])),
                frame(1, 3.0, Some(vec![0.0, 0.0, 0.0, 5.0])),
                frame(2, 3.0, None),
            ],
            bounds: None,
            warnings: vec!["w1".into()],
            inputs: Vec::new(),
        };
        let s = summarize(&scan);
        assert_eq!(s.frames, 3);
        assert_eq!(s.frames_with_depth, 2);
        assert_eq!(s.rgb_sizes, vec![((2, 2), 3)]);
        assert_eq!(s.depth_sizes, vec![((1, 1), 2)]);
        assert!((s.depth_coverage - 4.0 / 12.0).abs() < 1e-12);
        assert_eq!(
            s.depth_range,
            Some(DepthRange {
                min: 1.0,
                median: 3.0,
                max: 5.0
            })
        );
        assert!((s.trajectory_length - 3.0).abs() < 1e-12);
        let text = s.to_string();
        assert!(text.contains("frames      3 (2 with depth)"), "{text}");
        assert!(text.contains("1x1 on disk, resampled"), "{text}");
        assert!(text.contains("33.3% of pixels"), "{text}");
        assert!(text.contains("  - w1"), "{text}");
    }
}
