//! Cameras and training views expressed in the NeRF's local unit cube.

use super::march::LocalRay;
use crate::scan::Intrinsics;
use glam::DMat4;

/// A pinhole camera in local coordinates (OpenCV axes).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct LocalCamera {
    /// Camera-to-local rotation, row-major.
    pub rotation: [[f32; 3]; 3],
    /// Camera centre in local coordinates.
    pub origin: [f32; 3],
    pub fx: f32,
    pub fy: f32,
    pub cx: f32,
    pub cy: f32,
    pub width: u32,
    pub height: u32,
}

impl LocalCamera {
    /// Camera from a camera-to-local pose (rotation part orthonormal).
    pub fn new(camera_to_local: &DMat4, k: &Intrinsics, width: u32, height: u32) -> LocalCamera {
        let m = camera_to_local;
        let mut rotation = [[0.0f32; 3]; 3];
        for (r, row) in rotation.iter_mut().enumerate() {
            for (c, v) in row.iter_mut().enumerate() {
                *v = m.col(c)[r] as f32;
            }
        }
        let t = m.w_axis;
        LocalCamera {
            rotation,
            origin: [t.x as f32, t.y as f32, t.z as f32],
            fx: k.fx as f32,
            fy: k.fy as f32,
            cx: k.cx as f32,
            cy: k.cy as f32,
            width,
            height,
        }
    }

    /// Ray through continuous pixel (u, v) (integers are pixel centres) and
    /// the factor turning local z-depth into distance along the ray.
    #[inline]
    pub fn ray(&self, u: f32, v: f32) -> (LocalRay, f32) {
        let d = [(u - self.cx) / self.fx, (v - self.cy) / self.fy, 1.0];
        let norm = (d[0] * d[0] + d[1] * d[1] + 1.0).sqrt();
        let r = &self.rotation;
        let mut dir = [0.0f32; 3];
        for (a, out) in dir.iter_mut().enumerate() {
            *out = (r[a][0] * d[0] + r[a][1] * d[1] + r[a][2] * d[2]) / norm;
        }
        (LocalRay { origin: self.origin, dir }, norm)
    }

    /// Number of pixels.
    pub fn pixels(&self) -> usize {
        self.width as usize * self.height as usize
    }
}

/// One training or evaluation view: camera, colour and optional depth.
#[derive(Clone, Debug)]
pub struct View {
    pub camera: LocalCamera,
    /// RGB8, row-major.
    pub rgb: Vec<u8>,
    /// Z-depth in local units per pixel, 0 = no measurement.
    pub depth: Option<Vec<f32>>,
    /// Pixels where the sensor returned nothing, away from any measured
    /// pixel (not a speck or an edge dropout): something the sensor cannot
    /// see may be there. `None` when the view's missing depth says nothing.
    pub no_return: Option<Vec<bool>>,
}
