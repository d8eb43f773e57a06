//! Validation during a fit (held-out evaluation): render a regular
//! subsample of each held-out view's pixels and compare with its colour and
//! sensor depth.

use crate::nerf::appearance::{apply, Affine};
use crate::nerf::field::Field;
use crate::nerf::occupancy::OccupancyGrid;
use crate::nerf::render::rays::{render_pixels, RenderOptions};
use crate::nerf::train::dataset::View;
use crate::nerf::train::metrics;

/// Accuracy on held-out views.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct Validation {
    pub psnr: f64,
    pub ssim: f64,
    /// Mean absolute depth error in metres where both the sensor and the
    /// model have depth; `None` when no pixel has both.
    pub depth_mae_m: Option<f64>,
}

/// Pixel grid of a view subsampled so its longer side has about `max_side` pixels.
pub fn subsample_grid(width: u32, height: u32, max_side: u32) -> (usize, usize, Vec<(f32, f32)>) {
    let step = (width.max(height) as f64 / max_side.max(1) as f64).max(1.0);
    let w = ((width as f64 / step).floor() as usize).max(1);
    let h = ((height as f64 / step).floor() as usize).max(1);
    let mut pixels = Vec::with_capacity(w * h);
    for j in 0..h {
        for i in 0..w {
            let u = ((i as f64 + 0.5) * step - 0.5).round().min(width as f64 - 1.0);
            let v = ((j as f64 + 0.5) * step - 0.5).round().min(height as f64 - 1.0);
            pixels.push((u as f32, v as f32));
        }
    }
    (w, h, pixels)
}

/// Evaluate on `views`; `metres_per_unit` converts local depth to metres.
/// With `appearance` (one map per view) the rendered colour goes through
/// the view's map, as the photo went through its camera's exposure.
pub fn validate(
    field: &Field,
    grid: &OccupancyGrid,
    opts: &RenderOptions,
    views: &[View],
    metres_per_unit: f64,
    max_side: u32,
    appearance: Option<&[Affine]>,
) -> Validation {
    let (mut psnr, mut ssim) = (0.0, 0.0);
    let (mut depth_sum, mut depth_n) = (0.0, 0usize);
    for (i, view) in views.iter().enumerate() {
        let map = appearance.and_then(|maps| maps.get(i));
        let cam = &view.camera;
        let (w, h, pixels) = subsample_grid(cam.width, cam.height, max_side);
        let out = render_pixels(field, grid, opts, cam, &pixels);
        let mut rendered = Vec::with_capacity(w * h * 3);
        let mut truth = Vec::with_capacity(w * h * 3);
        for (o, &(u, v)) in out.iter().zip(&pixels) {
            let idx = v as usize * cam.width as usize + u as usize;
            let rgb = map.map_or(o.rgb, |a| apply(a, o.rgb));
            rendered.extend(rgb.map(|c| (c * 255.0).round().clamp(0.0, 255.0) as u8));
            truth.extend_from_slice(&view.rgb[3 * idx..3 * idx + 3]);
            if let (Some(depth), Some(t)) = (&view.depth, o.depth_median) {
                let z_true = depth[idx];
                if z_true > 0.0 {
                    let t_per_z = cam.ray(u, v).1;
                    depth_sum += ((t / t_per_z - z_true) as f64).abs() * metres_per_unit;
                    depth_n += 1;
                }
            }
        }
        psnr += metrics::psnr(&rendered, &truth);
        ssim += metrics::ssim(&rendered, &truth, w, h);
    }
    let n = views.len().max(1) as f64;
    Validation {
        psnr: psnr / n,
        ssim: ssim / n,
        depth_mae_m: (depth_n > 0).then(|| depth_sum / depth_n as f64),
    }
}
