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
use crate::nerf::field::simd::grid as simd;

/// What one level's backward reads: its geometry and its F rows of d_out.
struct LevelInput<'a> {
    level: &'a GridLevel,
    /// Feature-major `rows[f * n + b]`.
    rows: &'a [f32],
    n: usize,
    use_simd: bool,
}

impl LevelInput<'_> {
    /// Gradient of sample `b` for the level's features.
    #[inline(always)]
    fn d<const F: usize>(&self, b: usize) -> [f32; F] {
        std::array::from_fn(|f| self.rows[f * self.n + b])
    }
}

/// Corner entries and weighted gradients of up to 8 consecutive samples.
struct Group<const F: usize> {
    /// `idx[s][c]`: entry of corner c of sample s, within the level.
    idx: [[u32; 8]; 8],
    /// `g[s][c][f]`: weight of corner c times sample s's gradient of feature f.
    g: [[[f32; F]; 8]; 8],
    /// First sample and number of samples.
    b0: usize,
    lanes: usize,
}

impl<const F: usize> Group<F> {
    fn new() -> Self {
        Group {
            idx: [[0; 8]; 8],
            g: [[[0.0; F]; 8]; 8],
            b0: 0,
            lanes: 0,
        }
    }

    /// Fills the group from block lanes `lane0..` (samples `b0..`); returns
    /// the lowest and highest entry.
    #[inline(always)]
    #[allow(clippy::needless_range_loop)] // s indexes five parallel arrays
    fn fill(&mut self, input: &LevelInput, block: &Block, lane0: usize, b0: usize) -> (u32, u32) {
        self.b0 = b0;
        self.lanes = (block.len - lane0).min(8);
        let cols = [
            &block.x[lane0..lane0 + 8],
            &block.y[lane0..lane0 + 8],
            &block.z[lane0..lane0 + 8],
        ];
        if input.use_simd && self.lanes == 8 && F == 2 {
            let (rows, n) = (input.rows, input.n);
            let d = [&rows[b0..b0 + 8], &rows[n + b0..n + b0 + 8]];
            let g = self.g.as_flattened_mut().as_flattened_mut();
            if let Some(span) = simd::group_grad_f2(input.level, cols, d, &mut self.idx, g) {
                return span;
            }
        }
        let (mut lo, mut hi) = (u32::MAX, 0);
        for s in 0..self.lanes {
            let (ci, cw) = input.level.corners([cols[0][s], cols[1][s], cols[2][s]]);
            let d = input.d::<F>(b0 + s);
            self.idx[s] = ci;
            lo = ci.into_iter().fold(lo, u32::min);
            hi = ci.into_iter().fold(hi, u32::max);
            for (gc, w) in self.g[s].iter_mut().zip(cw) {
                *gc = d.map(|d| w * d);
            }
        }
        (lo, hi)
    }

    /// Hints the CPU to fetch the gradient lines this group will write.
    #[inline(always)]
    fn prefetch(&self, base: usize, grad: &GridGrad) {
        for idx in &self.idx[..self.lanes] {
            // Corners 2k and 2k+1 are x-neighbours, nearly always on one cache line.
            for c in (0..8).step_by(2) {
                simd::prefetch(&grad.values, (base + idx[c] as usize) * F);
            }
        }
    }
}

/// The samples summed so far whose corners are the same 8 entries.
struct Run<const F: usize> {
    idx: [u32; 8],
    acc: [[f32; F]; 8],
    live: bool,
}

impl<const F: usize> Run<F> {
    /// Adds sample `s` of `group` to the run, first writing the run out when
    /// the sample's entries differ.
    #[inline(always)]
    fn push(&mut self, group: &Group<F>, s: usize, base: usize, grad: &mut GridGrad) {
        if self.live && group.idx[s] == self.idx {
            for (acc, g) in self.acc.iter_mut().zip(&group.g[s]) {
                for (a, g) in acc.iter_mut().zip(g) {
                    *a += *g;
                }
            }
        } else {
            self.flush(base, grad);
            (self.idx, self.acc, self.live) = (group.idx[s], group.g[s], true);
        }
    }

    /// Adds the run's gradients to its 8 entries (offset by `base`).
    #[inline(always)]
    fn flush(&mut self, base: usize, grad: &mut GridGrad) {
        if self.live {
            for (idx, acc) in self.idx.iter().zip(&self.acc) {
                grad.add_entry::<F>(base + *idx as usize, acc);
            }
            self.live = false;
        }
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
    let input = LevelInput {
        level,
        rows,
        n,
        use_simd,
    };
    let base = level.param_offset / F;
    let mut run = Run::<F> {
        idx: [0; 8],
        acc: [[0.0; F]; 8],
        live: false,
    };
    // Range of entries the level's samples reach (for the summary bitset).
    let (mut lo, mut hi) = (u32::MAX, 0u32);
    let mut groups = [Group::<F>::new(), Group::<F>::new()];
    for start in (0..n).step_by(BLOCK) {
        block.load(&positions[start..]);
        let count = block.len.div_ceil(8);
        // Software pipeline: group k + 1 is filled and its lines prefetched
        // while group k is scattered.
        let span = groups[0].fill(&input, block, 0, start);
        (lo, hi) = (lo.min(span.0), hi.max(span.1));
        for k in 0..count {
            let [even, odd] = &mut groups;
            let (cur, next) = if k % 2 == 0 { (even, odd) } else { (odd, even) };
            if k + 1 < count {
                let span = next.fill(&input, block, 8 * (k + 1), start + 8 * (k + 1));
                (lo, hi) = (lo.min(span.0), hi.max(span.1));
                next.prefetch(base, grad);
            }
            for s in 0..cur.lanes {
                // A sample with no gradient on this level touches nothing.
                if input.d::<F>(cur.b0 + s).iter().any(|&d| d != 0.0) {
                    run.push(cur, s, base, grad);
                }
            }
        }
    }
    run.flush(base, grad);
    if lo <= hi {
        grad.mark_summary((base + lo as usize) * F / 64, (base + hi as usize) * F / 64);
    }
}
