//! The ultralytics YOLO dataset layout of a labelling run (`label --yolo`):
//! `yolo/images/<stem>.<ext>` (the colour frames, hard-linked or copied),
//! `yolo/labels/<stem>.txt` (boxes, or outline polygons with
//! `--yolo-seg`), `train.txt` / `val.txt` (image lists split by contiguous
//! frame blocks) and `data.yaml`. Ultralytics finds a label by replacing
//! `/images/` with `/labels/` in the image path and the extension with
//! `.txt`, which this layout satisfies as it is.

use super::contour::instance_polygon;
use super::label::FrameLabel;
use super::parse::BoxSet;
use crate::mask::components;
use crate::rng::Rng;
use std::fmt::Write as _;
use std::path::Path;

/// Folder of the YOLO dataset inside the label output folder.
pub const DIR: &str = "yolo";
/// Blocks the labelled frames are cut into for the train/val split.
pub const SPLIT_BLOCKS: usize = 10;
/// Default share of the frames in the validation list.
pub const DEFAULT_VAL_FRACTION: f64 = 0.2;
/// RNG stream of the split (separate from any other use of the seed).
const SPLIT_STREAM: u64 = 0x5910;

/// How the colour frames get into `yolo/images/`.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, clap::ValueEnum)]
pub enum ImageMode {
    /// Hard links to the scan's files (no extra disk space; copies where
    /// the file system cannot link, e.g. across devices).
    #[default]
    Link,
    /// Independent copies.
    Copy,
}

impl ImageMode {
    /// Name used on the command line.
    pub fn name(self) -> &'static str {
        match self {
            ImageMode::Link => "link",
            ImageMode::Copy => "copy",
        }
    }
}

/// What `label --yolo` writes.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct YoloOptions {
    pub images: ImageMode,
    /// Outline polygons (`--yolo-seg`) instead of boxes.
    pub segments: bool,
    /// Share of the frames listed in `val.txt`, in [0, 1).
    pub val_fraction: f64,
    /// Seed of the split.
    pub seed: u64,
}

impl Default for YoloOptions {
    fn default() -> Self {
        YoloOptions {
            images: ImageMode::Link,
            segments: false,
            val_fraction: DEFAULT_VAL_FRACTION,
            seed: 0,
        }
    }
}

/// One `class x1 y1 x2 y2 ...` line per visible instance (instance-id
/// order): its outline polygon normalised to the image size. The class is
/// the category index (0-based, as in `data.yaml`).
pub fn segment_lines(label: &FrameLabel, boxes: &BoxSet) -> String {
    let (w, h) = (label.width as usize, label.height as usize);
    let parts = components(&label.mask, w, h);
    let mut out = String::new();
    for inst in &label.instances {
        let Some(class) = boxes
            .by_instance(inst.instance_id)
            .and_then(|b| boxes.category_id(&b.label))
        else {
            continue;
        };
        let Ok(id) = u16::try_from(inst.instance_id) else {
            continue;
        };
        let polygon = instance_polygon(&parts, w, h, id);
        if polygon.len() < 3 {
            continue;
        }
        let _ = write!(out, "{}", class - 1);
        for p in &polygon {
            let _ = write!(out, " {:.6} {:.6}", p[0] / w as f64, p[1] / h as f64);
        }
        out.push('\n');
    }
    out
}

/// Which of `n` frames (in frame order) go to validation: the frames are
/// cut into [`SPLIT_BLOCKS`] contiguous blocks of nearly equal length (one
/// frame per block when fewer), and a seeded draw picks
/// `round(blocks * fraction)` of them, at least one and never all (with
/// two or more frames and a fraction above 0). Neighbouring frames, near
/// duplicates, so stay on one side except at the few block borders.
pub fn val_frames(n: usize, fraction: f64, seed: u64) -> Vec<bool> {
    let blocks = n.min(SPLIT_BLOCKS);
    let mut val = vec![false; n];
    if blocks < 2 || !(fraction > 0.0) {
        return val;
    }
    let picked = ((blocks as f64 * fraction).round() as usize).clamp(1, blocks - 1);
    // Partial Fisher-Yates: the first `picked` entries are a seeded sample.
    let mut order: Vec<usize> = (0..blocks).collect();
    let mut rng = Rng::new(seed, SPLIT_STREAM);
    for i in 0..picked {
        let j = i + rng.below((blocks - i) as u64) as usize;
        order.swap(i, j);
    }
    for &b in &order[..picked] {
        // Block b holds frames [b n / blocks, (b + 1) n / blocks).
        for v in &mut val[b * n / blocks..(b + 1) * n / blocks] {
            *v = true;
        }
    }
    val
}

/// `data.yaml` for ultralytics: the dataset root, the two lists and the
/// class names by index. Strings are written as YAML double-quoted scalars
/// (JSON string syntax, a subset of them).
pub fn data_yaml(root: &Path, boxes: &BoxSet, options: &YoloOptions, train: usize, val: usize) -> Option<String> {
    let quote = |s: &str| serde_json::to_string(s).unwrap_or_default();
    let root = root.to_str()?;
    let mut out = String::new();
    let _ = writeln!(
        out,
        "# Written by nerflabel {} (label --yolo{}): {train} training and {val} validation frames,\n\
         # split by contiguous frame blocks (seed {}, val fraction {}). Moving this folder:\n\
         # update `path` below, or delete that line (ultralytics then uses this file's folder).",
        env!("CARGO_PKG_VERSION"),
        if options.segments { " --yolo-seg" } else { "" },
        options.seed,
        options.val_fraction
    );
    let _ = writeln!(out, "path: {}", quote(root));
    let _ = writeln!(out, "train: train.txt");
    let _ = writeln!(out, "val: val.txt");
    let _ = writeln!(out, "nc: {}", boxes.categories.len());
    let _ = writeln!(out, "names:");
    for (i, name) in boxes.categories.iter().enumerate() {
        let _ = writeln!(out, "  {i}: {}", quote(name));
    }
    Some(out)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::boxes::parse::Box3;
    use nalgebra::{Point3, Rotation3, Vector3};

    #[test]
    fn split_is_seeded_block_wise_and_near_the_fraction() {
        let n = 120;
        let val = val_frames(n, 0.2, 7);
        assert_eq!(val, val_frames(n, 0.2, 7), "same seed, same split");
        assert_ne!(val, val_frames(n, 0.2, 8), "another seed, another split");
        assert_eq!(val.iter().filter(|&&v| v).count(), 24);
        // Two blocks of 12: at most two runs of validation frames.
        let runs = (0..n).filter(|&i| val[i] && (i == 0 || !val[i - 1])).count();
        assert!((1..=2).contains(&runs), "{runs} runs");
        for (n, fraction, want) in [
            (20, 0.25, 6),
            (7, 0.2, 1),
            (2, 0.9, 1),
            (1, 0.5, 0),
            (30, 0.0, 0),
            (10, 0.99, 9),
        ] {
            let count = val_frames(n, fraction, 0).iter().filter(|&&v| v).count();
            assert_eq!(count, want, "{n} frames, fraction {fraction}");
        }
        // Over seeds every block is drawn sometimes.
        let mut seen = [false; 10];
        for seed in 0..200 {
            for (b, s) in seen.iter_mut().enumerate() {
                *s |= val_frames(100, 0.1, seed)[b * 10];
            }
        }
        assert!(seen.iter().all(|&s| s));
    }

    #[test]
    fn data_yaml_quotes_names_and_lists_them_by_index() {
        let b = |label: &str, id: u32| Box3 {
            label: label.into(),
            instance_id: id,
            center: Point3::origin(),
            size: Vector3::repeat(1.0),
            rotation: Rotation3::identity(),
        };
        let boxes = BoxSet::from_boxes(vec![b("mug", 1), b("a: \"b\"", 2), b("mug", 3)]);
        let yaml = data_yaml(Path::new("/data/x y"), &boxes, &YoloOptions::default(), 8, 2).unwrap();
        let lines: Vec<&str> = yaml.lines().filter(|l| !l.starts_with('#')).collect();
        assert_eq!(
            lines,
            vec![
                "path: \"/data/x y\"",
                "train: train.txt",
                "val: val.txt",
                "nc: 2",
                "names:",
                "  0: \"mug\"",
                "  1: \"a: \\\"b\\\"\""
            ]
        );
    }
}
