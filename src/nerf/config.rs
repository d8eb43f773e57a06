//! Model and training settings derived from the scene itself: the finest
//! grid cell, step sizes and depth-loss widths follow the scene's scale, so
//! a tabletop and a room (or the same scene at 1/100 scale) get the same
//! treatment in local units.

use super::field::{FieldConfig, GridSpec};
use super::hash_grid::HashGridConfig;
use super::occupancy::DEFAULT_RESOLUTION;
use super::train::{StepSpec, TrainConfig};
use serde::{Deserialize, Serialize};
use std::str::FromStr;

/// Speed/quality trade-off.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Preset {
    Fast,
    Default,
    Quality,
}

impl FromStr for Preset {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, String> {
        match s {
            "fast" => Ok(Preset::Fast),
            "default" => Ok(Preset::Default),
            "quality" => Ok(Preset::Quality),
            other => Err(format!("unknown preset `{other}` (expected fast, default or quality)")),
        }
    }
}

impl Preset {
    /// Finest grid cell as a multiple of the typical pixel footprint.
    fn pixels_per_cell(self) -> f64 {
        match self {
            Preset::Fast => 12.0,
            Preset::Default => 3.0,
            Preset::Quality => 2.0,
        }
    }

    /// Fewest finest cells across the unit cube: low-resolution scans still
    /// get geometry finer than their pixels (depth supervision resolves it).
    fn min_cells(self) -> f64 {
        match self {
            Preset::Fast => 128.0,
            Preset::Default => 256.0,
            Preset::Quality => 384.0,
        }
    }

    fn samples_per_step(self) -> usize {
        match self {
            Preset::Fast => 1 << 15,
            Preset::Default => 1 << 16,
            Preset::Quality => 1 << 17,
        }
    }
}

/// Everything needed to build and train a model for one scene.
#[derive(Clone, Debug, PartialEq)]
pub struct NerfSettings {
    pub field: FieldConfig,
    pub train: TrainConfig,
    pub occupancy_resolution: usize,
    pub render_step: StepSpec,
}

/// Weight of the no-return term, on unless `fit --no-unseen-objects`: the
/// line-of-sight weight, so no return counts as much as free space seen.
pub const NO_RETURN_WEIGHT: f32 = 0.1;

/// Most finest-level cells across the unit cube.
const FINEST_CELLS: f64 = 2048.0;

/// Settings for a scene whose unit cube spans `metres_per_unit` metres and
/// whose cameras see `pixel_footprint_m` metres per pixel at their typical
/// viewing distance: the finest cell is a few pixel footprints, so detail
/// follows what the sensor resolves, at any scene scale.
pub fn settings_for_scene(
    metres_per_unit: f64,
    pixel_footprint_m: f64,
    preset: Preset,
    seed: u64,
    lambda_depth: Option<f32>,
) -> NerfSettings {
    let wanted = pixel_footprint_m * preset.pixels_per_cell();
    let cells = if wanted.is_finite() && wanted > 0.0 { metres_per_unit / wanted } else { 256.0 };
    let cells = cells.clamp(preset.min_cells(), FINEST_CELLS);
    let grid = HashGridConfig::for_scene(metres_per_unit, metres_per_unit / cells);
    let finest = grid.finest_resolution.max(16) as f32;
    // About one finest cell per step; far steps grow slowly for big scenes.
    let step = StepSpec { min_step: 0.75 / finest, max_step: 1.0 / 32.0, cone: 1.0 / 256.0 };
    let train = TrainConfig {
        samples_per_step: preset.samples_per_step(),
        max_samples_per_ray: 1024,
        learning_rate: 1e-2,
        warmup_steps: 128,
        lambda_depth: lambda_depth.unwrap_or(0.1),
        lambda_line_of_sight: 0.1,
        surface_window: 1.5 / finest,
        lambda_no_return: 0.0,
        step,
        occupancy_every: 16,
        occupancy_decay: 0.95,
        seed,
    };
    NerfSettings {
        field: FieldConfig { grid: GridSpec::from(&grid), density_hidden: vec![64], color_hidden: vec![64, 64] },
        train,
        occupancy_resolution: DEFAULT_RESOLUTION,
        render_step: step,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn presets_order_from_coarse_and_cheap_to_fine_and_costly() {
        // Tabletop-like (6 m cube, 2 mm pixels) and room-like (20 m, 8 mm) scenes.
        for (metres, footprint) in [(6.0, 0.002), (20.0, 0.008)] {
            let [fast, default, quality] = [Preset::Fast, Preset::Default, Preset::Quality]
                .map(|p| settings_for_scene(metres, footprint, p, 0, None));
            let finest = |s: &NerfSettings| s.field.grid.finest_resolution;
            assert!(finest(&fast) < finest(&default) && finest(&default) < finest(&quality), "{metres} m");
            assert!(fast.train.samples_per_step <= default.train.samples_per_step);
            assert!(default.train.samples_per_step <= quality.train.samples_per_step);
            // The step follows the finest cell.
            assert!(quality.train.step.min_step < default.train.step.min_step);
        }
    }
}
