//! AVX2+FMA register-blocked kernels behind [`super::mlp_tile`].
//!
//! Products keep up to 6 neurons x 16 samples (12 ymm accumulators) in
//! registers with broadcast weights; weight gradients keep 4 x 3 neuron pairs
//! of 8-lane partial sums in registers while streaming the tile's samples.
//! Callers (only `mlp_tile`) have checked every extent, so these functions
//! trust their pointers.

// Register blocks read best as index loops over their rows and columns.
#![allow(clippy::needless_range_loop)]

use std::arch::x86_64::*;

pub(super) const EPI_LINEAR: u8 = 0;
pub(super) const EPI_RELU: u8 = 1;
pub(super) const EPI_MASK: u8 = 2;

/// Arguments of [`gemm_tile`]; see `mlp_tile::gemm_tile` for the meaning.
pub(super) struct GemmArgs {
    pub a: *const f32,
    pub a_rs: usize,
    pub a_ks: usize,
    /// Null for no bias.
    pub bias: *const f32,
    pub k_len: usize,
    pub x: *const f32,
    pub ldx: usize,
    pub rows: usize,
    pub cols: usize,
    pub y: *mut f32,
    pub ldy: usize,
    pub epi: u8,
    /// Mask rows for `EPI_MASK`, else null.
    pub m: *const f32,
    pub ldm: usize,
}

/// Arguments of [`grad_tile`]; see `mlp_tile::grad_tile`.
pub(super) struct GradArgs {
    pub dz: *const f32,
    pub ldz: usize,
    pub x: *const f32,
    pub ldx: usize,
    pub out: usize,
    pub inp: usize,
    pub cols: usize,
    pub dwv: *mut f32,
}

/// Tile product with epilogue. Safety: AVX2+FMA present; all extents valid.
#[target_feature(enable = "avx2,fma")]
pub(super) unsafe fn gemm_tile(g: &GemmArgs) {
    // SAFETY: forwarded contract of this function.
    unsafe {
        match g.epi {
            EPI_LINEAR => gemm_epi::<EPI_LINEAR>(g),
            EPI_RELU => gemm_epi::<EPI_RELU>(g),
            _ => gemm_epi::<EPI_MASK>(g),
        }
    }
}

#[target_feature(enable = "avx2,fma")]
#[inline]
unsafe fn gemm_epi<const E: u8>(g: &GemmArgs) {
    let mut c = 0;
    while c < g.cols {
        // Blocks of 6 rows; a remainder of 7..9 becomes two blocks of >= 3
        // so no block is left with too few accumulators to hide latency.
        let mut r = 0;
        while g.rows - r >= 10 || g.rows - r == 6 {
            // SAFETY (all micro calls): r + block <= rows and c + 16 <= cols.
            unsafe { micro::<6, E>(g, r, c) };
            r += 6;
        }
        // SAFETY: as above.
        unsafe {
            match g.rows - r {
                0 => {}
                1 => micro::<1, E>(g, r, c),
                2 => micro::<2, E>(g, r, c),
                3 => micro::<3, E>(g, r, c),
                4 => micro::<4, E>(g, r, c),
                5 => micro::<5, E>(g, r, c),
                7 => {
                    micro::<4, E>(g, r, c);
                    micro::<3, E>(g, r + 4, c);
                }
                8 => {
                    micro::<4, E>(g, r, c);
                    micro::<4, E>(g, r + 4, c);
                }
                _ => {
                    micro::<5, E>(g, r, c);
                    micro::<4, E>(g, r + 5, c);
                }
            }
        }
        c += 16;
    }
}

/// `MR` rows x 16 columns starting at (`r0`, `c0`).
#[target_feature(enable = "avx2,fma")]
#[inline]
unsafe fn micro<const MR: usize, const E: u8>(g: &GemmArgs, r0: usize, c0: usize) {
    let zero = _mm256_setzero_ps();
    let mut lo = [zero; MR];
    let mut hi = [zero; MR];
    // SAFETY: the caller guarantees rows r0..r0+MR and columns c0..c0+16 lie
    // inside A, bias, x, y and the mask as checked by mlp_tile.
    unsafe {
        if !g.bias.is_null() {
            for r in 0..MR {
                let b = _mm256_broadcast_ss(&*g.bias.add(r0 + r));
                lo[r] = b;
                hi[r] = b;
            }
        }
        let mut xp = g.x.add(c0);
        let mut ap = g.a.add(r0 * g.a_rs);
        for _ in 0..g.k_len {
            let x0 = _mm256_loadu_ps(xp);
            let x1 = _mm256_loadu_ps(xp.add(8));
            for r in 0..MR {
                let w = _mm256_broadcast_ss(&*ap.add(r * g.a_rs));
                lo[r] = _mm256_fmadd_ps(w, x0, lo[r]);
                hi[r] = _mm256_fmadd_ps(w, x1, hi[r]);
            }
            xp = xp.add(g.ldx);
            ap = ap.add(g.a_ks);
        }
        for r in 0..MR {
            let (mut a, mut b) = (lo[r], hi[r]);
            if E == EPI_RELU {
                a = _mm256_max_ps(a, zero);
                b = _mm256_max_ps(b, zero);
            } else if E == EPI_MASK {
                let mp = g.m.add((r0 + r) * g.ldm + c0);
                a = _mm256_and_ps(a, _mm256_cmp_ps::<_CMP_GT_OQ>(_mm256_loadu_ps(mp), zero));
                b = _mm256_and_ps(b, _mm256_cmp_ps::<_CMP_GT_OQ>(_mm256_loadu_ps(mp.add(8)), zero));
            }
            let yp = g.y.add((r0 + r) * g.ldy + c0);
            _mm256_storeu_ps(yp, a);
            _mm256_storeu_ps(yp.add(8), b);
        }
    }
}

/// Weight-gradient partials. Safety: AVX2+FMA present; all extents valid.
#[target_feature(enable = "avx2,fma")]
pub(super) unsafe fn grad_tile(g: &GradArgs) {
    let mut o = 0;
    while o < g.out {
        // Blocks of 4 output rows; 5 left splits as 3 + 2.
        let left = g.out - o;
        let mo = if left == 5 { 3 } else { left.min(4) };
        // SAFETY (all calls): o + mo <= out and i + mi <= inp.
        unsafe {
            match mo {
                4 => grad_rows::<4>(g, o),
                3 => grad_rows::<3>(g, o),
                2 => grad_rows::<2>(g, o),
                _ => grad_rows::<1>(g, o),
            }
        }
        o += mo;
    }
}

/// All input blocks for output rows `o0..o0+MO`.
#[target_feature(enable = "avx2,fma")]
#[inline]
unsafe fn grad_rows<const MO: usize>(g: &GradArgs, o0: usize) {
    let mut i = 0;
    while i < g.inp {
        // Blocks of 3 inputs; 4 left splits as 2 + 2, 1 after >= 3 too.
        let left = g.inp - i;
        let mi = match left {
            4 => 2,
            l if l >= 3 => 3,
            l => l,
        };
        // SAFETY: o0 + MO <= out and i + mi <= inp (forwarded contract).
        unsafe {
            match mi {
                3 => grad_micro::<MO, 3>(g, o0, i),
                2 => grad_micro::<MO, 2>(g, o0, i),
                _ => grad_micro::<MO, 1>(g, o0, i),
            }
        }
        i += mi;
    }
}

/// Partials of the `MO x MI` neuron pairs at (`o0`, `i0`) over all columns.
#[target_feature(enable = "avx2,fma")]
#[inline]
unsafe fn grad_micro<const MO: usize, const MI: usize>(g: &GradArgs, o0: usize, i0: usize) {
    let zero = _mm256_setzero_ps();
    let mut acc = [[zero; MI]; MO];
    // SAFETY: rows o0..o0+MO of dz, i0..i0+MI of x and their partials exist,
    // and cols is within both row strides' extents (checked by mlp_tile).
    unsafe {
        for r in 0..MO {
            for c in 0..MI {
                acc[r][c] = _mm256_loadu_ps(g.dwv.add(((o0 + r) * g.inp + i0 + c) * 8));
            }
        }
        let dz = g.dz.add(o0 * g.ldz);
        let x = g.x.add(i0 * g.ldx);
        let mut t = 0;
        while t < g.cols {
            let mut xv = [zero; MI];
            for c in 0..MI {
                xv[c] = _mm256_loadu_ps(x.add(c * g.ldx + t));
            }
            for r in 0..MO {
                let d = _mm256_loadu_ps(dz.add(r * g.ldz + t));
                for c in 0..MI {
                    acc[r][c] = _mm256_fmadd_ps(d, xv[c], acc[r][c]);
                }
            }
            t += 8;
        }
        for r in 0..MO {
            for c in 0..MI {
                _mm256_storeu_ps(g.dwv.add(((o0 + r) * g.inp + i0 + c) * 8), acc[r][c]);
            }
        }
    }
}

/// Bias-gradient partials. Safety: AVX2 present; all extents valid.
#[target_feature(enable = "avx2,fma")]
pub(super) unsafe fn rowsum_tile(dz: *const f32, ldz: usize, rows: usize, cols: usize, dbv: *mut f32) {
    for r in 0..rows {
        // SAFETY: row r < rows, columns < cols, partial r < rows (checked).
        unsafe {
            let row = dz.add(r * ldz);
            let mut s0 = _mm256_loadu_ps(dbv.add(r * 8));
            let mut s1 = _mm256_setzero_ps();
            let mut t = 0;
            while t + 16 <= cols {
                s0 = _mm256_add_ps(s0, _mm256_loadu_ps(row.add(t)));
                s1 = _mm256_add_ps(s1, _mm256_loadu_ps(row.add(t + 8)));
                t += 16;
            }
            if t < cols {
                s0 = _mm256_add_ps(s0, _mm256_loadu_ps(row.add(t)));
            }
            _mm256_storeu_ps(dbv.add(r * 8), _mm256_add_ps(s0, s1));
        }
    }
}
