//! Volume compositing along one ray, numerically stable at any density.
//!
//! alpha = -expm1(-sigma*delta); transmittance is the exponential of an
//! exclusive prefix sum of optical depth (log space), so thousands of opaque
//! samples never underflow into NaN. Gradients use suffix sums of
//! weight x upstream gradient and never divide by (1 - alpha).

/// Transmittance below which a ray is treated as fully absorbed.
pub const TERMINATION_TRANSMITTANCE: f32 = 1e-4;
/// Accumulated weight below which a ray reports "no surface".
pub const MIN_SURFACE_WEIGHT: f32 = 0.5;

/// Result of compositing one ray's samples.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct RayComposite {
    /// Sum of weights, in [0, 1].
    pub opacity: f32,
    /// Transmittance after the last sample, 1 - opacity.
    pub transmittance: f32,
    /// Number of samples that received weight before termination.
    pub used: usize,
}

/// Weights w_i = T_i * alpha_i for optical depths tau_i = sigma_i * delta_i.
///
/// `weights` receives one weight per sample; samples after termination get 0.
pub fn weights_from_optical_depth(tau: &[f32], weights: &mut [f32]) -> RayComposite {
    debug_assert_eq!(tau.len(), weights.len());
    let mut log_t = 0.0f32; // log transmittance before the sample, <= 0
    let mut used = tau.len();
    for (i, (&tau_i, w)) in tau.iter().zip(weights.iter_mut()).enumerate() {
        let tau_i = sanitize_tau(tau_i);
        let t_before = log_t.exp();
        if t_before < TERMINATION_TRANSMITTANCE {
            used = i;
            break;
        }
        let alpha = -(-tau_i).exp_m1();
        *w = t_before * alpha;
        log_t -= tau_i;
    }
    for w in weights[used..].iter_mut() {
        *w = 0.0;
    }
    let transmittance = log_t.exp();
    RayComposite {
        opacity: (1.0 - transmittance).clamp(0.0, 1.0),
        transmittance,
        used,
    }
}

/// Optical depth safe for exp: NaN and negatives become 0, +inf saturates.
#[inline]
pub fn sanitize_tau(tau: f32) -> f32 {
    if tau > 0.0 {
        tau.min(1e4)
    } else {
        0.0 // also catches NaN
    }
}

/// Gradient of a loss with respect to every tau_i.
///
/// `grad_w[i]` = dL/dw_i treating weights as independent, `grad_t_final` =
/// dL/dT_final (background term). Uses
/// dL/dtau_i = T_{i+1} g_i - sum_{k>i} w_k g_k - T_final g_T.
pub fn optical_depth_backward(
    tau: &[f32],
    weights: &[f32],
    composite: &RayComposite,
    grad_w: &[f32],
    grad_t_final: f32,
    grad_tau: &mut [f32],
) {
    let n = composite.used;
    // Forward pass again for T_{i+1} (stored in grad_tau), log space.
    let mut log_t = 0.0f32;
    for i in 0..n {
        log_t -= sanitize_tau(tau[i]);
        grad_tau[i] = log_t.exp();
    }
    // Suffix sum of w_k g_k for k > i, walked backwards.
    let mut suffix = composite.transmittance * grad_t_final;
    for i in (0..n).rev() {
        let t_after = grad_tau[i];
        // Clamped or invalid optical depths have zero derivative.
        let differentiable = tau[i] >= 0.0 && tau[i] < 1e4;
        grad_tau[i] = if differentiable {
            t_after * grad_w[i] - suffix
        } else {
            0.0
        };
        suffix += weights[i] * grad_w[i];
    }
    for g in grad_tau[n..].iter_mut() {
        *g = 0.0;
    }
}

/// First crossing of accumulated weight 0.5 ("median depth"), linearly
/// interpolated inside the crossing segment; `None` when the ray holds less
/// than [`MIN_SURFACE_WEIGHT`] in total.
pub fn median_depth(t_start: &[f32], delta: &[f32], weights: &[f32]) -> Option<f32> {
    let mut acc = 0.0f32;
    for i in 0..weights.len() {
        let next = acc + weights[i];
        if next >= MIN_SURFACE_WEIGHT {
            let frac = if weights[i] > 0.0 {
                (MIN_SURFACE_WEIGHT - acc) / weights[i]
            } else {
                0.0
            };
            return Some(t_start[i] + frac.clamp(0.0, 1.0) * delta[i]);
        }
        acc = next;
    }
    None
}

#[cfg(test)]
mod tests {
    use super::*;

    fn loss_of(tau: &[f32], g: &[f32], g_t: f32) -> f64 {
        // L = sum w_i g_i + T_final g_T, in f64 for finite differences.
        let mut log_t = 0.0f64;
        let mut loss = 0.0f64;
        for (&ti, &gi) in tau.iter().zip(g) {
            let ti = ti as f64;
            let w = log_t.exp() * -(-ti).exp_m1();
            loss += w * gi as f64;
            log_t -= ti;
        }
        loss + log_t.exp() * g_t as f64
    }

    #[test]
    fn weights_sum_to_opacity_and_stay_bounded_from_tiny_to_huge_tau() {
        for exp in -10..=4 {
            let tau_value = 10f32.powi(exp);
            for n in [1usize, 3, 100, 5000] {
                let tau = vec![tau_value; n];
                let mut w = vec![0.0; n];
                let c = weights_from_optical_depth(&tau, &mut w);
                let sum: f32 = w.iter().sum();
                assert!(
                    w.iter().all(|x| x.is_finite() && (0.0..=1.0).contains(x)),
                    "tau {tau_value} n {n}"
                );
                assert!(sum <= 1.0 + 1e-5, "sum {sum}");
                assert!(
                    (sum - c.opacity).abs() < 1e-3 + 1e-4 * n as f32 * tau_value.min(1.0),
                    "sum {sum} opacity {}",
                    c.opacity
                );
                assert!(c.transmittance.is_finite() && c.transmittance >= 0.0);
            }
        }
    }

    #[test]
    fn saturated_and_invalid_tau_are_safe() {
        let tau = [f32::NAN, -3.0, f32::INFINITY, 1e30, 0.5];
        let mut w = [0.0; 5];
        let c = weights_from_optical_depth(&tau, &mut w);
        assert_eq!(w[0], 0.0);
        assert_eq!(w[1], 0.0);
        assert!((w[2] - 1.0).abs() < 1e-6, "infinite density absorbs everything: {w:?}");
        assert!(c.used <= 3, "terminates after the opaque sample");
        let mut g = [0.0; 5];
        optical_depth_backward(&tau, &w, &c, &[1.0; 5], 0.3, &mut g);
        assert!(g.iter().all(|x| x.is_finite()));
    }

    #[test]
    fn gradient_matches_finite_differences() {
        let mut rng = crate::rng::Rng::new(3, 0);
        for case in 0..50 {
            let n = 1 + rng.below(40) as usize;
            let scale = [0.001f32, 0.05, 0.5, 3.0][case % 4];
            let tau: Vec<f32> = (0..n).map(|_| rng.f32() * scale).collect();
            let g: Vec<f32> = (0..n).map(|_| rng.f32() * 2.0 - 1.0).collect();
            let g_t = rng.f32() - 0.5;
            let mut w = vec![0.0; n];
            let c = weights_from_optical_depth(&tau, &mut w);
            let mut grad = vec![0.0; n];
            optical_depth_backward(&tau, &w, &c, &g, g_t, &mut grad);
            for i in 0..c.used {
                let eps = (tau[i] * 1e-2).max(1e-4);
                let mut plus = tau.clone();
                plus[i] += eps;
                let mut minus = tau.clone();
                minus[i] = (minus[i] - eps).max(0.0);
                let fd = (loss_of(&plus, &g, g_t) - loss_of(&minus, &g, g_t)) / (plus[i] - minus[i]) as f64;
                let err = (fd - grad[i] as f64).abs();
                assert!(
                    err < 2e-3 * (1.0 + fd.abs()),
                    "case {case} i {i}: analytic {} fd {fd}",
                    grad[i]
                );
            }
        }
    }

    #[test]
    fn median_depth_is_first_crossing_and_none_for_empty_rays() {
        let t = [1.0, 2.0, 3.0, 4.0];
        let d = [1.0; 4];
        assert_eq!(median_depth(&t, &d, &[0.1, 0.2, 0.6, 0.1]), Some(3.0 + 0.2 / 0.6));
        assert_eq!(median_depth(&t, &d, &[0.1, 0.1, 0.1, 0.1]), None);
        assert_eq!(median_depth(&t, &d, &[0.0; 4]), None);
    }
}
