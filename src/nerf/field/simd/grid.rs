//! AVX2 kernels for the hash grid, 8 positions at a time: the forward pass of
//! a 2-feature level (each corner's feature pair loaded as one 64-bit
//! element), and the backward's corner entries and weighted gradients,
//! transposed sample-major for the scalar scatter. Plus a prefetch hint.
//!
//! The kernels repeat the scalar path's operations in the same order (no FMA
//! contraction), so their results are bit-identical to `GridLevel::corners`
//! and the scalar encode.

use crate::nerf::field::hash_grid::{GridLevel, PRIMES};

/// True when the AVX2+FMA kernels can run on this CPU.
pub fn available() -> bool {
    #[cfg(target_arch = "x86_64")]
    {
        std::is_x86_feature_detected!("avx2") && std::is_x86_feature_detected!("fma")
    }
    #[cfg(not(target_arch = "x86_64"))]
    {
        false
    }
}

/// Hints the CPU to bring `data[i]` into L1 (nothing when `i` is out of bounds).
#[inline(always)]
pub fn prefetch(data: &[f32], i: usize) {
    #[cfg(target_arch = "x86_64")]
    if i < data.len() {
        use std::arch::x86_64::{_mm_prefetch, _MM_HINT_T0};
        // SAFETY: prefetching is a hint that never faults, and the address is inside `data`.
        unsafe { _mm_prefetch::<_MM_HINT_T0>(data.as_ptr().add(i).cast()) }
    }
    #[cfg(not(target_arch = "x86_64"))]
    let _ = (data, i);
}

/// Table entries a level's indices can reach, if its geometry is consistent
/// and small enough for 32-bit offsets.
fn entries_reachable(level: &GridLevel) -> Option<usize> {
    let res = level.resolution as u64;
    if res == 0 {
        return None;
    }
    let n = if level.dense {
        let side = res + 1;
        if level.stride_y as u64 != side || level.stride_z as u64 != side * side {
            return None;
        }
        side * side * side
    } else {
        level.mask as u64 + 1
    };
    (n <= 1 << 28).then_some(n as usize)
}

/// Encodes one level for a block of positions into two feature rows.
///
/// `xyz` are clamped coordinate columns padded to a multiple of 8 and at least
/// `out0.len()` long; `table` is the level's table (2 f32 per entry). Returns
/// false (writing nothing) when AVX2 is missing or the inputs do not fit.
pub fn encode_level_f2(level: &GridLevel, table: &[f32], xyz: [&[f32]; 3], out0: &mut [f32], out1: &mut [f32]) -> bool {
    let n = out0.len();
    let padded = xyz[0].len();
    let shapes_ok =
        padded.is_multiple_of(8) && padded >= n && xyz[1].len() == padded && xyz[2].len() == padded && out1.len() == n;
    let table_ok = entries_reachable(level).is_some_and(|e| table.len() >= 2 * e);
    if !(shapes_ok && table_ok && available()) {
        return false;
    }
    #[cfg(target_arch = "x86_64")]
    {
        // SAFETY: AVX2 and FMA were detected above; every index the kernel
        // forms is below `entries_reachable(level)`, and `table` holds 2 f32
        // for each of those entries; slices are only read/written in bounds.
        unsafe { avx2::encode_level_f2(level, table, xyz, out0, out1) };
        true
    }
    #[cfg(not(target_arch = "x86_64"))]
    {
        false
    }
}

/// Corner entries `idx[s][c]` and weighted gradients `g[16 s + 2 c + f] =
/// w[s][c] * d[f][s]` of 8 samples on a 2-feature level, sample-major for the
/// scatter. `xyz` and `d` are columns of 8, `g` has 128 elements. Returns
/// the lowest and highest entry, or None (writing nothing) when AVX2 is
/// missing or a length is wrong.
pub fn group_grad_f2(
    level: &GridLevel,
    xyz: [&[f32]; 3],
    d: [&[f32]; 2],
    idx: &mut [[u32; 8]; 8],
    g: &mut [f32],
) -> Option<(u32, u32)> {
    if xyz.iter().chain(&d).any(|c| c.len() != 8) || g.len() != 128 || level.resolution == 0 || !available() {
        return None;
    }
    #[cfg(target_arch = "x86_64")]
    {
        // SAFETY: AVX2 and FMA were detected above; all columns are 8 long,
        // `idx` is 8 x 8 u32 and `g` holds 128 f32.
        Some(unsafe { avx2::group_grad_f2(level, xyz, d, idx, g) })
    }
    #[cfg(not(target_arch = "x86_64"))]
    {
        None
    }
}

#[cfg(target_arch = "x86_64")]
mod avx2 {
    use super::*;
    use std::arch::x86_64::*;

    /// Cell coordinate (clamped to 0..res-1) and fraction of 8 coordinates.
    #[inline]
    #[target_feature(enable = "avx2,fma")]
    fn axis(v: __m256, res_f: __m256, res_max: __m256i) -> (__m256i, __m256) {
        let v = _mm256_min_ps(_mm256_max_ps(v, _mm256_setzero_ps()), _mm256_set1_ps(1.0));
        let p = _mm256_mul_ps(v, res_f);
        // p >= 0 (NaN became 0), so truncation is floor, as in the scalar path.
        let i = _mm256_cvttps_epi32(p);
        // Integer clamp keeps indices in range whatever the float did.
        let i = _mm256_min_epi32(_mm256_max_epi32(i, _mm256_setzero_si256()), res_max);
        (i, _mm256_sub_ps(p, _mm256_cvtepi32_ps(i)))
    }

    /// Corner entries and weights of 8 positions; corner bit 0/1/2 = +x/+y/+z.
    #[inline]
    #[target_feature(enable = "avx2,fma")]
    fn corners(level: &GridLevel, x: __m256, y: __m256, z: __m256) -> ([__m256i; 8], [__m256; 8]) {
        let res_f = _mm256_set1_ps(level.resolution as f32);
        let res_max = _mm256_set1_epi32(level.resolution as i32 - 1);
        let (ix, fx) = axis(x, res_f, res_max);
        let (iy, fy) = axis(y, res_f, res_max);
        let (iz, fz) = axis(z, res_f, res_max);
        let one = _mm256_set1_ps(1.0);
        let wx = [_mm256_sub_ps(one, fx), fx];
        let wy = [_mm256_sub_ps(one, fy), fy];
        let wz = [_mm256_sub_ps(one, fz), fz];
        let xs = [ix, _mm256_add_epi32(ix, _mm256_set1_epi32(1))];
        let (sy, sz) = if level.dense {
            (level.stride_y, level.stride_z)
        } else {
            (PRIMES[1], PRIMES[2])
        };
        let (sy, sz) = (_mm256_set1_epi32(sy as i32), _mm256_set1_epi32(sz as i32));
        let y0 = _mm256_mullo_epi32(iy, sy);
        let z0 = _mm256_mullo_epi32(iz, sz);
        let ys = [y0, _mm256_add_epi32(y0, sy)];
        let zs = [z0, _mm256_add_epi32(z0, sz)];
        let mask = _mm256_set1_epi32(level.mask as i32);
        let mut idx = [_mm256_setzero_si256(); 8];
        let mut w = [_mm256_setzero_ps(); 8];
        for c in 0..8 {
            let (i, j, k) = (c & 1, (c >> 1) & 1, c >> 2);
            idx[c] = if level.dense {
                _mm256_add_epi32(_mm256_add_epi32(xs[i], ys[j]), zs[k])
            } else {
                _mm256_and_si256(_mm256_xor_si256(_mm256_xor_si256(xs[i], ys[j]), zs[k]), mask)
            };
            w[c] = _mm256_mul_ps(_mm256_mul_ps(wx[i], wy[j]), wz[k]);
        }
        (idx, w)
    }

    /// Transposes 8 rows of 8 lanes (`rows[r]` lane `l` -> `out[l]` lane `r`).
    #[inline]
    #[target_feature(enable = "avx2,fma")]
    fn transpose8(r: [__m256; 8]) -> [__m256; 8] {
        let t0 = _mm256_unpacklo_ps(r[0], r[1]);
        let t1 = _mm256_unpackhi_ps(r[0], r[1]);
        let t2 = _mm256_unpacklo_ps(r[2], r[3]);
        let t3 = _mm256_unpackhi_ps(r[2], r[3]);
        let t4 = _mm256_unpacklo_ps(r[4], r[5]);
        let t5 = _mm256_unpackhi_ps(r[4], r[5]);
        let t6 = _mm256_unpacklo_ps(r[6], r[7]);
        let t7 = _mm256_unpackhi_ps(r[6], r[7]);
        let u0 = _mm256_shuffle_ps::<0x44>(t0, t2);
        let u1 = _mm256_shuffle_ps::<0xEE>(t0, t2);
        let u2 = _mm256_shuffle_ps::<0x44>(t1, t3);
        let u3 = _mm256_shuffle_ps::<0xEE>(t1, t3);
        let u4 = _mm256_shuffle_ps::<0x44>(t4, t6);
        let u5 = _mm256_shuffle_ps::<0xEE>(t4, t6);
        let u6 = _mm256_shuffle_ps::<0x44>(t5, t7);
        let u7 = _mm256_shuffle_ps::<0xEE>(t5, t7);
        [
            _mm256_permute2f128_ps::<0x20>(u0, u4),
            _mm256_permute2f128_ps::<0x20>(u1, u5),
            _mm256_permute2f128_ps::<0x20>(u2, u6),
            _mm256_permute2f128_ps::<0x20>(u3, u7),
            _mm256_permute2f128_ps::<0x31>(u0, u4),
            _mm256_permute2f128_ps::<0x31>(u1, u5),
            _mm256_permute2f128_ps::<0x31>(u2, u6),
            _mm256_permute2f128_ps::<0x31>(u3, u7),
        ]
    }

    /// See [`super::group_grad_f2`].
    ///
    /// # Safety
    /// AVX2 and FMA must be available; every column must be 8 long and `g`
    /// must hold 128 f32.
    #[target_feature(enable = "avx2,fma")]
    pub unsafe fn group_grad_f2(
        level: &GridLevel,
        xyz: [&[f32]; 3],
        d: [&[f32]; 2],
        idx: &mut [[u32; 8]; 8],
        g: &mut [f32],
    ) -> (u32, u32) {
        // SAFETY: the caller guarantees 8 readable f32 per column.
        let (x, y, z, d0, d1) = unsafe {
            (
                _mm256_loadu_ps(xyz[0].as_ptr()),
                _mm256_loadu_ps(xyz[1].as_ptr()),
                _mm256_loadu_ps(xyz[2].as_ptr()),
                _mm256_loadu_ps(d[0].as_ptr()),
                _mm256_loadu_ps(d[1].as_ptr()),
            )
        };
        let (ci, cw) = corners(level, x, y, z);
        let (mut fi, mut f0, mut f1) = (
            [_mm256_setzero_ps(); 8],
            [_mm256_setzero_ps(); 8],
            [_mm256_setzero_ps(); 8],
        );
        for c in 0..8 {
            fi[c] = _mm256_castsi256_ps(ci[c]);
            f0[c] = _mm256_mul_ps(cw[c], d0);
            f1[c] = _mm256_mul_ps(cw[c], d1);
        }
        let (ti, g0, g1) = (transpose8(fi), transpose8(f0), transpose8(f1));
        let (mut lo, mut hi) = (ci[0], ci[0]);
        for v in &ci[1..] {
            lo = _mm256_min_epu32(lo, *v);
            hi = _mm256_max_epu32(hi, *v);
        }
        let (mut lo8, mut hi8) = ([0u32; 8], [0u32; 8]);
        for s in 0..8 {
            // Interleave the two features: corners 0,1 | 4,5 and 2,3 | 6,7, then reorder halves.
            let lo = _mm256_unpacklo_ps(g0[s], g1[s]);
            let hi = _mm256_unpackhi_ps(g0[s], g1[s]);
            let first = _mm256_permute2f128_ps::<0x20>(lo, hi);
            let second = _mm256_permute2f128_ps::<0x31>(lo, hi);
            // SAFETY: idx[s] is 8 u32; g[16 s..16 s + 16] is in bounds (g holds 128).
            unsafe {
                _mm256_storeu_ps(idx[s].as_mut_ptr().cast(), ti[s]);
                let gs = g.as_mut_ptr().add(16 * s);
                _mm256_storeu_ps(gs, first);
                _mm256_storeu_ps(gs.add(8), second);
            }
        }
        // SAFETY: lo8 and hi8 are 8 u32 each.
        unsafe {
            _mm256_storeu_si256(lo8.as_mut_ptr().cast(), lo);
            _mm256_storeu_si256(hi8.as_mut_ptr().cast(), hi);
        }
        (
            lo8.into_iter().fold(u32::MAX, u32::min),
            hi8.into_iter().fold(0, u32::max),
        )
    }

    /// The feature pairs of 8 entries (as 64-bit elements): entries 0-3 and
    /// 4-7. Eight scalar loads, not two gathers: on the AMD cores this runs
    /// on they encode 25-35 % faster (`bench_grid`); the values are the same.
    ///
    /// # Safety
    /// Every lane of `idx` is an entry whose 8 bytes lie inside the table at `base`.
    #[inline]
    #[target_feature(enable = "avx2,fma")]
    unsafe fn load_pairs(base: *const f64, idx: __m256i) -> (__m256d, __m256d) {
        let mut e = [0u32; 8];
        _mm256_storeu_si256(e.as_mut_ptr().cast(), idx);
        // SAFETY: the caller vouches for every entry; the table is f32, so reads are unaligned.
        let at = |k: usize| unsafe { base.add(e[k] as usize).read_unaligned() };
        (
            _mm256_setr_pd(at(0), at(1), at(2), at(3)),
            _mm256_setr_pd(at(4), at(5), at(6), at(7)),
        )
    }

    /// See [`super::encode_level_f2`].
    ///
    /// # Safety
    /// AVX2 and FMA must be available; the columns must be padded to a
    /// multiple of 8 and cover `out0`; `table` must hold 2 f32 for every entry
    /// index the level's geometry can produce (`entries_reachable`).
    #[target_feature(enable = "avx2,fma")]
    pub unsafe fn encode_level_f2(
        level: &GridLevel,
        table: &[f32],
        xyz: [&[f32]; 3],
        out0: &mut [f32],
        out1: &mut [f32],
    ) {
        let n = out0.len();
        if n == 0 {
            return;
        }
        let base = table.as_ptr().cast::<f64>();
        let dup_lo = _mm256_setr_epi32(0, 0, 1, 1, 2, 2, 3, 3);
        let dup_hi = _mm256_setr_epi32(4, 4, 5, 5, 6, 6, 7, 7);
        // SAFETY: for every s < n, s + 8 <= padded column length (padded >= n > 0, a multiple of 8).
        let load = |s: usize| unsafe {
            (
                _mm256_loadu_ps(xyz[0].as_ptr().add(s)),
                _mm256_loadu_ps(xyz[1].as_ptr().add(s)),
                _mm256_loadu_ps(xyz[2].as_ptr().add(s)),
            )
        };
        let (x, y, z) = load(0);
        let mut next = corners(level, x, y, z);
        let mut s = 0;
        while s < n {
            // The next group's corners are computed before this group's loads
            // complete, overlapping arithmetic with the loads (measured ~5%).
            let (idx, w) = next;
            if s + 8 < n {
                let (x, y, z) = load(s + 8);
                next = corners(level, x, y, z);
            }
            // Pairs (f0, f1) of samples 0-3 in `lo`, 4-7 in `hi`.
            let mut lo = _mm256_setzero_ps();
            let mut hi = _mm256_setzero_ps();
            for c in 0..8 {
                // SAFETY: idx[c] lanes are entry indices below the reachable
                // count, and entry e occupies table[2e..2e+2] (8 bytes at base + 8e).
                let (vl, vh) = unsafe { load_pairs(base, idx[c]) };
                let wl = _mm256_permutevar8x32_ps(w[c], dup_lo);
                let wh = _mm256_permutevar8x32_ps(w[c], dup_hi);
                lo = _mm256_add_ps(lo, _mm256_mul_ps(wl, _mm256_castpd_ps(vl)));
                hi = _mm256_add_ps(hi, _mm256_mul_ps(wh, _mm256_castpd_ps(vh)));
            }
            // De-interleave: shuffle gives samples 0 1 4 5 | 2 3 6 7, the 64-bit permute restores order.
            let f0 = _mm256_castpd_ps(_mm256_permute4x64_pd::<0b11_01_10_00>(_mm256_castps_pd(
                _mm256_shuffle_ps::<0b10_00_10_00>(lo, hi),
            )));
            let f1 = _mm256_castpd_ps(_mm256_permute4x64_pd::<0b11_01_10_00>(_mm256_castps_pd(
                _mm256_shuffle_ps::<0b11_01_11_01>(lo, hi),
            )));
            if s + 8 <= n {
                // SAFETY: out0 and out1 have n >= s + 8 elements.
                unsafe {
                    _mm256_storeu_ps(out0.as_mut_ptr().add(s), f0);
                    _mm256_storeu_ps(out1.as_mut_ptr().add(s), f1);
                }
            } else {
                let (mut t0, mut t1) = ([0f32; 8], [0f32; 8]);
                // SAFETY: t0 and t1 are 8 f32 each.
                unsafe {
                    _mm256_storeu_ps(t0.as_mut_ptr(), f0);
                    _mm256_storeu_ps(t1.as_mut_ptr(), f1);
                }
                out0[s..].copy_from_slice(&t0[..n - s]);
                out1[s..].copy_from_slice(&t1[..n - s]);
            }
            s += 8;
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::nerf::field::hash_grid::HashGridConfig;

    fn levels() -> Vec<GridLevel> {
        HashGridConfig {
            levels: 3,
            features_per_level: 2,
            log2_table_size: 10,
            base_resolution: 4,
            finest_resolution: 30,
        }
        .level_layout()
    }

    #[test]
    fn kernels_refuse_inputs_that_would_read_out_of_bounds() {
        let cols = [0.5f32; 16];
        let xyz = [&cols[..], &cols[..], &cols[..]];
        for level in levels() {
            let full = vec![0.0f32; level.entries * 2];
            let (mut o0, mut o1) = ([7.0f32; 16], [7.0f32; 16]);
            // A table one entry short, columns not padded to 8, or a length mismatch: refused, nothing written.
            assert!(!encode_level_f2(&level, &full[..full.len() - 2], xyz, &mut o0, &mut o1));
            assert!(!encode_level_f2(
                &level,
                &full,
                [&cols[..15], &cols[..15], &cols[..15]],
                &mut o0[..15],
                &mut o1[..15]
            ));
            assert!(!encode_level_f2(&level, &full, xyz, &mut o0[..9], &mut o1[..8]));
            assert!(o0.iter().chain(&o1).all(|v| *v == 7.0));
            let (mut idx, mut g) = ([[0u32; 8]; 8], [0f32; 128]);
            assert!(group_grad_f2(
                &level,
                [&cols[..7], &cols[..8], &cols[..8]],
                [&cols[..8]; 2],
                &mut idx,
                &mut g
            )
            .is_none());
            assert!(group_grad_f2(&level, [&cols[..8]; 3], [&cols[..8]; 2], &mut idx, &mut g[..127]).is_none());
            if available() {
                // Empty output: accepted, nothing read.
                assert!(encode_level_f2(&level, &full, [&[], &[], &[]], &mut [], &mut []));
                assert!(encode_level_f2(&level, &full, xyz, &mut o0[..13], &mut o1[..13]));
                assert!(o0[..13].iter().all(|v| *v == 0.0) && o0[13..].iter().all(|v| *v == 7.0));
            }
        }
    }

    #[test]
    fn group_grad_matches_corner_weights_times_gradient() {
        if !available() {
            eprintln!("skipping: no AVX2+FMA on this CPU");
            return;
        }
        let mut rng = crate::rng::Rng::new(40, 0);
        let col = |r: &mut crate::rng::Rng| -> Vec<f32> { (0..8).map(|_| r.f32() * 1.2 - 0.1).collect() };
        for level in levels() {
            let (x, y, z, d0, d1) = (
                col(&mut rng),
                col(&mut rng),
                col(&mut rng),
                col(&mut rng),
                col(&mut rng),
            );
            let (mut idx, mut g) = ([[0u32; 8]; 8], [0f32; 128]);
            let (lo, hi) = group_grad_f2(&level, [&x, &y, &z], [&d0, &d1], &mut idx, &mut g).expect("AVX2 present");
            for s in 0..8 {
                let (ci, cw) = level.corners([x[s], y[s], z[s]]);
                assert_eq!(idx[s], ci);
                for c in 0..8 {
                    assert_eq!(g[16 * s + 2 * c].to_bits(), (cw[c] * d0[s]).to_bits());
                    assert_eq!(g[16 * s + 2 * c + 1].to_bits(), (cw[c] * d1[s]).to_bits());
                }
            }
            let all = idx.iter().flatten();
            assert_eq!((lo, hi), (*all.clone().min().unwrap_or(&0), *all.max().unwrap_or(&0)));
        }
    }
}
