//! Gradient of a loss with respect to the encoded positions: how the loss
//! changes when a sample moves, through each level's trilinear blend. Camera
//! pose learning needs it (a pose moves every sample of its rays); the field's
//! own parameters never do, so this pass runs only for the rays whose pose is
//! learnt.

use super::{unit, GridLevel, HashGrid};

impl GridLevel {
    /// The 8 corner entries of `p` (as [`GridLevel::corners`]) and, per
    /// corner, the derivative of its trilinear weight along x, y and z in
    /// unit-cube coordinates. Zero along an axis where `p` lies outside the
    /// cube (the encoding is clamped there, so flat).
    #[inline(always)]
    fn corner_weight_gradients(&self, p: [f32; 3]) -> ([u32; 8], [[f32; 3]; 8]) {
        let (idx, _) = self.corners(p);
        let res = self.resolution as f32;
        let frac = |x: f32| {
            let q = unit(x) * res;
            let i = (q as i32).clamp(0, self.resolution as i32 - 1);
            let inside = (0.0..=1.0).contains(&x);
            (q - i as f32, if inside { res } else { 0.0 })
        };
        let (fx, sx) = frac(p[0]);
        let (fy, sy) = frac(p[1]);
        let (fz, sz) = frac(p[2]);
        let (wx, wy, wz) = ([1.0 - fx, fx], [1.0 - fy, fy], [1.0 - fz, fz]);
        let sign = [-1.0f32, 1.0];
        let mut dw = [[0f32; 3]; 8];
        for (c, d) in dw.iter_mut().enumerate() {
            let (i, j, k) = (c & 1, (c >> 1) & 1, c >> 2);
            *d = [
                sign[i] * sx * wy[j] * wz[k],
                wx[i] * sign[j] * sy * wz[k],
                wx[i] * wy[j] * sign[k] * sz,
            ];
        }
        (idx, dw)
    }
}

impl HashGrid {
    /// Adds d(loss)/d(position) to `out[b]` for every position, from the
    /// feature-major gradient of the encoding `d_out` (shaped like
    /// [`HashGrid::encode`]'s output), over the `levels` coarsest levels only:
    /// the finest cells' blends change slope every cell, which makes the
    /// gradient a poor guide for moving a whole camera (BARF's coarse-to-fine
    /// argument). `only` lists the positions wanted (others are left as they
    /// are). Panics on mismatched lengths.
    pub fn position_gradient(
        &self,
        positions: &[[f32; 3]],
        d_out: &[f32],
        levels: usize,
        only: &[usize],
        out: &mut [[f32; 3]],
    ) {
        let n = positions.len();
        let fpl = self.config.features_per_level;
        assert_eq!(
            d_out.len(),
            n * self.output_dim(),
            "HashGrid::position_gradient: d_out has the wrong length"
        );
        assert_eq!(out.len(), n, "HashGrid::position_gradient: out has the wrong length");
        for (l, level) in self.levels.iter().enumerate().take(levels) {
            let table = &self.params[level.param_offset..level.param_offset + level.entries * fpl];
            let rows = &d_out[l * fpl * n..(l + 1) * fpl * n];
            for &b in only {
                let (idx, dw) = level.corner_weight_gradients(positions[b]);
                let mut g = [0f32; 3];
                for f in 0..fpl {
                    let d = rows[f * n + b];
                    if d == 0.0 {
                        continue;
                    }
                    for c in 0..8 {
                        let v = d * table[idx[c] as usize * fpl + f];
                        for a in 0..3 {
                            g[a] += v * dw[c][a];
                        }
                    }
                }
                for a in 0..3 {
                    out[b][a] += g[a];
                }
            }
        }
    }
}
