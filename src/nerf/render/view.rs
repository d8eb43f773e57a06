//! Render whole views of a trained model in the scan's metric world frame:
//! colour (optional), metric z-depth and opacity per pixel.
//!
//! For many views of one model, [`ViewRenderer::pruned`] first re-estimates
//! from the field which cells hold density, at twice the grid's resolution
//! ([`crate::nerf::occupancy::from_field`]).

use crate::nerf::appearance::{as_photographed, off_axis_r2, Affine, Vignetting, IDENTITY, NO_VIGNETTING};
use crate::nerf::camera::LocalCamera;

use crate::nerf::model_file::Model;
use crate::nerf::occupancy::from_field::rendering_grid;
use crate::nerf::occupancy::OccupancyGrid;
use crate::nerf::render::rays::{render_image, render_pixels, RayOutput};
use crate::poses::{GeometryError, SceneTransform};
use crate::scan::Intrinsics;
use nalgebra::IsometryMatrix3;

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
    /// The grid rays are marched through, when not the model's own.
    pruned: Option<OccupancyGrid>,
    /// Colour map applied to rendered colour (the identity: neutral).
    appearance: Affine,
    /// The lens's falloff applied before it (none: neutral).
    lens: Vignetting,
}

/// An 8-bit channel of a colour in [0, 1].
#[inline]
fn to_u8(c: f32) -> u8 {
    (c * 255.0).round().clamp(0.0, 255.0) as u8
}

impl<'a> ViewRenderer<'a> {
    /// Renderer for `model` (fails if its stored transform is invalid).
    pub fn new(model: &'a Model) -> Result<Self, GeometryError> {
        Ok(ViewRenderer {
            model,
            transform: model.scene_transform()?,
            pruned: None,
            appearance: IDENTITY,
            lens: NO_VIGNETTING,
        })
    }

    /// Renderer for `model` through a grid re-estimated from the field
    /// ([`rendering_grid`]: worth it for many views, the set-up costs about
    /// as much as rendering a few views with the model's own grid).
    pub fn pruned(model: &'a Model) -> Result<Self, GeometryError> {
        let grid = rendering_grid(&model.field, &model.occupancy);
        Self::with_grid(model, grid)
    }

    /// Renderer for `model` marching through `grid` instead of the model's own.
    pub fn with_grid(model: &'a Model, grid: OccupancyGrid) -> Result<Self, GeometryError> {
        Ok(ViewRenderer {
            model,
            transform: model.scene_transform()?,
            pruned: Some(grid),
            appearance: IDENTITY,
            lens: NO_VIGNETTING,
        })
    }

    /// Render colour as seen through `map` (a frame's appearance,
    /// `Model::frame_appearance`) instead of the model's neutral colour.
    pub fn with_appearance(mut self, map: Affine) -> Self {
        self.appearance = map;
        self
    }

    /// Render colour as the camera's lens darkens it (`Model::vignetting`):
    /// with a frame's map, a view as that frame was captured.
    pub fn with_lens(mut self, lens: Vignetting) -> Self {
        self.lens = lens;
        self
    }

    /// An 8-bit colour from a rendered one through the lens and the
    /// appearance map, for a ray whose direction in the camera is
    /// `t_per_z` times as long as its z (`LocalCamera::ray`).
    #[inline]
    fn colour_u8(&self, rgb: [f32; 3], t_per_z: f32) -> [u8; 3] {
        as_photographed(&self.appearance, &self.lens, off_axis_r2(t_per_z), rgb).map(to_u8)
    }

    /// The occupancy grid rays are marched through.
    pub fn grid(&self) -> &OccupancyGrid {
        self.pruned.as_ref().unwrap_or(&self.model.occupancy)
    }

    /// The camera in the model's local frame.
    pub fn local_camera(
        &self,
        camera_to_world: &IsometryMatrix3<f64>,
        k: &Intrinsics,
        width: u32,
        height: u32,
    ) -> LocalCamera {
        LocalCamera::new(&self.transform.world_to_local_pose(camera_to_world), k, width, height)
    }

    /// Z-depth in metres of a ray's surface through pixel (u, v), 0 = none.
    #[inline]
    fn depth_m(&self, camera: &LocalCamera, o: &RayOutput, u: f32, v: f32) -> f32 {
        let metres_per_unit = 1.0 / self.transform.scale() as f32;
        let t_per_z = camera.ray(u, v).1;
        o.depth_median
            .map(|t| t / t_per_z * metres_per_unit)
            .filter(|z| z.is_finite() && *z > 0.0)
            .unwrap_or(0.0)
    }

    /// Render the listed pixels (integer = pixel centre) of a camera.
    pub fn render_pixels(
        &self,
        camera: &LocalCamera,
        pixels: &[(f32, f32)],
        color: bool,
    ) -> (Vec<[u8; 3]>, Vec<f32>, Vec<f32>) {
        let opts = self.model.render_options(color);
        let out = render_pixels(&self.model.field, self.grid(), &opts, camera, pixels);
        let rgb = if color {
            out.iter()
                .zip(pixels)
                .map(|(o, &(u, v))| self.colour_u8(o.rgb, camera.ray(u, v).1))
                .collect()
        } else {
            Vec::new()
        };
        let depth = out
            .iter()
            .zip(pixels)
            .map(|(o, &(u, v))| self.depth_m(camera, o, u, v))
            .collect();
        let opacity = out.iter().map(|o| o.opacity).collect();
        (rgb, depth, opacity)
    }

    /// Render every pixel of a view.
    pub fn render_view(
        &self,
        camera_to_world: &IsometryMatrix3<f64>,
        k: &Intrinsics,
        width: u32,
        height: u32,
        color: bool,
    ) -> ViewRender {
        let camera = self.local_camera(camera_to_world, k, width, height);
        let opts = self.model.render_options(color);
        let out = render_image(&self.model.field, self.grid(), &opts, &camera);
        let w = width.max(1) as usize;
        let rgb = if color {
            out.iter()
                .enumerate()
                .flat_map(|(i, o)| self.colour_u8(o.rgb, camera.ray((i % w) as f32, (i / w) as f32).1))
                .collect()
        } else {
            Vec::new()
        };
        let depth_m = out
            .iter()
            .enumerate()
            .map(|(i, o)| self.depth_m(&camera, o, (i % w) as f32, (i / w) as f32))
            .collect();
        let opacity = out.iter().map(|o| o.opacity).collect();
        ViewRender {
            width,
            height,
            rgb,
            depth_m,
            opacity,
        }
    }
}
