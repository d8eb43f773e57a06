//! Per-frame appearance: handheld cameras change exposure and white balance
//! from frame to frame, so each training frame's colour is the field's
//! colour through an affine map of its own (a 3x3 matrix and an offset).
//! Training learns the maps beside the field (`train::appearance`) and keeps
//! their mean at the identity, so the field's own colour is the scan's
//! average, *neutral* appearance. Rendering applies a frame's map, or none.

use crate::scan::Intrinsics;

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

/// A lens's vignetting, one per scan (one camera): colour reaching the
/// image is scaled by `1 + k1 r^2 + k2 r^4 + k3 r^6`, where `r^2` is the
/// squared tangent of the angle off the optical axis,
/// `((u - cx) / fx)^2 + ((v - cy) / fy)^2`. Every consumer camera's
/// corners get less light than its centre; a field cannot show that (a
/// surface moves across the image as the camera moves), so without it the
/// field averages the falloff into every surface.
pub type Vignetting = [f32; 3];

/// The lens that darkens nothing.
pub const NO_VIGNETTING: Vignetting = [0.0; 3];

/// Smallest gain a vignetting may give: keeps colour and its gradient
/// alive while the coefficients are still far off.
const MIN_GAIN: f32 = 0.05;

/// Squared off-axis tangent of a ray whose direction in the camera is
/// `t_per_z` times as long as its z (`LocalCamera::ray`'s second value).
#[inline]
pub fn off_axis_r2(t_per_z: f32) -> f32 {
    t_per_z * t_per_z - 1.0
}

/// The field's colour `rgb` as the photo records it: through the lens's
/// falloff at squared off-axis tangent `r2`, then the frame's map.
#[inline]
pub fn as_photographed(map: &Affine, lens: &Vignetting, r2: f32, rgb: [f32; 3]) -> [f32; 3] {
    let gain = vignetting_gain(lens, r2);
    apply(map, rgb.map(|c| gain * c))
}

/// Gain of `k` at squared off-axis tangent `r2`.
#[inline]
pub fn vignetting_gain(k: &Vignetting, r2: f32) -> f32 {
    (1.0 + r2 * (k[0] + r2 * (k[1] + r2 * k[2]))).max(MIN_GAIN)
}

/// Backward of [`vignetting_gain`]: adds `g` (the loss gradient with
/// respect to the gain) times the gain's derivative to `grad_k`.
#[inline]
pub fn vignetting_backward(k: &Vignetting, r2: f32, g: f32, grad_k: &mut [f32]) {
    if vignetting_gain(k, r2) > MIN_GAIN {
        let mut power = r2;
        for gk in grad_k.iter_mut().take(3) {
            *gk += g * power;
            power *= r2;
        }
    }
}

/// The light `k` leaves in the farthest corner of a `width` x `height`
/// image taken with `intrinsics`, as a share of the centre's.
pub fn corner_gain(k: &Vignetting, intrinsics: &Intrinsics, width: u32, height: u32) -> f32 {
    vignetting_gain(k, intrinsics.corner_tan2(width, height) as f32)
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
    fn vignetting_gradient_matches_finite_differences() {
        let k: Vignetting = [-0.3, 0.1, -0.05];
        let r2 = 0.4f32;
        let mut grad = [0.0f32; 3];
        vignetting_backward(&k, r2, 1.0, &mut grad);
        let h = 1e-3f32;
        for i in 0..3 {
            let (mut up, mut down) = (k, k);
            up[i] += h;
            down[i] -= h;
            let fd = (vignetting_gain(&up, r2) - vignetting_gain(&down, r2)) / (2.0 * h);
            assert!((fd - grad[i]).abs() < 1e-3, "k[{i}]: {fd} vs {}", grad[i]);
        }
        assert_eq!(vignetting_gain(&NO_VIGNETTING, 0.7), 1.0);
        // A gain held at its floor passes no gradient.
        let mut grad = [0.0f32; 3];
        vignetting_backward(&[-10.0, 0.0, 0.0], 0.5, 1.0, &mut grad);
        assert_eq!(grad, [0.0; 3]);
    }

    #[test]
    fn corner_gain_is_taken_at_the_farthest_corner() {
        // Principal point off centre: the far corner is (99, 79).
        let k: Vignetting = [-0.5, 0.0, 0.0];
        let intrinsics = Intrinsics {
            fx: 100.0,
            fy: 100.0,
            cx: 30.0,
            cy: 20.0,
        };
        let g = corner_gain(&k, &intrinsics, 100, 80);
        let r2 = (0.69f32).powi(2) + (0.59f32).powi(2);
        assert!((g - (1.0 - 0.5 * r2)).abs() < 1e-5, "{g}");
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
