//! Render a fixture's held-out views with a model and compare with the
//! exact ground truth renders.

use crate::fixture::{read_meta, trajectory, FixtureError};
use crate::nerf::model_file::Model;
use crate::nerf::render::view::ViewRenderer;
use crate::nerf::train::metrics::{depth_mae, psnr, ssim};
use crate::poses::GeometryError;
use std::path::Path;

/// Accuracy of a model on a fixture's held-out views.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct HoldoutScore {
    pub views: usize,
    pub psnr: f64,
    pub ssim: f64,
    /// Mean absolute z-depth error (metres) where both have a surface.
    pub depth_mae_m: f64,
    /// Fraction of ground-truth surface pixels where the model found none.
    pub depth_missing: f64,
}

/// Why scoring failed.
#[derive(Debug, thiserror::Error)]
pub enum ScoreError {
    #[error(transparent)]
    Fixture(#[from] FixtureError),
    #[error(transparent)]
    Geometry(#[from] GeometryError),
    #[error("{0}: the fixture has no held-out views")]
    NoHoldout(std::path::PathBuf),
}

/// Score `model` on the held-out views of the fixture in `fixture`.
pub fn score_holdout(model: &Model, fixture: &Path) -> Result<HoldoutScore, ScoreError> {
    let meta = read_meta(fixture)?;
    if meta.holdout == 0 {
        return Err(ScoreError::NoHoldout(fixture.to_path_buf()));
    }
    let scene = meta.build_scene();
    let path = trajectory(&scene, meta.frames, meta.holdout, meta.seed);
    let renderer = ViewRenderer::new(model)?;
    let mut score = HoldoutScore {
        views: path.holdout.len(),
        ..Default::default()
    };
    let (mut depth_sum, mut depth_views, mut missing, mut surface) = (0.0, 0usize, 0usize, 0usize);
    for pose in &path.holdout {
        let truth = scene.render(pose, &meta.intrinsics, meta.width, meta.height);
        let view = renderer.render_view(pose, &meta.intrinsics, meta.width, meta.height, true);
        score.psnr += psnr(&view.rgb, truth.rgb.as_raw());
        score.ssim += ssim(&view.rgb, truth.rgb.as_raw(), meta.width as usize, meta.height as usize);
        if let Some(mae) = depth_mae(&view.depth_m, &truth.depth) {
            depth_sum += mae;
            depth_views += 1;
        }
        for (&p, &t) in view.depth_m.iter().zip(&truth.depth) {
            if t > 0.0 {
                surface += 1;
                if p <= 0.0 {
                    missing += 1;
                }
            }
        }
    }
    let n = score.views as f64;
    score.psnr /= n;
    score.ssim /= n;
    score.depth_mae_m = if depth_views > 0 {
        depth_sum / depth_views as f64
    } else {
        f64::INFINITY
    };
    score.depth_missing = missing as f64 / surface.max(1) as f64;
    Ok(score)
}
