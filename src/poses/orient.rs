//! Orientation of the local frame: principal axes of a point set (the
//! covariance's eigenvectors, basis chosen closest to the world axes),
//! refined by a descent on the volume of the rotated bounding box.

use glam::{DMat3, DQuat, DVec3};

/// First and last angle step of the volume descent, radians.
const FIRST_STEP: f64 = 0.1;
const LAST_STEP: f64 = 1e-4;
/// Padding (fraction of the longest edge) added to every edge before taking
/// the volume, so flat clouds still compare by their other edges.
const VOLUME_PAD: f64 = 0.1;

/// Eigenvalues (descending) and unit eigenvectors (matching columns) of a
/// symmetric matrix (nalgebra's symmetric eigen decomposition).
pub(crate) fn symmetric_eigen(m: DMat3) -> (DVec3, DMat3) {
    let a = nalgebra::Matrix3::from_column_slice(&m.to_cols_array());
    // Symmetrise: the solver reads one triangle only.
    let eigen = nalgebra::SymmetricEigen::new((a + a.transpose()) * 0.5);
    let mut order = [0usize, 1, 2];
    order.sort_by(|&i, &j| eigen.eigenvalues[j].total_cmp(&eigen.eigenvalues[i]));
    let values = DVec3::from_array(order.map(|i| eigen.eigenvalues[i]));
    let col = |i: usize| {
        let c = eigen.eigenvectors.column(i);
        DVec3::new(c[0], c[1], c[2])
    };
    (values, DMat3::from_cols(col(order[0]), col(order[1]), col(order[2])))
}

/// Covariance matrix of the points about their mean; `None` when empty.
pub(crate) fn covariance(points: &[DVec3]) -> Option<DMat3> {
    if points.is_empty() {
        return None;
    }
    let n = points.len() as f64;
    let mean = points.iter().copied().sum::<DVec3>() / n;
    let mut c = [[0.0f64; 3]; 3];
    for p in points {
        let d = *p - mean;
        for (i, row) in c.iter_mut().enumerate() {
            for (j, x) in row.iter_mut().enumerate() {
                *x += d[i] * d[j];
            }
        }
    }
    Some(DMat3::from_cols_array_2d(&c) * (1.0 / n))
}

/// Principal axes as the columns of a rotation (det +1), reordered and
/// sign-flipped to be as close to the identity as possible. `None` when the
/// points do not spread at all.
pub(crate) fn principal_axes(points: &[DVec3]) -> Option<DMat3> {
    let cov = covariance(points)?;
    let (values, vectors) = symmetric_eigen(cov);
    if !(values.x.is_finite() && values.x > 0.0 && vectors.is_finite()) {
        return None;
    }
    Some(closest_to_identity(vectors))
}

/// Among the 24 right-handed signed permutations of `basis`'s columns, the
/// one with the largest trace (smallest rotation angle from the identity).
pub(crate) fn closest_to_identity(basis: DMat3) -> DMat3 {
    const PERMS: [[usize; 3]; 6] = [[0, 1, 2], [0, 2, 1], [1, 0, 2], [1, 2, 0], [2, 0, 1], [2, 1, 0]];
    let cols = [basis.x_axis, basis.y_axis, basis.z_axis];
    let mut best = (f64::NEG_INFINITY, DMat3::IDENTITY);
    for perm in PERMS {
        for signs in 0..8u32 {
            let sign = |i: usize| if signs & (1 << i) == 0 { 1.0 } else { -1.0 };
            let m = DMat3::from_cols(
                cols[perm[0]] * sign(0),
                cols[perm[1]] * sign(1),
                cols[perm[2]] * sign(2),
            );
            if m.determinant() <= 0.0 {
                continue;
            }
            let trace = m.x_axis.x + m.y_axis.y + m.z_axis.z;
            if trace > best.0 {
                best = (trace, m);
            }
        }
    }
    best.1
}

/// Volume of the bounding box of `rotation * points`, each edge padded by
/// [`VOLUME_PAD`] of the longest one.
pub(crate) fn rotated_volume(points: &[DVec3], rotation: DQuat) -> f64 {
    let m = DMat3::from_quat(rotation);
    let (mut lo, mut hi) = (DVec3::INFINITY, DVec3::NEG_INFINITY);
    for p in points {
        let q = m * *p;
        lo = lo.min(q);
        hi = hi.max(q);
    }
    let e = (hi - lo).max(DVec3::ZERO);
    let e = e + DVec3::splat(VOLUME_PAD * e.max_element());
    e.x * e.y * e.z
}

/// Coordinate descent from `start` over small rotations about the local axes
/// that shrinks [`rotated_volume`]; returns the rotation and its volume.
pub(crate) fn min_volume_rotation(points: &[DVec3], start: DQuat) -> (DQuat, f64) {
    let mut q = start.normalize();
    let mut best = rotated_volume(points, q);
    let mut step = FIRST_STEP;
    while step >= LAST_STEP {
        let mut improved = false;
        for axis in [DVec3::X, DVec3::Y, DVec3::Z] {
            for angle in [step, -step] {
                let candidate = (DQuat::from_axis_angle(axis, angle) * q).normalize();
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
    use glam::DQuat;

    #[test]
    fn symmetric_eigen_diagonalises_random_symmetric_matrices() {
        let mut rng = Rng::new(5, 0);
        for _ in 0..200 {
            let r =
                DMat3::from_quat(DQuat::from_xyzw(rng.normal(), rng.normal(), rng.normal(), rng.normal()).normalize());
            let l = DVec3::new(rng.range(-3.0, 3.0), rng.range(-3.0, 3.0), rng.range(-3.0, 3.0));
            let m = r * DMat3::from_diagonal(l) * r.transpose();
            let (values, vectors) = symmetric_eigen(m);
            assert!(values.x >= values.y && values.y >= values.z);
            for i in 0..3 {
                let v = vectors.col(i);
                assert!((m * v - v * values[i]).length() < 1e-12, "{m:?}");
                assert!((v.length() - 1.0).abs() < 1e-12);
            }
            assert!((vectors.transpose() * vectors - DMat3::IDENTITY)
                .abs()
                .to_cols_array()
                .iter()
                .all(|x| *x < 1e-12));
        }
    }

    #[test]
    fn elongated_cloud_axes_follow_its_rotation_and_stay_near_identity() {
        let rot = DQuat::from_rotation_z(0.3) * DQuat::from_rotation_x(-0.1);
        let mut rng = Rng::new(1, 0);
        let pts: Vec<DVec3> = (0..5000)
            .map(|_| rot * DVec3::new(rng.range(-4.0, 4.0), rng.range(-2.0, 2.0), rng.range(-1.0, 1.0)))
            .collect();
        let axes = principal_axes(&pts).unwrap();
        let expected = DMat3::from_quat(rot);
        for i in 0..3 {
            assert!(axes.col(i).dot(expected.col(i)) > 0.995, "axis {i}: {axes:?}");
        }
        assert!((axes.determinant() - 1.0).abs() < 1e-12);
    }

    #[test]
    fn planar_and_collinear_clouds_still_give_rotations() {
        let planar: Vec<DVec3> = (0..100)
            .map(|i| DVec3::new((i % 10) as f64, (i / 10) as f64 * 0.5, 0.0))
            .collect();
        let axes = principal_axes(&planar).unwrap();
        assert!((axes.determinant() - 1.0).abs() < 1e-12);
        assert!(axes.z_axis.z.abs() > 1.0 - 1e-12, "normal of a z-plane is z: {axes:?}");
        let line: Vec<DVec3> = (0..10).map(|i| DVec3::new(1.0, 2.0, 3.0) * i as f64).collect();
        let axes = principal_axes(&line).unwrap();
        assert!((axes.determinant() - 1.0).abs() < 1e-12);
        assert!(principal_axes(&[DVec3::ONE; 5]).is_none());
        assert!(principal_axes(&[]).is_none());
    }

    #[test]
    fn volume_descent_recovers_a_box_surface_rotation() {
        // Points on the faces of a box with a hole: PCA is biased, the descent is not.
        let rot = DQuat::from_rotation_z(0.4) * DQuat::from_rotation_y(0.15);
        let mut rng = Rng::new(2, 0);
        let half = DVec3::new(2.0, 1.5, 1.0);
        let mut pts = Vec::new();
        for i in 0..6000 {
            let mut p = DVec3::new(rng.range(-1.0, 1.0), rng.range(-1.0, 1.0), rng.range(-1.0, 1.0)) * half;
            let a = i % 3;
            p[a] = if i % 2 == 0 { half[a] } else { -half[a] };
            if a == 2 && p[a] > 0.0 && p.x > 0.0 {
                continue; // part of the ceiling was never seen
            }
            pts.push(rot * p);
        }
        let start = DQuat::from_mat3(&principal_axes(&pts).unwrap().transpose());
        let (q, volume) = min_volume_rotation(&pts, start);
        let m = DMat3::from_quat(q * rot);
        for i in 0..3 {
            assert!(m.col(i)[i].abs() > 0.9999, "local axis {i}: {m:?}");
        }
        assert!(volume <= rotated_volume(&pts, start));
    }
}
