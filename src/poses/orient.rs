//! Orientation of the local frame: principal axes of a point set (the
//! covariance's eigenvectors, basis chosen closest to the world axes),
//! refined by a descent on the volume of the rotated bounding box.

use nalgebra::{Matrix3, Point3, Rotation3, SymmetricEigen, UnitQuaternion, Vector3};

/// First and last angle step of the volume descent, radians.
const FIRST_STEP: f64 = 0.1;
const LAST_STEP: f64 = 1e-4;
/// Padding (fraction of the longest edge) added to every edge before taking
/// the volume, so flat clouds still compare by their other edges.
const VOLUME_PAD: f64 = 0.1;

/// Eigenvalues (descending) and unit eigenvectors (matching columns) of a
/// symmetric matrix (nalgebra's symmetric eigen decomposition).
pub(crate) fn symmetric_eigen(m: Matrix3<f64>) -> (Vector3<f64>, Matrix3<f64>) {
    // Symmetrise: the solver reads one triangle only.
    let eigen = SymmetricEigen::new((m + m.transpose()) * 0.5);
    let mut order = [0usize, 1, 2];
    order.sort_by(|&i, &j| eigen.eigenvalues[j].total_cmp(&eigen.eigenvalues[i]));
    let values = Vector3::from(order.map(|i| eigen.eigenvalues[i]));
    let vectors = Matrix3::from_columns(&order.map(|i| eigen.eigenvectors.column(i).into_owned()));
    (values, vectors)
}

/// Covariance matrix of the points about their mean; `None` when empty.
pub(crate) fn covariance(points: &[Point3<f64>]) -> Option<Matrix3<f64>> {
    if points.is_empty() {
        return None;
    }
    let n = points.len() as f64;
    let mean = points.iter().map(|p| p.coords).sum::<Vector3<f64>>() / n;
    let mut c = Matrix3::zeros();
    for p in points {
        let d = p.coords - mean;
        for i in 0..3 {
            for j in 0..3 {
                c[(i, j)] += d[i] * d[j];
            }
        }
    }
    Some(c * (1.0 / n))
}

/// Principal axes as the columns of a rotation, reordered and sign-flipped
/// to be as close to the identity as possible. `None` when the points do
/// not spread at all.
pub(crate) fn principal_axes(points: &[Point3<f64>]) -> Option<Rotation3<f64>> {
    let cov = covariance(points)?;
    let (values, vectors) = symmetric_eigen(cov);
    if !(values.x.is_finite() && values.x > 0.0 && vectors.iter().all(|x| x.is_finite())) {
        return None;
    }
    Some(closest_to_identity(vectors))
}

/// Among the 24 right-handed signed permutations of `basis`'s columns, the
/// one with the largest trace (smallest rotation angle from the identity).
pub(crate) fn closest_to_identity(basis: Matrix3<f64>) -> Rotation3<f64> {
    const PERMS: [[usize; 3]; 6] = [[0, 1, 2], [0, 2, 1], [1, 0, 2], [1, 2, 0], [2, 0, 1], [2, 1, 0]];
    let mut best = (f64::NEG_INFINITY, Matrix3::identity());
    for perm in PERMS {
        for signs in 0..8u32 {
            let sign = |i: usize| if signs & (1 << i) == 0 { 1.0 } else { -1.0 };
            let m = Matrix3::from_columns(&[
                basis.column(perm[0]) * sign(0),
                basis.column(perm[1]) * sign(1),
                basis.column(perm[2]) * sign(2),
            ]);
            if m.determinant() <= 0.0 {
                continue;
            }
            let trace = m.trace();
            if trace > best.0 {
                best = (trace, m);
            }
        }
    }
    Rotation3::from_matrix_unchecked(best.1)
}

/// Volume of the bounding box of `rotation * points`, each edge padded by
/// [`VOLUME_PAD`] of the longest one.
pub(crate) fn rotated_volume(points: &[Point3<f64>], rotation: UnitQuaternion<f64>) -> f64 {
    let m = rotation.to_rotation_matrix();
    let (mut lo, mut hi) = (Vector3::repeat(f64::INFINITY), Vector3::repeat(f64::NEG_INFINITY));
    for p in points {
        let q = m * p.coords;
        lo = lo.inf(&q);
        hi = hi.sup(&q);
    }
    let e = (hi - lo).sup(&Vector3::zeros());
    let e = e.add_scalar(VOLUME_PAD * e.max());
    e.x * e.y * e.z
}

/// Coordinate descent from `start` over small rotations about the local axes
/// that shrinks [`rotated_volume`]; returns the rotation and its volume.
pub(crate) fn min_volume_rotation(points: &[Point3<f64>], start: UnitQuaternion<f64>) -> (UnitQuaternion<f64>, f64) {
    let mut q = UnitQuaternion::new_normalize(start.into_inner());
    let mut best = rotated_volume(points, q);
    let mut step = FIRST_STEP;
    while step >= LAST_STEP {
        let mut improved = false;
        for axis in [Vector3::x_axis(), Vector3::y_axis(), Vector3::z_axis()] {
            for angle in [step, -step] {
                let candidate =
                    UnitQuaternion::new_normalize((UnitQuaternion::from_axis_angle(&axis, angle) * q).into_inner());
                let v = rotated_volume(points, candidate);
                // Demand a real gain so that rounding cannot decide ties.
                if v < best * (1.0 - 1e-9) {
                    q = candidate;
                    best = v;
                    improved = true;
                }
            }
        }
        if !improved {
            step *= 0.5;
        }
    }
    (q, best)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::rng::Rng;

    fn rot(axis: Vector3<f64>, angle: f64) -> UnitQuaternion<f64> {
        UnitQuaternion::from_scaled_axis(axis * angle)
    }

    #[test]
    fn symmetric_eigen_diagonalises_random_symmetric_matrices() {
        let mut rng = Rng::new(5, 0);
        for _ in 0..200 {
            let q = nalgebra::Quaternion::new(rng.normal(), rng.normal(), rng.normal(), rng.normal());
            let r = UnitQuaternion::new_normalize(q).to_rotation_matrix().into_inner();
            let l = Vector3::new(rng.range(-3.0, 3.0), rng.range(-3.0, 3.0), rng.range(-3.0, 3.0));
            let m = r * Matrix3::from_diagonal(&l) * r.transpose();
            let (values, vectors) = symmetric_eigen(m);
            assert!(values.x >= values.y && values.y >= values.z);
            for i in 0..3 {
                let v = vectors.column(i);
                assert!((m * v - v * values[i]).norm() < 1e-12, "{m:?}");
                assert!((v.norm() - 1.0).abs() < 1e-12);
            }
            assert!((vectors.transpose() * vectors - Matrix3::identity()).amax() < 1e-12);
        }
    }

    #[test]
    fn elongated_cloud_axes_follow_its_rotation_and_stay_near_identity() {
        let rot = rot(Vector3::z(), 0.3) * rot(Vector3::x(), -0.1);
        let mut rng = Rng::new(1, 0);
        let pts: Vec<Point3<f64>> = (0..5000)
            .map(|_| rot * Point3::new(rng.range(-4.0, 4.0), rng.range(-2.0, 2.0), rng.range(-1.0, 1.0)))
            .collect();
        let axes = principal_axes(&pts).unwrap();
        let expected = rot.to_rotation_matrix();
        for i in 0..3 {
            assert!(
                axes.matrix().column(i).dot(&expected.matrix().column(i)) > 0.995,
                "axis {i}: {axes:?}"
            );
        }
        assert!((axes.matrix().determinant() - 1.0).abs() < 1e-12);
    }

    #[test]
    fn planar_and_collinear_clouds_still_give_rotations() {
        let planar: Vec<Point3<f64>> = (0..100)
            .map(|i| Point3::new((i % 10) as f64, (i / 10) as f64 * 0.5, 0.0))
            .collect();
        let axes = principal_axes(&planar).unwrap();
        assert!((axes.matrix().determinant() - 1.0).abs() < 1e-12);
        assert!(axes[(2, 2)].abs() > 1.0 - 1e-12, "normal of a z-plane is z: {axes:?}");
        let line: Vec<Point3<f64>> = (0..10).map(|i| Point3::new(1.0, 2.0, 3.0) * i as f64).collect();
        let axes = principal_axes(&line).unwrap();
        assert!((axes.matrix().determinant() - 1.0).abs() < 1e-12);
        assert!(principal_axes(&[Point3::new(1.0, 1.0, 1.0); 5]).is_none());
        assert!(principal_axes(&[]).is_none());
    }

    #[test]
    fn volume_descent_recovers_a_box_surface_rotation() {
        // Points on the faces of a box with a hole: PCA is biased, the descent is not.
        let rot = rot(Vector3::z(), 0.4) * rot(Vector3::y(), 0.15);
        let mut rng = Rng::new(2, 0);
        let half = Vector3::new(2.0, 1.5, 1.0);
        let mut pts = Vec::new();
        for i in 0..6000 {
            let mut p =
                Vector3::new(rng.range(-1.0, 1.0), rng.range(-1.0, 1.0), rng.range(-1.0, 1.0)).component_mul(&half);
            let a = i % 3;
            p[a] = if i % 2 == 0 { half[a] } else { -half[a] };
            if a == 2 && p[a] > 0.0 && p.x > 0.0 {
                continue; // part of the ceiling was never seen
            }
            pts.push(rot * Point3::from(p));
        }
        let start = UnitQuaternion::from_rotation_matrix(&principal_axes(&pts).unwrap().inverse());
        let (q, volume) = min_volume_rotation(&pts, start);
        let m = (q * rot).to_rotation_matrix();
        for i in 0..3 {
            assert!(m[(i, i)].abs() > 0.9999, "local axis {i}: {m:?}");
        }
        assert!(volume <= rotated_volume(&pts, start));
    }
}
