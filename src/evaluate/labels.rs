//! Labels against exact ground truth: run the labeller on a fixture's (or a
//! reference box's) frames and score the masks, per object and in total.

use crate::boxes::metrics::MaskScores;
use crate::boxes::{BoxSet, DepthSource, FrameLabel, LabelError, LabelOptions, Labeler};
use crate::nerf::model_file::Model;
use crate::scan::{Frame, Scan};
use std::path::Path;
use std::time::Instant;

/// Ground-truth instance mask of scan frame `index`.
pub type TruthMask = (usize, Vec<u16>);

/// Scores of one labelling run.
#[derive(Clone, Debug)]
pub struct LabelEvaluation {
    pub source: DepthSource,
    pub scores: MaskScores,
    /// Wall time of labelling (not scoring).
    pub seconds: f64,
    pub frames: usize,
    /// Fraction of pixels whose depth was rendered.
    pub rendered_fraction: f64,
    /// The labels, for error images.
    pub labels: Vec<FrameLabel>,
}

/// Read a one-channel 8- or 16-bit PNG (instance ids, depth units) as 16-bit values.
pub fn read_gray16(path: &Path) -> Result<Vec<u16>, String> {
    match image::open(path).map_err(|e| format!("{}: {e}", path.display()))? {
        image::DynamicImage::ImageLuma8(m) => Ok(m.into_raw().into_iter().map(u16::from).collect()),
        image::DynamicImage::ImageLuma16(m) => Ok(m.into_raw()),
        other => Err(format!(
            "{}: unexpected colour type {:?}",
            path.display(),
            other.color()
        )),
    }
}

/// Read a fixture's ground-truth masks (`gt/masks/NAME.png`) of every `every`-th scan frame.
pub fn fixture_truth(dir: &Path, scan: &Scan, every: usize) -> Result<Vec<TruthMask>, String> {
    (scan.frames.iter().enumerate().step_by(every.max(1)))
        .map(|(i, f)| Ok((i, read_gray16(&dir.join("gt/masks").join(format!("{}.png", f.name)))?)))
        .collect()
}

/// Label the frames of `truth` with `options` (support planes excluded and
/// sensor depth fused, as the CLI does) and score them.
pub fn evaluate_labels(
    scan: &Scan,
    boxes: &BoxSet,
    model: Option<&Model>,
    truth: &[TruthMask],
    options: LabelOptions,
) -> Result<LabelEvaluation, LabelError> {
    let source = options.source;
    let mut labeler = Labeler::new(boxes, model, options)?;
    labeler.exclude_supports(scan)?;
    labeler.fuse_sensor_depth(scan);
    let frames: Vec<&Frame> = truth.iter().map(|(i, _)| &scan.frames[*i]).collect();
    let t = Instant::now();
    let labels = labeler.label_frames(&frames, &|_| {});
    let seconds = t.elapsed().as_secs_f64();
    let mut scores = MaskScores::default();
    let mut pixels = 0usize;
    for (l, (_, gt)) in labels.iter().zip(truth) {
        scores.add(&l.mask, gt, l.width as usize);
        pixels += l.mask.len();
    }
    let rays: usize = labels.iter().map(|l| l.rendered_rays).sum();
    Ok(LabelEvaluation {
        source,
        scores,
        seconds,
        frames: frames.len(),
        rendered_fraction: rays as f64 / pixels.max(1) as f64,
        labels,
    })
}
