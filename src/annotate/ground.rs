//! The scan's up axis and the ground frame the top view looks along.
//!
//! Up starts as the mean of the cameras' up directions (handheld scans are
//! filmed upright), then snaps to the normal of the largest plane of the
//! surface points within 25° of it (the floor or the table), and to a world
//! axis when within half a degree of one (exact in generated scenes).

use crate::poses::symmetric_eigen;
use crate::rng::Rng;
use crate::scan::Scan;
use nalgebra::{Matrix3, Point3, Rotation3, Vector3};

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
    pub x: Vector3<f64>,
    pub y: Vector3<f64>,
    pub up: Vector3<f64>,
}

impl Ground {
    /// The frame of a z-up world.
    pub fn z_up() -> Ground {
        Ground::from_up(Vector3::z())
    }

    /// A ground frame around a unit up vector (x as close to world x as possible).
    pub fn from_up(up: Vector3<f64>) -> Ground {
        let up = unit(&up);
        let seed = if up.x.abs() < 0.9 { Vector3::x() } else { Vector3::y() };
        let x = unit(&(seed - up * seed.dot(&up)));
        Ground { x, y: up.cross(&x), up }
    }

    /// The scan's up axis from its cameras and surface points (world metres).
    pub fn estimate(scan: &Scan, points: &[Point3<f64>]) -> Ground {
        let cameras: Vector3<f64> = (scan.frames.iter())
            .map(|f| -f.camera_to_world.rotation.matrix().column(1))
            .filter(|v| v.iter().all(|c| c.is_finite()))
            .sum();
        let guess = if cameras.norm() > 1e-9 {
            unit(&cameras)
        } else {
            Vector3::z()
        };
        let up = plane_normal(points, guess).unwrap_or(guess);
        Ground::from_up(snap(up))
    }

    /// World point to ground coordinates.
    pub fn to_ground(&self, p: &Point3<f64>) -> Point3<f64> {
        Point3::from(self.to_ground_dir(&p.coords))
    }

    /// World direction to ground coordinates.
    pub fn to_ground_dir(&self, d: &Vector3<f64>) -> Vector3<f64> {
        Vector3::new(self.x.dot(d), self.y.dot(d), self.up.dot(d))
    }

    /// Ground point to world coordinates.
    pub fn to_world(&self, g: &Point3<f64>) -> Point3<f64> {
        Point3::from(self.to_world_dir(&g.coords))
    }

    /// Ground direction to world coordinates.
    pub fn to_world_dir(&self, g: &Vector3<f64>) -> Vector3<f64> {
        self.x * g.x + self.y * g.y + self.up * g.z
    }

    /// Ground-to-world rotation.
    pub fn rotation(&self) -> Rotation3<f64> {
        Rotation3::from_matrix_unchecked(Matrix3::from_columns(&[self.x, self.y, self.up]))
    }
}

/// `v` times its reciprocal length (the rounding of the glam code this replaced).
fn unit(v: &Vector3<f64>) -> Vector3<f64> {
    v * (1.0 / v.norm())
}

/// A world axis when `up` is within [`SNAP_DEG`] of it.
fn snap(up: Vector3<f64>) -> Vector3<f64> {
    let axes = [
        Vector3::x(),
        Vector3::y(),
        Vector3::z(),
        -Vector3::x(),
        -Vector3::y(),
        -Vector3::z(),
    ];
    let limit = SNAP_DEG.to_radians().cos();
    axes.into_iter().find(|a| a.dot(&up) >= limit).unwrap_or(up)
}

/// Normal (oriented along `guess`) of the plane holding most of `points`
/// among those within [`MAX_TILT_DEG`] of `guess`, refined by least squares.
fn plane_normal(points: &[Point3<f64>], guess: Vector3<f64>) -> Option<Vector3<f64>> {
    let stride = points.len().div_ceil(MAX_POINTS).max(1);
    let pts: Vec<Vector3<f64>> = points.iter().step_by(stride).map(|p| p.coords).collect();
    if pts.len() < 3 {
        return None;
    }
    let mut rng = Rng::new(0, 0x9d);
    let cos_tilt = MAX_TILT_DEG.to_radians().cos();
    let pick = |rng: &mut Rng| pts[rng.below(pts.len() as u64) as usize];
    let mut best: Option<(usize, Vector3<f64>, f64)> = None;
    for _ in 0..TRIALS {
        let (a, b, c) = (pick(&mut rng), pick(&mut rng), pick(&mut rng));
        let n = (b - a).cross(&(c - a));
        if n.norm() < 1e-12 {
            continue;
        }
        let mut n = unit(&n);
        if n.dot(&guess) < 0.0 {
            n = -n;
        }
        if n.dot(&guess) < cos_tilt {
            continue;
        }
        let d = -n.dot(&a);
        let count = pts.iter().filter(|p| (n.dot(p) + d).abs() <= INLIER_M).count();
        if best.is_none_or(|(k, _, _)| count > k) {
            best = Some((count, n, d));
        }
    }
    let (count, n, d) = best?;
    if (count as f64) < MIN_SHARE * pts.len() as f64 {
        return None;
    }
    let inliers: Vec<Vector3<f64>> = pts
        .iter()
        .copied()
        .filter(|p| (n.dot(p) + d).abs() <= INLIER_M)
        .collect();
    let mean = inliers.iter().sum::<Vector3<f64>>() / inliers.len() as f64;
    let mut cov = Matrix3::zeros();
    for p in &inliers {
        let q = p - mean;
        cov += q * q.transpose();
    }
    let (_, vectors) = symmetric_eigen(cov);
    let refined = vectors.column(2).into_owned();
    let refined = if refined.dot(&n) < 0.0 { -refined } else { refined };
    refined.iter().all(|c| c.is_finite()).then(|| unit(&refined))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn frame_round_trips_and_keeps_up() {
        let g = Ground::from_up(Vector3::new(0.1, -0.2, 1.0));
        let p = Point3::new(0.3, -1.2, 2.0);
        assert!(nalgebra::distance(&g.to_world(&g.to_ground(&p)), &p) < 1e-12);
        assert!((g.rotation().matrix().determinant() - 1.0).abs() < 1e-12);
        assert!((g.to_ground_dir(&g.up) - Vector3::z()).norm() < 1e-12);
    }

    #[test]
    fn a_tilted_floor_sets_up() {
        let normal = Vector3::new(0.05, 0.1, 1.0).normalize();
        let g = Ground::from_up(normal);
        let mut pts = Vec::new();
        for i in 0..100 {
            for j in 0..100 {
                pts.push(g.to_world(&Point3::new(i as f64 * 0.02, j as f64 * 0.02, 0.3)));
            }
        }
        let up = plane_normal(&pts, Vector3::z()).unwrap();
        assert!(up.dot(&normal) > 0.99999, "{up}");
    }
}
