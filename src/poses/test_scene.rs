//! Synthetic scans with exact depth for the geometry tests: cameras inside a
//! box-shaped room, each pixel's depth found by casting its ray to the walls.

use crate::glam_bridge::{ToGlam, ToNalgebra};
use crate::rng::Rng;
use crate::scan::{DepthMap, Frame, Intrinsics, Layout, RgbImage, Scan};
use glam::{DMat3, DMat4, DQuat, DVec3};
use std::f64::consts::TAU;

/// What room to build and how to film it.
#[derive(Clone, Debug)]
pub struct Room {
    /// Half edge lengths in the room's own frame (before `scale`).
    pub half: DVec3,
    /// Room frame to world rotation, about the world origin.
    pub rotation: DQuat,
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
            half: DVec3::new(2.0, 1.5, 1.25),
            rotation: DQuat::IDENTITY,
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
    pub fn local_box(&self) -> (DVec3, DVec3) {
        (-self.half, self.half)
    }

    /// Room frame point to world.
    pub fn to_world(&self, p: DVec3) -> DVec3 {
        self.rotation * p * self.scale
    }

    /// Camera-to-world pose of frame `k` in the room frame (unscaled).
    fn room_pose(&self, k: usize) -> DMat4 {
        let yaw = TAU * k as f64 / self.frames as f64;
        let eye = DVec3::new(
            0.35 * self.half.x * yaw.cos(),
            0.35 * self.half.y * yaw.sin(),
            0.1 * self.half.z * yaw.sin(),
        );
        let forward = DVec3::new((yaw + 0.3).cos(), (yaw + 0.3).sin(), 0.4 * (3.0 * yaw).sin()).normalize();
        let right = forward.cross(DVec3::Z).normalize();
        let down = forward.cross(right);
        DMat4::from_cols(
            right.extend(0.0),
            down.extend(0.0),
            forward.extend(0.0),
            eye.extend(1.0),
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
        let world_rot = DMat4::from_quat(self.rotation);
        let frames = (0..self.frames)
            .map(|i| {
                let pose = self.room_pose(i);
                let rot = DMat3::from_mat4(pose);
                let eye = pose.w_axis.truncate();
                let mut rng = Rng::new(99, i as u64);
                let mut rgb = RgbImage::new(w, h);
                let mut metres = vec![0.0f32; (w * h) as usize];
                for v in 0..h {
                    for u in 0..w {
                        let d = rot * k.unproject(u as f64, v as f64).to_glam();
                        let (t, axis) = exit(eye, d, self.half);
                        let mut z = (t * self.scale) as f32;
                        if rng.f64() < self.flying {
                            z *= 1000.0;
                        }
                        metres[(v * w + u) as usize] = z;
                        let shade = (40 * axis as u8).wrapping_add((u + v) as u8);
                        rgb.put_pixel(u, v, image::Rgb([shade, 255 - shade, 60 + 30 * axis as u8]));
                    }
                }
                let mut c2w = world_rot * pose;
                c2w.w_axis = (self.to_world(eye)).extend(1.0);
                Frame {
                    id: i as u64,
                    name: format!("{i:06}"),
                    rgb,
                    depth: self.with_depth.then_some(DepthMap {
                        width: w,
                        height: h,
                        metres,
                    }),
                    camera_to_world: c2w.to_na(),
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
fn exit(o: DVec3, d: DVec3, half: DVec3) -> (f64, usize) {
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
