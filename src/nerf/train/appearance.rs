//! Learning the training frames' appearance maps (`nerf::appearance`)
//! beside the field. Each map is stored as its difference from the
//! identity, so weight decay pulls it towards neutral; after every update
//! the mean difference is removed, so the maps' mean stays the identity and
//! the field keeps the scan's average colour. The lens's vignetting
//! (`nerf::appearance::Vignetting`), one for all frames, learns with them.

use crate::nerf::appearance::{Affine, Vignetting, IDENTITY, NO_VIGNETTING};
use crate::nerf::train::adam::Adam;

/// Learning rate of the maps relative to the field's: a map is fitted to
/// the few dozen rays a frame gets per step, so it must move slowly.
const RELATIVE_LEARNING_RATE: f32 = 1.0;
/// L2 pull of each map towards the identity (per entry of the difference).
const DECAY: f32 = 1e-4;
/// Learning rate of the vignetting relative to the field's. The real
/// cabinet scan (`fit --steps 1385`, seeds 1 / 5 / 7) held out 27.05 /
/// 27.03 / 26.44 dB at a tenth, 26.88 / 26.79 / 26.56 at 0.3 and 27.01 /
/// 26.77 / 26.20 at 1; but at a tenth a 250-step fit of a generated lens
/// losing 30 % in the corners learnt 2.5 % (0.3: 24 % after 400 steps,
/// 31 % after 600).
const LENS_RELATIVE_LEARNING_RATE: f32 = 0.3;

/// The maps of the training frames and their optimiser.
#[derive(Clone, Debug)]
pub struct AppearanceLearner {
    /// Differences from the identity, 12 per training frame.
    pub deltas: Vec<f32>,
    pub adam: Adam,
    /// The lens's vignetting and its optimiser.
    pub lens: Vignetting,
    pub lens_adam: Adam,
}

impl AppearanceLearner {
    /// Neutral maps for `frames` training frames.
    pub fn new(frames: usize) -> Self {
        let len = 12 * frames;
        AppearanceLearner {
            deltas: vec![0.0; len],
            adam: Adam::new(len),
            lens: NO_VIGNETTING,
            lens_adam: Adam::new(NO_VIGNETTING.len()),
        }
    }

    /// Length of the gradient [`Self::step`] takes: 12 per map, then the lens's.
    pub fn grad_len(&self) -> usize {
        self.deltas.len() + self.lens.len()
    }

    /// Where the lens's gradient starts in that vector.
    pub fn lens_offset(&self) -> usize {
        self.deltas.len()
    }

    pub fn frames(&self) -> usize {
        self.deltas.len() / 12
    }

    /// The map of training frame `view`.
    #[inline]
    pub fn map(&self, view: usize) -> Affine {
        let d = &self.deltas[12 * view..12 * view + 12];
        std::array::from_fn(|k| IDENTITY[k] + d[k])
    }

    /// Every training frame's map.
    pub fn maps(&self) -> Vec<Affine> {
        (0..self.frames()).map(|v| self.map(v)).collect()
    }

    /// One Adam update with the field's learning rate `lr`, then the mean
    /// difference removed.
    pub fn step(&mut self, grads: &[f32], lr: f32) {
        let (maps, lens) = grads.split_at(self.lens_offset());
        // One second moment per map: the entries share the colours that
        // drive them, and per-entry moments would move all twelve alike.
        self.adam
            .step_blocks(&mut self.deltas, maps, 12, RELATIVE_LEARNING_RATE * lr, DECAY);
        self.recentre();
        self.lens_adam
            .step_dense(&mut self.lens, lens, LENS_RELATIVE_LEARNING_RATE * lr, DECAY);
    }

    fn recentre(&mut self) {
        let frames = self.frames();
        if frames == 0 {
            return;
        }
        let mut mean = [0.0f64; 12];
        for d in self.deltas.chunks_exact(12) {
            for k in 0..12 {
                mean[k] += d[k] as f64;
            }
        }
        for d in self.deltas.chunks_exact_mut(12) {
            for k in 0..12 {
                d[k] -= (mean[k] / frames as f64) as f32;
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::nerf::appearance::{apply, apply_backward};
    use crate::rng::Rng;

    #[test]
    fn maps_recover_per_frame_gains_around_a_neutral_mean() {
        // Four frames photograph the same colours with gains 0.8, 0.9,
        // 1.1, 1.2 (mean 1). With the field's colour fixed at the truth,
        // the learnt maps must find the gains.
        let gains = [0.8f32, 0.9, 1.1, 1.2];
        let mut learner = AppearanceLearner::new(gains.len());
        let mut rng = Rng::new(7, 0);
        let mut grads = vec![0.0f32; learner.grad_len()];
        for _ in 0..3000 {
            grads.iter_mut().for_each(|g| *g = 0.0);
            for _ in 0..64 {
                let view = rng.below(4) as usize;
                let c = [rng.f32(), rng.f32(), rng.f32()];
                let target = c.map(|x| gains[view] * x);
                let a = learner.map(view);
                let out = apply(&a, c);
                let g: [f32; 3] = std::array::from_fn(|i| 2.0 * (out[i] - target[i]));
                apply_backward(&a, c, g, &mut grads[12 * view..12 * view + 12]);
            }
            learner.step(&grads, 0.1);
        }
        for (view, &gain) in gains.iter().enumerate() {
            let a = learner.map(view);
            for i in 0..3 {
                assert!((a[5 * i] - gain).abs() < 0.02, "frame {view}: {a:?}");
                assert!(a[4 * i + 3].abs() < 0.02, "frame {view}: offset {a:?}");
            }
        }
        let mean: f32 = learner.deltas.iter().sum::<f32>() / 48.0;
        assert!(mean.abs() < 1e-5);
        // No falloff in the photos: the lens stays neutral.
        assert!(learner.lens.iter().all(|k| k.abs() < 0.02), "{:?}", learner.lens);
    }

    #[test]
    fn lens_recovers_a_vignetting_beside_per_frame_gains() {
        // Two frames with gains 0.9 and 1.1 through a lens whose light
        // falls off as 1 - 0.4 r^2 (r^2 up to 0.6, a Kinect's corners).
        use crate::nerf::appearance::{vignetting_backward, vignetting_gain};
        let gains = [0.9f32, 1.1];
        let truth = [-0.4f32, 0.0, 0.0];
        let mut learner = AppearanceLearner::new(gains.len());
        let mut rng = Rng::new(3, 0);
        let mut grads = vec![0.0f32; learner.grad_len()];
        for _ in 0..4000 {
            grads.iter_mut().for_each(|g| *g = 0.0);
            for _ in 0..64 {
                let view = rng.below(2) as usize;
                let r2 = 0.6 * rng.f32();
                let c = [rng.f32(), rng.f32(), rng.f32()];
                let lit = vignetting_gain(&truth, r2);
                let target = c.map(|x| gains[view] * lit * x);
                let (a, lens) = (learner.map(view), learner.lens);
                let gain = vignetting_gain(&lens, r2);
                let shaded = c.map(|x| gain * x);
                let out = apply(&a, shaded);
                let g: [f32; 3] = std::array::from_fn(|i| 2.0 * (out[i] - target[i]));
                let back = apply_backward(&a, shaded, g, &mut grads[12 * view..12 * view + 12]);
                let g_gain = (0..3).map(|i| back[i] * c[i]).sum();
                let offset = learner.lens_offset();
                vignetting_backward(&lens, r2, g_gain, &mut grads[offset..]);
            }
            learner.step(&grads, 0.1);
        }
        let corner = vignetting_gain(&learner.lens, 0.6);
        assert!(
            (corner - vignetting_gain(&truth, 0.6)).abs() < 0.02,
            "{:?}",
            learner.lens
        );
        for (view, &gain) in gains.iter().enumerate() {
            assert!(
                (learner.map(view)[0] - gain).abs() < 0.03,
                "frame {view}: {:?}",
                learner.map(view)
            );
        }
    }
}
