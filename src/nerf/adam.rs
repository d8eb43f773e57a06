//! Adam with a dense path for the MLPs and a sparse path for hash-table
//! entries touched in the step (untouched entries keep their moments).

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
        Adam { m: vec![0.0; len], v: vec![0.0; len], beta1: 0.9, beta2: 0.99, eps: 1e-15, steps: 0 }
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

    fn corrections(&mut self) -> (f32, f32) {
        self.steps += 1;
        let t = self.steps.min(1_000_000) as i32;
        (1.0 - self.beta1.powi(t), 1.0 - self.beta2.powi(t))
    }

    /// Update every parameter; `weight_decay` adds an L2 pull to zero.
    pub fn step_dense(&mut self, params: &mut [f32], grads: &[f32], lr: f32, weight_decay: f32) {
        let (c1, c2) = self.corrections();
        let (b1, b2, eps) = (self.beta1, self.beta2, self.eps);
        for i in 0..params.len() {
            let g = clamp_gradient(grads[i] + weight_decay * params[i]);
            let m = b1 * self.m[i] + (1.0 - b1) * g;
            let v = b2 * self.v[i] + (1.0 - b2) * g * g;
            self.m[i] = m;
            self.v[i] = v;
            params[i] -= lr * (m / c1) / ((v / c2).sqrt() + eps);
        }
    }

    /// Update only the listed parameters (ascending, unique indices).
    pub fn step_sparse<I>(&mut self, params: &mut [f32], grads: &[f32], touched: I, lr: f32)
    where
        I: IntoIterator<Item = usize>,
    {
        let (c1, c2) = self.corrections();
        let (b1, b2, eps) = (self.beta1, self.beta2, self.eps);
        for i in touched {
            let g = clamp_gradient(grads[i]);
            let m = b1 * self.m[i] + (1.0 - b1) * g;
            let v = b2 * self.v[i] + (1.0 - b2) * g * g;
            self.m[i] = m;
            self.v[i] = v;
            params[i] -= lr * (m / c1) / ((v / c2).sqrt() + eps);
        }
    }
}

/// Keeps g*g finite in f32; Adam is invariant to gradient scale anyway.
#[inline]
fn clamp_gradient(g: f32) -> f32 {
    if g.is_finite() {
        g.clamp(-1e15, 1e15)
    } else {
        0.0
    }
}

#[cfg(test)]
mod tests {
    use super::*;

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
    fn sparse_update_leaves_untouched_entries_alone() {
        let mut x = vec![1.0f32; 4];
        let mut adam = Adam::new(4);
        adam.step_sparse(&mut x, &[1.0, 1.0, 1.0, 1.0], [1usize, 3], 0.1);
        assert_eq!(x[0], 1.0);
        assert_eq!(x[2], 1.0);
        assert!(x[1] < 1.0 && x[3] < 1.0);
    }
}
