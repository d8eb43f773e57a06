//! Backward pass of one level: corner entries and weighted gradients of each
//! sample (8 at a time, with AVX2 for 2-feature levels), then an in-order
//! scatter-add into the gradient buffer.
//!
//! Consecutive samples whose 8 corners are the same entries (common along a
//! ray at coarse levels) are summed first and written once: the scatter's
//! read-modify-writes are the cost. The gradient lines of the next 8 samples
//! are prefetched while the current 8 are scattered (after an encode has
//! evicted them, that is worth ~20%). Both paths compute every product with one
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

/// Corner entries and weighted gradients of up to 8 consecutive samples.
struct Group<const F: usize> {
    idx: [[u32; 8]; 8],
    g: [[[f32; F]; 8]; 8],
    /// Index of the first sample and number of samples.
    b0: usize,
    lanes: usize,
}

impl<const F: usize> Group<F> {
    fn new() -> Self {
        Group { idx: [[0; 8]; 8], g: [[[0.0; F]; 8]; 8], b0: 0, lanes: 0 }
    }

    /// Fills the group from block lanes `lane0..` (samples `b0..`); returns
    /// the lowest and highest entry.
    #[inline(always)]
    fn fill(&mut self, level: &GridLevel, block: &Block, lane0: usize, b0: usize, rows: &[f32], n: usize, use_simd: bool) -> (u32, u32) {
        self.b0 = b0;
        self.lanes = (block.len - lane0).min(8);
        let cols = [&block.x[lane0..lane0 + 8], &block.y[lane0..lane0 + 8], &block.z[lane0..lane0 + 8]];
        if use_simd && self.lanes == 8 {
            if let Some(span) = group_simd(level, cols, rows, n, b0, &mut self.idx, &mut self.g) {
                return span;
            }
        }
        let (mut lo, mut hi) = (u32::MAX, 0);
        for s in 0..self.lanes {
            let (ci, cw) = level.corners([cols[0][s], cols[1][s], cols[2][s]]);
            self.idx[s] = ci;
            lo = ci.into_iter().fold(lo, u32::min);
            hi = ci.into_iter().fold(hi, u32::max);
            for c in 0..8 {
                for f in 0..F {
                    self.g[s][c][f] = cw[c] * rows[f * n + b0 + s];
                }
            }
        }
        (lo, hi)
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
    let mut groups = [Group::<F>::new(), Group::<F>::new()];
    for start in (0..n).step_by(BLOCK) {
        block.load(&positions[start..]);
        let count = block.len.div_ceil(8);
        // Software pipeline: fill group k + 1 and prefetch its gradient lines
        // while group k is scattered.
        let span = groups[0].fill(level, block, 0, start, rows, n, use_simd);
        (lo, hi) = (lo.min(span.0), hi.max(span.1));
        for k in 0..count {
            let (cur, next) = groups.split_at_mut(1);
            let (cur, next) = if k % 2 == 0 { (&mut cur[0], &mut next[0]) } else { (&mut next[0], &mut cur[0]) };
            if k + 1 < count {
                let span = next.fill(level, block, 8 * (k + 1), start + 8 * (k + 1), rows, n, use_simd);
                (lo, hi) = (lo.min(span.0), hi.max(span.1));
                // Corners 2k and 2k+1 are x-neighbours, nearly always on one cache line.
                for s in 0..next.lanes {
                    for c in (0..8).step_by(2) {
                        simd::prefetch(&grad.values, (base + next.idx[s][c] as usize) * F);
                    }
                }
            }
            for s in 0..cur.lanes {
                let b = cur.b0 + s;
                if (0..F).all(|f| rows[f * n + b] == 0.0) {
                    continue;
                }
                if live && cur.idx[s] == run_idx {
                    for c in 0..8 {
                        for f in 0..F {
                            run_acc[c][f] += cur.g[s][c][f];
                        }
                    }
                } else {
                    if live {
                        flush(&run_idx, &run_acc, base, grad);
                    }
                    (run_idx, run_acc, live) = (cur.idx[s], cur.g[s], true);
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
