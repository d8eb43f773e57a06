//! The scan's up axis and the ground frame the top view looks along.
//!
//! Up starts as the mean of the cameras' up directions (handheld scans are
//! filmed upright), then snaps to the normal of the largest plane of the
//! surface points within 25° of it (the floor or the table), and to a world
//! axis when within half a degree of one (exact in generated scenes).

use crate::glam_bridge::{ToGlam, ToNalgebra};
use crate::poses::symmetric_eigen;
use crate::rng::Rng;
use crate::scan::Scan;
use glam::{DMat3, DVec3};

/// Planes considered for the up axis lie within this angle of the cameras' up.
const MAX_TILT_DEG: f64 = 25.0;
/// RANSAC hypotheses for the ground plane.
const TRIALS: usize = 400;
/// Inlier distance of the RANSAC plane, metres.
const INLIER_M: f64 = 0.01;
/// The plane must hold this share of the points to set the up axis.
const MIN_SHARE: f64 = 0.05;
/// Snap to a world axis within this angle, degrees.
const SNAP_DEG: f64 = 0.5;
/// Points the plane search looks at.
const MAX_POINTS: usize = 200_000;

/// An orthonormal frame whose z is the scan's up: world <-> ground.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Ground {
    pub x: DVec3,
    pub y: DVec3,
    pub up: DVec3,
}

impl Ground {
    /// The frame of a z-up world.
    pub fn z_up() -> Ground {
        Ground::from_up(DVec3::Z)
    }

    /// A ground frame around a unit up vector (x as close to world x as possible).
    pub fn from_up(up: DVec3) -> Ground {
        let up = up.normalize();
        let seed = if up.x.abs() < 0.9 { DVec3::X } else { DVec3::Y };
        let x = (seed - up * seed.dot(up)).normalize();
        Ground { x, y: up.cross(x), up }
    }

    /// The scan's up axis from its cameras and surface points (world metres).
    pub fn estimate(scan: &Scan, points: &[DVec3]) -> Ground {
        let cameras: DVec3 = (scan.frames.iter())
            .map(|f| -f.camera_to_world.to_glam().y_axis.truncate())
            .filter(|v| v.is_finite())
            .sum();
        let guess = if cameras.length() > 1e-9 {
            cameras.normalize()
        } else {
            DVec3::Z
        };
        let up = plane_normal(points, guess).unwrap_or(guess);
        Ground::from_up(snap(up))
    }

    /// World point to ground coordinates.
    pub fn to_ground(&self, p: DVec3) -> DVec3 {
        DVec3::new(self.x.dot(p), self.y.dot(p), self.up.dot(p))
    }

    /// World direction to ground coordinates.
    pub fn to_ground_dir(&self, d: DVec3) -> DVec3 {
        self.to_ground(d)
    }

    /// Ground point to world coordinates.
    pub fn to_world(&self, g: DVec3) -> DVec3 {
        self.x * g.x + self.y * g.y + self.up * g.z
    }

    /// Ground direction to world coordinates.
    pub fn to_world_dir(&self, g: DVec3) -> DVec3 {
        self.to_world(g)
    }

    /// Ground-to-world rotation.
    pub fn rotation(&self) -> DMat3 {
        DMat3::from_cols(self.x, self.y, self.up)
    }
}

/// A world axis when `up` is within [`SNAP_DEG`] of it.
fn snap(up: DVec3) -> DVec3 {
    let axes = [DVec3::X, DVec3::Y, DVec3::Z, -DVec3::X, -DVec3::Y, -DVec3::Z];
    let limit = SNAP_DEG.to_radians().cos();
    axes.into_iter().find(|a| a.dot(up) >= limit).unwrap_or(up)
}

/// Normal (oriented along `guess`) of the plane holding most of `points`
/// among those within [`MAX_TILT_DEG`] of `guess`, refined by least squares.
fn plane_normal(points: &[DVec3], guess: DVec3) -> Option<DVec3> {
    let stride = points.len().div_ceil(MAX_POINTS).max(1);
    let pts: Vec<DVec3> = points.iter().step_by(stride).copied().collect();
    if pts.len() < 3 {
        return None;
    }
    let mut rng = Rng::new(0, 0x9d);
    let cos_tilt = MAX_TILT_DEG.to_radians().cos();
    let pick = |rng: &mut Rng| pts[rng.below(pts.len() as u64) as usize];
    let mut best: Option<(usize, DVec3, f64)> = None;
    for _ in 0..TRIALS {
        let (a, b, c) = (pick(&mut rng), pick(&mut rng), pick(&mut rng));
        let n = (b - a).cross(c - a);
        if n.length() < 1e-12 {
            continue;
        }
        let mut n = n.normalize();
        if n.dot(guess) < 0.0 {
            n = -n;
        }
        if n.dot(guess) < cos_tilt {
            continue;
        }
        let d = -n.dot(a);
        let count = pts.iter().filter(|p| (n.dot(**p) + d).abs() <= INLIER_M).count();
        if best.is_none_or(|(k, _, _)| count > k) {
            best = Some((count, n, d));
        }
    }
    let (count, n, d) = best?;
    if (count as f64) < MIN_SHARE * pts.len() as f64 {
        return None;
    }
    let inliers: Vec<DVec3> = pts
        .iter()
        .copied()
        .filter(|p| (n.dot(*p) + d).abs() <= INLIER_M)
        .collect();
    let mean = inliers.iter().copied().sum::<DVec3>() / inliers.len() as f64;
    let mut cov = DMat3::ZERO;
    for p in &inliers {
        let q = *p - mean;
        cov += DMat3::from_cols(q * q.x, q * q.y, q * q.z);
    }
    let (_, vectors) = symmetric_eigen(cov.to_na());
    let refined = vectors.to_glam().z_axis;
    let refined = if refined.dot(n) < 0.0 { -refined } else { refined };
    refined.is_finite().then_some(refined.normalize())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn frame_round_trips_and_keeps_up() {
        let g = Ground::from_up(DVec3::new(0.1, -0.2, 1.0));
        let p = DVec3::new(0.3, -1.2, 2.0);
        assert!(g.to_world(g.to_ground(p)).distance(p) < 1e-12);
        assert!((g.rotation().determinant() - 1.0).abs() < 1e-12);
        assert!((g.to_ground(g.up) - DVec3::Z).length() < 1e-12);
    }

    #[test]
    fn a_tilted_floor_sets_up() {
        let normal = DVec3::new(0.05, 0.1, 1.0).normalize();
        let g = Ground::from_up(normal);
        let mut pts = Vec::new();
        for i in 0..100 {
            for j in 0..100 {
                pts.push(g.to_world(DVec3::new(i as f64 * 0.02, j as f64 * 0.02, 0.3)));
            }
        }
        let up = plane_normal(&pts, DVec3::Z).unwrap();
        assert!(up.dot(normal) > 0.99999, "{up}");
    }
}
