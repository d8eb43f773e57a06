//! Backward pass of one level: corner entries and weighted gradients of each
//! sample (8 at a time, with AVX2 for 2-feature levels), then an in-order
//! scatter-add into the gradient buffer.
//!
//! Consecutive samples whose 8 corners are the same entries (common along a
//! ray at coarse levels) are summed first and written once: the scatter's
//! read-modify-writes are the cost. Both paths compute every product with one
//! multiply and sum in the same order, so their results are bit-identical.

use super::{Block, GridGrad, GridLevel, BLOCK};
use crate::nerf::simd::grid as simd;

/// Adds one run's gradients to its 8 entries (offset by `base`).
#[inline(always)]
fn flush<const F: usize>(idx: &[u32; 8], acc: &[[f32; F]; 8], base: usize, grad: &mut GridGrad) {
    for c in 0..8 {
        grad.add_entry::<F>(base + idx[c] as usize, &acc[c]);
    }
}

/// Accumulates one level's gradient; `rows` are the level's F rows of d_out.
pub(super) fn level<const F: usize>(
    level: &GridLevel,
    positions: &[[f32; 3]],
    rows: &[f32],
    block: &mut Block,
    use_simd: bool,
    grad: &mut GridGrad,
) {
    let n = positions.len();
    let base = level.param_offset / F;
    // The current run: its entries, summed gradient, and whether it exists.
    let (mut run_idx, mut run_acc, mut live) = ([0u32; 8], [[0f32; F]; 8], false);
    // Range of entries the level's samples reach (for the summary bitset).
    let (mut lo, mut hi) = (u32::MAX, 0u32);
    let mut idx = [[0u32; 8]; 8];
    let mut g = [[[0f32; F]; 8]; 8];
    for start in (0..n).step_by(BLOCK) {
        block.load(&positions[start..]);
        for lane0 in (0..block.len).step_by(8) {
            let lanes = (block.len - lane0).min(8);
            let b0 = start + lane0;
            let cols = [&block.x[lane0..lane0 + 8], &block.y[lane0..lane0 + 8], &block.z[lane0..lane0 + 8]];
            let simd_span = if use_simd && lanes == 8 { group_simd(level, cols, rows, n, b0, &mut idx, &mut g) } else { None };
            if let Some((l, h)) = simd_span {
                (lo, hi) = (lo.min(l), hi.max(h));
            } else {
                for s in 0..lanes {
                    let (ci, cw) = level.corners([cols[0][s], cols[1][s], cols[2][s]]);
                    idx[s] = ci;
                    lo = ci.into_iter().fold(lo, u32::min);
                    hi = ci.into_iter().fold(hi, u32::max);
                    for c in 0..8 {
                        for f in 0..F {
                            g[s][c][f] = cw[c] * rows[f * n + b0 + s];
                        }
                    }
                }
            }
            for s in 0..lanes {
                if (0..F).all(|f| rows[f * n + b0 + s] == 0.0) {
                    continue;
                }
                if live && idx[s] == run_idx {
                    for c in 0..8 {
                        for f in 0..F {
                            run_acc[c][f] += g[s][c][f];
                        }
                    }
                } else {
                    if live {
                        flush(&run_idx, &run_acc, base, grad);
                    }
                    (run_idx, run_acc, live) = (idx[s], g[s], true);
                }
            }
        }
    }
    if live {
        flush(&run_idx, &run_acc, base, grad);
    }
    if lo <= hi {
        grad.mark_summary((base + lo as usize) * F / 64, (base + hi as usize) * F / 64);
    }
}

/// The AVX2 group kernel, for 2-feature levels only.
#[inline(always)]
fn group_simd<const F: usize>(
    level: &GridLevel,
    cols: [&[f32]; 3],
    rows: &[f32],
    n: usize,
    b0: usize,
    idx: &mut [[u32; 8]; 8],
    g: &mut [[[f32; F]; 8]; 8],
) -> Option<(u32, u32)> {
    if F != 2 {
        return None;
    }
    let d = [&rows[b0..b0 + 8], &rows[n + b0..n + b0 + 8]];
    simd::group_grad_f2(level, cols, d, idx, g.as_flattened_mut().as_flattened_mut())
}
