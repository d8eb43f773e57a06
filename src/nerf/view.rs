//! Render whole views of a trained model in the scan's metric world frame:
//! colour (optional), metric z-depth and opacity per pixel.

use super::camera::LocalCamera;
use super::fit::{model_transform, render_options};
use super::model_file::Model;
use super::render::render_pixels;
use crate::poses::{GeometryError, SceneTransform};
use crate::scan::Intrinsics;
use glam::DMat4;

/// A rendered view.
#[derive(Clone, Debug)]
pub struct ViewRender {
    pub width: u32,
    pub height: u32,
    /// RGB8, row-major (empty when colour was not requested).
    pub rgb: Vec<u8>,
    /// Z-depth in metres of the first surface crossing, 0 = no surface.
    pub depth_m: Vec<f32>,
    /// Accumulated opacity per pixel.
    pub opacity: Vec<f32>,
}

/// A model ready to render views in world coordinates.
pub struct ViewRenderer<'a> {
    pub model: &'a Model,
    pub transform: SceneTransform,
}

impl<'a> ViewRenderer<'a> {
    /// Renderer for `model` (fails if its stored transform is invalid).
    pub fn new(model: &'a Model) -> Result<Self, GeometryError> {
        Ok(ViewRenderer { model, transform: model_transform(model)? })
    }

    /// The camera in the model's local frame.
    pub fn local_camera(&self, camera_to_world: &DMat4, k: &Intrinsics, width: u32, height: u32) -> LocalCamera {
        LocalCamera::new(&self.transform.world_to_local_pose(camera_to_world), k, width, height)
    }

    /// Render the listed pixels (integer = pixel centre) of a camera.
    pub fn render_pixels(&self, camera: &LocalCamera, pixels: &[(f32, f32)], color: bool) -> (Vec<[u8; 3]>, Vec<f32>, Vec<f32>) {
        let opts = render_options(self.model, color);
        let out = render_pixels(&self.model.field, &self.model.occupancy, &opts, camera, pixels);
        let metres_per_unit = 1.0 / self.transform.scale as f32;
        let mut rgb = Vec::with_capacity(if color { out.len() } else { 0 });
        let mut depth = Vec::with_capacity(out.len());
        let mut opacity = Vec::with_capacity(out.len());
        for (o, &(u, v)) in out.iter().zip(pixels) {
            if color {
                rgb.push(o.rgb.map(|c| (c * 255.0).round().clamp(0.0, 255.0) as u8));
            }
            let t_per_z = camera.ray(u, v).1;
            depth.push(o.depth_median.map(|t| t / t_per_z * metres_per_unit).filter(|z| z.is_finite() && *z > 0.0).unwrap_or(0.0));
            opacity.push(o.opacity);
        }
        (rgb, depth, opacity)
    }

    /// Render every pixel of a view.
    pub fn render_view(&self, camera_to_world: &DMat4, k: &Intrinsics, width: u32, height: u32, color: bool) -> ViewRender {
        let camera = self.local_camera(camera_to_world, k, width, height);
        let pixels: Vec<(f32, f32)> =
            (0..height).flat_map(|v| (0..width).map(move |u| (u as f32, v as f32))).collect();
        let (rgb, depth_m, opacity) = self.render_pixels(&camera, &pixels, color);
        ViewRender { width, height, rgb: rgb.into_iter().flatten().collect(), depth_m, opacity }
    }
}
