//! Sizing a hash grid to a scene: finest cell from the scene's extent, levels
//! from a growth factor, table size from the surface area the finest level
//! can resolve, so a small scene gets a small (often fully dense) model.

use super::HashGridConfig;

/// Finest resolution cap (cells per side).
pub const FINEST_CAP: u32 = 4096;
/// Coarsest resolution for grids that are at least this fine.
pub const BASE_RESOLUTION: u32 = 16;
/// Largest growth factor between consecutive levels.
pub const MAX_GROWTH: f64 = 1.45;
/// Table size cap for scene-sized grids (entries per level).
pub const LOG2_TABLE_CAP: u32 = 19;
/// Smallest hashed table (entries per level).
const LOG2_TABLE_MIN: u32 = 12;
/// Table entries per finest-level face cell (res^2): scenes are surfaces, so
/// the cells that get samples grow like res^2 (a tabletop: the table, the
/// objects, the free space next to them), not res^3. Kept small because on a
/// CPU the grid runs at cache speed: a 2^16 table instead of 2^17 makes
/// encode+backward ~1.3x faster for a tabletop.
const ENTRIES_PER_FACE: u64 = 2;
/// A finest level with at most this many vertices is stored dense outright.
const DENSE_FINEST_MAX: u64 = 1 << 16;
/// Fallback cells per side when the inputs are not usable numbers.
const FALLBACK_FINEST: u32 = 128;

/// See [`HashGridConfig::for_scene`].
pub fn for_scene(extent_m: f64, target_cell_m: f64) -> HashGridConfig {
    let ratio = extent_m / target_cell_m;
    let finest = if ratio.is_finite() && ratio > 0.0 {
        (ratio.ceil().min(FINEST_CAP as f64) as u32).max(2)
    } else {
        FALLBACK_FINEST
    };
    let base = BASE_RESOLUTION.min(finest);
    let levels = if finest == base {
        1
    } else {
        // Smallest count whose growth factor is at most MAX_GROWTH.
        let steps = ((finest as f64 / base as f64).ln() / MAX_GROWTH.ln() - 1e-9)
            .ceil()
            .max(1.0);
        steps as usize + 1
    };
    let side = finest as u64 + 1;
    let dense_finest = side * side * side;
    let hashed = ceil_log2(ENTRIES_PER_FACE * finest as u64 * finest as u64).clamp(LOG2_TABLE_MIN, LOG2_TABLE_CAP);
    // Dense when that costs at most twice the hashed table: no collisions for little memory.
    let log2_table_size = if dense_finest <= DENSE_FINEST_MAX || dense_finest <= 2u64 << hashed {
        ceil_log2(dense_finest).min(LOG2_TABLE_CAP)
    } else {
        hashed
    };
    HashGridConfig {
        levels,
        features_per_level: 2,
        log2_table_size,
        base_resolution: base,
        finest_resolution: finest,
    }
}

/// Smallest k with 2^k >= n (n >= 1).
fn ceil_log2(n: u64) -> u32 {
    n.max(1).next_power_of_two().trailing_zeros()
}
