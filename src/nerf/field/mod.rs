//! The radiance field: hash encoding -> density MLP (log-density + geometry
//! features) -> colour MLP (geometry features + SH view direction).
//! Batched, feature-major, with reusable workspaces; a density-only path
//! skips the colour branch entirely.

pub mod hash_grid;
pub mod mlp;
pub mod sh;
pub mod simd;

use crate::rng::Rng;
use hash_grid::{GridGrad, HashGrid, HashGridConfig};
use mlp::{Mlp, MlpConfig, MlpWorkspace};
use serde::{Deserialize, Serialize};
use sh::SH_COEFFS;
use std::time::Instant;

/// Outputs of the density network: raw log-density plus geometry features.
pub const DENSITY_OUTPUTS: usize = 16;
/// Raw log-density is clamped here in the forward pass (sigma <= e^20).
const MAX_LOG_DENSITY: f32 = 20.0;
/// Gradient of trunc_exp uses exp(clamp(x, -15, 15)).
const GRAD_LOG_DENSITY: f32 = 15.0;

/// Network widths and the hash grid.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct FieldConfig {
    pub grid: GridSpec,
    pub density_hidden: Vec<usize>,
    pub color_hidden: Vec<usize>,
}

/// Serialisable copy of [`HashGridConfig`].
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct GridSpec {
    pub levels: usize,
    pub features_per_level: usize,
    pub log2_table_size: u32,
    pub base_resolution: u32,
    pub finest_resolution: u32,
}

impl From<GridSpec> for HashGridConfig {
    fn from(g: GridSpec) -> Self {
        HashGridConfig {
            levels: g.levels,
            features_per_level: g.features_per_level,
            log2_table_size: g.log2_table_size,
            base_resolution: g.base_resolution,
            finest_resolution: g.finest_resolution,
        }
    }
}

impl From<&HashGridConfig> for GridSpec {
    fn from(g: &HashGridConfig) -> Self {
        GridSpec {
            levels: g.levels,
            features_per_level: g.features_per_level,
            log2_table_size: g.log2_table_size,
            base_resolution: g.base_resolution,
            finest_resolution: g.finest_resolution,
        }
    }
}

impl FieldConfig {
    fn density_mlp(&self) -> MlpConfig {
        let grid: HashGridConfig = self.grid.into();
        MlpConfig {
            input: grid.output_dim(),
            hidden: self.density_hidden.clone(),
            output: DENSITY_OUTPUTS,
        }
    }

    fn color_mlp(&self) -> MlpConfig {
        MlpConfig {
            input: DENSITY_OUTPUTS + SH_COEFFS,
            hidden: self.color_hidden.clone(),
            output: 3,
        }
    }
}

/// The trainable field.
#[derive(Clone)]
pub struct Field {
    pub config: FieldConfig,
    pub grid: HashGrid,
    pub density: Mlp,
    pub color: Mlp,
}

/// Gradients of every parameter of a [`Field`].
pub struct FieldGrad {
    pub grid: GridGrad,
    pub density: Vec<f32>,
    pub color: Vec<f32>,
}

impl FieldGrad {
    /// Zero every gradient (the grid only where touched).
    pub fn clear(&mut self) {
        self.grid.clear();
        self.density.iter_mut().for_each(|g| *g = 0.0);
        self.color.iter_mut().for_each(|g| *g = 0.0);
    }

    /// Add another buffer into this one (callers fix the order); the
    /// other's grid gradient is left empty (see [`GridGrad::drain_from`]).
    pub fn drain_from(&mut self, other: &mut FieldGrad) {
        self.grid.drain_from(&mut other.grid);
        for (a, b) in self.density.iter_mut().zip(&other.density) {
            *a += b;
        }
        for (a, b) in self.color.iter_mut().zip(&other.color) {
            *a += b;
        }
    }

    /// True when every MLP gradient is finite (the grid's are checked by
    /// [`GridGrad::touched_rms`]).
    pub fn mlps_finite(&self) -> bool {
        self.density.iter().chain(&self.color).all(|g| g.is_finite())
    }
}

/// Thread-seconds a workspace's passes spent in the hash grid and in the
/// MLPs (with their activations and the direction encoding), for the
/// training benchmark's breakdown.
#[derive(Clone, Copy, Debug, Default)]
pub struct FieldSeconds {
    pub grid: f64,
    pub mlp: f64,
}

/// Buffers for one batch of samples, reused across calls.
#[derive(Default)]
pub struct FieldWorkspace {
    /// Time spent so far (callers reset it when they want a fresh count).
    pub seconds: FieldSeconds,
    encoded: Vec<f32>,
    density_out: Vec<f32>,
    color_in: Vec<f32>,
    color_out: Vec<f32>,
    d_density_out: Vec<f32>,
    d_color_out: Vec<f32>,
    d_color_in: Vec<f32>,
    d_encoded: Vec<f32>,
    density_ws: Option<MlpWorkspace>,
    color_ws: Option<MlpWorkspace>,
    /// Density per sample (local units) of the last forward.
    pub sigma: Vec<f32>,
    /// Colour per sample in [0,1], feature-major [3][n], of the last forward.
    pub rgb: Vec<f32>,
    n: usize,
    /// Samples encoded by the last [`Field::density_for_training`].
    encoded_n: usize,
}

fn sized(buf: &mut Vec<f32>, len: usize) -> &mut [f32] {
    if buf.len() < len {
        buf.resize(len, 0.0);
    }
    &mut buf[..len]
}

/// sigma = exp(raw), clamped so it never overflows.
#[inline]
pub fn density_activation(raw: f32) -> f32 {
    clamped_log_density(raw).exp()
}

/// [`density_activation`] of each of `raw` into `sigma`, the exponential
/// taken eight lanes at a time ([`simd::exp`]): within two ulps of it, for
/// renderers (training keeps the scalar one, whose bits its models hold).
pub fn density_activation_simd(raw: &[f32], sigma: &mut [f32]) {
    let n = raw.len().min(sigma.len());
    for (s, &raw) in sigma.iter_mut().zip(raw) {
        *s = clamped_log_density(raw);
    }
    simd::exp::exp(&mut sigma[..n]);
}

/// The log density the activation exponentiates: clamped so it never
/// overflows, and -inf (a density of 0) for NaN.
#[inline]
fn clamped_log_density(raw: f32) -> f32 {
    if raw.is_nan() {
        f32::NEG_INFINITY
    } else {
        raw.min(MAX_LOG_DENSITY)
    }
}

/// d sigma / d raw of the truncated exponential.
#[inline]
fn density_activation_grad(raw: f32) -> f32 {
    if raw.is_nan() {
        return 0.0;
    }
    raw.clamp(-GRAD_LOG_DENSITY, GRAD_LOG_DENSITY).exp()
}

/// The colour network's output activation (also the environment's).
#[inline]
pub fn sigmoid(x: f32) -> f32 {
    1.0 / (1.0 + (-x).exp())
}

impl Field {
    /// A freshly initialised field.
    pub fn new(config: FieldConfig, rng: &mut Rng) -> Field {
        let grid = HashGrid::new(config.grid.into(), rng);
        let density = Mlp::new(config.density_mlp(), rng);
        let color = Mlp::new(config.color_mlp(), rng);
        Field {
            config,
            grid,
            density,
            color,
        }
    }

    /// Rebuild from saved parameters; `None` when the lengths do not fit.
    pub fn from_params(config: FieldConfig, grid: Vec<f32>, density: Vec<f32>, color: Vec<f32>) -> Option<Field> {
        let grid = HashGrid::from_params(config.grid.into(), grid).ok()?;
        let density = Mlp::from_params(config.density_mlp(), density).ok()?;
        let color = Mlp::from_params(config.color_mlp(), color).ok()?;
        Some(Field {
            config,
            grid,
            density,
            color,
        })
    }

    /// Total trainable parameters.
    pub fn param_count(&self) -> usize {
        self.grid.param_count() + self.density.param_count() + self.color.param_count()
    }

    /// Zeroed gradient buffers for this field.
    pub fn new_grad(&self) -> FieldGrad {
        FieldGrad {
            grid: GridGrad::new(self.grid.param_count()),
            density: vec![0.0; self.density.param_count()],
            color: vec![0.0; self.color.param_count()],
        }
    }

    /// Density only (no colour branch) for a batch of local points.
    pub fn density_only(&self, positions: &[[f32; 3]], ws: &mut FieldWorkspace, sigma: &mut [f32]) {
        let raw = self.raw_density_only(positions, ws);
        for (s, &raw) in sigma.iter_mut().zip(raw) {
            *s = density_activation(raw);
        }
    }

    /// [`Self::density_only`] with the activation's exponential taken eight
    /// lanes at a time ([`simd::exp`]): within two ulps of it but not the
    /// same bits, so renderers use it and training (whose models must not
    /// change) does not.
    pub fn density_only_simd_exp(&self, positions: &[[f32; 3]], ws: &mut FieldWorkspace, sigma: &mut [f32]) {
        let raw = self.raw_density_only(positions, ws);
        density_activation_simd(raw, sigma);
    }

    /// The density network's raw (log) density output for a batch.
    fn raw_density_only<'w>(&self, positions: &[[f32; 3]], ws: &'w mut FieldWorkspace) -> &'w [f32] {
        let n = positions.len();
        if n == 0 {
            return &[];
        }
        let enc_dim = self.grid.config.output_dim();
        let encoded = sized(&mut ws.encoded, enc_dim * n);
        self.grid.encode(positions, encoded);
        // Only the density output: the features feed the colour network.
        let out = sized(&mut ws.density_out, n);
        let mlp_ws = ws.density_ws.get_or_insert_with(MlpWorkspace::new);
        self.density
            .forward_leading(&ws.encoded[..enc_dim * n], n, 1, mlp_ws, out);
        &ws.density_out[..n]
    }

    /// Density and colour for a batch; `train` keeps activations for
    /// [`Field::backward`]. Results land in `ws.sigma` and `ws.rgb`.
    pub fn forward(&self, positions: &[[f32; 3]], dirs: &[[f32; 3]], ws: &mut FieldWorkspace, train: bool) {
        let n = positions.len();
        ws.n = n;
        sized(&mut ws.sigma, n);
        sized(&mut ws.rgb, 3 * n);
        if n == 0 {
            return;
        }
        let enc_dim = self.grid.config.output_dim();
        let started = Instant::now();
        self.grid.encode(positions, sized(&mut ws.encoded, enc_dim * n));
        ws.seconds.grid += started.elapsed().as_secs_f64();
        self.forward_encoded(dirs, ws, train);
    }

    /// First half of a training forward: every sample's grid encoding (kept
    /// in `ws` for [`Field::forward_train_kept`]) and its density, without
    /// the colour branch. Samples behind where a ray's light is used up
    /// carry no gradient and can be left out of the rest.
    pub fn density_for_training<'w>(&self, positions: &[[f32; 3]], ws: &'w mut FieldWorkspace) -> &'w [f32] {
        let n = positions.len();
        let started = Instant::now();
        self.raw_density_only(positions, ws);
        ws.seconds.grid += started.elapsed().as_secs_f64();
        ws.n = 0;
        ws.encoded_n = n;
        let sigma = sized(&mut ws.sigma, n);
        for (s, &raw) in sigma.iter_mut().zip(&ws.density_out[..n]) {
            *s = density_activation(raw);
        }
        &ws.sigma[..n]
    }

    /// Second half of a training forward: keeps the samples `kept`
    /// (ascending indices into the last [`Field::density_for_training`];
    /// `dirs` are theirs) and runs both networks on them with activations
    /// kept, as [`Field::forward`] would on those samples alone.
    pub fn forward_train_kept(&self, kept: &[u32], dirs: &[[f32; 3]], ws: &mut FieldWorkspace) {
        let (n, m) = (ws.encoded_n, kept.len());
        assert_eq!(
            dirs.len(),
            m,
            "Field::forward_train_kept: one direction per kept sample"
        );
        assert!(
            kept.windows(2).all(|p| p[0] < p[1]) && kept.last().is_none_or(|&k| (k as usize) < n),
            "Field::forward_train_kept: kept samples must ascend within the density pass"
        );
        let started = Instant::now();
        // In place: kept entry i of row f moves to f m + i <= f n + kept[i],
        // never onto an entry still to be read.
        let enc_dim = self.grid.config.output_dim();
        for f in 0..enc_dim {
            for (i, &k) in kept.iter().enumerate() {
                ws.encoded[f * m + i] = ws.encoded[f * n + k as usize];
            }
        }
        ws.seconds.grid += started.elapsed().as_secs_f64();
        ws.n = m;
        sized(&mut ws.sigma, m);
        sized(&mut ws.rgb, 3 * m);
        if m > 0 {
            self.forward_encoded(dirs, ws, true);
        }
    }

    /// Both networks on the encodings in `ws.encoded` (one per direction).
    fn forward_encoded(&self, dirs: &[[f32; 3]], ws: &mut FieldWorkspace, train: bool) {
        let n = dirs.len();
        let enc_dim = self.grid.config.output_dim();
        let encoded = Instant::now();
        sized(&mut ws.density_out, DENSITY_OUTPUTS * n);
        {
            let mlp_ws = ws.density_ws.get_or_insert_with(MlpWorkspace::new);
            let (input, out) = (&ws.encoded[..enc_dim * n], &mut ws.density_out[..DENSITY_OUTPUTS * n]);
            if train {
                self.density.forward_train(input, n, mlp_ws, out);
            } else {
                self.density.forward(input, n, mlp_ws, out);
            }
        }
        for b in 0..n {
            ws.sigma[b] = density_activation(ws.density_out[b]);
        }
        // Colour input: the density outputs then the SH of the direction.
        let color_in = sized(&mut ws.color_in, (DENSITY_OUTPUTS + SH_COEFFS) * n);
        color_in[..DENSITY_OUTPUTS * n].copy_from_slice(&ws.density_out[..DENSITY_OUTPUTS * n]);
        let mut coeffs = [0.0f32; SH_COEFFS];
        for (b, d) in dirs.iter().enumerate().take(n) {
            sh::encode(*d, &mut coeffs);
            for (k, c) in coeffs.iter().enumerate() {
                color_in[(DENSITY_OUTPUTS + k) * n + b] = *c;
            }
        }
        sized(&mut ws.color_out, 3 * n);
        {
            let mlp_ws = ws.color_ws.get_or_insert_with(MlpWorkspace::new);
            let input = &ws.color_in[..(DENSITY_OUTPUTS + SH_COEFFS) * n];
            let out = &mut ws.color_out[..3 * n];
            if train {
                self.color.forward_train(input, n, mlp_ws, out);
            } else {
                self.color.forward(input, n, mlp_ws, out);
            }
        }
        for i in 0..3 * n {
            ws.rgb[i] = sigmoid(ws.color_out[i]);
        }
        ws.seconds.mlp += encoded.elapsed().as_secs_f64();
    }

    /// Backward of the last training forward: `d_sigma[n]` and
    /// `d_rgb` (feature-major [3][n]) accumulate into `grad`.
    pub fn backward(
        &self,
        positions: &[[f32; 3]],
        ws: &mut FieldWorkspace,
        d_sigma: &[f32],
        d_rgb: &[f32],
        grad: &mut FieldGrad,
    ) {
        let n = ws.n;
        if n == 0 {
            return;
        }
        let started = Instant::now();
        let d_color_out = sized(&mut ws.d_color_out, 3 * n);
        for i in 0..3 * n {
            let s = ws.rgb[i];
            d_color_out[i] = d_rgb[i] * s * (1.0 - s);
        }
        // Only the density outputs' part of the colour input is learnt.
        sized(&mut ws.d_color_in, DENSITY_OUTPUTS * n);
        {
            let mlp_ws = ws.color_ws.get_or_insert_with(MlpWorkspace::new);
            self.color.backward_leading_inputs(
                mlp_ws,
                &ws.d_color_out[..3 * n],
                n,
                &mut grad.color,
                Some((&mut ws.d_color_in[..DENSITY_OUTPUTS * n], DENSITY_OUTPUTS)),
            );
        }
        let d_density_out = sized(&mut ws.d_density_out, DENSITY_OUTPUTS * n);
        d_density_out.copy_from_slice(&ws.d_color_in[..DENSITY_OUTPUTS * n]);
        for b in 0..n {
            d_density_out[b] += d_sigma[b] * density_activation_grad(ws.density_out[b]);
        }
        let enc_dim = self.grid.config.output_dim();
        sized(&mut ws.d_encoded, enc_dim * n);
        {
            let mlp_ws = ws.density_ws.get_or_insert_with(MlpWorkspace::new);
            self.density.backward(
                mlp_ws,
                &ws.d_density_out[..DENSITY_OUTPUTS * n],
                n,
                &mut grad.density,
                Some(&mut ws.d_encoded[..enc_dim * n]),
            );
        }
        let mlp_done = Instant::now();
        ws.seconds.mlp += (mlp_done - started).as_secs_f64();
        self.grid
            .backward(positions, &ws.d_encoded[..enc_dim * n], &mut grad.grid);
        ws.seconds.grid += mlp_done.elapsed().as_secs_f64();
    }

    /// After [`Field::backward`]: adds to `out[b]` the loss gradient with
    /// respect to position `b` for the samples listed in `only`, through the
    /// `levels` coarsest grid levels (see [`HashGrid::position_gradient`]).
    /// The direction's part is left out (a camera's small turn barely
    /// changes a view direction's colour).
    pub fn position_gradient(
        &self,
        positions: &[[f32; 3]],
        ws: &mut FieldWorkspace,
        levels: usize,
        only: &[usize],
        out: &mut [[f32; 3]],
    ) {
        let n = ws.n;
        let enc_dim = self.grid.config.output_dim();
        let started = Instant::now();
        self.grid.position_gradient(
            &positions[..n],
            &ws.d_encoded[..enc_dim * n],
            levels,
            only,
            &mut out[..n],
        );
        ws.seconds.grid += started.elapsed().as_secs_f64();
    }
}

#[cfg(test)]
#[allow(clippy::needless_range_loop)] // index loops mirror the formulas they check
mod tests {
    use super::*;

    fn loss(field: &Field, pos: &[[f32; 3]], dirs: &[[f32; 3]], a: &[f32], c: &[f32]) -> f64 {
        let mut ws = FieldWorkspace::default();
        field.forward(pos, dirs, &mut ws, false);
        let n = pos.len();
        let mut l = 0.0f64;
        for b in 0..n {
            l += (a[b] * ws.sigma[b]) as f64;
        }
        for i in 0..3 * n {
            l += (c[i] * ws.rgb[i]) as f64;
        }
        l
    }

    /// A small-scene field whose grid values are large enough for the
    /// encoding to matter, and the generator that drew them.
    fn field_with_random_grid(seed: u64, density_hidden: Vec<usize>, color_hidden: Vec<usize>) -> (Field, Rng) {
        let mut rng = Rng::new(seed, 0);
        let grid = HashGridConfig::for_scene(1.0, 1.0 / 32.0);
        let config = FieldConfig {
            grid: GridSpec::from(&grid),
            density_hidden,
            color_hidden,
        };
        let mut field = Field::new(config, &mut rng);
        for p in field.grid.params.iter_mut() {
            *p = rng.f32() - 0.5;
        }
        (field, rng)
    }

    #[test]
    fn training_on_kept_samples_is_training_on_those_samples_alone() {
        let (field, mut rng) = field_with_random_grid(11, vec![64], vec![64, 64]);
        let n = 301;
        let pos: Vec<[f32; 3]> = (0..n).map(|_| [rng.f32(), rng.f32(), rng.f32()]).collect();
        let kept: Vec<u32> = (0..n as u32).filter(|k| k % 3 != 1 && *k != 0).collect();
        let m = kept.len();
        let pos_kept: Vec<[f32; 3]> = kept.iter().map(|&k| pos[k as usize]).collect();
        let dirs_kept = vec![[0.6, 0.0, -0.8]; m];
        let d_sigma: Vec<f32> = (0..m).map(|_| rng.f32() - 0.5).collect();
        let d_rgb: Vec<f32> = (0..3 * m).map(|_| rng.f32() - 0.5).collect();

        let mut alone = FieldWorkspace::default();
        field.forward(&pos_kept, &dirs_kept, &mut alone, true);
        let mut want = field.new_grad();
        field.backward(&pos_kept, &mut alone, &d_sigma, &d_rgb, &mut want);

        let mut ws = FieldWorkspace::default();
        let sigma_all = field.density_for_training(&pos, &mut ws).to_vec();
        for (i, &k) in kept.iter().enumerate() {
            let close = (sigma_all[k as usize] - alone.sigma[i]).abs() <= 1e-5 * alone.sigma[i].max(1.0);
            assert!(
                close,
                "density pass {} against {}",
                sigma_all[k as usize], alone.sigma[i]
            );
        }
        field.forward_train_kept(&kept, &dirs_kept, &mut ws);
        assert_eq!(ws.sigma[..m], alone.sigma[..m]);
        assert_eq!(ws.rgb[..3 * m], alone.rgb[..3 * m]);
        let mut got = field.new_grad();
        field.backward(&pos_kept, &mut ws, &d_sigma, &d_rgb, &mut got);
        assert_eq!(got.density, want.density);
        assert_eq!(got.color, want.color);
        assert!(got.grid.touched().eq(want.grid.touched()));
        assert_eq!(got.grid.values_and_touched().0, want.grid.values_and_touched().0);
    }

    #[test]
    fn field_backward_matches_finite_differences() {
        let (field, mut rng) = field_with_random_grid(9, vec![16], vec![16]);
        let n = 37;
        let pos: Vec<[f32; 3]> = (0..n).map(|_| [rng.f32(), rng.f32(), rng.f32()]).collect();
        let dirs: Vec<[f32; 3]> = (0..n)
            .map(|_| {
                let d = [rng.f32() - 0.5, rng.f32() - 0.5, rng.f32() - 0.5];
                let l = (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt();
                [d[0] / l, d[1] / l, d[2] / l]
            })
            .collect();
        let a: Vec<f32> = (0..n).map(|_| rng.f32() - 0.5).collect();
        let c: Vec<f32> = (0..3 * n).map(|_| rng.f32() - 0.5).collect();
        let mut ws = FieldWorkspace::default();
        field.forward(&pos, &dirs, &mut ws, true);
        let mut grad = field.new_grad();
        field.backward(&pos, &mut ws, &a, &c, &mut grad);

        let check = |analytic: f32, numeric: f64, what: &str| {
            assert!(
                (analytic as f64 - numeric).abs() < 2e-2 * (1.0 + numeric.abs()),
                "{what}: analytic {analytic} numeric {numeric}"
            );
        };
        let eps = 1e-2f32;
        for k in (0..field.density.params.len()).step_by(37) {
            let mut f = field.clone();
            f.density.params[k] += eps;
            let up = loss(&f, &pos, &dirs, &a, &c);
            f.density.params[k] -= 2.0 * eps;
            let down = loss(&f, &pos, &dirs, &a, &c);
            check(
                grad.density[k],
                (up - down) / (2.0 * eps as f64),
                &format!("density param {k}"),
            );
        }
        for k in (0..field.color.params.len()).step_by(23) {
            let mut f = field.clone();
            f.color.params[k] += eps;
            let up = loss(&f, &pos, &dirs, &a, &c);
            f.color.params[k] -= 2.0 * eps;
            let down = loss(&f, &pos, &dirs, &a, &c);
            check(
                grad.color[k],
                (up - down) / (2.0 * eps as f64),
                &format!("colour param {k}"),
            );
        }
        let touched: Vec<usize> = grad.grid.touched().collect();
        assert!(!touched.is_empty());
        for &k in touched.iter().step_by(touched.len() / 20 + 1) {
            let mut f = field.clone();
            f.grid.params[k] += eps;
            let up = loss(&f, &pos, &dirs, &a, &c);
            f.grid.params[k] -= 2.0 * eps;
            let down = loss(&f, &pos, &dirs, &a, &c);
            check(
                grad.grid.values[k],
                (up - down) / (2.0 * eps as f64),
                &format!("grid param {k}"),
            );
        }
    }
}
