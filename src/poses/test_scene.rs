//! Synthetic scans with exact depth for the geometry tests: cameras inside a
//! box-shaped room, each pixel's depth found by casting its ray to the walls.

use crate::rng::Rng;
use crate::scan::{DepthMap, Frame, Intrinsics, Layout, RgbImage, Scan};
use nalgebra::{IsometryMatrix3, Matrix3, Point3, Rotation3, Translation3, UnitQuaternion, Vector3};
use std::f64::consts::TAU;

/// What room to build and how to film it.
#[derive(Clone, Debug)]
pub struct Room {
    /// Half edge lengths in the room's own frame (before `scale`).
    pub half: Vector3<f64>,
    /// Room frame to world rotation, about the world origin.
    pub rotation: UnitQuaternion<f64>,
    /// Uniform scale applied after the rotation.
    pub scale: f64,
    pub frames: usize,
    pub width: u32,
    pub height: u32,
    /// Fraction of pixels whose depth is multiplied by 1000.
    pub flying: f64,
    /// Whether frames carry depth at all.
    pub with_depth: bool,
}

impl Default for Room {
    fn default() -> Self {
        Room {
            half: Vector3::new(2.0, 1.5, 1.25),
            rotation: UnitQuaternion::identity(),
            scale: 1.0,
            frames: 24,
            width: 64,
            height: 48,
            flying: 0.0,
            with_depth: true,
        }
    }
}

impl Room {
    /// Room corners in the room frame (centred on the origin).
    pub fn local_box(&self) -> (Point3<f64>, Point3<f64>) {
        (Point3::from(-self.half), Point3::from(self.half))
    }

    /// Room frame point to world.
    pub fn to_world(&self, p: &Point3<f64>) -> Point3<f64> {
        self.rotation * p * self.scale
    }

    /// Camera-to-world pose of frame `k` in the room frame (unscaled).
    fn room_pose(&self, k: usize) -> IsometryMatrix3<f64> {
        let yaw = TAU * k as f64 / self.frames as f64;
        let eye = Vector3::new(
            0.35 * self.half.x * yaw.cos(),
            0.35 * self.half.y * yaw.sin(),
            0.1 * self.half.z * yaw.sin(),
        );
        let forward = Vector3::new((yaw + 0.3).cos(), (yaw + 0.3).sin(), 0.4 * (3.0 * yaw).sin()).normalize();
        let right = forward.cross(&Vector3::z()).normalize();
        let down = forward.cross(&right);
        IsometryMatrix3::from_parts(
            Translation3::from(eye),
            Rotation3::from_matrix_unchecked(Matrix3::from_columns(&[right, down, forward])),
        )
    }

    /// Build the scan.
    pub fn scan(&self) -> Scan {
        let (w, h) = (self.width, self.height);
        let k = Intrinsics {
            fx: 0.6 * w as f64,
            fy: 0.6 * w as f64,
            cx: (w as f64 - 1.0) / 2.0,
            cy: (h as f64 - 1.0) / 2.0,
        };
        let world_rot = self.rotation.to_rotation_matrix();
        let frames = (0..self.frames)
            .map(|i| {
                let pose = self.room_pose(i);
                let rot = pose.rotation;
                let eye = Point3::from(pose.translation.vector);
                let mut rng = Rng::new(99, i as u64);
                let mut rgb = RgbImage::new(w, h);
                let mut metres = vec![0.0f32; (w * h) as usize];
                for v in 0..h {
                    for u in 0..w {
                        let d = rot * k.unproject(u as f64, v as f64);
                        let (t, axis) = exit(&eye, &d, &self.half);
                        let mut z = (t * self.scale) as f32;
                        if rng.f64() < self.flying {
                            z *= 1000.0;
                        }
                        metres[(v * w + u) as usize] = z;
                        let shade = (40 * axis as u8).wrapping_add((u + v) as u8);
                        rgb.put_pixel(u, v, image::Rgb([shade, 255 - shade, 60 + 30 * axis as u8]));
                    }
                }
                let c2w = IsometryMatrix3::from_parts(
                    Translation3::from(self.to_world(&eye).coords),
                    world_rot * pose.rotation,
                );
                Frame {
                    id: i as u64,
                    name: format!("{i:06}"),
                    rgb,
                    depth: self.with_depth.then_some(DepthMap {
                        width: w,
                        height: h,
                        metres,
                    }),
                    camera_to_world: c2w,
                    intrinsics: k,
                    depth_size: None,
                }
            })
            .collect();
        Scan {
            root: "synthetic".into(),
            layout: Layout::Native,
            frames,
            bounds: None,
            warnings: Vec::new(),
            inputs: Vec::new(),
        }
    }
}

/// Ray parameter where `o + t d` leaves the box [-half, half] from inside,
/// and the axis of the wall it hits (0..6).
fn exit(o: &Point3<f64>, d: &Vector3<f64>, half: &Vector3<f64>) -> (f64, usize) {
    let mut best = (f64::INFINITY, 0);
    for a in 0..3 {
        if d[a] != 0.0 {
            let (wall, id) = if d[a] > 0.0 {
                (half[a], 2 * a)
            } else {
                (-half[a], 2 * a + 1)
            };
            let t = (wall - o[a]) / d[a];
            if t < best.0 {
                best = (t, id);
            }
        }
    }
    best
}
