//! Cameras and rays in the NeRF's local unit cube, shared by the occupancy
//! grid, rendering and training.

use crate::poses::Aabb;
use crate::scan::Intrinsics;
use nalgebra::{IsometryMatrix3, Matrix3, Point3, Vector3};

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
    pub fn new(camera_to_local: &IsometryMatrix3<f64>, k: &Intrinsics, width: u32, height: u32) -> LocalCamera {
        let m = camera_to_local.rotation.matrix();
        let mut rotation = [[0.0f32; 3]; 3];
        for (r, row) in rotation.iter_mut().enumerate() {
            for (c, v) in row.iter_mut().enumerate() {
                *v = m[(r, c)] as f32;
            }
        }
        let t = camera_to_local.translation.vector;
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
        (
            LocalRay {
                origin: self.origin,
                dir,
            },
            norm,
        )
    }

    /// The camera-to-local rotation as an f64 matrix.
    pub fn rotation_matrix(&self) -> Matrix3<f64> {
        Matrix3::from_fn(|r, c| self.rotation[r][c] as f64)
    }

    /// Number of pixels.
    pub fn pixels(&self) -> usize {
        self.width as usize * self.height as usize
    }
}

/// A ray in local (unit-cube) coordinates.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct LocalRay {
    pub origin: [f32; 3],
    /// Unit direction.
    pub dir: [f32; 3],
}

impl LocalRay {
    /// Point at distance `t`.
    #[inline]
    pub fn at(&self, t: f32) -> [f32; 3] {
        [
            self.origin[0] + t * self.dir[0],
            self.origin[1] + t * self.dir[1],
            self.origin[2] + t * self.dir[2],
        ]
    }
}

/// Parameter interval of a ray inside [0,1]^3 (t >= 0), `None` on a miss.
pub fn unit_cube_interval(o: [f32; 3], d: [f32; 3]) -> Option<(f32, f32)> {
    Aabb::UNIT.ray_interval(&Point3::from(o), &Vector3::from(d))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn unit_cube_interval_handles_parallel_rays_faces_and_misses() {
        assert_eq!(unit_cube_interval([0.5, 0.5, -1.0], [0.0, 0.0, 1.0]), Some((1.0, 2.0)));
        // Parallel to a face with the origin on it.
        assert_eq!(unit_cube_interval([0.0, 0.5, -1.0], [0.0, 0.0, 1.0]), Some((1.0, 2.0)));
        assert_eq!(unit_cube_interval([-0.1, 0.5, -1.0], [0.0, 0.0, 1.0]), None);
        // Looking away.
        assert_eq!(unit_cube_interval([0.5, 0.5, -1.0], [0.0, 0.0, -1.0]), None);
        // Inside.
        let (t0, t1) = unit_cube_interval([0.5, 0.5, 0.5], [1.0, 0.0, 0.0]).unwrap();
        assert_eq!(t0, 0.0);
        assert!((t1 - 0.5).abs() < 1e-6);
        assert_eq!(unit_cube_interval([f32::NAN, 0.5, 0.5], [1.0, 0.0, 0.0]), None);
    }
}
