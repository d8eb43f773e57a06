//! Accuracy of instance masks against ground truth: per-object IoU
//! aggregated over frames, mean per-frame IoU and 2D box IoU. Used by the
//! benchmark, the end-to-end tests and the demo.

use std::collections::BTreeMap;

/// Running totals over many frames.
#[derive(Clone, Debug, Default)]
pub struct MaskScores {
    /// Per instance: summed intersection and union pixel counts.
    totals: BTreeMap<u16, (u64, u64)>,
    /// Per instance: per-frame IoUs (frames where the instance is in either mask).
    per_frame: BTreeMap<u16, Vec<f64>>,
    /// Mean IoU of each frame over the instances in either mask.
    frame_means: Vec<f64>,
    /// 2D box IoU per (frame, ground-truth instance); a missed instance counts 0.
    box_ious: Vec<f64>,
}

/// Tight box `[x0, y0, x1, y1)` of every instance in a mask.
fn tight_boxes(mask: &[u16], width: usize) -> BTreeMap<u16, [usize; 4]> {
    let mut out: BTreeMap<u16, [usize; 4]> = BTreeMap::new();
    for (i, &id) in mask.iter().enumerate() {
        if id == 0 {
            continue;
        }
        let (x, y) = (i % width, i / width);
        let b = out.entry(id).or_insert([x, y, x + 1, y + 1]);
        *b = [b[0].min(x), b[1].min(y), b[2].max(x + 1), b[3].max(y + 1)];
    }
    out
}

fn box_iou(a: [usize; 4], b: [usize; 4]) -> f64 {
    let iw = a[2].min(b[2]).saturating_sub(a[0].max(b[0]));
    let ih = a[3].min(b[3]).saturating_sub(a[1].max(b[1]));
    let inter = (iw * ih) as f64;
    let area = |r: [usize; 4]| ((r[2] - r[0]) * (r[3] - r[1])) as f64;
    inter / (area(a) + area(b) - inter)
}

impl MaskScores {
    /// Add one frame: predicted and ground-truth id masks of equal size.
    pub fn add(&mut self, predicted: &[u16], truth: &[u16], width: usize) {
        assert_eq!(predicted.len(), truth.len(), "masks of one frame must have the same size");
        let mut counts: BTreeMap<u16, (u64, u64, u64)> = BTreeMap::new(); // (pred, truth, both)
        for (&p, &t) in predicted.iter().zip(truth) {
            if p != 0 {
                counts.entry(p).or_default().0 += 1;
            }
            if t != 0 {
                counts.entry(t).or_default().1 += 1;
            }
            if p != 0 && p == t {
                counts.entry(p).or_default().2 += 1;
            }
        }
        let mut frame = Vec::new();
        for (&id, &(p, t, both)) in &counts {
            let union = p + t - both;
            let e = self.totals.entry(id).or_default();
            e.0 += both;
            e.1 += union;
            let iou = both as f64 / union as f64;
            self.per_frame.entry(id).or_default().push(iou);
            frame.push(iou);
        }
        if !frame.is_empty() {
            self.frame_means.push(frame.iter().sum::<f64>() / frame.len() as f64);
        }
        let pred_boxes = tight_boxes(predicted, width);
        for (id, t) in tight_boxes(truth, width) {
            self.box_ious.push(pred_boxes.get(&id).map_or(0.0, |&p| box_iou(p, t)));
        }
    }

    /// IoU of each instance with intersections and unions summed over frames.
    pub fn per_object(&self) -> BTreeMap<u16, f64> {
        self.totals.iter().map(|(&id, &(i, u))| (id, if u > 0 { i as f64 / u as f64 } else { 0.0 })).collect()
    }

    /// Mean over frames of each instance's IoU (frames where it is in either mask).
    pub fn per_object_mean_frame(&self) -> BTreeMap<u16, f64> {
        self.per_frame.iter().map(|(&id, v)| (id, v.iter().sum::<f64>() / v.len().max(1) as f64)).collect()
    }

    /// Mean over frames of the frame's mean instance IoU.
    pub fn mean_frame_iou(&self) -> f64 {
        self.frame_means.iter().sum::<f64>() / self.frame_means.len().max(1) as f64
    }

    /// Mean over the objects of their aggregated IoU.
    pub fn mean_object_iou(&self) -> f64 {
        let v = self.per_object();
        v.values().sum::<f64>() / v.len().max(1) as f64
    }

    /// Mean 2D box IoU over (frame, ground-truth instance) pairs.
    pub fn mean_box_iou(&self) -> f64 {
        self.box_ious.iter().sum::<f64>() / self.box_ious.len().max(1) as f64
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn scores_of_a_hand_made_pair() {
        // 4x2 masks. Truth: id 1 on the left 2x2, id 2 at (3, 0). Prediction: id 1 on 3 of the
        // 4 pixels plus one extra, id 2 missing, a spurious id 3.
        let truth = [1, 1, 0, 2, 1, 1, 0, 0];
        let pred = [1, 1, 1, 0, 1, 0, 0, 3];
        let mut s = MaskScores::default();
        s.add(&pred, &truth, 4);
        let obj = s.per_object();
        assert_eq!(obj[&1], 3.0 / 5.0);
        assert_eq!(obj[&2], 0.0);
        assert_eq!(obj[&3], 0.0);
        assert!((s.mean_frame_iou() - 0.2).abs() < 1e-12);
        // Box of 1: truth [0,0,2,2), prediction [0,0,3,2): 4/6. Box of 2 missed: 0.
        assert!((s.mean_box_iou() - (4.0 / 6.0) / 2.0).abs() < 1e-12);
        s.add(&truth, &truth, 4);
        assert_eq!(s.per_object()[&1], 7.0 / 9.0);
        assert!((s.per_object_mean_frame()[&1] - 0.8).abs() < 1e-12);
    }
}
