//! The colour a ray brings from beyond the scene's cube (sky, walls past the
//! sensor's range): a smooth function of its direction, spherical harmonics
//! of degree 3 through a sigmoid, learnt with the field. Without it the
//! field explains such colour with faint fog spread through the cube, and
//! every ray that leaves the scene then marches through that fog.

use crate::nerf::field::sh::{self, SH_COEFFS};
use crate::nerf::field::sigmoid;

/// Parameters of an [`Environment`]: one set of coefficients per channel.
pub const ENVIRONMENT_PARAMS: usize = 3 * SH_COEFFS;

/// Colour by direction, `sigmoid(sum_k coeffs[c][k] Y_k(dir))` per channel.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Environment {
    pub coeffs: [f32; ENVIRONMENT_PARAMS],
}

impl Environment {
    /// The same colour in every direction (channels clamped into (0, 1)).
    pub fn uniform(colour: [f32; 3]) -> Self {
        let mut coeffs = [0.0; ENVIRONMENT_PARAMS];
        let mut basis = [0.0; SH_COEFFS];
        sh::encode([0.0, 0.0, 1.0], &mut basis);
        for c in 0..3 {
            let p = colour[c].clamp(1e-3, 1.0 - 1e-3);
            coeffs[c * SH_COEFFS] = (p / (1.0 - p)).ln() / basis[0];
        }
        Environment { coeffs }
    }

    /// From stored coefficients (`None` unless there are exactly enough, all finite).
    pub fn from_slice(values: &[f32]) -> Option<Self> {
        let coeffs: [f32; ENVIRONMENT_PARAMS] = values.try_into().ok()?;
        coeffs.iter().all(|v| v.is_finite()).then_some(Environment { coeffs })
    }

    /// Colour seen along unit direction `dir`.
    #[inline]
    pub fn colour(&self, dir: [f32; 3]) -> [f32; 3] {
        let mut basis = [0.0; SH_COEFFS];
        sh::encode(dir, &mut basis);
        self.colour_of_basis(&basis)
    }

    /// Colour for a direction's SH basis (see [`sh::encode`]).
    #[inline]
    pub fn colour_of_basis(&self, basis: &[f32; SH_COEFFS]) -> [f32; 3] {
        std::array::from_fn(|c| {
            let k = &self.coeffs[c * SH_COEFFS..(c + 1) * SH_COEFFS];
            sigmoid(k.iter().zip(basis).map(|(a, b)| a * b).sum())
        })
    }

    /// Backward of [`Environment::colour_of_basis`]: adds to `grads` the
    /// gradient with respect to the coefficients, given the colour it gave
    /// and the loss gradient `g` with respect to that colour.
    #[inline]
    pub fn backward(colour: [f32; 3], basis: &[f32; SH_COEFFS], g: [f32; 3], grads: &mut [f32]) {
        for c in 0..3 {
            let d = g[c] * colour[c] * (1.0 - colour[c]);
            for (gk, b) in grads[c * SH_COEFFS..(c + 1) * SH_COEFFS].iter_mut().zip(basis) {
                *gk += d * b;
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_uniform_environment_gives_its_colour_everywhere() {
        let env = Environment::uniform([0.2, 0.5, 0.9]);
        for dir in [[0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [0.0, -0.6, 0.8]] {
            let c = env.colour(dir);
            for (got, want) in c.iter().zip([0.2, 0.5, 0.9]) {
                assert!((got - want).abs() < 1e-5, "{c:?}");
            }
        }
    }

    #[test]
    fn backward_matches_finite_differences() {
        let mut env = Environment::uniform([0.3, 0.6, 0.4]);
        for (k, v) in env.coeffs.iter_mut().enumerate() {
            *v += 0.1 * ((k as f32) * 0.7).sin();
        }
        let dir = [0.48, -0.6, 0.64];
        let mut basis = [0.0; SH_COEFFS];
        sh::encode(dir, &mut basis);
        let g = [0.7, -1.3, 0.4];
        let loss = |e: &Environment| e.colour(dir).iter().zip(g).map(|(c, g)| c * g).sum::<f32>();
        let mut grads = [0.0; ENVIRONMENT_PARAMS];
        Environment::backward(env.colour(dir), &basis, g, &mut grads);
        for (k, &analytic) in grads.iter().enumerate() {
            let h = 1e-2;
            let (mut up, mut down) = (env, env);
            up.coeffs[k] += h;
            down.coeffs[k] -= h;
            let numeric = (loss(&up) - loss(&down)) / (2.0 * h);
            assert!(
                (numeric - analytic).abs() < 1e-3,
                "coefficient {k}: {numeric} vs {analytic}"
            );
        }
    }
}
