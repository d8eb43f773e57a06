//! Accuracy of instance masks against ground truth: per-object IoU
//! aggregated over frames, mean per-frame IoU, 2D box IoU, and per object
//! the pixel counts behind them (false positives and negatives) and a
//! boundary F-score. Used by the benchmark, the end-to-end tests and the demo.

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
    /// Per instance: pixel and boundary counts summed over frames.
    counts: BTreeMap<u16, ObjectCounts>,
}

/// Boundary pixels within this distance of the other mask's boundary count as matched.
pub const BOUNDARY_TOLERANCE_PX: i64 = 2;

/// Pixel and boundary counts of one instance, summed over frames.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct ObjectCounts {
    /// Pixels labelled with the instance.
    pub predicted: u64,
    /// Pixels of the instance in the ground truth.
    pub truth: u64,
    /// Pixels labelled with the instance that are the instance.
    pub both: u64,
    /// Boundary pixels of the prediction, and how many lie near a true boundary pixel.
    pub predicted_boundary: u64,
    pub predicted_boundary_matched: u64,
    /// Boundary pixels of the truth, and how many lie near a predicted boundary pixel.
    pub truth_boundary: u64,
    pub truth_boundary_matched: u64,
}

impl ObjectCounts {
    /// Intersection over union.
    pub fn iou(&self) -> f64 {
        let union = self.predicted + self.truth - self.both;
        if union == 0 {
            0.0
        } else {
            self.both as f64 / union as f64
        }
    }

    /// Predicted over true pixel count (1 = unbiased).
    pub fn pixel_ratio(&self) -> f64 {
        self.predicted as f64 / self.truth.max(1) as f64
    }

    /// Pixels labelled with the instance that are something else.
    pub fn false_positives(&self) -> u64 {
        self.predicted - self.both
    }

    /// Pixels of the instance left without its label.
    pub fn false_negatives(&self) -> u64 {
        self.truth - self.both
    }

    /// Boundary F-score: harmonic mean of boundary precision and recall within
    /// [`BOUNDARY_TOLERANCE_PX`] pixels.
    pub fn boundary_f(&self) -> f64 {
        let p = self.predicted_boundary_matched as f64 / self.predicted_boundary.max(1) as f64;
        let r = self.truth_boundary_matched as f64 / self.truth_boundary.max(1) as f64;
        if p + r == 0.0 {
            0.0
        } else {
            2.0 * p * r / (p + r)
        }
    }

    fn add(&mut self, o: &ObjectCounts) {
        self.predicted += o.predicted;
        self.truth += o.truth;
        self.both += o.both;
        self.predicted_boundary += o.predicted_boundary;
        self.predicted_boundary_matched += o.predicted_boundary_matched;
        self.truth_boundary += o.truth_boundary;
        self.truth_boundary_matched += o.truth_boundary_matched;
    }
}

/// Pixels of instance `id` with a 4-neighbour of another id (the image edge does not count).
fn boundary(mask: &[u16], width: usize, id: u16) -> Vec<(i64, i64)> {
    let height = mask.len() / width;
    let mut out = Vec::new();
    for y in 0..height {
        for x in 0..width {
            if mask[y * width + x] != id {
                continue;
            }
            let other = |nx: usize, ny: usize| mask[ny * width + nx] != id;
            let edge = (x > 0 && other(x - 1, y))
                || (x + 1 < width && other(x + 1, y))
                || (y > 0 && other(x, y - 1))
                || (y + 1 < height && other(x, y + 1));
            if edge {
                out.push((x as i64, y as i64));
            }
        }
    }
    out
}

/// How many of `points` lie within the tolerance of a pixel set in `near` (a width x height bitmap).
fn matched(points: &[(i64, i64)], near: &[bool], width: usize) -> u64 {
    let height = (near.len() / width) as i64;
    let t = BOUNDARY_TOLERANCE_PX;
    let hit = |&(x, y): &(i64, i64)| {
        (-t..=t).any(|dy| {
            (-t..=t).any(|dx| {
                let (nx, ny) = (x + dx, y + dy);
                dx * dx + dy * dy <= t * t
                    && nx >= 0
                    && ny >= 0
                    && (nx as usize) < width
                    && ny < height
                    && near[ny as usize * width + nx as usize]
            })
        })
    };
    points.iter().filter(|p| hit(p)).count() as u64
}

/// Boundary counts of instance `id` in one frame.
fn boundary_counts(predicted: &[u16], truth: &[u16], width: usize, id: u16) -> ObjectCounts {
    let bp = boundary(predicted, width, id);
    let bt = boundary(truth, width, id);
    let bitmap = |points: &[(i64, i64)]| {
        let mut m = vec![false; truth.len()];
        for &(x, y) in points {
            m[y as usize * width + x as usize] = true;
        }
        m
    };
    ObjectCounts {
        predicted_boundary: bp.len() as u64,
        predicted_boundary_matched: matched(&bp, &bitmap(&bt), width),
        truth_boundary: bt.len() as u64,
        truth_boundary_matched: matched(&bt, &bitmap(&bp), width),
        ..ObjectCounts::default()
    }
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
        assert_eq!(
            predicted.len(),
            truth.len(),
            "masks of one frame must have the same size"
        );
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
            let mut c = boundary_counts(predicted, truth, width, id);
            (c.predicted, c.truth, c.both) = (p, t, both);
            self.counts.entry(id).or_default().add(&c);
        }
        if !frame.is_empty() {
            self.frame_means.push(frame.iter().sum::<f64>() / frame.len() as f64);
        }
        let pred_boxes = tight_boxes(predicted, width);
        for (id, t) in tight_boxes(truth, width) {
            self.box_ious.push(pred_boxes.get(&id).map_or(0.0, |&p| box_iou(p, t)));
        }
    }

    /// Append the frames of `later` (scored after this one's): the same
    /// totals as adding them here one by one.
    pub fn merge(&mut self, later: MaskScores) {
        for (id, (i, u)) in later.totals {
            let e = self.totals.entry(id).or_default();
            e.0 += i;
            e.1 += u;
        }
        for (id, ious) in later.per_frame {
            self.per_frame.entry(id).or_default().extend(ious);
        }
        self.frame_means.extend(later.frame_means);
        self.box_ious.extend(later.box_ious);
        for (id, c) in later.counts {
            self.counts.entry(id).or_default().add(&c);
        }
    }

    /// IoU of each instance with intersections and unions summed over frames.
    pub fn per_object(&self) -> BTreeMap<u16, f64> {
        self.totals
            .iter()
            .map(|(&id, &(i, u))| (id, if u > 0 { i as f64 / u as f64 } else { 0.0 }))
            .collect()
    }

    /// Pixel and boundary counts of each instance, summed over frames.
    pub fn object_counts(&self) -> &BTreeMap<u16, ObjectCounts> {
        &self.counts
    }

    /// Counts of all instances together.
    pub fn total_counts(&self) -> ObjectCounts {
        let mut all = ObjectCounts::default();
        for c in self.counts.values() {
            all.add(c);
        }
        all
    }

    /// Mean over frames of each instance's IoU (frames where it is in either mask).
    pub fn per_object_mean_frame(&self) -> BTreeMap<u16, f64> {
        self.per_frame
            .iter()
            .map(|(&id, v)| (id, v.iter().sum::<f64>() / v.len().max(1) as f64))
            .collect()
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

    /// Frames scored apart and merged in order give the scores of adding
    /// them one after the other, to the bit.
    #[test]
    fn merged_frames_score_as_frames_added_in_order() {
        let mut rng = crate::rng::Rng::new(3, 0);
        let (w, h) = (24, 16);
        let mut mask = |ids: u64| -> Vec<u16> {
            let (x0, y0) = (rng.below(12) as usize, rng.below(8) as usize);
            let id = 1 + rng.below(ids) as u16;
            (0..w * h)
                .map(|i| {
                    if i % w >= x0 && i / w >= y0 && i % w < x0 + 9 {
                        id
                    } else {
                        0
                    }
                })
                .collect()
        };
        let frames: Vec<(Vec<u16>, Vec<u16>)> = (0..7).map(|_| (mask(3), mask(3))).collect();
        let mut sequential = MaskScores::default();
        let mut merged = MaskScores::default();
        for (predicted, truth) in &frames {
            sequential.add(predicted, truth, w);
            let mut one = MaskScores::default();
            one.add(predicted, truth, w);
            merged.merge(one);
        }
        assert!(sequential.mean_frame_iou() > 0.0);
        assert_eq!(format!("{sequential:?}"), format!("{merged:?}"));
    }

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
        let c = s.object_counts()[&1];
        assert_eq!((c.predicted, c.truth, c.both), (4, 4, 3));
        assert_eq!((c.false_positives(), c.false_negatives()), (1, 1));
        s.add(&truth, &truth, 4);
        assert_eq!(s.per_object()[&1], 7.0 / 9.0);
        assert!((s.per_object_mean_frame()[&1] - 0.8).abs() < 1e-12);
        assert_eq!(s.total_counts().truth, 2 * (4 + 1));
    }

    #[test]
    fn boundary_score_tolerates_two_pixels_and_not_three() {
        // A 20x20 square in a 40x40 frame, predicted shifted right by `shift` pixels.
        let square = |shift: usize| {
            let mut m = vec![0u16; 40 * 40];
            for y in 10..30 {
                for x in 10 + shift..30 + shift {
                    m[y * 40 + x] = 1;
                }
            }
            m
        };
        let score = |shift| {
            let mut s = MaskScores::default();
            s.add(&square(shift), &square(0), 40);
            s.object_counts()[&1]
        };
        assert_eq!(score(0).boundary_f(), 1.0);
        assert_eq!(score(2).boundary_f(), 1.0);
        // Shifted by 3, only the top and bottom edges still match (within 2 px).
        let f3 = score(3).boundary_f();
        assert!(f3 > 0.5 && f3 < 0.95, "{f3}");
        let c = score(3);
        assert_eq!((c.false_positives(), c.false_negatives()), (60, 60));
        assert!((c.pixel_ratio() - 1.0).abs() < 1e-12);
    }
}
