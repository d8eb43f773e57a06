//! Small fully connected networks (ReLU hidden layers, linear output) with
//! fused, cache-blocked forward and backward passes over feature-major
//! batches.
//!
//! Batches are cut into tiles of [`TILE`] samples and every layer of a tile
//! runs before the next tile starts, so a tile's activations stay in cache.
//! Parameter layout (stored as is in the model file): for each layer in
//! order, its weights row-major `[out][in]`, then its biases `[out]`.
//!
//! Results are deterministic: the same parameters, inputs and `n` give
//! bit-identical outputs and gradients on a given kernel, whatever the
//! workspace was used for before.

use thiserror::Error;

pub use crate::nerf::field::simd::mlp_tile::MlpKernel;
use crate::nerf::field::simd::mlp_tile::{self, Epilogue, COL_BLOCK, LANES};
use crate::rng::Rng;

/// Samples per tile (a multiple of the kernels' column block).
pub const TILE: usize = 128;
/// Largest layer width accepted (caps sizes read from a model file).
pub const MAX_WIDTH: usize = 4096;
/// Largest number of hidden layers accepted.
pub const MAX_HIDDEN_LAYERS: usize = 16;

/// Layer widths of a network: `input -> hidden... (ReLU) -> output (linear)`.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct MlpConfig {
    /// Input features per sample.
    pub input: usize,
    /// Widths of the ReLU hidden layers, in order.
    pub hidden: Vec<usize>,
    /// Linear outputs per sample.
    pub output: usize,
}

/// A network description or parameter vector that cannot be used.
#[derive(Debug, Error, PartialEq)]
pub enum MlpError {
    /// A layer has no neurons.
    #[error("MLP layer {layer} has width 0")]
    ZeroWidth { layer: usize },
    /// A layer is wider than [`MAX_WIDTH`].
    #[error("MLP layer {layer} has width {width}, more than the maximum {MAX_WIDTH}")]
    TooWide { layer: usize, width: usize },
    /// More than [`MAX_HIDDEN_LAYERS`] hidden layers.
    #[error("MLP has {count} hidden layers, more than the maximum {MAX_HIDDEN_LAYERS}")]
    TooManyLayers { count: usize },
    /// The parameter vector's length does not fit the widths.
    #[error("MLP parameter vector has {found} values, expected {expected} for widths {widths:?}")]
    ParamCount {
        expected: usize,
        found: usize,
        widths: Vec<usize>,
    },
    /// A parameter is NaN or infinite.
    #[error("MLP parameter {index} is not finite ({value})")]
    NonFinite { index: usize, value: f32 },
}

impl MlpConfig {
    /// All widths in order, input first and output last.
    pub fn widths(&self) -> Vec<usize> {
        let mut w = Vec::with_capacity(self.hidden.len() + 2);
        w.push(self.input);
        w.extend_from_slice(&self.hidden);
        w.push(self.output);
        w
    }

    /// Checks the widths and returns the number of parameters.
    pub fn param_count(&self) -> Result<usize, MlpError> {
        if self.hidden.len() > MAX_HIDDEN_LAYERS {
            return Err(MlpError::TooManyLayers {
                count: self.hidden.len(),
            });
        }
        let widths = self.widths();
        for (layer, &width) in widths.iter().enumerate() {
            if width == 0 {
                return Err(MlpError::ZeroWidth { layer });
            }
            if width > MAX_WIDTH {
                return Err(MlpError::TooWide { layer, width });
            }
        }
        // Widths are capped, so these products cannot overflow.
        Ok(widths.windows(2).map(|p| (p[0] + 1) * p[1]).sum())
    }
}

/// One linear layer's shape and where its parameters sit in `params`.
#[derive(Clone, Copy, Debug)]
struct Layer {
    inp: usize,
    out: usize,
    w: usize,
    b: usize,
    relu: bool,
    /// Row of this layer's input within a training tile of activations.
    act_row: usize,
}

/// A fully connected network with all weights and biases in one vector.
#[derive(Clone, Debug)]
pub struct Mlp {
    /// Layer widths.
    pub config: MlpConfig,
    /// Weights and biases, layer by layer (see the module docs for the layout).
    pub params: Vec<f32>,
    layers: Vec<Layer>,
    /// Rows of one training tile: the inputs of every layer stacked.
    act_rows: usize,
    max_width: usize,
    kernel: MlpKernel,
}

impl Mlp {
    /// New network with He/Kaiming-uniform weights and zero biases.
    ///
    /// Hidden layers use the ReLU gain (bound `sqrt(6 / fan_in)`), the linear
    /// output layer gain 1 (bound `sqrt(3 / fan_in)`). Panics on widths that
    /// [`MlpConfig::param_count`] rejects.
    pub fn new(config: MlpConfig, rng: &mut Rng) -> Mlp {
        let count = match config.param_count() {
            Ok(c) => c,
            Err(e) => panic!("Mlp::new: {e}"),
        };
        let mut params = vec![0.0f32; count];
        let layers = layout(&config);
        for l in &layers {
            let gain = if l.relu { 2.0 } else { 1.0 };
            let bound = (3.0 * gain / l.inp as f64).sqrt() as f32;
            for w in &mut params[l.w..l.w + l.inp * l.out] {
                *w = (2.0 * rng.f32() - 1.0) * bound;
            }
        }
        Self::build(config, params)
    }

    /// Network from a stored parameter vector (e.g. read from the model file).
    pub fn from_params(config: MlpConfig, params: Vec<f32>) -> Result<Mlp, MlpError> {
        let expected = config.param_count()?;
        if params.len() != expected {
            return Err(MlpError::ParamCount {
                expected,
                found: params.len(),
                widths: config.widths(),
            });
        }
        if let Some((index, &value)) = params.iter().enumerate().find(|(_, v)| !v.is_finite()) {
            return Err(MlpError::NonFinite { index, value });
        }
        Ok(Self::build(config, params))
    }

    fn build(config: MlpConfig, params: Vec<f32>) -> Mlp {
        let layers = layout(&config);
        let act_rows = layers.iter().map(|l| l.inp).sum();
        let max_width = config.widths().into_iter().max().unwrap_or(1);
        Mlp {
            config,
            params,
            layers,
            act_rows,
            max_width,
            kernel: MlpKernel::best(),
        }
    }

    /// Number of weights and biases.
    pub fn param_count(&self) -> usize {
        self.layers.last().map_or(0, |l| l.b + l.out)
    }

    /// Multiply-add FLOPs (2 per weight) of one sample's forward pass.
    pub fn flops_forward_per_sample(&self) -> usize {
        self.layers.iter().map(|l| 2 * l.inp * l.out).sum()
    }

    /// FLOPs of one sample's backward pass with `d_input` requested: weight
    /// gradients plus input gradients of every layer (twice the forward).
    pub fn flops_backward_per_sample(&self) -> usize {
        2 * self.flops_forward_per_sample()
    }

    /// The kernel set in use.
    pub fn kernel(&self) -> MlpKernel {
        self.kernel
    }

    /// Selects a kernel set (falls back to scalar if the CPU lacks it);
    /// returns the one now in use.
    pub fn set_kernel(&mut self, kernel: MlpKernel) -> MlpKernel {
        self.kernel = kernel.supported();
        self.kernel
    }

    /// Inference: `input[i * n + b]` is feature `i` of sample `b`; writes
    /// `output[o * n + b]`. Slices may be longer than `width * n`.
    pub fn forward(&self, input: &[f32], n: usize, ws: &mut MlpWorkspace, output: &mut [f32]) {
        self.forward_leading(input, n, self.config.output, ws, output);
    }

    /// Inference of the first `rows` outputs only (the last layer computes
    /// just those): `output[o * n + b]` for `o < rows`, bit for bit what
    /// [`Mlp::forward`] gives there. A density-only pass needs one of the
    /// density network's outputs.
    pub fn forward_leading(&self, input: &[f32], n: usize, rows: usize, ws: &mut MlpWorkspace, output: &mut [f32]) {
        let rows = rows.min(self.config.output);
        self.check_io(input.len(), output.len(), n, rows);
        let tile_len = self.max_width * TILE;
        ws.tile_a.ensure(tile_len);
        ws.tile_b.ensure(tile_len);
        let (mut src, mut dst) = (ws.tile_a.slice_mut(tile_len), ws.tile_b.slice_mut(tile_len));
        for t0 in (0..n).step_by(TILE) {
            let valid = (n - t0).min(TILE);
            let cols = valid.next_multiple_of(COL_BLOCK);
            gather(input, n, self.config.input, t0, valid, cols, src);
            for (k, l) in self.layers.iter().enumerate() {
                let out_rows = if k + 1 == self.layers.len() { rows } else { l.out };
                self.layer_forward(l, out_rows, src, cols, dst);
                std::mem::swap(&mut src, &mut dst);
            }
            scatter(src, rows, t0, valid, output, n);
        }
    }

    /// Training forward: like [`Mlp::forward`], and keeps every layer's input
    /// in `ws` for [`Mlp::backward`].
    pub fn forward_train(&self, input: &[f32], n: usize, ws: &mut MlpWorkspace, output: &mut [f32]) {
        self.check_io(input.len(), output.len(), n, self.config.output);
        let tiles = n.div_ceil(TILE);
        let tile_stride = self.act_rows * TILE;
        ws.acts.ensure(tiles * tile_stride);
        ws.tile_a.ensure(self.max_width * TILE);
        ws.trained = Some(self.shape_key(n));
        let acts = ws.acts.slice_mut(tiles * tile_stride);
        let out_tile = ws.tile_a.slice_mut(self.max_width * TILE);
        for (tile, t0) in (0..n).step_by(TILE).enumerate() {
            let valid = (n - t0).min(TILE);
            let cols = valid.next_multiple_of(COL_BLOCK);
            let tile_acts = &mut acts[tile * tile_stride..][..tile_stride];
            gather(input, n, self.config.input, t0, valid, cols, tile_acts);
            for (k, l) in self.layers.iter().enumerate() {
                let (before, after) = tile_acts.split_at_mut((l.act_row + l.inp) * TILE);
                let src = &before[l.act_row * TILE..];
                let dst = if k + 1 < self.layers.len() {
                    after
                } else {
                    &mut *out_tile
                };
                self.layer_forward(l, l.out, src, cols, dst);
            }
            scatter(out_tile, self.config.output, t0, valid, output, n);
        }
    }

    /// Backward of the last [`Mlp::forward_train`] on `ws` (same `n`):
    /// `d_output[o * n + b]`; ADDS the parameter gradients into `grad`
    /// (length [`Mlp::param_count`]) and, if given, WRITES `d_input[i * n + b]`.
    pub fn backward(
        &self,
        ws: &mut MlpWorkspace,
        d_output: &[f32],
        n: usize,
        grad: &mut [f32],
        d_input: Option<&mut [f32]>,
    ) {
        let rows = self.config.input;
        self.backward_leading_inputs(ws, d_output, n, grad, d_input.map(|d| (d, rows)));
    }

    /// [`Mlp::backward`] writing only the first `rows` inputs' gradients
    /// (`d_input[i * n + b]` for `i < rows`): the colour network's direction
    /// inputs are not learnt, and skipping them saves a sixth of its backward.
    pub fn backward_leading_inputs(
        &self,
        ws: &mut MlpWorkspace,
        d_output: &[f32],
        n: usize,
        grad: &mut [f32],
        d_input: Option<(&mut [f32], usize)>,
    ) {
        assert!(
            ws.trained == Some(self.shape_key(n)),
            "Mlp::backward: the workspace holds no forward_train of this network with n = {n}"
        );
        assert!(
            d_output.len() >= self.config.output * n,
            "Mlp::backward: d_output shorter than output * n"
        );
        let count = self.param_count();
        assert_eq!(grad.len(), count, "Mlp::backward: grad length must equal param_count");
        if let Some((d, rows)) = &d_input {
            assert!(*rows <= self.config.input, "Mlp::backward: more input rows than inputs");
            assert!(d.len() >= rows * n, "Mlp::backward: d_input shorter than rows * n");
        }
        let mut d_input = d_input;
        let tile_len = self.max_width * TILE;
        let tile_stride = self.act_rows * TILE;
        ws.tile_a.ensure(tile_len);
        ws.tile_b.ensure(tile_len);
        ws.partials.ensure(count * LANES);
        let partials = ws.partials.slice_mut(count * LANES);
        partials.fill(0.0);
        let acts = ws.acts.slice(n.div_ceil(TILE) * tile_stride);
        let (mut dz, mut dx) = (ws.tile_a.slice_mut(tile_len), ws.tile_b.slice_mut(tile_len));
        let w_all = &self.params;
        for (tile, t0) in (0..n).step_by(TILE).enumerate() {
            let valid = (n - t0).min(TILE);
            let cols = valid.next_multiple_of(COL_BLOCK);
            let tile_acts = &acts[tile * tile_stride..][..tile_stride];
            gather(d_output, n, self.config.output, t0, valid, cols, dz);
            for (k, l) in self.layers.iter().enumerate().rev() {
                let x = &tile_acts[l.act_row * TILE..][..l.inp * TILE];
                let (dw, db) = partials[l.w * LANES..(l.b + l.out) * LANES].split_at_mut(l.inp * l.out * LANES);
                mlp_tile::grad_tile(self.kernel, dz, TILE, x, TILE, l.out, l.inp, cols, dw);
                mlp_tile::rowsum_tile(self.kernel, dz, TILE, l.out, cols, db);
                let w = &w_all[l.w..l.w + l.inp * l.out];
                if k > 0 {
                    // dz_prev = (W^T dz) where the layer's input was positive.
                    let epi = Epilogue::MaskPositive { mask: x, ld: TILE };
                    mlp_tile::gemm_tile(
                        self.kernel,
                        w,
                        1,
                        l.inp,
                        None,
                        l.out,
                        dz,
                        TILE,
                        l.inp,
                        cols,
                        epi,
                        dx,
                        TILE,
                    );
                    std::mem::swap(&mut dz, &mut dx);
                } else if let Some((d_in, rows)) = d_input.as_mut() {
                    mlp_tile::gemm_tile(
                        self.kernel,
                        w,
                        1,
                        l.inp,
                        None,
                        l.out,
                        dz,
                        TILE,
                        *rows,
                        cols,
                        Epilogue::Linear,
                        dx,
                        TILE,
                    );
                    scatter(dx, *rows, t0, valid, d_in, n);
                }
            }
        }
        mlp_tile::reduce_lanes(partials, grad);
    }

    /// One layer on one tile: `dst = act(W src + b)`.
    /// Layer `l`'s first `rows` outputs (weights are row-major, so they are
    /// the first `rows` rows).
    fn layer_forward(&self, l: &Layer, rows: usize, src: &[f32], cols: usize, dst: &mut [f32]) {
        let w = &self.params[l.w..l.w + l.inp * rows];
        let b = &self.params[l.b..l.b + rows];
        let epi = if l.relu { Epilogue::Relu } else { Epilogue::Linear };
        mlp_tile::gemm_tile(
            self.kernel,
            w,
            l.inp,
            1,
            Some(b),
            l.inp,
            src,
            TILE,
            rows,
            cols,
            epi,
            dst,
            TILE,
        );
    }

    /// Checks a pass over `n` samples that writes `rows` output rows.
    fn check_io(&self, input_len: usize, output_len: usize, n: usize, rows: usize) {
        assert_eq!(self.params.len(), self.param_count(), "Mlp: params length changed");
        assert!(input_len >= self.config.input * n, "Mlp: input shorter than input * n");
        assert!(output_len >= rows * n, "Mlp: output shorter than rows * n");
    }

    /// Identifies a forward_train so backward can refuse a mismatched one.
    fn shape_key(&self, n: usize) -> (usize, usize, usize, usize) {
        (n, self.act_rows, self.config.output, self.layers.len())
    }
}

/// Layer shapes and parameter offsets of a checked config.
fn layout(config: &MlpConfig) -> Vec<Layer> {
    let widths = config.widths();
    let mut layers = Vec::with_capacity(widths.len() - 1);
    let (mut offset, mut act_row) = (0, 0);
    for (k, p) in widths.windows(2).enumerate() {
        let (inp, out) = (p[0], p[1]);
        let relu = k + 2 < widths.len();
        layers.push(Layer {
            inp,
            out,
            w: offset,
            b: offset + inp * out,
            relu,
            act_row,
        });
        offset += (inp + 1) * out;
        act_row += inp;
    }
    layers
}

/// Copies samples `t0..t0 + valid` of `rows` feature-major rows (stride `n`)
/// into a tile, zeroing columns `valid..cols`.
fn gather(src: &[f32], n: usize, rows: usize, t0: usize, valid: usize, cols: usize, tile: &mut [f32]) {
    for r in 0..rows {
        let dst = &mut tile[r * TILE..][..cols];
        dst[..valid].copy_from_slice(&src[r * n + t0..][..valid]);
        dst[valid..].fill(0.0);
    }
}

/// Copies the first `valid` columns of a tile's `rows` rows to samples
/// `t0..t0 + valid` of a feature-major array with stride `n`.
fn scatter(tile: &[f32], rows: usize, t0: usize, valid: usize, dst: &mut [f32], n: usize) {
    for r in 0..rows {
        dst[r * n + t0..][..valid].copy_from_slice(&tile[r * TILE..][..valid]);
    }
}

/// Reusable buffers of an [`Mlp`]'s passes: they grow to the largest batch
/// seen and are then reused without allocating. Keep one per network and
/// thread when training (it holds the activations of the last
/// [`Mlp::forward_train`]).
#[derive(Debug, Default)]
pub struct MlpWorkspace {
    /// Training activations, tile by tile: every layer's input rows, each
    /// `TILE` wide.
    acts: AlignedBuf,
    /// Ping-pong tiles for inference and backward.
    tile_a: AlignedBuf,
    tile_b: AlignedBuf,
    /// 8-lane partial sums of the parameter gradients.
    partials: AlignedBuf,
    /// Shape of the last forward_train.
    trained: Option<(usize, usize, usize, usize)>,
}

impl MlpWorkspace {
    /// Empty workspace; buffers are allocated by the first calls.
    pub fn new() -> Self {
        Self::default()
    }

    /// Floats currently allocated (constant once warmed up for a batch size).
    pub fn capacity_floats(&self) -> usize {
        [&self.acts, &self.tile_a, &self.tile_b, &self.partials]
            .iter()
            .map(|b| b.data.capacity())
            .sum()
    }
}

/// A float buffer whose usable part starts on a 64-byte boundary.
#[derive(Debug, Default)]
struct AlignedBuf {
    data: Vec<f32>,
    start: usize,
}

impl AlignedBuf {
    const ALIGN_FLOATS: usize = 16;

    /// Makes at least `len` aligned floats available; allocates only to grow.
    fn ensure(&mut self, len: usize) {
        if self.data.len() >= len + self.start && !self.data.is_empty() {
            return;
        }
        self.data = vec![0.0; len + Self::ALIGN_FLOATS];
        let off = self.data.as_ptr().align_offset(Self::ALIGN_FLOATS * 4);
        // An impossible alignment only costs speed: unaligned loads are used.
        self.start = if off < Self::ALIGN_FLOATS { off } else { 0 };
    }

    fn slice(&self, len: usize) -> &[f32] {
        &self.data[self.start..self.start + len]
    }

    fn slice_mut(&mut self, len: usize) -> &mut [f32] {
        &mut self.data[self.start..self.start + len]
    }
}

#[cfg(test)]
#[allow(clippy::needless_range_loop)]
mod tests {
    use super::*;

    fn cfg(input: usize, hidden: &[usize], output: usize) -> MlpConfig {
        MlpConfig {
            input,
            hidden: hidden.to_vec(),
            output,
        }
    }

    fn random(len: usize, rng: &mut Rng) -> Vec<f32> {
        (0..len).map(|_| 2.0 * rng.f32() - 1.0).collect()
    }

    /// Network with random (non-zero) biases so bias paths are exercised.
    fn random_mlp(config: MlpConfig, seed: u64) -> Mlp {
        let mut rng = Rng::new(seed, 1);
        let mut mlp = Mlp::new(config, &mut rng);
        for l in mlp.layers.clone() {
            for b in &mut mlp.params[l.b..l.b + l.out] {
                *b = 0.3 * (2.0 * rng.f32() - 1.0);
            }
        }
        mlp
    }

    /// Plain f64 forward and backward, one sample at a time:
    /// (output, grad of sum(d_output * output), d_input).
    fn reference(mlp: &Mlp, input: &[f32], n: usize, d_out: &[f32]) -> (Vec<f64>, Vec<f64>, Vec<f64>) {
        let p: Vec<f64> = mlp.params.iter().map(|&v| v as f64).collect();
        let (ni, no) = (mlp.config.input, mlp.config.output);
        let mut out = vec![0.0; no * n];
        let mut grad = vec![0.0; p.len()];
        let mut d_in = vec![0.0; ni * n];
        for b in 0..n {
            let mut acts = vec![(0..ni).map(|i| input[i * n + b] as f64).collect::<Vec<_>>()];
            for l in &mlp.layers {
                let x = acts.last().unwrap();
                let y: Vec<f64> = (0..l.out)
                    .map(|o| {
                        let s = p[l.b + o] + (0..l.inp).map(|i| p[l.w + o * l.inp + i] * x[i]).sum::<f64>();
                        if l.relu {
                            s.max(0.0)
                        } else {
                            s
                        }
                    })
                    .collect();
                acts.push(y);
            }
            for o in 0..no {
                out[o * n + b] = acts.last().unwrap()[o];
            }
            let mut dz: Vec<f64> = (0..no).map(|o| d_out[o * n + b] as f64).collect();
            for (k, l) in mlp.layers.iter().enumerate().rev() {
                let x = &acts[k];
                let mut dx = vec![0.0; l.inp];
                for o in 0..l.out {
                    grad[l.b + o] += dz[o];
                    for i in 0..l.inp {
                        grad[l.w + o * l.inp + i] += dz[o] * x[i];
                        dx[i] += p[l.w + o * l.inp + i] * dz[o];
                    }
                }
                if k > 0 {
                    dz = dx.iter().zip(x).map(|(d, &h)| if h > 0.0 { *d } else { 0.0 }).collect();
                } else {
                    for i in 0..ni {
                        d_in[i * n + b] = dx[i];
                    }
                }
            }
        }
        (out, grad, d_in)
    }

    /// Normwise-relative comparison: each error within `rel` of the array's
    /// largest reference magnitude (plus `rel` of the element itself).
    fn assert_close(what: &str, got: &[f32], want: &[f64], rel: f64) {
        assert_eq!(got.len(), want.len(), "{what}: length");
        let scale = want.iter().fold(0.0f64, |m, v| m.max(v.abs())).max(1e-30);
        for (i, (&g, &w)) in got.iter().zip(want).enumerate() {
            let err = (g as f64 - w).abs();
            assert!(
                err <= rel * (scale + w.abs()),
                "{what}[{i}]: got {g}, want {w} (scale {scale})"
            );
        }
    }

    fn kernels() -> Vec<MlpKernel> {
        let mut k = vec![MlpKernel::Scalar];
        if MlpKernel::best() == MlpKernel::Avx2Fma {
            k.push(MlpKernel::Avx2Fma);
        } else {
            eprintln!("AVX2+FMA not available: only the scalar kernel is tested");
        }
        k
    }

    #[test]
    fn kernels_match_f64_reference_on_odd_shapes_and_tails() {
        let shapes = [
            cfg(1, &[], 1),
            cfg(3, &[5], 2),
            cfg(7, &[13, 9], 3),
            cfg(32, &[64], 16),
            cfg(32, &[64, 64], 3),
            cfg(17, &[33, 7], 1),
            cfg(48, &[128], 16),
            cfg(16, &[32, 31, 30], 11),
        ];
        let ns = [1, 7, 8, 15, 16, 17, 100, 127, 128, 129, 300];
        let mut rng = Rng::new(11, 0);
        for (s, config) in shapes.iter().enumerate() {
            let base = random_mlp(config.clone(), 100 + s as u64);
            for &n in &ns {
                let input = random(config.input * n, &mut rng);
                let d_out = random(config.output * n, &mut rng);
                let grad0 = random(base.param_count(), &mut rng);
                let (want_out, want_grad, want_din) = reference(&base, &input, n, &d_out);
                let want_grad: Vec<f64> = want_grad.iter().zip(&grad0).map(|(g, &g0)| g + g0 as f64).collect();
                for kernel in kernels() {
                    let mut mlp = base.clone();
                    assert_eq!(mlp.set_kernel(kernel), kernel);
                    let what = format!("{config:?} n={n} {}", kernel.name());
                    let mut ws = MlpWorkspace::new();
                    let mut out = vec![f32::NAN; config.output * n];
                    mlp.forward(&input, n, &mut ws, &mut out);
                    assert_close(&format!("{what} forward"), &out, &want_out, 1e-5);
                    let mut out_train = vec![f32::NAN; config.output * n];
                    mlp.forward_train(&input, n, &mut ws, &mut out_train);
                    assert_eq!(out, out_train, "{what}: forward_train differs from forward");
                    for rows in [1, config.output.div_ceil(2)] {
                        let mut leading = vec![f32::NAN; rows * n];
                        mlp.forward_leading(&input, n, rows, &mut ws, &mut leading);
                        assert_eq!(leading, out[..rows * n], "{what}: first {rows} outputs differ");
                    }
                    let mut grad = grad0.clone();
                    let mut d_in = vec![f32::NAN; config.input * n];
                    mlp.backward(&mut ws, &d_out, n, &mut grad, Some(&mut d_in));
                    assert_close(&format!("{what} grad"), &grad, &want_grad, 1e-5);
                    assert_close(&format!("{what} d_input"), &d_in, &want_din, 1e-5);
                }
            }
        }
    }

    /// sum_{o,b} c[o][b] * y[o][b] accumulated in f64.
    fn loss(mlp: &Mlp, input: &[f32], n: usize, c: &[f32], ws: &mut MlpWorkspace) -> f64 {
        let mut out = vec![0.0; mlp.config.output * n];
        mlp.forward(input, n, ws, &mut out);
        out.iter().zip(c).map(|(&y, &c)| y as f64 * c as f64).sum()
    }

    /// ReLU on/off pattern of every hidden unit; a finite difference is only
    /// exact when it does not change across the step.
    fn relu_pattern(mlp: &Mlp, input: &[f32], n: usize) -> Vec<bool> {
        let mut pattern = Vec::new();
        for b in 0..n {
            let mut x: Vec<f64> = (0..mlp.config.input).map(|i| input[i * n + b] as f64).collect();
            for l in &mlp.layers {
                let p = &mlp.params;
                let z: Vec<f64> = (0..l.out)
                    .map(|o| p[l.b + o] as f64 + (0..l.inp).map(|i| p[l.w + o * l.inp + i] as f64 * x[i]).sum::<f64>())
                    .collect();
                if l.relu {
                    pattern.extend(z.iter().map(|&v| v > 0.0));
                }
                x = z.into_iter().map(|v| if l.relu { v.max(0.0) } else { v }).collect();
            }
        }
        pattern
    }

    #[test]
    fn backward_matches_central_finite_differences() {
        // The loss is piecewise linear in any single parameter or input, so a
        // central difference that keeps the ReLU pattern is exact up to
        // rounding; a wrong transpose, mask or bias term is off by O(1).
        let config = cfg(3, &[5, 4], 2);
        let n = 6;
        let eps = 1e-2f32;
        let mut rng = Rng::new(5, 0);
        for kernel in kernels() {
            let mut mlp = random_mlp(config.clone(), 42);
            mlp.set_kernel(kernel);
            let input = random(config.input * n, &mut rng);
            let c = random(config.output * n, &mut rng);
            let mut ws = MlpWorkspace::new();
            let mut out = vec![0.0; config.output * n];
            mlp.forward_train(&input, n, &mut ws, &mut out);
            let mut grad = vec![0.0; mlp.param_count()];
            let mut d_in = vec![0.0; config.input * n];
            mlp.backward(&mut ws, &c, n, &mut grad, Some(&mut d_in));
            let gmax = grad.iter().chain(&d_in).fold(0.0f32, |m, v| m.max(v.abs())) as f64;
            let (mut checked, mut skipped) = (0, 0);
            let mut check = |what: String, analytic: f32, plus: &Mlp, minus: &Mlp, in_p: &[f32], in_m: &[f32]| {
                if relu_pattern(plus, in_p, n) != relu_pattern(minus, in_m, n) {
                    skipped += 1;
                    return;
                }
                let mut ws = MlpWorkspace::new();
                let fd = (loss(plus, in_p, n, &c, &mut ws) - loss(minus, in_m, n, &c, &mut ws)) / (2.0 * eps as f64);
                let err = (fd - analytic as f64).abs();
                assert!(
                    err <= 1e-3 * gmax,
                    "{what} ({}): analytic {analytic}, finite difference {fd}",
                    kernel.name()
                );
                checked += 1;
            };
            for j in 0..mlp.param_count() {
                let (mut plus, mut minus) = (mlp.clone(), mlp.clone());
                plus.params[j] += eps;
                minus.params[j] -= eps;
                check(format!("param {j}"), grad[j], &plus, &minus, &input, &input);
            }
            for j in 0..input.len() {
                let (mut in_p, mut in_m) = (input.clone(), input.clone());
                in_p[j] += eps;
                in_m[j] -= eps;
                check(format!("input {j}"), d_in[j], &mlp, &mlp, &in_p, &in_m);
            }
            assert!(
                skipped * 10 <= checked,
                "too many kinks: {skipped} skipped, {checked} checked"
            );
            assert!(gmax > 0.1, "degenerate test network: largest gradient {gmax}");
        }
    }

    #[test]
    fn backward_accumulates_into_grad_and_leaves_padding_out() {
        let config = cfg(5, &[9], 3);
        let n = 37;
        let mlp = random_mlp(config.clone(), 7);
        let mut rng = Rng::new(8, 0);
        let input = random(config.input * n, &mut rng);
        let d_out = random(config.output * n, &mut rng);
        let mut ws = MlpWorkspace::new();
        let mut out = vec![0.0; config.output * n];
        mlp.forward_train(&input, n, &mut ws, &mut out);
        let mut once = vec![0.0; mlp.param_count()];
        mlp.backward(&mut ws, &d_out, n, &mut once, None);
        let mut twice = once.clone();
        mlp.backward(&mut ws, &d_out, n, &mut twice, None);
        for (a, b) in once.iter().zip(&twice) {
            assert_eq!(2.0 * a, *b, "second backward must add the same gradient");
        }
        // Zero output gradient gives exactly zero parameter gradient, so the
        // zero-padded columns of the last tile contribute nothing.
        let mut zero = vec![0.0; mlp.param_count()];
        mlp.backward(&mut ws, &vec![0.0; config.output * n], n, &mut zero, None);
        assert!(zero.iter().all(|&g| g == 0.0));
    }

    #[test]
    fn results_do_not_depend_on_workspace_history() {
        let config = cfg(32, &[64], 16);
        let mlp = random_mlp(config.clone(), 9);
        let mut rng = Rng::new(10, 0);
        let run = |ws: &mut MlpWorkspace, n: usize, input: &[f32], d_out: &[f32]| {
            let mut out = vec![0.0; config.output * n];
            mlp.forward_train(input, n, ws, &mut out);
            let mut grad = vec![0.0; mlp.param_count()];
            let mut d_in = vec![0.0; config.input * n];
            mlp.backward(ws, d_out, n, &mut grad, Some(&mut d_in));
            (out, grad, d_in)
        };
        let n = 300;
        let input = random(config.input * n, &mut rng);
        let d_out = random(config.output * n, &mut rng);
        let fresh = run(&mut MlpWorkspace::new(), n, &input, &d_out);
        let mut used = MlpWorkspace::new();
        let big = 1000;
        run(
            &mut used,
            big,
            &random(config.input * big, &mut rng),
            &random(config.output * big, &mut rng),
        );
        assert_eq!(fresh, run(&mut used, n, &input, &d_out));
    }

    #[test]
    fn leading_input_gradients_are_the_full_backward_s_first_rows() {
        let config = cfg(32, &[64, 64], 3);
        let mlp = random_mlp(config.clone(), 15);
        let mut rng = Rng::new(16, 0);
        let (n, rows) = (261, 16);
        let input = random(config.input * n, &mut rng);
        let d_out = random(config.output * n, &mut rng);
        let mut out = vec![0.0; config.output * n];
        let mut ws = MlpWorkspace::new();
        mlp.forward_train(&input, n, &mut ws, &mut out);
        let (mut grad_all, mut d_all) = (vec![0.0; mlp.param_count()], vec![0.0; config.input * n]);
        mlp.backward(&mut ws, &d_out, n, &mut grad_all, Some(&mut d_all));
        let (mut grad_lead, mut d_lead) = (vec![0.0; mlp.param_count()], vec![f32::NAN; rows * n]);
        mlp.backward_leading_inputs(&mut ws, &d_out, n, &mut grad_lead, Some((&mut d_lead, rows)));
        assert_eq!(grad_lead, grad_all);
        assert_eq!(d_lead[..], d_all[..rows * n]);
        assert!(
            d_all[rows * n..].iter().any(|&g| g != 0.0),
            "the rows left out carry gradient"
        );
    }

    #[test]
    fn workspace_stops_allocating_after_warm_up() {
        let config = cfg(32, &[64, 64], 3);
        let mlp = random_mlp(config.clone(), 12);
        let mut rng = Rng::new(13, 0);
        let n = 1000;
        let input = random(config.input * n, &mut rng);
        let d_out = random(config.output * n, &mut rng);
        let mut out = vec![0.0; config.output * n];
        let mut grad = vec![0.0; mlp.param_count()];
        let mut d_in = vec![0.0; config.input * n];
        let mut ws = MlpWorkspace::new();
        assert_eq!(ws.capacity_floats(), 0);
        mlp.forward_train(&input, n, &mut ws, &mut out);
        mlp.backward(&mut ws, &d_out, n, &mut grad, Some(&mut d_in));
        mlp.forward(&input, n, &mut ws, &mut out);
        let warm = ws.capacity_floats();
        assert!(
            warm >= (config.input + 128) * n,
            "activations must be kept: {warm} floats"
        );
        for m in [n, 999, 1, 513] {
            mlp.forward_train(&input[..config.input * m], m, &mut ws, &mut out[..config.output * m]);
            mlp.backward(&mut ws, &d_out[..config.output * m], m, &mut grad, None);
            mlp.forward(&input[..config.input * m], m, &mut ws, &mut out[..config.output * m]);
            assert_eq!(ws.capacity_floats(), warm, "allocated again at n = {m}");
        }
    }

    #[test]
    fn from_params_round_trips_and_rejects_bad_vectors() {
        let config = cfg(4, &[6], 2);
        let mut rng = Rng::new(14, 0);
        let mlp = Mlp::new(config.clone(), &mut rng);
        assert_eq!(mlp.param_count(), (4 + 1) * 6 + (6 + 1) * 2);
        let copy = Mlp::from_params(config.clone(), mlp.params.clone()).unwrap();
        let n = 19;
        let input = random(config.input * n, &mut rng);
        let (mut a, mut b) = (vec![0.0; 2 * n], vec![0.0; 2 * n]);
        let mut ws = MlpWorkspace::new();
        mlp.forward(&input, n, &mut ws, &mut a);
        copy.forward(&input, n, &mut ws, &mut b);
        assert_eq!(a, b);
        assert!(matches!(
            Mlp::from_params(config.clone(), vec![0.0; 5]),
            Err(MlpError::ParamCount {
                expected: 44,
                found: 5,
                ..
            })
        ));
        let mut bad = mlp.params.clone();
        bad[7] = f32::NAN;
        assert!(matches!(
            Mlp::from_params(config.clone(), bad),
            Err(MlpError::NonFinite { index: 7, .. })
        ));
        assert_eq!(
            Mlp::from_params(cfg(4, &[0], 2), vec![]).unwrap_err(),
            MlpError::ZeroWidth { layer: 1 }
        );
        assert!(matches!(
            Mlp::from_params(cfg(MAX_WIDTH + 1, &[], 1), vec![]),
            Err(MlpError::TooWide { layer: 0, .. })
        ));
    }

    #[test]
    fn new_uses_kaiming_uniform_weights_and_zero_biases() {
        let config = cfg(64, &[128], 16);
        let mlp = Mlp::new(config, &mut Rng::new(15, 0));
        for l in &mlp.layers {
            let bound = ((if l.relu { 6.0 } else { 3.0 }) / l.inp as f64).sqrt();
            let w = &mlp.params[l.w..l.w + l.inp * l.out];
            assert!(w.iter().all(|&v| (v as f64).abs() <= bound));
            let var = w.iter().map(|&v| (v as f64).powi(2)).sum::<f64>() / w.len() as f64;
            let want = bound * bound / 3.0;
            assert!((var / want - 1.0).abs() < 0.1, "weight variance {var}, want {want}");
            assert!(mlp.params[l.b..l.b + l.out].iter().all(|&b| b == 0.0));
        }
        assert_eq!(mlp.flops_forward_per_sample(), 2 * (64 * 128 + 128 * 16));
        assert_eq!(mlp.flops_backward_per_sample(), 2 * mlp.flops_forward_per_sample());
    }
}
