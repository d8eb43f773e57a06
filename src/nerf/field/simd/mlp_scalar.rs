//! Portable kernels behind [`super::mlp_tile`]: the same blocking as the AVX2
//! path, written as fixed-size array loops the compiler can vectorise for the
//! baseline target. Extents were checked by the caller; indexing still
//! bounds-checks, so a mistake here panics instead of corrupting memory.

use super::mlp_tile::{Epilogue, COL_BLOCK, LANES};

/// Output rows per register block.
const MR: usize = 4;
/// Columns per register block: MR x HALF accumulators fit 16 SSE registers.
const HALF: usize = 8;

/// See `mlp_tile::gemm_tile`.
#[allow(clippy::too_many_arguments)]
pub(super) fn gemm_tile(
    a: &[f32],
    a_rs: usize,
    a_ks: usize,
    bias: Option<&[f32]>,
    k_len: usize,
    x: &[f32],
    ldx: usize,
    rows: usize,
    cols: usize,
    epi: Epilogue<'_>,
    y: &mut [f32],
    ldy: usize,
) {
    debug_assert!(cols.is_multiple_of(COL_BLOCK));
    for c0 in (0..cols).step_by(HALF) {
        for r0 in (0..rows).step_by(MR) {
            let mr = MR.min(rows - r0);
            let mut acc = [[0.0f32; HALF]; MR];
            if let Some(b) = bias {
                for (r, row) in acc.iter_mut().enumerate().take(mr) {
                    *row = [b[r0 + r]; HALF];
                }
            }
            for k in 0..k_len {
                let xr = &x[k * ldx + c0..][..HALF];
                for (r, row) in acc.iter_mut().enumerate().take(mr) {
                    let w = a[(r0 + r) * a_rs + k * a_ks];
                    for (s, xv) in row.iter_mut().zip(xr) {
                        *s += w * xv;
                    }
                }
            }
            for (r, row) in acc.iter().enumerate().take(mr) {
                let out = &mut y[(r0 + r) * ldy + c0..][..HALF];
                match epi {
                    Epilogue::Linear => out.copy_from_slice(row),
                    Epilogue::Relu => {
                        for (o, s) in out.iter_mut().zip(row) {
                            *o = s.max(0.0);
                        }
                    }
                    Epilogue::MaskPositive { mask, ld } => {
                        let m = &mask[(r0 + r) * ld + c0..][..HALF];
                        for ((o, s), mv) in out.iter_mut().zip(row).zip(m) {
                            *o = if *mv > 0.0 { *s } else { 0.0 };
                        }
                    }
                }
            }
        }
    }
}

/// See `mlp_tile::grad_tile`. Blocks of 2 x 2 neuron pairs share row loads.
#[allow(clippy::too_many_arguments)]
pub(super) fn grad_tile(
    dz: &[f32],
    ldz: usize,
    x: &[f32],
    ldx: usize,
    out: usize,
    inp: usize,
    cols: usize,
    dwv: &mut [f32],
) {
    for o0 in (0..out).step_by(2) {
        let mo = 2.min(out - o0);
        for i0 in (0..inp).step_by(2) {
            let mi = 2.min(inp - i0);
            let mut acc = [[[0.0f32; LANES]; 2]; 2];
            for r in 0..mo {
                for c in 0..mi {
                    acc[r][c].copy_from_slice(&dwv[((o0 + r) * inp + i0 + c) * LANES..][..LANES]);
                }
            }
            for t in (0..cols).step_by(LANES) {
                let d0 = &dz[o0 * ldz + t..][..LANES];
                let d1 = &dz[(o0 + mo - 1) * ldz + t..][..LANES];
                let x0 = &x[i0 * ldx + t..][..LANES];
                let x1 = &x[(i0 + mi - 1) * ldx + t..][..LANES];
                for l in 0..LANES {
                    acc[0][0][l] += d0[l] * x0[l];
                    acc[0][1][l] += d0[l] * x1[l];
                    acc[1][0][l] += d1[l] * x0[l];
                    acc[1][1][l] += d1[l] * x1[l];
                }
            }
            // Blocks at an odd edge computed a duplicate row or column;
            // only the real pairs are stored.
            for r in 0..mo {
                for c in 0..mi {
                    dwv[((o0 + r) * inp + i0 + c) * LANES..][..LANES].copy_from_slice(&acc[r][c]);
                }
            }
        }
    }
}

/// See `mlp_tile::rowsum_tile`.
pub(super) fn rowsum_tile(dz: &[f32], ldz: usize, rows: usize, cols: usize, dbv: &mut [f32]) {
    for r in 0..rows {
        let part = &mut dbv[r * LANES..][..LANES];
        for chunk in dz[r * ldz..][..cols].chunks_exact(LANES) {
            for l in 0..LANES {
                part[l] += chunk[l];
            }
        }
    }
}
