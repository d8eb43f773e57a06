//! Safe tile kernels of the fused MLP, dispatched between AVX2+FMA and the
//! portable path.
//!
//! A tile is a feature-major block `rows x cols` with row stride `ld` (one row
//! per neuron, one column per sample). Column counts are padded by the caller
//! to multiples of [`COL_BLOCK`]. Every entry point checks all extents against
//! the slices before touching memory, so the unsafe kernels below it only see
//! in-bounds pointers.

#[cfg(target_arch = "x86_64")]
use super::mlp_avx2;
use super::mlp_scalar;

/// Samples per register block: tile column counts must be multiples of this.
pub const COL_BLOCK: usize = 16;
/// Lanes of a weight-gradient partial sum (one `__m256`).
pub const LANES: usize = 8;

/// Which kernel set runs the MLP.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum MlpKernel {
    /// 256-bit AVX2 with fused multiply-add (run-time detected).
    Avx2Fma,
    /// Portable Rust, vectorised only by the compiler's baseline target.
    Scalar,
}

impl MlpKernel {
    /// The fastest kernel this CPU supports.
    pub fn best() -> Self {
        if super::avx2_fma_available() {
            MlpKernel::Avx2Fma
        } else {
            MlpKernel::Scalar
        }
    }

    /// `self` if this CPU supports it, else the portable kernel.
    pub fn supported(self) -> Self {
        match self {
            MlpKernel::Avx2Fma if super::avx2_fma_available() => MlpKernel::Avx2Fma,
            _ => MlpKernel::Scalar,
        }
    }

    /// Short name for logs and benchmarks.
    pub fn name(self) -> &'static str {
        match self {
            MlpKernel::Avx2Fma => "avx2+fma",
            MlpKernel::Scalar => "scalar",
        }
    }

    /// True when the AVX2 path may run (re-checked so a forged value is safe).
    #[inline]
    fn use_avx2(self) -> bool {
        self == MlpKernel::Avx2Fma && super::avx2_fma_available()
    }
}

/// What happens to each finished sum before it is stored.
#[derive(Clone, Copy, Debug)]
pub enum Epilogue<'a> {
    /// Store as is.
    Linear,
    /// Store `max(sum, 0)`.
    Relu,
    /// Store the sum where `mask[r * ld + c] > 0`, else 0 (ReLU backward).
    MaskPositive { mask: &'a [f32], ld: usize },
}

/// One matrix product on a tile: `y[r][c] = epi(bias[r] + sum_k A(r, k) * x[k][c])`
/// for `r < rows`, `c < cols`, where `A(r, k) = a[r * a_rs + k * a_ks]`.
///
/// With `a_rs = k_len, a_ks = 1` this is `W x` for a row-major `W`; with
/// `a_rs = 1, a_ks = rows` it is `W^T x` without transposing `W`.
#[allow(clippy::too_many_arguments)]
pub fn gemm_tile(
    kernel: MlpKernel,
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
    assert!(
        cols.is_multiple_of(COL_BLOCK),
        "gemm_tile: cols {cols} not a multiple of {COL_BLOCK}"
    );
    if rows == 0 || cols == 0 {
        return;
    }
    if k_len > 0 {
        assert!(
            (rows - 1) * a_rs + (k_len - 1) * a_ks < a.len(),
            "gemm_tile: A out of bounds"
        );
        assert!((k_len - 1) * ldx + cols <= x.len(), "gemm_tile: x out of bounds");
    }
    if let Some(b) = bias {
        assert!(b.len() >= rows, "gemm_tile: bias shorter than rows");
    }
    assert!((rows - 1) * ldy + cols <= y.len(), "gemm_tile: y out of bounds");
    if let Epilogue::MaskPositive { mask, ld } = epi {
        assert!((rows - 1) * ld + cols <= mask.len(), "gemm_tile: mask out of bounds");
    }
    #[cfg(target_arch = "x86_64")]
    if kernel.use_avx2() {
        let (epi_code, m, ldm) = match epi {
            Epilogue::Linear => (mlp_avx2::EPI_LINEAR, std::ptr::null(), 0),
            Epilogue::Relu => (mlp_avx2::EPI_RELU, std::ptr::null(), 0),
            Epilogue::MaskPositive { mask, ld } => (mlp_avx2::EPI_MASK, mask.as_ptr(), ld),
        };
        let args = mlp_avx2::GemmArgs {
            a: a.as_ptr(),
            a_rs,
            a_ks,
            bias: bias.map_or(std::ptr::null(), |b| b.as_ptr()),
            k_len,
            x: x.as_ptr(),
            ldx,
            rows,
            cols,
            y: y.as_mut_ptr(),
            ldy,
            epi: epi_code,
            m,
            ldm,
        };
        // SAFETY: AVX2+FMA detected by use_avx2; every extent was checked
        // against its slice above; y is an exclusive borrow so it aliases
        // none of the inputs.
        unsafe { mlp_avx2::gemm_tile(&args) };
        return;
    }
    let _ = kernel;
    mlp_scalar::gemm_tile(a, a_rs, a_ks, bias, k_len, x, ldx, rows, cols, epi, y, ldy);
}

/// Weight-gradient partials of one tile: for `o < out`, `i < inp`, lane `l`,
/// `dwv[(o * inp + i) * 8 + l] += sum_j dz[o][8j + l] * x[i][8j + l]` over the
/// first `cols` columns. Reduce the lanes with [`reduce_lanes`] at the end.
#[allow(clippy::too_many_arguments)]
pub fn grad_tile(
    kernel: MlpKernel,
    dz: &[f32],
    ldz: usize,
    x: &[f32],
    ldx: usize,
    out: usize,
    inp: usize,
    cols: usize,
    dwv: &mut [f32],
) {
    assert!(
        cols.is_multiple_of(LANES),
        "grad_tile: cols {cols} not a multiple of {LANES}"
    );
    if out == 0 || inp == 0 || cols == 0 {
        return;
    }
    assert!((out - 1) * ldz + cols <= dz.len(), "grad_tile: dz out of bounds");
    assert!((inp - 1) * ldx + cols <= x.len(), "grad_tile: x out of bounds");
    assert!(out * inp * LANES <= dwv.len(), "grad_tile: partials too short");
    #[cfg(target_arch = "x86_64")]
    if kernel.use_avx2() {
        let args = mlp_avx2::GradArgs {
            dz: dz.as_ptr(),
            ldz,
            x: x.as_ptr(),
            ldx,
            out,
            inp,
            cols,
            dwv: dwv.as_mut_ptr(),
        };
        // SAFETY: AVX2+FMA detected; extents checked above; dwv is exclusive.
        unsafe { mlp_avx2::grad_tile(&args) };
        return;
    }
    let _ = kernel;
    mlp_scalar::grad_tile(dz, ldz, x, ldx, out, inp, cols, dwv);
}

/// Bias-gradient partials: `dbv[r * 8 + l] += sum_j dz[r][8j + l]`.
pub fn rowsum_tile(kernel: MlpKernel, dz: &[f32], ldz: usize, rows: usize, cols: usize, dbv: &mut [f32]) {
    assert!(
        cols.is_multiple_of(LANES),
        "rowsum_tile: cols {cols} not a multiple of {LANES}"
    );
    if rows == 0 || cols == 0 {
        return;
    }
    assert!((rows - 1) * ldz + cols <= dz.len(), "rowsum_tile: dz out of bounds");
    assert!(rows * LANES <= dbv.len(), "rowsum_tile: partials too short");
    #[cfg(target_arch = "x86_64")]
    if kernel.use_avx2() {
        // SAFETY: AVX2+FMA detected; extents checked above; dbv is exclusive.
        unsafe { mlp_avx2::rowsum_tile(dz.as_ptr(), ldz, rows, cols, dbv.as_mut_ptr()) };
        return;
    }
    let _ = kernel;
    mlp_scalar::rowsum_tile(dz, ldz, rows, cols, dbv);
}

/// `out[j] += sum of the 8 lanes of partials[j]`, in a fixed order.
pub fn reduce_lanes(partials: &[f32], out: &mut [f32]) {
    assert!(partials.len() >= out.len() * LANES, "reduce_lanes: partials too short");
    for (o, p) in out.iter_mut().zip(partials.chunks_exact(LANES)) {
        // Pairwise tree: the same order on every kernel and every run.
        let s = ((p[0] + p[4]) + (p[2] + p[6])) + ((p[1] + p[5]) + (p[3] + p[7]));
        *o += s;
    }
}
