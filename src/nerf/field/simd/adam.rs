//! Adam on one word of 64 hash-grid parameters, only the lanes a bitmask
//! marks as touched written back. Written with intrinsics because the lane
//! loop the compiler made of it (a select per lane from the mask's bits,
//! the word copied through the stack) ran 3.4 times slower than streaming
//! the same memory: it was a sixth to a third of a training step on
//! 640x480 scans.
//!
//! Every operation is the scalar rule's, in its order (no fused multiply-add,
//! IEEE division and square root), so both paths give the same bits.

/// One step's constants: decay rates, eps, bias corrections, learning rate
/// and the L2 pull to zero added to each gradient.
#[derive(Clone, Copy, Debug)]
pub struct AdamRule {
    pub b1: f32,
    pub b2: f32,
    pub eps: f32,
    pub c1: f32,
    pub c2: f32,
    pub lr: f32,
    pub weight_decay: f32,
}

impl AdamRule {
    /// Adam on one parameter with its raw gradient (see [`AdamRule::gradient`]).
    #[inline(always)]
    pub fn apply(&self, param: &mut f32, m: &mut f32, v: &mut f32, raw_gradient: f32) {
        let g = self.gradient(raw_gradient, *param);
        self.apply_with(param, m, v, g, (1.0 - self.b2) * g * g);
    }

    /// The gradient a parameter steps along: its raw gradient plus the L2
    /// pull, clamped.
    #[inline(always)]
    pub fn gradient(&self, raw_gradient: f32, param: f32) -> f32 {
        clamp_gradient(raw_gradient + self.weight_decay * param)
    }

    /// Adam on one parameter with its (clamped, decayed) gradient `g` and the
    /// second moment's new term given.
    #[inline(always)]
    pub fn apply_with(&self, param: &mut f32, m: &mut f32, v: &mut f32, g: f32, v_term: f32) {
        *m = self.b1 * *m + (1.0 - self.b1) * g;
        *v = self.b2 * *v + v_term;
        *param -= self.lr * (*m / self.c1) / ((*v / self.c2).sqrt() + self.eps);
    }
}

/// Keeps g*g finite in f32 (non-finite gradients count as zero); Adam is
/// invariant to gradient scale anyway.
#[inline(always)]
fn clamp_gradient(g: f32) -> f32 {
    if g.is_finite() {
        g.clamp(-GRADIENT_LIMIT, GRADIENT_LIMIT)
    } else {
        0.0
    }
}

/// Largest gradient magnitude: its square stays finite in f32.
const GRADIENT_LIMIT: f32 = 1e15;

/// One word of 64 parameters: values, moments and gradients (zeroed once
/// used), and which lanes the step touched (bit k for lane k).
pub struct AdamWord<'a> {
    pub params: &'a mut [f32; 64],
    pub m: &'a mut [f32; 64],
    pub v: &'a mut [f32; 64],
    pub grads: &'a mut [f32; 64],
    pub touched: u64,
}

/// [`AdamRule::apply`] on the touched lanes of `word`; the untouched keep
/// their values and moments. The touched lanes' gradients are zeroed; the
/// untouched must hold zero already.
pub fn adam_word(rule: &AdamRule, word: AdamWord) {
    #[cfg(target_arch = "x86_64")]
    if super::avx2_fma_available() {
        // SAFETY: AVX2 was detected just above.
        unsafe { avx2::adam_word(rule, word) };
        return;
    }
    adam_word_scalar(rule, word)
}

fn adam_word_scalar(rule: &AdamRule, word: AdamWord) {
    for k in 0..64 {
        if (word.touched >> k) & 1 == 1 {
            rule.apply(&mut word.params[k], &mut word.m[k], &mut word.v[k], word.grads[k]);
        }
    }
    *word.grads = [0.0; 64];
}

#[cfg(target_arch = "x86_64")]
mod avx2 {
    use super::{AdamRule, AdamWord, GRADIENT_LIMIT};
    use std::arch::x86_64::*;

    #[target_feature(enable = "avx2")]
    pub(super) unsafe fn adam_word(rule: &AdamRule, word: AdamWord) {
        let AdamWord {
            params,
            m,
            v,
            grads,
            touched,
        } = word;
        let splat = _mm256_set1_ps;
        let (b1, one_b1) = (splat(rule.b1), splat(1.0 - rule.b1));
        let (b2, one_b2) = (splat(rule.b2), splat(1.0 - rule.b2));
        let (c1, c2, eps, lr, decay) = (
            splat(rule.c1),
            splat(rule.c2),
            splat(rule.eps),
            splat(rule.lr),
            splat(rule.weight_decay),
        );
        let (limit, low, infinity) = (splat(GRADIENT_LIMIT), splat(-GRADIENT_LIMIT), splat(f32::INFINITY));
        let sign = splat(-0.0);
        let lane_bits = _mm256_setr_epi32(1, 2, 4, 8, 16, 32, 64, 128);
        let zero = _mm256_setzero_ps();
        for block in 0..8 {
            let byte = ((touched >> (8 * block)) & 0xff) as i32;
            if byte == 0 {
                continue;
            }
            // Lane k of the block is touched when bit k of its byte is set.
            let selected = _mm256_and_si256(_mm256_set1_epi32(byte), lane_bits);
            let mask = _mm256_castsi256_ps(_mm256_cmpeq_epi32(selected, lane_bits));
            let at = 8 * block;
            // SAFETY: `at + 8 <= 64`, inside each array of the word.
            let (pp, mp, vp, gp) = unsafe {
                (
                    params.as_mut_ptr().add(at),
                    m.as_mut_ptr().add(at),
                    v.as_mut_ptr().add(at),
                    grads.as_mut_ptr().add(at),
                )
            };
            // SAFETY: eight floats at each pointer (above); unaligned loads and stores.
            unsafe {
                let (p0, m0, v0, raw) = (
                    _mm256_loadu_ps(pp),
                    _mm256_loadu_ps(mp),
                    _mm256_loadu_ps(vp),
                    _mm256_loadu_ps(gp),
                );
                let g = _mm256_add_ps(raw, _mm256_mul_ps(decay, p0));
                // Finite: |g| < inf (false for NaN); then clamped, else zero.
                let finite = _mm256_cmp_ps::<_CMP_LT_OQ>(_mm256_andnot_ps(sign, g), infinity);
                let g = _mm256_and_ps(finite, _mm256_min_ps(_mm256_max_ps(g, low), limit));
                let m1 = _mm256_add_ps(_mm256_mul_ps(b1, m0), _mm256_mul_ps(one_b1, g));
                let v1 = _mm256_add_ps(_mm256_mul_ps(b2, v0), _mm256_mul_ps(_mm256_mul_ps(one_b2, g), g));
                let denominator = _mm256_add_ps(_mm256_sqrt_ps(_mm256_div_ps(v1, c2)), eps);
                let step = _mm256_div_ps(_mm256_mul_ps(lr, _mm256_div_ps(m1, c1)), denominator);
                let p1 = _mm256_sub_ps(p0, step);
                _mm256_storeu_ps(pp, _mm256_blendv_ps(p0, p1, mask));
                _mm256_storeu_ps(mp, _mm256_blendv_ps(m0, m1, mask));
                _mm256_storeu_ps(vp, _mm256_blendv_ps(v0, v1, mask));
                _mm256_storeu_ps(gp, zero);
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn rule() -> AdamRule {
        AdamRule {
            b1: 0.9,
            b2: 0.99,
            eps: 1e-15,
            c1: 0.271,
            c2: 0.0297,
            lr: 0.01,
            weight_decay: 1e-3,
        }
    }

    #[test]
    fn the_vector_word_is_the_scalar_rule_bit_for_bit() {
        let mut rng = crate::rng::Rng::new(5, 0);
        let mut arrays = || -> [f32; 64] { std::array::from_fn(|_| rng.normal() as f32) };
        let (p, m, v) = (arrays(), arrays(), arrays().map(f32::abs));
        let mut g = arrays();
        // Gradients the clamp must handle, on touched lanes.
        g[3] = f32::NAN;
        g[9] = f32::INFINITY;
        g[17] = -3e20;
        g[40] = 1e-30;
        let touched = 0xf0f0_0000_ffff_0a0a_u64 | (1 << 3) | (1 << 9) | (1 << 17) | (1 << 40);
        // Untouched lanes hold no gradient (the buffer's invariant).
        for (k, g) in g.iter_mut().enumerate() {
            if (touched >> k) & 1 == 0 {
                *g = 0.0;
            }
        }
        // The word's four arrays, stepped by one of the two paths.
        let stepped = |kernel: fn(&AdamRule, AdamWord)| {
            let (mut params, mut m, mut v, mut grads) = (p, m, v, g);
            let word = AdamWord {
                params: &mut params,
                m: &mut m,
                v: &mut v,
                grads: &mut grads,
                touched,
            };
            kernel(&rule(), word);
            (params, m, v, grads)
        };
        let (vector, scalar) = (stepped(adam_word), stepped(adam_word_scalar));
        for (k, &start) in p.iter().enumerate() {
            let lane = |s: &([f32; 64], [f32; 64], [f32; 64], [f32; 64])| {
                (s.0[k].to_bits(), s.1[k].to_bits(), s.2[k].to_bits())
            };
            assert_eq!(lane(&vector), lane(&scalar), "lane {k}");
            assert!(
                vector.0[k].is_finite() && vector.1[k].is_finite() && vector.2[k].is_finite(),
                "lane {k}"
            );
            let moved = vector.0[k] != start;
            assert_eq!(moved, (touched >> k) & 1 == 1, "lane {k}: only touched lanes move");
        }
        assert!(
            vector.3.iter().chain(&scalar.3).all(|&g| g == 0.0),
            "gradients consumed"
        );
    }
}
