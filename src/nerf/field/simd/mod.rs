//! The only home of `unsafe` and `std::arch`: AVX2+FMA kernels chosen at run
//! time with portable fallbacks.
//!
//! Besides the per-module kernels this root offers a few generic vector
//! helpers ([`dot`], [`axpy`]), the run-time feature check
//! [`avx2_fma_available`], [`vectorised`] for plain lane loops elsewhere,
//! and [`measure_fma_peak_gflops`] for benchmarks.

pub mod adam;
pub mod exp;
pub mod grid;
#[cfg(target_arch = "x86_64")]
mod mlp_avx2;
mod mlp_scalar;
pub mod mlp_tile;

use std::time::Instant;

/// Treat subnormal floats as zero on the calling thread (threads it starts
/// afterwards inherit the setting). Tiny gradients late in training
/// are subnormal, and x86 handles each through a microcode assist about a
/// hundred times slower than a normal FMA: measured on the cabinet scan,
/// training fell from 690 k to 85 k samples/s once they appeared. Values
/// that small carry nothing a 32-bit step could use.
pub fn flush_subnormals() {
    #[cfg(target_arch = "x86_64")]
    {
        // Flush-to-zero (results) and denormals-are-zero (inputs).
        const FTZ_DAZ: u32 = 0x8040;
        let mut csr: u32 = 0;
        // SAFETY: SSE is part of x86_64; the control register is read into
        // and loaded from a local, and only the two flags above change.
        unsafe {
            std::arch::asm!("stmxcsr [{}]", in(reg) &mut csr as *mut u32, options(nostack, preserves_flags));
            csr |= FTZ_DAZ;
            std::arch::asm!("ldmxcsr [{}]", in(reg) &csr as *const u32, options(nostack, preserves_flags, readonly));
        }
    }
}

/// [`flush_subnormals`] on the calling thread and on every worker of the
/// current rayon pool (already started threads do not see a later change).
pub fn flush_subnormals_on_all_threads() {
    flush_subnormals();
    rayon::broadcast(|_| flush_subnormals());
}

/// True when this CPU supports AVX2 and FMA (checked once, then cached by std).
#[inline]
pub fn avx2_fma_available() -> bool {
    #[cfg(target_arch = "x86_64")]
    {
        is_x86_feature_detected!("avx2") && is_x86_feature_detected!("fma")
    }
    #[cfg(not(target_arch = "x86_64"))]
    {
        false
    }
}

/// Runs `f`, compiled for AVX2 and FMA when the CPU has them: a branch-free
/// lane loop inlined into `f` (`#[inline(always)]`) then vectorises 8 lanes
/// wide. For loops outside this module that need no intrinsics; the same
/// arithmetic either way (Rust never fuses a multiply and an add by itself).
#[inline(always)]
pub fn vectorised<R>(f: impl FnOnce() -> R) -> R {
    #[cfg(target_arch = "x86_64")]
    if avx2_fma_available() {
        // SAFETY: AVX2 and FMA were detected just above.
        return unsafe { with_avx2_fma(f) };
    }
    f()
}

/// `f` compiled with AVX2 and FMA enabled (see [`vectorised`]).
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2,fma")]
fn with_avx2_fma<R>(f: impl FnOnce() -> R) -> R {
    f()
}

/// Dot product of two equal-length slices (fixed summation order per length).
pub fn dot(a: &[f32], b: &[f32]) -> f32 {
    assert_eq!(a.len(), b.len(), "dot: slices differ in length");
    #[cfg(target_arch = "x86_64")]
    if avx2_fma_available() {
        // SAFETY: AVX2 and FMA were detected just above; lengths are equal.
        return unsafe { avx2::dot(a, b) };
    }
    let mut lanes = [0.0f32; 8];
    let chunks = a.len() / 8;
    for c in 0..chunks {
        for l in 0..8 {
            lanes[l] += a[c * 8 + l] * b[c * 8 + l];
        }
    }
    let mut sum = lanes.iter().sum::<f32>();
    for i in chunks * 8..a.len() {
        sum += a[i] * b[i];
    }
    sum
}

/// `y += alpha * x` over equal-length slices.
pub fn axpy(alpha: f32, x: &[f32], y: &mut [f32]) {
    assert_eq!(x.len(), y.len(), "axpy: slices differ in length");
    #[cfg(target_arch = "x86_64")]
    if avx2_fma_available() {
        // SAFETY: AVX2 and FMA were detected just above; lengths are equal.
        unsafe { avx2::axpy(alpha, x, y) };
        return;
    }
    for (yi, xi) in y.iter_mut().zip(x) {
        *yi += alpha * xi;
    }
}

/// Single-thread f32 FMA throughput in GFLOP/s (one FMA = 2 FLOP): the best
/// of short register-only rounds over about `seconds`, so time stolen by
/// other processes on a shared machine does not lower it; 0 without AVX2+FMA.
pub fn measure_fma_peak_gflops(seconds: f64) -> f64 {
    #[cfg(target_arch = "x86_64")]
    if avx2_fma_available() {
        use std::hint::black_box;
        const ITERS: u64 = 1 << 18;
        // Opaque arguments stop the compiler from hoisting the pure call or
        // folding any accumulator.
        let round = || {
            let t = Instant::now();
            // SAFETY: AVX2 and FMA were detected just above.
            black_box(unsafe { avx2::fma_loop(black_box(ITERS), black_box(0.999_999), black_box(1e-6)) });
            t.elapsed().as_secs_f64()
        };
        round(); // warm up the core clock
        let start = Instant::now();
        let mut best = f64::INFINITY;
        while best.is_infinite() || start.elapsed().as_secs_f64() < seconds {
            best = best.min(round());
        }
        return ITERS as f64 * avx2::FMA_LOOP_FLOPS_PER_ITER / best.max(1e-9) * 1e-9;
    }
    let _ = seconds;
    0.0
}

#[cfg(target_arch = "x86_64")]
mod avx2 {
    use std::arch::x86_64::*;

    /// Independent accumulators in [`fma_loop`]: FMA latency (4) times the
    /// two FMA ports is 8; 12 leaves margin for slower cores.
    const ACCS: usize = 12;
    pub(super) const FMA_LOOP_FLOPS_PER_ITER: f64 = (ACCS * 8 * 2) as f64;

    #[target_feature(enable = "avx2,fma")]
    pub(super) unsafe fn dot(a: &[f32], b: &[f32]) -> f32 {
        let n = a.len().min(b.len());
        let (pa, pb) = (a.as_ptr(), b.as_ptr());
        let mut acc = [_mm256_setzero_ps(); 4];
        let mut i = 0;
        while i + 32 <= n {
            for (k, s) in acc.iter_mut().enumerate() {
                // SAFETY: i + 8k + 8 <= n, within both slices.
                *s = unsafe {
                    _mm256_fmadd_ps(
                        _mm256_loadu_ps(pa.add(i + 8 * k)),
                        _mm256_loadu_ps(pb.add(i + 8 * k)),
                        *s,
                    )
                };
            }
            i += 32;
        }
        while i + 8 <= n {
            // SAFETY: i + 8 <= n.
            acc[0] = unsafe { _mm256_fmadd_ps(_mm256_loadu_ps(pa.add(i)), _mm256_loadu_ps(pb.add(i)), acc[0]) };
            i += 8;
        }
        let v = _mm256_add_ps(_mm256_add_ps(acc[0], acc[1]), _mm256_add_ps(acc[2], acc[3]));
        let mut sum = hsum(v);
        for j in i..n {
            sum += a[j] * b[j];
        }
        sum
    }

    #[target_feature(enable = "avx2,fma")]
    pub(super) unsafe fn axpy(alpha: f32, x: &[f32], y: &mut [f32]) {
        let n = x.len().min(y.len());
        let a = _mm256_set1_ps(alpha);
        let (px, py) = (x.as_ptr(), y.as_mut_ptr());
        let mut i = 0;
        while i + 8 <= n {
            // SAFETY: i + 8 <= n, within both slices; x and y cannot alias
            // (shared and exclusive borrows).
            unsafe {
                let v = _mm256_fmadd_ps(a, _mm256_loadu_ps(px.add(i)), _mm256_loadu_ps(py.add(i)));
                _mm256_storeu_ps(py.add(i), v);
            }
            i += 8;
        }
        for j in i..n {
            y[j] = alpha.mul_add(x[j], y[j]);
        }
    }

    /// Horizontal sum of the 8 lanes in a fixed order.
    #[target_feature(enable = "avx2,fma")]
    pub(crate) fn hsum(v: __m256) -> f32 {
        let s = _mm_add_ps(_mm256_castps256_ps128(v), _mm256_extractf128_ps(v, 1));
        let s = _mm_add_ps(s, _mm_movehl_ps(s, s));
        let s = _mm_add_ss(s, _mm_shuffle_ps(s, s, 1));
        _mm_cvtss_f32(s)
    }

    /// `iters` rounds of ACCS independent FMAs `a = a * m + c` on registers.
    #[target_feature(enable = "avx2,fma")]
    pub(super) fn fma_loop(iters: u64, m: f32, c: f32) -> f32 {
        // With m < 1 the values contract towards c / (1 - m): they stay
        // normal (no denormal slow path) and finite.
        let m = _mm256_set1_ps(m);
        let c = _mm256_set1_ps(c);
        let mut acc = [_mm256_setzero_ps(); ACCS];
        for (k, a) in acc.iter_mut().enumerate() {
            *a = _mm256_set1_ps(0.5 + 0.01 * k as f32);
        }
        for _ in 0..iters {
            for a in acc.iter_mut() {
                *a = _mm256_fmadd_ps(*a, m, c);
            }
        }
        let mut s = _mm256_setzero_ps();
        for a in acc {
            s = _mm256_add_ps(s, a);
        }
        hsum(s)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::rng::Rng;

    #[test]
    fn subnormal_results_are_flushed_to_zero_on_every_worker() {
        let tiny = || std::hint::black_box(1e-30f32) * std::hint::black_box(1e-10f32);
        // Without the flag the product is subnormal, not zero.
        let plain = std::thread::spawn(tiny).join().unwrap();
        assert!(plain > 0.0 && !plain.is_normal(), "{plain}");
        let pool = rayon::ThreadPoolBuilder::new().num_threads(3).build().unwrap();
        let products = pool.install(|| {
            flush_subnormals_on_all_threads();
            rayon::broadcast(|_| tiny())
        });
        assert_eq!(products, vec![0.0; 3]);
    }

    fn random(n: usize, rng: &mut Rng) -> Vec<f32> {
        (0..n).map(|_| rng.f32() * 2.0 - 1.0).collect()
    }

    #[test]
    fn dot_and_axpy_match_f64_reference_for_all_tail_lengths() {
        let mut rng = Rng::new(3, 0);
        for n in 0..70 {
            let a = random(n, &mut rng);
            let b = random(n, &mut rng);
            let want: f64 = a.iter().zip(&b).map(|(x, y)| *x as f64 * *y as f64).sum();
            let scale: f64 = a.iter().zip(&b).map(|(x, y)| (*x as f64 * *y as f64).abs()).sum();
            assert!((dot(&a, &b) as f64 - want).abs() <= 1e-6 * (scale + 1.0), "dot n={n}");
            let mut y = b.clone();
            axpy(0.75, &a, &mut y);
            for i in 0..n {
                let w = b[i] as f64 + 0.75 * a[i] as f64;
                assert!((y[i] as f64 - w).abs() <= 1e-6, "axpy n={n} i={i}");
            }
        }
    }

    #[test]
    fn fma_peak_is_positive_when_avx2_present() {
        let g = measure_fma_peak_gflops(0.01);
        if avx2_fma_available() {
            assert!(g > 0.0 && g.is_finite(), "measured {g} GFLOP/s");
        } else {
            assert_eq!(g, 0.0);
        }
    }
}
