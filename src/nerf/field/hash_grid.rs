//! Multi-resolution hash encoding (Instant-NGP) on the CPU.
//!
//! Each level is a grid of `res` cells per side over the unit cube whose
//! `(res+1)^3` vertices hold `features_per_level` f32 each. Coarse levels whose
//! vertices fit the table are stored dense; finer ones are hashed into
//! `2^log2_table_size` entries with Instant-NGP's spatial hash. A position's
//! feature for a level is the trilinear blend of its cell's 8 corners, so the
//! encoding is linear in the parameters.
//!
//! The level loop is outermost, so one level's table (at most a few MiB) stays
//! in cache while all positions visit it, in blocks of 256 SIMD-friendly columns. With
//! AVX2+FMA, 2-feature levels use the AVX2 kernels of
//! [`crate::nerf::field::simd::grid`]; their results are bit-identical to the scalar
//! path, so outputs do not depend on the CPU.

mod backward;
mod grad;
mod sizing;
mod spatial;
#[cfg(test)]
mod tests;

pub use grad::GridGrad;

use crate::nerf::field::simd::grid as simd;
use crate::rng::Rng;
use serde::{Deserialize, Serialize};
use std::cell::RefCell;
use std::ops::Range;

/// Instant-NGP hash primes for x, y, z.
pub const PRIMES: [u32; 3] = [1, 2_654_435_761, 805_459_861];
/// Largest accepted `log2_table_size`.
pub const MAX_LOG2_TABLE_SIZE: u32 = 24;
/// Largest accepted resolution (cells per side) of any level.
pub const MAX_RESOLUTION: u32 = 1 << 16;
/// Largest accepted number of levels.
pub const MAX_LEVELS: usize = 32;
/// Positions processed per block (a multiple of 8 for the SIMD kernels).
const BLOCK: usize = 256;

/// Shape of a hash grid: levels, features, table size and resolutions.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct HashGridConfig {
    /// Number of resolution levels.
    pub levels: usize,
    /// Features stored per vertex and level (1, 2, 4 or 8; 2 is the fast path).
    pub features_per_level: usize,
    /// Hashed levels hold `2^log2_table_size` entries.
    pub log2_table_size: u32,
    /// Cells per side of the coarsest level.
    pub base_resolution: u32,
    /// Cells per side of the finest level.
    pub finest_resolution: u32,
}

/// A hash grid configuration or parameter vector that cannot be used.
#[derive(Debug, thiserror::Error)]
pub enum GridError {
    /// The configuration is out of the supported range.
    #[error("hash grid config: {0}")]
    Config(String),
    /// The parameter vector does not match the configuration.
    #[error("hash grid: expected {expected} parameters for this config, found {found}")]
    ParamCount { expected: usize, found: usize },
    /// A parameter is NaN or infinite.
    #[error("hash grid: parameter {index} is not finite ({value})")]
    NonFinite { index: usize, value: f32 },
}

impl HashGridConfig {
    /// Grid sized to a scene whose unit cube spans `extent_m` metres, with
    /// finest cells of about `target_cell_m` metres.
    pub fn for_scene(extent_m: f64, target_cell_m: f64) -> HashGridConfig {
        sizing::for_scene(extent_m, target_cell_m)
    }

    /// Width of the encoding: `levels * features_per_level`.
    pub fn output_dim(&self) -> usize {
        self.levels * self.features_per_level
    }

    /// Checks that every field is in the supported range.
    pub fn validate(&self) -> Result<(), GridError> {
        let bad = |m: String| Err(GridError::Config(m));
        if self.levels == 0 || self.levels > MAX_LEVELS {
            return bad(format!("levels must be in 1..={MAX_LEVELS}, got {}", self.levels));
        }
        if ![1, 2, 4, 8].contains(&self.features_per_level) {
            return bad(format!(
                "features_per_level must be 1, 2, 4 or 8, got {}",
                self.features_per_level
            ));
        }
        if self.log2_table_size == 0 || self.log2_table_size > MAX_LOG2_TABLE_SIZE {
            return bad(format!(
                "log2_table_size must be in 1..={MAX_LOG2_TABLE_SIZE}, got {}",
                self.log2_table_size
            ));
        }
        if self.base_resolution == 0 || self.finest_resolution > MAX_RESOLUTION {
            return bad(format!(
                "resolutions must be in 1..={MAX_RESOLUTION}, got base {} finest {}",
                self.base_resolution, self.finest_resolution
            ));
        }
        if self.finest_resolution < self.base_resolution {
            return bad(format!(
                "finest resolution {} is below base resolution {}",
                self.finest_resolution, self.base_resolution
            ));
        }
        Ok(())
    }

    /// Cells per side of each level, coarsest first (non-decreasing).
    pub fn resolutions(&self) -> Vec<u32> {
        let (base, finest) = (self.base_resolution as f64, self.finest_resolution as f64);
        if self.levels <= 1 {
            return vec![self.finest_resolution; self.levels];
        }
        let growth = (finest / base).ln() / (self.levels - 1) as f64;
        (0..self.levels)
            .map(|l| {
                let r = (base * (growth * l as f64).exp()).round() as u32;
                r.clamp(self.base_resolution, self.finest_resolution)
            })
            .collect()
    }

    /// Layout of every level (resolution, dense or hashed, offset in params).
    pub fn level_layout(&self) -> Vec<GridLevel> {
        let table = 1u64 << self.log2_table_size.min(MAX_LOG2_TABLE_SIZE);
        let mut offset = 0usize;
        self.resolutions()
            .into_iter()
            .map(|res| {
                let side = res as u64 + 1;
                let dense = side * side * side <= table;
                let entries = if dense { side * side * side } else { table } as usize;
                let level = GridLevel {
                    resolution: res,
                    dense,
                    entries,
                    param_offset: offset,
                    mask: (table - 1) as u32,
                    stride_y: side as u32,
                    stride_z: if dense { (side * side) as u32 } else { 0 },
                };
                offset += entries * self.features_per_level;
                level
            })
            .collect()
    }

    /// Total number of f32 parameters of a grid with this config.
    pub fn param_count(&self) -> usize {
        self.level_layout().iter().map(|l| l.entries).sum::<usize>() * self.features_per_level
    }
}

/// One level of a grid: its resolution and where its table lives in `params`.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct GridLevel {
    /// Cells per side.
    pub resolution: u32,
    /// Stored dense (no hashing) because all vertices fit the table.
    pub dense: bool,
    /// Number of table entries (each `features_per_level` f32).
    pub entries: usize,
    /// Index in `params` of the level's first f32.
    pub param_offset: usize,
    /// Hash mask (`table size - 1`), used by hashed levels.
    pub(crate) mask: u32,
    /// Vertex index stride along y (dense levels).
    pub(crate) stride_y: u32,
    /// Vertex index stride along z (dense levels).
    pub(crate) stride_z: u32,
}

impl GridLevel {
    /// Table entries of the 8 cell corners of `p` (clamped to the unit cube,
    /// NaN -> 0) and their trilinear weights; corner bit 0/1/2 = +x/+y/+z.
    #[inline(always)]
    pub(crate) fn corners(&self, p: [f32; 3]) -> ([u32; 8], [f32; 8]) {
        let (x0, fx) = self.cell(p[0]);
        let (y0, fy) = self.cell(p[1]);
        let (z0, fz) = self.cell(p[2]);
        let (wx, wy, wz) = ([1.0 - fx, fx], [1.0 - fy, fy], [1.0 - fz, fz]);
        let xs = [x0, x0 + 1];
        let (ys, zs) = if self.dense {
            let y = y0 * self.stride_y;
            let z = z0 * self.stride_z;
            ([y, y + self.stride_y], [z, z + self.stride_z])
        } else {
            let y = y0.wrapping_mul(PRIMES[1]);
            let z = z0.wrapping_mul(PRIMES[2]);
            ([y, y.wrapping_add(PRIMES[1])], [z, z.wrapping_add(PRIMES[2])])
        };
        let mut idx = [0u32; 8];
        let mut w = [0f32; 8];
        for c in 0..8 {
            let (i, j, k) = (c & 1, (c >> 1) & 1, c >> 2);
            idx[c] = if self.dense {
                xs[i] + ys[j] + zs[k]
            } else {
                (xs[i] ^ ys[j] ^ zs[k]) & self.mask
            };
            w[c] = wx[i] * wy[j] * wz[k];
        }
        (idx, w)
    }

    /// Lower cell coordinate and fraction along one axis; the SIMD kernels
    /// repeat these exact operations.
    #[inline(always)]
    fn cell(&self, x: f32) -> (u32, f32) {
        // p >= 0 (NaN became 0), so truncation is floor.
        let p = unit(x) * self.resolution as f32;
        let i = (p as i32).clamp(0, self.resolution as i32 - 1);
        (i as u32, p - i as f32)
    }
}

/// `x` clamped to [0, 1], NaN -> 0 (`f32::clamp` would keep the NaN).
#[inline(always)]
#[allow(clippy::manual_clamp)]
fn unit(x: f32) -> f32 {
    x.max(0.0).min(1.0)
}

/// Multi-resolution hash encoding with all levels' tables in `params`.
#[derive(Clone, Debug)]
pub struct HashGrid {
    /// Shape of the grid.
    pub config: HashGridConfig,
    /// All levels' tables, level after level, `features_per_level` f32 per entry.
    pub params: Vec<f32>,
    levels: Vec<GridLevel>,
}

/// Positions of one block, clamped to the unit cube, as SIMD-friendly columns.
struct Block {
    x: [f32; BLOCK],
    y: [f32; BLOCK],
    z: [f32; BLOCK],
    len: usize,
}

impl Block {
    fn new() -> Block {
        Block {
            x: [0.0; BLOCK],
            y: [0.0; BLOCK],
            z: [0.0; BLOCK],
            len: 0,
        }
    }

    /// Loads up to BLOCK positions; lanes past the end are 0 so SIMD reads stay defined.
    fn load(&mut self, positions: &[[f32; 3]]) {
        self.len = positions.len().min(BLOCK);
        for (i, p) in positions.iter().take(BLOCK).enumerate() {
            (self.x[i], self.y[i], self.z[i]) = (unit(p[0]), unit(p[1]), unit(p[2]));
        }
        let padded = self.len.next_multiple_of(8).min(BLOCK);
        for i in self.len..padded {
            (self.x[i], self.y[i], self.z[i]) = (0.0, 0.0, 0.0);
        }
    }
}

impl HashGrid {
    /// New grid with parameters drawn from U(-1e-4, 1e-4).
    ///
    /// Panics if `config` fails [`HashGridConfig::validate`] (a programming error;
    /// configs read from files go through [`HashGrid::from_params`]).
    pub fn new(config: HashGridConfig, rng: &mut Rng) -> HashGrid {
        if let Err(e) = config.validate() {
            panic!("HashGrid::new: {e}");
        }
        let levels = config.level_layout();
        let count = config.param_count();
        let mut params = Vec::with_capacity(count);
        params.extend((0..count).map(|_| (rng.f32() * 2.0 - 1.0) * 1e-4));
        HashGrid { config, params, levels }
    }

    /// Grid from saved parameters, checking them against the config.
    pub fn from_params(config: HashGridConfig, params: Vec<f32>) -> Result<HashGrid, GridError> {
        config.validate()?;
        let expected = config.param_count();
        if params.len() != expected {
            return Err(GridError::ParamCount {
                expected,
                found: params.len(),
            });
        }
        if let Some((index, &value)) = params.iter().enumerate().find(|(_, v)| !v.is_finite()) {
            return Err(GridError::NonFinite { index, value });
        }
        Ok(HashGrid {
            levels: config.level_layout(),
            config,
            params,
        })
    }

    /// Number of f32 parameters.
    pub fn param_count(&self) -> usize {
        self.params.len()
    }

    /// Width of the encoding.
    pub fn output_dim(&self) -> usize {
        self.config.output_dim()
    }

    /// Layout of every level, coarsest first.
    pub fn levels(&self) -> &[GridLevel] {
        &self.levels
    }

    /// Encodes `positions` (clamped to [0,1]^3, NaN -> 0) into feature-major
    /// `out[f * n + b]`. Panics if `out.len() != n * output_dim()`.
    pub fn encode(&self, positions: &[[f32; 3]], out: &mut [f32]) {
        self.encode_levels(positions, 0..self.levels.len(), out);
    }

    /// Encodes only `levels` into their rows of the output: `out` is the
    /// contiguous slice `[levels.start * F * n .. levels.end * F * n]` of
    /// `encode`'s `out`. Threads that take disjoint level ranges get exactly
    /// `encode`'s result. Panics on a bad range or length.
    pub fn encode_levels(&self, positions: &[[f32; 3]], levels: Range<usize>, out: &mut [f32]) {
        self.encode_impl(positions, levels, out, true);
    }

    /// `encode` with the SIMD kernels allowed or not (for tests and benchmarks).
    pub fn encode_with(&self, positions: &[[f32; 3]], out: &mut [f32], allow_simd: bool) {
        self.encode_impl(positions, 0..self.levels.len(), out, allow_simd);
    }

    fn encode_impl(&self, positions: &[[f32; 3]], levels: Range<usize>, out: &mut [f32], allow_simd: bool) {
        let n = positions.len();
        let fpl = self.config.features_per_level;
        assert!(
            levels.start <= levels.end && levels.end <= self.levels.len(),
            "HashGrid::encode: bad level range {levels:?}"
        );
        assert_eq!(
            out.len(),
            n * levels.len() * fpl,
            "HashGrid::encode: out has the wrong length"
        );
        let use_simd = allow_simd && fpl == 2 && simd::available();
        thread_local! {
            /// Positions as columns for the SIMD kernel, kept between calls.
            static COLUMNS: RefCell<[Vec<f32>; 3]> = const { RefCell::new([Vec::new(), Vec::new(), Vec::new()]) };
        }
        COLUMNS.with_borrow_mut(|columns| {
            if use_simd {
                // Converted once for all levels; lanes past the end are 0 so the kernel's reads stay defined.
                let padded = n.next_multiple_of(8);
                for (a, column) in columns.iter_mut().enumerate() {
                    column.clear();
                    column.extend(positions.iter().map(|p| unit(p[a])));
                    column.resize(padded, 0.0);
                }
            }
            let mut block = Block::new();
            for (row, level) in self.levels[levels].iter().enumerate() {
                let table = &self.params[level.param_offset..level.param_offset + level.entries * fpl];
                if use_simd {
                    let [x, y, z] = &*columns;
                    let (out0, out1) = out[2 * row * n..2 * (row + 1) * n].split_at_mut(n);
                    if simd::encode_level_f2(level, table, [x, y, z], out0, out1) {
                        continue;
                    }
                }
                for start in (0..n).step_by(BLOCK) {
                    block.load(&positions[start..]);
                    let first = row * fpl * n + start;
                    match fpl {
                        1 => encode_level_scalar::<1>(level, table, &block, out, first, n),
                        2 => encode_level_scalar::<2>(level, table, &block, out, first, n),
                        4 => encode_level_scalar::<4>(level, table, &block, out, first, n),
                        _ => encode_level_scalar::<8>(level, table, &block, out, first, n),
                    }
                }
            }
        });
    }

    /// Accumulates d(loss)/d(params) into `grad.values` from feature-major
    /// `d_out` (shaped like `encode`'s `out`) and records as touched the 8
    /// corner entries of every sample whose gradient on that level is not all
    /// zero (so touched can include a zero-weight corner, e.g. on a cube face).
    /// Panics if `d_out` or `grad` have the wrong length.
    pub fn backward(&self, positions: &[[f32; 3]], d_out: &[f32], grad: &mut GridGrad) {
        self.backward_levels(positions, 0..self.levels.len(), d_out, grad);
    }

    /// `backward` for `levels` only; `d_rows` is their slice of `d_out`, as in
    /// [`HashGrid::encode_levels`]. Levels own disjoint parameters, so
    /// threads on disjoint level ranges, each with its own [`GridGrad`],
    /// merge into exactly the single-threaded gradient whatever the split.
    pub fn backward_levels(&self, positions: &[[f32; 3]], levels: Range<usize>, d_rows: &[f32], grad: &mut GridGrad) {
        self.backward_impl(positions, levels, d_rows, grad, true);
    }

    /// `backward` with the SIMD kernels allowed or not (for tests and benchmarks).
    pub fn backward_with(&self, positions: &[[f32; 3]], d_out: &[f32], grad: &mut GridGrad, allow_simd: bool) {
        self.backward_impl(positions, 0..self.levels.len(), d_out, grad, allow_simd);
    }

    fn backward_impl(
        &self,
        positions: &[[f32; 3]],
        levels: Range<usize>,
        d_rows: &[f32],
        grad: &mut GridGrad,
        allow_simd: bool,
    ) {
        let n = positions.len();
        let fpl = self.config.features_per_level;
        assert!(
            levels.start <= levels.end && levels.end <= self.levels.len(),
            "HashGrid::backward: bad level range {levels:?}"
        );
        assert_eq!(
            d_rows.len(),
            n * levels.len() * fpl,
            "HashGrid::backward: d_out has the wrong length"
        );
        assert_eq!(
            grad.values.len(),
            self.params.len(),
            "HashGrid::backward: gradient buffer of another grid"
        );
        let use_simd = allow_simd && simd::available();
        let mut block = Block::new();
        for (row, level) in self.levels[levels].iter().enumerate() {
            let rows = &d_rows[row * fpl * n..(row + 1) * fpl * n];
            match fpl {
                1 => backward::level::<1>(level, positions, rows, &mut block, use_simd, grad),
                2 => backward::level::<2>(level, positions, rows, &mut block, use_simd, grad),
                4 => backward::level::<4>(level, positions, rows, &mut block, use_simd, grad),
                _ => backward::level::<8>(level, positions, rows, &mut block, use_simd, grad),
            }
        }
    }
}

/// Scalar encode of one block on one level: `out[first + f*n + i]`.
fn encode_level_scalar<const F: usize>(
    level: &GridLevel,
    table: &[f32],
    block: &Block,
    out: &mut [f32],
    first: usize,
    n: usize,
) {
    for i in 0..block.len {
        let (idx, w) = level.corners([block.x[i], block.y[i], block.z[i]]);
        let mut acc = [0f32; F];
        for c in 0..8 {
            let e = idx[c] as usize * F;
            let v = &table[e..e + F];
            for f in 0..F {
                acc[f] += w[c] * v[f];
            }
        }
        for f in 0..F {
            out[first + f * n + i] = acc[f];
        }
    }
}
