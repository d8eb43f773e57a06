//! What `label` is asked to do (depth source, frame range, full depth) and
//! what can go wrong while doing it.

use super::classify::Overlap;
use super::parse::BoxError;
use crate::poses::GeometryError;
use std::fmt;
use std::path::PathBuf;
use std::str::FromStr;

/// Where the surface depth behind each pixel comes from.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, clap::ValueEnum)]
pub enum DepthSource {
    /// First surface crossing rendered from the trained NeRF.
    Nerf,
    /// The scan's own depth (the raw-depth baseline; no model needed).
    Sensor,
    /// Sensor depth where it agrees with the rendered depth, rendered depth elsewhere.
    Fused,
}

impl DepthSource {
    /// Every source, in the order benchmarks print them.
    pub const ALL: [DepthSource; 3] = [DepthSource::Sensor, DepthSource::Nerf, DepthSource::Fused];

    /// Name used on the command line and in outputs.
    pub fn name(self) -> &'static str {
        match self {
            DepthSource::Nerf => "nerf",
            DepthSource::Sensor => "sensor",
            DepthSource::Fused => "fused",
        }
    }

    /// Whether labelling with this source needs a trained model.
    pub fn needs_model(self) -> bool {
        self != DepthSource::Sensor
    }
}

/// The default source: the most accurate in the benchmark (README table).
pub const DEFAULT_SOURCE: DepthSource = DepthSource::Fused;

impl fmt::Display for DepthSource {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.name())
    }
}

impl FromStr for DepthSource {
    type Err = LabelError;
    fn from_str(s: &str) -> Result<Self, Self::Err> {
        <DepthSource as clap::ValueEnum>::from_str(s.trim(), true).map_err(|_| {
            LabelError::Option(format!(
                "unknown depth source `{s}`: expected one of {}",
                crate::value_names::<DepthSource>()
            ))
        })
    }
}

/// Frame ids `start..end` (start inclusive, end exclusive; either may be open).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct FrameRange {
    pub start: Option<u64>,
    pub end: Option<u64>,
}

impl FrameRange {
    /// Whether frame id `id` is in the range.
    pub fn contains(&self, id: u64) -> bool {
        self.start.is_none_or(|s| id >= s) && self.end.is_none_or(|e| id < e)
    }
}

impl fmt::Display for FrameRange {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        let part = |v: Option<u64>| v.map(|v| v.to_string()).unwrap_or_default();
        write!(f, "{}..{}", part(self.start), part(self.end))
    }
}

impl FromStr for FrameRange {
    type Err = LabelError;
    /// `A..B`, `A..` or `..B` with frame ids.
    fn from_str(s: &str) -> Result<Self, Self::Err> {
        let bad = |why: &str| {
            LabelError::Option(format!(
                "frame range `{s}`: {why} (expected A..B with frame ids, B exclusive)"
            ))
        };
        let (a, b) = s.trim().split_once("..").ok_or_else(|| bad("missing `..`"))?;
        let id = |t: &str| -> Result<Option<u64>, LabelError> {
            let t = t.trim();
            if t.is_empty() {
                Ok(None)
            } else {
                t.parse::<u64>()
                    .map(Some)
                    .map_err(|_| bad(&format!("`{t}` is not a frame id")))
            }
        };
        let range = FrameRange {
            start: id(a)?,
            end: id(b)?,
        };
        if let (Some(a), Some(b)) = (range.start, range.end) {
            if a >= b {
                return Err(bad("the range is empty"));
            }
        }
        Ok(range)
    }
}

/// How to label.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct LabelOptions {
    pub source: DepthSource,
    /// Depth for every pixel: rendered (completed) with the nerf and fused
    /// sources, the scan's own depth with the sensor source. Otherwise only
    /// pixels whose ray can meet a box are rendered.
    pub full_depth: bool,
    /// Fused source: sensor depth is kept where it is within this many finest
    /// grid cells of the rendered depth.
    pub fused_tolerance_cells: f64,
    /// Accumulated opacity at which a rendered ray has reached its surface.
    pub surface_opacity: f32,
    /// Rendered surfaces are placed to within about a grid cell where the
    /// sensor measured them and about two where only colour did (the
    /// finest level's trilinear footprint is two cells wide): a surface
    /// point outside every box but within this many finest cells in front
    /// of a box the ray enters belongs to that box. Catches the top of an
    /// object without sensor depth rendered a little above its box.
    pub box_tolerance_cells: f64,
    /// Mask clean-up: fill enclosed holes and drop detached specks smaller
    /// than this fraction of their instance (0 = off).
    pub cleanup_fraction: f64,
    /// Label exactly what each box encloses: no support or wall plane is
    /// excluded (`Labeler::exclude_supports` does nothing), and a point in
    /// several boxes goes by the overlap rule alone ([`super::reach`] is off).
    pub exact_boxes: bool,
    /// Which box a point inside several boxes belongs to.
    pub overlap: Overlap,
    /// Move silhouettes onto the frame's colour edges ([`super::boundary`]);
    /// on by default.
    pub snap_to_colour: bool,
    /// Full depth of a few frames only: march the model's own occupancy
    /// grid (re-estimating a finer one pays off over many whole frames,
    /// not over a few).
    pub few_frames: bool,
}

impl Default for LabelOptions {
    fn default() -> Self {
        LabelOptions {
            source: DEFAULT_SOURCE,
            full_depth: false,
            fused_tolerance_cells: 1.0,
            surface_opacity: 0.5,
            box_tolerance_cells: 2.0,
            exact_boxes: false,
            overlap: Overlap::Smallest,
            cleanup_fraction: 0.02,
            snap_to_colour: true,
            few_frames: false,
        }
    }
}

/// Why labelling failed.
#[derive(Debug, thiserror::Error)]
pub enum LabelError {
    #[error("{0}")]
    Option(String),
    #[error("depth source `{0}` needs a trained model; run `nerflabel fit` first or use --source sensor")]
    MissingModel(DepthSource),
    #[error("the model cannot be used: {0}")]
    Geometry(#[from] GeometryError),
    #[error(transparent)]
    Boxes(#[from] BoxError),
    #[error("no frame of the scan lies in the range {0}")]
    NoFrames(FrameRange),
    #[error("{path}: {source}")]
    Io { path: PathBuf, source: std::io::Error },
    #[error("{path}: could not encode PNG: {source}")]
    Encode { path: PathBuf, source: image::ImageError },
    #[error("{path}: could not write JSON: {source}")]
    Json { path: PathBuf, source: serde_json::Error },
    #[error("{path}: holds `{entry}` but was not written by `nerflabel label`; refusing to replace it (choose an empty or new --out folder)")]
    NotOurs { path: PathBuf, entry: String },
    #[error(
        "{path}: cannot update the labels of the other frames: {reason}; label every frame instead (without --frames)"
    )]
    Merge { path: PathBuf, reason: String },
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn frame_ranges_parse_and_reject_nonsense() {
        let r: FrameRange = "3..7".parse().unwrap();
        assert_eq!(
            r,
            FrameRange {
                start: Some(3),
                end: Some(7)
            }
        );
        assert!(!r.contains(2) && r.contains(3) && r.contains(6) && !r.contains(7));
        let open: FrameRange = " 5.. ".parse().unwrap();
        assert!(open.contains(5) && open.contains(u64::MAX) && !open.contains(4));
        let head: FrameRange = "..2".parse().unwrap();
        assert!(head.contains(0) && head.contains(1) && !head.contains(2));
        assert_eq!(head.to_string(), "..2");
        for bad in ["3", "7..3", "4..4", "a..5", "1..-2"] {
            let msg = bad.parse::<FrameRange>().expect_err(bad).to_string();
            assert!(msg.contains(&format!("`{bad}`")), "{msg}");
        }
    }

    #[test]
    fn sources_parse_by_name() {
        for s in DepthSource::ALL {
            assert_eq!(s.name().parse::<DepthSource>().unwrap(), s);
        }
        assert_eq!("NeRF".parse::<DepthSource>().unwrap(), DepthSource::Nerf);
        assert!("tsdf"
            .parse::<DepthSource>()
            .unwrap_err()
            .to_string()
            .contains("`tsdf`"));
        assert!(!DepthSource::Sensor.needs_model() && DepthSource::Fused.needs_model());
    }
}
