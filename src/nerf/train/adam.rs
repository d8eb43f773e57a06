//! Adam with a dense path for the MLPs and a sparse path for hash-table
//! entries touched in the step (untouched entries keep their moments).

use crate::nerf::field::simd::adam::{adam_word, AdamRule, AdamWord};

/// Adam state for one parameter vector.
#[derive(Clone, Debug)]
pub struct Adam {
    m: Vec<f32>,
    v: Vec<f32>,
    beta1: f32,
    beta2: f32,
    eps: f32,
    steps: u64,
}

impl Adam {
    /// Zeroed moments for `len` parameters (eps 1e-15 as in Instant-NGP).
    pub fn new(len: usize) -> Self {
        Adam {
            m: vec![0.0; len],
            v: vec![0.0; len],
            beta1: 0.9,
            beta2: 0.99,
            eps: 1e-15,
            steps: 0,
        }
    }

    /// Number of updates applied.
    pub fn steps(&self) -> u64 {
        self.steps
    }

    /// Moments for the model file / resume.
    pub fn moments(&self) -> (&[f32], &[f32]) {
        (&self.m, &self.v)
    }

    /// Restore moments and step count (lengths must match).
    pub fn restore(&mut self, m: Vec<f32>, v: Vec<f32>, steps: u64) -> bool {
        if m.len() != self.m.len() || v.len() != self.v.len() {
            return false;
        }
        self.m = m;
        self.v = v;
        self.steps = steps;
        true
    }

    /// Counts a step and returns the rule every parameter of it follows.
    fn next_step(&mut self, lr: f32, weight_decay: f32) -> AdamRule {
        self.steps += 1;
        self.rule_at(self.steps, lr, weight_decay)
    }

    /// The rule of step `step` (counted from 1): its bias corrections.
    fn rule_at(&self, step: u64, lr: f32, weight_decay: f32) -> AdamRule {
        let t = step.min(1_000_000) as i32;
        AdamRule {
            b1: self.beta1,
            b2: self.beta2,
            eps: self.eps,
            c1: 1.0 - self.beta1.powi(t),
            c2: 1.0 - self.beta2.powi(t),
            lr,
            weight_decay,
        }
    }

    /// Update every parameter; `weight_decay` adds an L2 pull to zero.
    pub fn step_dense(&mut self, params: &mut [f32], grads: &[f32], lr: f32, weight_decay: f32) {
        let rule = self.next_step(lr, weight_decay);
        for i in 0..params.len() {
            rule.apply(&mut params[i], &mut self.m[i], &mut self.v[i], grads[i]);
        }
    }

    /// [`Adam::step_dense`] with one second moment per block of `block`
    /// consecutive parameters (the mean square of the block's gradient), so
    /// a block moves along its gradient instead of every entry by about the
    /// learning rate whatever its share of the gradient.
    pub fn step_blocks(&mut self, params: &mut [f32], grads: &[f32], block: usize, lr: f32, weight_decay: f32) {
        let rule = self.next_step(lr, weight_decay);
        let block = block.max(1);
        for start in (0..params.len()).step_by(block) {
            let range = start..(start + block).min(params.len());
            let g: Vec<f32> = range.clone().map(|i| rule.gradient(grads[i], params[i])).collect();
            let mean_square = g.iter().map(|x| x * x).sum::<f32>() / g.len() as f32;
            for (i, g) in range.zip(g) {
                let v_term = (1.0 - rule.b2) * mean_square;
                rule.apply_with(&mut params[i], &mut self.m[i], &mut self.v[i], g, v_term);
            }
        }
    }

    /// RMS over all parameters of the step the next [`Adam::step_dense`]
    /// would take at learning rate 1, without changing any state.
    pub fn dense_step_rms(&self, params: &[f32], grads: &[f32], weight_decay: f32) -> f32 {
        let rule = self.rule_at(self.steps + 1, 1.0, weight_decay);
        let AdamRule {
            b1, b2, eps, c1, c2, ..
        } = rule;
        let mut sum = 0.0f64;
        for i in 0..params.len() {
            let g = rule.gradient(grads[i], params[i]);
            let m = b1 * self.m[i] + (1.0 - b1) * g;
            let v = b2 * self.v[i] + (1.0 - b2) * g * g;
            let step = (m / c1) / ((v / c2).sqrt() + eps);
            sum += step as f64 * step as f64;
        }
        (sum / params.len().max(1) as f64).sqrt() as f32
    }

    /// Update only the listed parameters (ascending, unique indices).
    pub fn step_sparse<I>(&mut self, params: &mut [f32], grads: &[f32], touched: I, lr: f32)
    where
        I: IntoIterator<Item = usize>,
    {
        self.step_sparse_decayed(params, grads, touched, lr, 0.0);
    }

    /// [`Adam::step_sparse`] with an L2 pull to zero on the listed parameters
    /// only: an entry decays when it is touched, never while unused.
    pub fn step_sparse_decayed<I>(&mut self, params: &mut [f32], grads: &[f32], touched: I, lr: f32, weight_decay: f32)
    where
        I: IntoIterator<Item = usize>,
    {
        let rule = self.next_step(lr, weight_decay);
        for i in touched {
            rule.apply(&mut params[i], &mut self.m[i], &mut self.v[i], grads[i]);
        }
    }
}

impl Adam {
    /// [`Adam::step_sparse_decayed`] on parallel threads: the parameters are
    /// cut into `parts` ranges whose length is a multiple of `block` (itself
    /// a multiple of 64), and `touched(start, len)` lists the touched
    /// parameters of a range as `(first index, bitmask)` words of 64. Each
    /// parameter's update is the sequential one, so results do not depend on
    /// the number of parts; whole words run as one contiguous loop. The
    /// gradients of the touched parameters are zeroed as they are consumed
    /// (the buffer is ready for the next step without another pass over it).
    // The sequential step's arguments plus how to cut the range.
    #[allow(clippy::too_many_arguments)]
    pub fn step_sparse_decayed_parallel<F, I>(
        &mut self,
        params: &mut [f32],
        grads: &mut [f32],
        touched: F,
        block: usize,
        parts: usize,
        lr: f32,
        weight_decay: f32,
    ) where
        F: Fn(usize, usize) -> I + Sync,
        I: Iterator<Item = (usize, u64)>,
    {
        use rayon::prelude::*;
        let rule = self.next_step(lr, weight_decay);
        let block = block.max(1);
        let len = params.len().div_ceil(parts.max(1)).div_ceil(block).max(1) * block;
        params
            .par_chunks_mut(len)
            .zip(self.m.par_chunks_mut(len))
            .zip(self.v.par_chunks_mut(len))
            .zip(grads.par_chunks_mut(len))
            .enumerate()
            .for_each(|(part, (((params, ms), vs), grads))| {
                let start = part * len;
                for (first, bits) in touched(start, len) {
                    let k0 = first - start;
                    if bits.count_ones() >= WHOLE_WORD_MIN_TOUCHED && k0 + 64 <= params.len() {
                        fn slice_of_64(s: &mut [f32], k0: usize) -> &mut [f32; 64] {
                            (&mut s[k0..k0 + 64]).try_into().expect("64 entries")
                        }
                        let word = AdamWord {
                            params: slice_of_64(params, k0),
                            m: slice_of_64(ms, k0),
                            v: slice_of_64(vs, k0),
                            grads: slice_of_64(grads, k0),
                            touched: bits,
                        };
                        adam_word(&rule, word);
                    } else {
                        let mut rest = bits;
                        while rest != 0 {
                            let k = k0 + rest.trailing_zeros() as usize;
                            rest &= rest - 1;
                            rule.apply(&mut params[k], &mut ms[k], &mut vs[k], std::mem::take(&mut grads[k]));
                        }
                    }
                }
            });
    }
}

/// Touched entries from which a word of 64 is updated whole (every lane
/// computed, the untouched ones left as they were) rather than bit by bit.
const WHOLE_WORD_MIN_TOUCHED: u32 = 8;

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_parallel_sparse_step_is_the_sequential_one_bit_for_bit() {
        let mut rng = crate::rng::Rng::new(3, 0);
        let n = 10_000;
        // Whole words at the start, then words updated whole with some lanes
        // untouched (30 %), then words updated entry by entry (3 %).
        let touched: Vec<usize> = (0..n)
            .filter(|&i| i < 640 || rng.f32() < if i < 6000 { 0.3 } else { 0.03 })
            .collect();
        let grads: Vec<f32> = (0..n).map(|_| rng.f32() - 0.5).collect();
        let start: Vec<f32> = (0..n).map(|_| rng.f32()).collect();
        let mut seq = (Adam::new(n), start.clone());
        for _ in 0..3 {
            seq.0
                .step_sparse_decayed(&mut seq.1, &grads, touched.iter().copied(), 0.01, 1e-3);
        }
        for parts in [1, 2, 3] {
            let mut par = (Adam::new(n), start.clone());
            // Touched indices of a range as 64-wide words.
            let within = |s: usize, len: usize| {
                let mut words: Vec<(usize, u64)> = Vec::new();
                for &i in touched.iter().filter(|&&i| i >= s && i < s + len) {
                    let first = i / 64 * 64;
                    match words.last_mut() {
                        Some((f, bits)) if *f == first => *bits |= 1 << (i - first),
                        _ => words.push((first, 1 << (i - first))),
                    }
                }
                words.into_iter()
            };
            for _ in 0..3 {
                let mut consumed = grads.clone();
                par.0
                    .step_sparse_decayed_parallel(&mut par.1, &mut consumed, within, 64, parts, 0.01, 1e-3);
                let left = touched.iter().filter(|&&i| consumed[i] != 0.0).count();
                assert_eq!(left, 0, "touched gradients are consumed");
            }
            assert_eq!(par.1, seq.1, "{parts} parts");
            assert_eq!(par.0.moments(), seq.0.moments());
        }
    }

    #[test]
    fn a_block_steps_along_its_gradient() {
        // Per-entry Adam would move both entries by the learning rate; with
        // one second moment per block the step keeps the gradient's ratio.
        let mut adam = Adam::new(4);
        let mut params = [0.0f32; 4];
        adam.step_blocks(&mut params, &[1.0, 0.1, -2.0, 0.0], 2, 0.01, 0.0);
        assert!((params[0] / params[1] - 10.0).abs() < 1e-3, "{params:?}");
        assert!(params[0] < 0.0 && params[2] > 0.0 && params[3] == 0.0);
        // The block's RMS step is the learning rate.
        let rms = ((params[0] * params[0] + params[1] * params[1]) / 2.0).sqrt();
        assert!((rms - 0.01).abs() < 1e-5, "{rms}");
    }

    #[test]
    fn minimises_a_quadratic_and_survives_extreme_gradient_scales() {
        // 1e-20 is below eps: no progress, but no blow-up either.
        for scale in [1e-20f32, 1.0, 1e20] {
            let mut x = vec![3.0f32, -2.0];
            let mut adam = Adam::new(2);
            for _ in 0..2000 {
                let g: Vec<f32> = x.iter().map(|&xi| scale * 2.0 * (xi - 1.0)).collect();
                adam.step_dense(&mut x, &g, 0.01, 0.0);
            }
            assert!(x.iter().all(|v| v.is_finite()), "scale {scale}");
            if scale >= 1.0 {
                assert!(x.iter().all(|v| (v - 1.0).abs() < 0.05), "scale {scale}: {x:?}");
            } else {
                assert!((x[0] - 3.0).abs() < 0.05 && (x[1] + 2.0).abs() < 0.05, "{x:?}");
            }
        }
    }

    #[test]
    fn dense_step_rms_is_the_step_taken_and_changes_nothing() {
        let mut rng = crate::rng::Rng::new(3, 0);
        let mut x: Vec<f32> = (0..50).map(|_| rng.normal() as f32).collect();
        let mut adam = Adam::new(x.len());
        for step in 0..5 {
            let g: Vec<f32> = (0..x.len()).map(|i| ((i + step) as f32).sin()).collect();
            let before = x.clone();
            let predicted = adam.dense_step_rms(&x, &g, 1e-3);
            assert_eq!(adam.steps(), step as u64, "the dry run applies nothing");
            adam.step_dense(&mut x, &g, 0.5, 1e-3);
            let taken: f32 = before.iter().zip(&x).map(|(a, b)| (a - b) * (a - b)).sum::<f32>() / x.len() as f32;
            let taken = taken.sqrt() / 0.5;
            assert!(
                (taken - predicted).abs() < 1e-4 * predicted,
                "step {step}: predicted {predicted}, taken {taken}"
            );
        }
    }

    #[test]
    fn tiny_same_sign_gradients_drift_without_the_prior_and_settle_with_it() {
        // The long-run hash-grid drift: a gradient of 1e-10 that never changes
        // sign moves an entry by the learning rate at every step (eps 1e-15).
        let (lr, steps) = (1e-2f32, 20_000);
        let mut free = vec![0.0f32];
        let mut held = vec![0.0f32];
        let (mut a, mut b) = (Adam::new(1), Adam::new(1));
        for _ in 0..steps {
            a.step_sparse(&mut free, &[1e-10], [0usize], lr);
            b.step_sparse_decayed(&mut held, &[1e-10], [0usize], lr, 1e-8);
        }
        assert!(free[0] < -0.9 * lr * steps as f32, "no prior: {}", free[0]);
        // With the prior the entry settles near -gradient / decay = -0.01.
        assert!((held[0] + 0.01).abs() < 0.005, "with the prior: {}", held[0]);
        // A real gradient still moves it: 1e-6 against the same prior reaches -10 within 2000 steps.
        let mut x = vec![0.0f32];
        let mut c = Adam::new(1);
        for _ in 0..2000 {
            c.step_sparse_decayed(&mut x, &[1e-6], [0usize], lr, 1e-8);
        }
        assert!(x[0] < -10.0, "{}", x[0]);
    }

    #[test]
    fn sparse_update_leaves_untouched_entries_alone() {
        let mut x = vec![1.0f32; 4];
        let mut adam = Adam::new(4);
        adam.step_sparse(&mut x, &[1.0, 1.0, 1.0, 1.0], [1usize, 3], 0.1);
        assert_eq!(x[0], 1.0);
        assert_eq!(x[2], 1.0);
        assert!(x[1] < 1.0 && x[3] < 1.0);
    }
}
