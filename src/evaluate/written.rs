//! The labels a `label` run wrote, scored against the scan's own ground
//! truth where it has some (a generated scan's `gt/masks`): kept beside the
//! labels as `evaluation.json`, which `report --plot` draws beside the fit's
//! curve.

use super::labels::read_gray16;
use crate::boxes::metrics::MaskScores;
use rayon::prelude::*;
use serde::{Deserialize, Serialize};
use std::path::Path;

/// File name of the score in a label output folder.
pub const EVALUATION_FILE: &str = "evaluation.json";

/// How a label output folder scores against ground-truth masks.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct WrittenLabelScore {
    /// The ground-truth masks folder.
    pub truth: String,
    /// The model the depth came from (`None`: sensor depth).
    pub model: Option<String>,
    /// Depth source name.
    pub source: String,
    /// Frames scored (those with a ground-truth mask).
    pub frames: usize,
    /// Mean over frames of the mean IoU of the instances present.
    pub miou: f64,
    /// Predicted / true object pixels.
    pub pixel_ratio: f64,
}

/// Score every mask in `labels/masks` that has a mask of the same name in
/// `truth`; `None` when no frame has both.
pub fn score_written_labels(labels: &Path, truth: &Path) -> Result<Option<(MaskScores, usize)>, String> {
    let masks = labels.join("masks");
    let entries = std::fs::read_dir(&masks).map_err(|e| format!("{}: {e}", masks.display()))?;
    let mut names: Vec<std::ffi::OsString> = entries
        .filter_map(Result::ok)
        .map(|e| e.file_name())
        .filter(|n| Path::new(n).extension().is_some_and(|x| x == "png"))
        .collect();
    names.sort();
    // Frames are read and scored in parallel, then merged in name order
    // (the same scores as one after the other).
    let per_frame: Vec<Option<MaskScores>> = names
        .par_iter()
        .map(|name| {
            let true_path = truth.join(name);
            if !true_path.is_file() {
                return Ok(None);
            }
            let predicted = read_gray16(&masks.join(name))?;
            let (width, _) =
                image::image_dimensions(&true_path).map_err(|e| format!("{}: {e}", true_path.display()))?;
            let exact = read_gray16(&true_path)?;
            if exact.len() != predicted.len() {
                return Err(format!(
                    "{}: {} pixels where the labels have {}",
                    true_path.display(),
                    exact.len(),
                    predicted.len()
                ));
            }
            let mut frame = MaskScores::default();
            frame.add(&predicted, &exact, width as usize);
            Ok(Some(frame))
        })
        .collect::<Result<_, String>>()?;
    let mut scores = MaskScores::default();
    let mut frames = 0;
    for frame in per_frame.into_iter().flatten() {
        scores.merge(frame);
        frames += 1;
    }
    Ok((frames > 0).then_some((scores, frames)))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn write(path: &Path, ids: &[u8], w: u32, h: u32) {
        std::fs::create_dir_all(path.parent().unwrap()).unwrap();
        image::GrayImage::from_raw(w, h, ids.to_vec())
            .unwrap()
            .save(path)
            .unwrap();
    }

    #[test]
    fn frames_with_truth_are_scored_and_others_skipped() {
        let dir = tempfile::tempdir().unwrap();
        let (labels, truth) = (dir.path().join("labels"), dir.path().join("gt"));
        // Frame a: exact. Frame b: one of two object pixels missed. Frame c: no truth.
        write(&labels.join("masks/a.png"), &[0, 1, 1, 0], 2, 2);
        write(&truth.join("a.png"), &[0, 1, 1, 0], 2, 2);
        write(&labels.join("masks/b.png"), &[0, 1, 0, 0], 2, 2);
        write(&truth.join("b.png"), &[0, 1, 1, 0], 2, 2);
        write(&labels.join("masks/c.png"), &[1, 1, 1, 1], 2, 2);
        let (scores, frames) = score_written_labels(&labels, &truth).unwrap().unwrap();
        assert_eq!(frames, 2);
        assert!(
            (scores.mean_frame_iou() - 0.75).abs() < 1e-12,
            "{}",
            scores.mean_frame_iou()
        );
        assert!((scores.total_counts().pixel_ratio() - 0.75).abs() < 1e-12);
        // No frame with truth: nothing to say.
        let empty = dir.path().join("none");
        std::fs::create_dir_all(&empty).unwrap();
        assert!(score_written_labels(&labels, &empty).unwrap().is_none());
    }
}
