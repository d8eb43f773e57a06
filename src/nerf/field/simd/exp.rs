//! Exponentials over whole slices, eight lanes at a time: the renderer's
//! surface search takes two per sample, and as libm calls they were 5 %
//! of `label --depth`'s CPU.
//!
//! `exp` is the classic range reduction (x = n ln 2 + r, |r| <= ln 2 / 2)
//! with a degree-7 polynomial for e^r; `exp_m1` uses a Taylor series
//! near 0, where `exp(x) - 1` would lose its leading digits. Both stay
//! within a few units in the last place of the exact value (tested
//! against f64). The scalar path runs the same operations (`mul_add` for
//! every FMA), so both give the same bits on every input.

/// Below this, e^x is under the smallest normal f32: 0.
const EXP_MIN: f32 = -87.336_55;
/// Above this, e^x overflows: infinity.
const EXP_MAX: f32 = 88.722_83;
/// log2(e), and ln 2 split in a part exact in few bits and the rest.
const LOG2_E: f32 = std::f32::consts::LOG2_E;
const LN2_HI: f32 = 0.693_359_4;
const LN2_LO: f32 = -2.121_944_4e-4;
/// Taylor coefficients 1/k! of e^r after 1 + r, highest first.
const EXP_TAIL: [f32; 6] = [1.0 / 5040.0, 1.0 / 720.0, 1.0 / 120.0, 1.0 / 24.0, 1.0 / 6.0, 0.5];
/// |x| below which `exp_m1` sums its series: beyond it, for x < 0,
/// `1 - e^x` exceeds `e^x`, so the subtraction loses under a bit.
const EXPM1_SERIES: f32 = 0.75;
/// Taylor coefficients 1/k! of e^x - 1 from x^10 down to x^2 (the next
/// term is under a tenth of an ulp at the series' edge).
const EXPM1_TAIL: [f32; 9] = [
    1.0 / 3_628_800.0,
    1.0 / 362_880.0,
    1.0 / 40320.0,
    1.0 / 5040.0,
    1.0 / 720.0,
    1.0 / 120.0,
    1.0 / 24.0,
    1.0 / 6.0,
    0.5,
];

/// `e^x` for each value, in place. NaN stays NaN.
pub fn exp(values: &mut [f32]) {
    over_slice::<false>(values);
}

/// `e^x - 1` for each value, in place. NaN stays NaN.
pub fn exp_m1(values: &mut [f32]) {
    over_slice::<true>(values);
}

/// [`exp`], or [`exp_m1`] when `M1`, on the vector path when the CPU has one.
fn over_slice<const M1: bool>(values: &mut [f32]) {
    #[cfg(target_arch = "x86_64")]
    if super::avx2_fma_available() {
        // SAFETY: AVX2 and FMA were detected just above.
        unsafe { avx2::for_lanes::<M1>(values) };
        return;
    }
    let scalar = if M1 { exp_m1_scalar } else { exp_scalar };
    values.iter_mut().for_each(|v| *v = scalar(*v));
}

/// One lane of [`exp`].
pub fn exp_scalar(x: f32) -> f32 {
    if x.is_nan() {
        return x;
    }
    let c = x.clamp(EXP_MIN, EXP_MAX);
    // Round to nearest: the vector path's rounding mode.
    let n = (c * LOG2_E).round_ties_even();
    let r = n.mul_add(-LN2_LO, n.mul_add(-LN2_HI, c));
    let mut p = EXP_TAIL[0];
    for &k in &EXP_TAIL[1..] {
        p = p.mul_add(r, k);
    }
    let e = (p * r).mul_add(r, r) + 1.0;
    let (low, high) = powers_of_two(n);
    let scaled = e * low * high;
    if x < EXP_MIN {
        0.0
    } else if x > EXP_MAX {
        f32::INFINITY
    } else {
        scaled
    }
}

/// One lane of [`exp_m1`].
pub fn exp_m1_scalar(x: f32) -> f32 {
    if x.abs() < EXPM1_SERIES {
        let mut p = EXPM1_TAIL[0];
        for &k in &EXPM1_TAIL[1..] {
            p = p.mul_add(x, k);
        }
        (p * x).mul_add(x, x)
    } else {
        exp_scalar(x) - 1.0
    }
}

/// 2^n for an integer-valued `n` in [-126, 128] as two factors whose
/// exponent fields hold (2^128 alone would not).
#[inline]
fn powers_of_two(n: f32) -> (f32, f32) {
    let n = n as i32;
    let half = n / 2;
    let power = |k: i32| f32::from_bits(((k + 127) as u32) << 23);
    (power(half), power(n - half))
}

#[cfg(target_arch = "x86_64")]
mod avx2 {
    use super::*;
    use std::arch::x86_64::*;

    /// `exp8` (or `exp_m1_8` when `M1`) over `values` eight at a time, the
    /// tail through a padded block (same lanes, so the same bits wherever a
    /// value sits).
    #[target_feature(enable = "avx2,fma")]
    pub(super) fn for_lanes<const M1: bool>(values: &mut [f32]) {
        let f = |v| if M1 { exp_m1_8(v) } else { exp8(v) };
        let mut chunks = values.chunks_exact_mut(8);
        for chunk in &mut chunks {
            // SAFETY: the chunk holds exactly 8 floats.
            unsafe { _mm256_storeu_ps(chunk.as_mut_ptr(), f(_mm256_loadu_ps(chunk.as_ptr()))) };
        }
        let tail = chunks.into_remainder();
        if !tail.is_empty() {
            let mut block = [0.0f32; 8];
            block[..tail.len()].copy_from_slice(tail);
            // SAFETY: `block` holds exactly 8 floats.
            unsafe { _mm256_storeu_ps(block.as_mut_ptr(), f(_mm256_loadu_ps(block.as_ptr()))) };
            tail.copy_from_slice(&block[..tail.len()]);
        }
    }

    #[target_feature(enable = "avx2,fma")]
    fn exp8(x: __m256) -> __m256 {
        let c = _mm256_min_ps(_mm256_max_ps(x, _mm256_set1_ps(EXP_MIN)), _mm256_set1_ps(EXP_MAX));
        let n = _mm256_round_ps(
            _mm256_mul_ps(c, _mm256_set1_ps(LOG2_E)),
            _MM_FROUND_TO_NEAREST_INT | _MM_FROUND_NO_EXC,
        );
        let r = _mm256_fmadd_ps(
            n,
            _mm256_set1_ps(-LN2_LO),
            _mm256_fmadd_ps(n, _mm256_set1_ps(-LN2_HI), c),
        );
        let mut p = _mm256_set1_ps(EXP_TAIL[0]);
        for &k in &EXP_TAIL[1..] {
            p = _mm256_fmadd_ps(p, r, _mm256_set1_ps(k));
        }
        let e = _mm256_add_ps(_mm256_fmadd_ps(_mm256_mul_ps(p, r), r, r), _mm256_set1_ps(1.0));
        // 2^n as the product of two powers whose exponent fields fit.
        let ni = _mm256_cvtps_epi32(n);
        let half = _mm256_srai_epi32(_mm256_add_epi32(ni, _mm256_srli_epi32(ni, 31)), 1);
        let bias = _mm256_set1_epi32(127);
        let p1 = _mm256_castsi256_ps(_mm256_slli_epi32(_mm256_add_epi32(half, bias), 23));
        let p2 = _mm256_castsi256_ps(_mm256_slli_epi32(
            _mm256_add_epi32(_mm256_sub_epi32(ni, half), bias),
            23,
        ));
        let scaled = _mm256_mul_ps(_mm256_mul_ps(e, p1), p2);
        // Out of range: 0 below, infinity above; NaN kept.
        let below = _mm256_cmp_ps(x, _mm256_set1_ps(EXP_MIN), _CMP_LT_OQ);
        let above = _mm256_cmp_ps(x, _mm256_set1_ps(EXP_MAX), _CMP_GT_OQ);
        let nan = _mm256_cmp_ps(x, x, _CMP_UNORD_Q);
        let out = _mm256_andnot_ps(below, scaled);
        let out = _mm256_blendv_ps(out, _mm256_set1_ps(f32::INFINITY), above);
        _mm256_blendv_ps(out, x, nan)
    }

    #[target_feature(enable = "avx2,fma")]
    fn exp_m1_8(x: __m256) -> __m256 {
        let mut p = _mm256_set1_ps(EXPM1_TAIL[0]);
        for &k in &EXPM1_TAIL[1..] {
            p = _mm256_fmadd_ps(p, x, _mm256_set1_ps(k));
        }
        let series = _mm256_fmadd_ps(_mm256_mul_ps(p, x), x, x);
        let shifted = _mm256_sub_ps(exp8(x), _mm256_set1_ps(1.0));
        let abs = _mm256_andnot_ps(_mm256_set1_ps(-0.0), x);
        let small = _mm256_cmp_ps(abs, _mm256_set1_ps(EXPM1_SERIES), _CMP_LT_OQ);
        _mm256_blendv_ps(shifted, series, small)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::rng::Rng;

    /// Units in the last place between `got` and the exact `want`.
    fn ulps(got: f32, want: f64) -> f64 {
        let w = want as f32;
        if got == w {
            return 0.0;
        }
        let ulp = (f32::from_bits(w.abs().to_bits() + 1) - w.abs()) as f64;
        (got as f64 - want).abs() / ulp
    }

    fn inputs(lo: f32, hi: f32) -> Vec<f32> {
        let mut rng = Rng::new(11, 0);
        (0..20_000).map(|_| lo + (hi - lo) * rng.f32()).collect()
    }

    /// The vector kernel on `xs` equals the scalar one to the bit, and each
    /// result is within `bound(x)` ulps of the exact value (`None`: unchecked).
    fn check(
        xs: &[f32],
        vector: fn(&mut [f32]),
        scalar: fn(f32) -> f32,
        exact: fn(f64) -> f64,
        bound: impl Fn(f32) -> Option<f64>,
    ) {
        let mut fast = xs.to_vec();
        vector(&mut fast);
        for (&x, &y) in xs.iter().zip(&fast) {
            assert_eq!(y.to_bits(), scalar(x).to_bits(), "at {x}: lanes and scalar differ");
            let want = exact(x as f64);
            if let Some(b) = bound(x) {
                assert!(ulps(y, want) <= b, "at {x}: {y}, exact {want}");
            }
        }
    }

    #[test]
    fn exp_is_within_two_ulps_and_the_paths_agree_to_the_bit() {
        // Results under the smallest normal float may be flushed: not checked.
        let normal = |x: f32| ((x as f64).exp() >= f32::MIN_POSITIVE as f64).then_some(2.0);
        check(&inputs(-87.0, 88.0), exp, exp_scalar, f64::exp, normal);
    }

    #[test]
    fn exp_m1_keeps_its_digits_near_zero_and_the_paths_agree_to_the_bit() {
        let mut xs = inputs(-20.0, 3.0);
        xs.extend(inputs(-1e-3, 1e-3));
        xs.extend(inputs(-1.0, 1.0));
        // Above the series, e^x - 1 inherits e^x's error on a value up to half as large.
        let bound = |x: f32| Some(if x < EXPM1_SERIES { 2.0 } else { 5.0 });
        check(&xs, exp_m1, exp_m1_scalar, f64::exp_m1, bound);
    }

    #[test]
    fn exp_ends_are_zero_infinity_and_nan() {
        let mut v = [
            -200.0,
            f32::NEG_INFINITY,
            100.0,
            f32::INFINITY,
            f32::NAN,
            0.0,
            -0.0,
            1.0,
            88.7,
        ];
        exp(&mut v);
        assert_eq!(&v[..4], &[0.0, 0.0, f32::INFINITY, f32::INFINITY]);
        assert!(v[4].is_nan());
        assert_eq!(&v[5..7], &[1.0, 1.0]);
        assert!(ulps(v[7], 1f64.exp()) <= 2.0);
        assert!(v[8].is_finite() && ulps(v[8], (88.7f32 as f64).exp()) <= 2.0);
        let mut m = [f32::NEG_INFINITY, -200.0, 0.0, f32::NAN];
        exp_m1(&mut m);
        assert_eq!(&m[..3], &[-1.0, -1.0, 0.0]);
        assert!(m[3].is_nan());
    }
}
