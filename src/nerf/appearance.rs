//! Per-frame appearance: handheld cameras change exposure and white balance
//! from frame to frame, so each training frame's colour is the field's
//! colour through an affine map of its own (a 3x3 matrix and an offset).
//! Training learns the maps beside the field (`train::appearance`) and keeps
//! their mean at the identity, so the field's own colour is the scan's
//! average, *neutral* appearance. Rendering applies a frame's map, or none.

/// Row-major 3x4 affine colour map `[a00 a01 a02 b0, a10 .. b1, a20 .. b2]`:
/// `out_i = sum_j a_ij c_j + b_i`.
pub type Affine = [f32; 12];

/// The map that changes nothing (the neutral appearance).
pub const IDENTITY: Affine = [1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0];

/// `a` applied to colour `c`.
#[inline]
pub fn apply(a: &Affine, c: [f32; 3]) -> [f32; 3] {
    std::array::from_fn(|i| a[4 * i] * c[0] + a[4 * i + 1] * c[1] + a[4 * i + 2] * c[2] + a[4 * i + 3])
}

/// Backward of [`apply`]: given `g`, the loss gradient with respect to the
/// output, adds the gradient with respect to `a`'s entries to `grad_a` and
/// returns the gradient with respect to `c` (`a^T g`).
#[inline]
pub fn apply_backward(a: &Affine, c: [f32; 3], g: [f32; 3], grad_a: &mut [f32]) -> [f32; 3] {
    for i in 0..3 {
        for j in 0..3 {
            grad_a[4 * i + j] += g[i] * c[j];
        }
        grad_a[4 * i + 3] += g[i];
    }
    std::array::from_fn(|j| a[j] * g[0] + a[4 + j] * g[1] + a[8 + j] * g[2])
}

/// One map per scan frame from the maps of the training frames: a frame
/// that trained keeps its own; a held-out frame gets the mean of the
/// nearest training frame on each side in scan order (exposure drifts
/// slowly along a capture), or the one side there is. `train_frames` are
/// the scan indices of `trained`'s maps, ascending.
pub fn per_frame(train_frames: &[usize], trained: &[Affine], frames: usize) -> Vec<Affine> {
    (0..frames)
        .map(|f| {
            let after = train_frames.partition_point(|&t| t < f);
            if train_frames.get(after) == Some(&f) {
                return trained[after];
            }
            let before = after.checked_sub(1).map(|i| &trained[i]);
            match (before, trained.get(after)) {
                (Some(a), Some(b)) => std::array::from_fn(|k| 0.5 * (a[k] + b[k])),
                (Some(a), None) | (None, Some(a)) => *a,
                (None, None) => IDENTITY,
            }
        })
        .collect()
}

/// The largest change of any output channel over colours in the unit cube:
/// how far `a` is from neutral, for reports.
pub fn strength(a: &Affine) -> f32 {
    (0..3)
        .map(|i| {
            let (mut lo, mut hi) = (a[4 * i + 3] - IDENTITY[4 * i + 3], a[4 * i + 3] - IDENTITY[4 * i + 3]);
            for j in 0..3 {
                let d = a[4 * i + j] - IDENTITY[4 * i + j];
                lo += d.min(0.0);
                hi += d.max(0.0);
            }
            lo.abs().max(hi.abs())
        })
        .fold(0.0, f32::max)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn backward_matches_finite_differences() {
        let a: Affine = [1.1, 0.05, -0.02, 0.03, 0.0, 0.9, 0.1, -0.05, 0.02, -0.03, 1.2, 0.01];
        let c = [0.3, 0.6, 0.2];
        let target = [0.5, 0.4, 0.3];
        let loss = |a: &Affine, c: [f32; 3]| -> f64 {
            let o = apply(a, c);
            (0..3).map(|i| ((o[i] - target[i]) as f64).powi(2)).sum()
        };
        let o = apply(&a, c);
        let g: [f32; 3] = std::array::from_fn(|i| 2.0 * (o[i] - target[i]));
        let mut grad_a = [0.0f32; 12];
        let grad_c = apply_backward(&a, c, g, &mut grad_a);
        let h = 1e-3f32;
        for k in 0..12 {
            let (mut up, mut down) = (a, a);
            up[k] += h;
            down[k] -= h;
            let fd = (loss(&up, c) - loss(&down, c)) / (2.0 * h as f64);
            assert!((fd - grad_a[k] as f64).abs() < 1e-3, "a[{k}]: {fd} vs {}", grad_a[k]);
        }
        for j in 0..3 {
            let (mut up, mut down) = (c, c);
            up[j] += h;
            down[j] -= h;
            let fd = (loss(&a, up) - loss(&a, down)) / (2.0 * h as f64);
            assert!((fd - grad_c[j] as f64).abs() < 1e-3, "c[{j}]: {fd} vs {}", grad_c[j]);
        }
    }

    #[test]
    fn held_out_frames_take_the_mean_of_their_training_neighbours() {
        let gain = |s: f32| -> Affine { std::array::from_fn(|k| if k % 5 == 0 { s } else { 0.0 }) };
        // Frames 0..6; 0, 3 and 5 held out.
        let trained = [gain(1.0), gain(2.0), gain(4.0)];
        let table = per_frame(&[1, 2, 4], &trained, 6);
        let gains: Vec<f32> = table.iter().map(|a| a[0]).collect();
        assert_eq!(gains, vec![1.0, 1.0, 2.0, 3.0, 4.0, 4.0]);
        assert_eq!(per_frame(&[], &[], 2), vec![IDENTITY; 2]);
    }

    #[test]
    fn strength_is_the_largest_channel_change() {
        assert_eq!(strength(&IDENTITY), 0.0);
        let mut a = IDENTITY;
        a[0] = 0.8; // red gain 0.8: white loses 0.2
        a[7] = 0.05; // green offset
        assert!((strength(&a) - 0.2).abs() < 1e-6);
    }
}
