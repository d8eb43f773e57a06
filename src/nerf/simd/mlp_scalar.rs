//! Portable kernels behind [`super::mlp_tile`]: the same blocking as the AVX2
//! path, written as fixed-size array loops the compiler can vectorise for the
//! baseline target. Extents were checked by the caller; indexing still
//! bounds-checks, so a mistake here panics instead of corrupting memory.

use super::mlp_tile::{Epilogue, COL_BLOCK, LANES};

/// Output rows per register block.
const MR: usize = 4;

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
    for c0 in (0..cols).step_by(COL_BLOCK) {
        for r0 in (0..rows).step_by(MR) {
            let mr = MR.min(rows - r0);
            let mut acc = [[0.0f32; COL_BLOCK]; MR];
            if let Some(b) = bias {
                for (r, row) in acc.iter_mut().enumerate().take(mr) {
                    *row = [b[r0 + r]; COL_BLOCK];
                }
            }
            for k in 0..k_len {
                let xr = &x[k * ldx + c0..][..COL_BLOCK];
                for (r, row) in acc.iter_mut().enumerate().take(mr) {
                    let w = a[(r0 + r) * a_rs + k * a_ks];
                    for (s, xv) in row.iter_mut().zip(xr) {
                        *s += w * xv;
                    }
                }
            }
            for (r, row) in acc.iter().enumerate().take(mr) {
                let out = &mut y[(r0 + r) * ldy + c0..][..COL_BLOCK];
                match epi {
                    Epilogue::Linear => out.copy_from_slice(row),
                    Epilogue::Relu => {
                        for (o, s) in out.iter_mut().zip(row) {
                            *o = s.max(0.0);
                        }
                    }
                    Epilogue::MaskPositive { mask, ld } => {
                        let m = &mask[(r0 + r) * ld + c0..][..COL_BLOCK];
                        for ((o, s), mv) in out.iter_mut().zip(row).zip(m) {
                            *o = if *mv > 0.0 { *s } else { 0.0 };
                        }
                    }
                }
            }
        }
    }
}

/// See `mlp_tile::grad_tile`.
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
    for o in 0..out {
        let drow = &dz[o * ldz..][..cols];
        for i in 0..inp {
            let xrow = &x[i * ldx..][..cols];
            let part: &mut [f32] = &mut dwv[(o * inp + i) * LANES..][..LANES];
            let mut acc = [0.0f32; LANES];
            acc.copy_from_slice(part);
            for (d, xv) in drow.chunks_exact(LANES).zip(xrow.chunks_exact(LANES)) {
                for l in 0..LANES {
                    acc[l] += d[l] * xv[l];
                }
            }
            part.copy_from_slice(&acc);
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
