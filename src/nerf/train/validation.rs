//! Validation during a fit (held-out evaluation): render a regular
//! subsample of each held-out view's pixels and compare with its colour and
//! sensor depth.

use crate::nerf::appearance::{as_photographed, off_axis_r2, Affine, Vignetting};
use crate::nerf::field::Field;
use crate::nerf::occupancy::OccupancyGrid;
use crate::nerf::render::rays::{render_pixels_past, RenderOptions};
use crate::nerf::train::dataset::View;
use crate::nerf::train::metrics;
use crate::scan::{vouched_free_distance, vouched_start, ColourBorder};

/// Accuracy on held-out views.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct Validation {
    pub psnr: f64,
    pub ssim: f64,
    /// Mean absolute depth error in metres where both the sensor and the
    /// model have depth; `None` when no pixel has both.
    pub depth_mae_m: Option<f64>,
}

/// Pixel grid of a view subsampled so its longer side has about `max_side`
/// pixels, less the points on lines its `border` leaves out (the points
/// stay where they are without a border, so figures compare across builds).
pub fn subsample_grid(
    width: u32,
    height: u32,
    max_side: u32,
    border: &ColourBorder,
) -> (usize, usize, Vec<(f32, f32)>) {
    let step = (width.max(height) as f64 / max_side.max(1) as f64).max(1.0);
    let (x0, y0, x1, y1) = border.kept_rect(width, height);
    let along = |count: u32, from: u32, to: u32| -> Vec<f32> {
        let n = ((count as f64 / step).floor() as usize).max(1);
        (0..n)
            .map(|i| ((i as f64 + 0.5) * step - 0.5).round().min(count as f64 - 1.0) as u32)
            .filter(|&p| p >= from && p < to)
            .map(|p| p as f32)
            .collect()
    };
    let (xs, ys) = (along(width, x0, x1), along(height, y0, y1));
    let pixels = ys.iter().flat_map(|&v| xs.iter().map(move |&u| (u, v))).collect();
    (xs.len(), ys.len(), pixels)
}

/// Evaluate on `views` (their scene pixels: dead border lines are left
/// out); `metres_per_unit` converts local depth to metres.
/// With `appearance` (one map per view, and the lens) the rendered colour
/// goes through the lens's falloff and the view's map, as the photo went
/// through its camera's lens and exposure.
pub fn validate(
    field: &Field,
    grid: &OccupancyGrid,
    opts: &RenderOptions,
    views: &[View],
    metres_per_unit: f64,
    max_side: u32,
    appearance: Option<(&[Affine], &Vignetting)>,
) -> Validation {
    let (mut psnr, mut ssim) = (0.0, 0.0);
    let (mut depth_sum, mut depth_n) = (0.0, 0usize);
    for (i, view) in views.iter().enumerate() {
        let map = appearance.and_then(|(maps, lens)| Some((maps.get(i)?, lens)));
        let cam = &view.camera;
        let (w, h, pixels) = subsample_grid(cam.width, cam.height, max_side, &view.colour_border);
        // Rays start past the space the view's own depth vouches free, as
        // `label` renders every frame: a held-out camera can stand in
        // density no training view constrained.
        let depth = view.depth.as_deref();
        let free_z = depth.map_or(0.0, vouched_free_distance);
        let near: Vec<f32> = pixels
            .iter()
            .map(|&(u, v)| {
                let measured = depth.map_or(0.0, |d| d[v as usize * cam.width as usize + u as usize]);
                vouched_start(measured, free_z, cam.ray(u, v).1)
            })
            .collect();
        let out = render_pixels_past(field, grid, opts, cam, &pixels, &near);
        let mut rendered = Vec::with_capacity(w * h * 3);
        let mut truth = Vec::with_capacity(w * h * 3);
        for (o, &(u, v)) in out.iter().zip(&pixels) {
            let idx = v as usize * cam.width as usize + u as usize;
            let rgb = map.map_or(o.rgb, |(a, lens)| {
                as_photographed(a, lens, off_axis_r2(cam.ray(u, v).1), o.rgb)
            });
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

#[cfg(test)]
mod tests {
    use super::*;
    use crate::nerf::train::step::tests::{colour_options, plane_views, small_config};
    use crate::rng::Rng;

    /// Regression: a held-out camera can stand in density no training view
    /// constrained (a room scan's last frame rendered its floor at 3 cm).
    /// Its rays start past the space its own depth vouches free, as `label`
    /// renders every frame. Here density fills all space: the plane is
    /// 0.45 away, the view vouches 0.225 free, so the rendered surface sits
    /// at the free distance, not on the lens.
    #[test]
    fn held_out_views_render_past_the_space_their_depth_vouches_free() {
        let (config, train) = small_config(1);
        let mut field = Field::new(config, &mut Rng::new(1, 0));
        let (outputs, params) = (field.density.config.output, field.density.params.len());
        field.density.params.fill(0.0);
        field.density.params[params - outputs..].fill(8.0);
        let opts = colour_options(&train);
        let views = plane_views(1, 32, true);
        let r = validate(&field, &OccupancyGrid::full(64), &opts, &views, 1.0, 32, None);
        let mae = r.depth_mae_m.unwrap();
        assert!(
            (0.2..0.25).contains(&mae),
            "depth error {mae} (0.45 on the lens, 0.225 past the free space)"
        );
        assert!(r.psnr.is_finite());
    }

    /// A dead last row and column (a converter's padding) are no view of
    /// the scene: with the border set, what they hold does not change the
    /// score, and the grid stays inside the kept lines.
    #[test]
    fn dead_border_lines_are_not_scored() {
        let (config, train) = small_config(2);
        let field = Field::new(config, &mut Rng::new(2, 0));
        let opts = colour_options(&train);
        let grid = OccupancyGrid::full(32);
        let border = ColourBorder {
            bottom: 1,
            right: 1,
            ..Default::default()
        };
        let mut views = plane_views(1, 32, true);
        views[0].colour_border = border;
        let clean = validate(&field, &grid, &opts, &views, 1.0, u32::MAX, None);
        let (w, h) = (views[0].camera.width as usize, views[0].camera.height as usize);
        for (i, px) in views[0].rgb.chunks_exact_mut(3).enumerate() {
            if i % w == w - 1 || i / w == h - 1 {
                px.fill(0);
            }
        }
        let padded = validate(&field, &grid, &opts, &views, 1.0, u32::MAX, None);
        assert_eq!(clean, padded);
        views[0].colour_border = ColourBorder::default();
        let scored = validate(&field, &grid, &opts, &views, 1.0, u32::MAX, None);
        assert!(
            scored.psnr < clean.psnr - 0.1,
            "the padding is scored without the border: {scored:?} vs {clean:?}"
        );
        let (gw, gh, pixels) = subsample_grid(32, 32, u32::MAX, &border);
        assert_eq!((gw, gh, pixels.len()), (31, 31, 961));
        assert!(pixels.iter().all(|&(u, v)| u < 31.0 && v < 31.0));
        // The points stay where they were: a coarse grid that never met the
        // dead lines is the same with the border as without.
        let none = ColourBorder::default();
        assert_eq!(
            subsample_grid(640, 480, 160, &border),
            subsample_grid(640, 480, 160, &none)
        );
        let (w, h, coarse) = subsample_grid(640, 480, 160, &none);
        assert_eq!((w, h, coarse[0], coarse[161]), (160, 120, (2.0, 2.0), (6.0, 6.0)));
    }
}
