//! Rigid-transform helpers for reading poses: quaternions to isometries,
//! axis-convention flips and re-orthonormalisation.

use nalgebra::{
    Isometry3, IsometryMatrix3, Matrix3, Matrix4, Quaternion, Rotation3, Translation3, UnitQuaternion, Vector3,
};

/// Camera-to-world from a translation and a scalar-last quaternion
/// (`qx qy qz qw`, Hamilton); `None` when the quaternion is not finite or
/// has (near) zero norm. The quaternion is normalised.
pub fn pose_from_translation_quaternion(t: [f64; 3], q: [f64; 4]) -> Option<Isometry3<f64>> {
    let quat = Quaternion::new(q[3], q[0], q[1], q[2]);
    let norm = quat.norm();
    if !norm.is_finite() || norm < 1e-6 || !t.iter().all(|v| v.is_finite()) {
        return None;
    }
    Some(Isometry3::from_parts(
        Translation3::from(Vector3::from(t)),
        UnitQuaternion::new_unchecked(quat / norm),
    ))
}

/// A checked rigid 4x4 (see [`super::check_pose`]) as an isometry, keeping
/// every element of its rotation block and translation.
pub fn isometry(m: &Matrix4<f64>) -> IsometryMatrix3<f64> {
    IsometryMatrix3::from_parts(
        Translation3::new(m[(0, 3)], m[(1, 3)], m[(2, 3)]),
        Rotation3::from_matrix_unchecked(m.fixed_view::<3, 3>(0, 0).into_owned()),
    )
}

/// Convert a camera-to-world pose with OpenGL camera axes (y up, z back)
/// to OpenCV axes (y down, z forward): right-multiply by diag(1, -1, -1, 1).
pub fn opengl_to_opencv(c2w: &Matrix4<f64>) -> Matrix4<f64> {
    let mut out = *c2w;
    for j in [1, 2] {
        out.set_column(j, &-c2w.column(j));
    }
    out
}

/// Largest entry of `|R^T R - I|` for the rotation block.
pub fn orthonormality_error(m: &Matrix4<f64>) -> f64 {
    let r: Matrix3<f64> = m.fixed_view::<3, 3>(0, 0).into_owned();
    let e = r.transpose() * r - Matrix3::identity();
    e.iter().fold(0.0f64, |acc, v| acc.max(v.abs()))
}

/// Nearest rotation to the rotation block (its polar factor, from the
/// SVD), keeping the translation. `None` when the block is singular or a
/// reflection.
pub fn orthonormalize(m: &Matrix4<f64>) -> Option<Matrix4<f64>> {
    let r: Matrix3<f64> = m.fixed_view::<3, 3>(0, 0).into_owned();
    let det = r.determinant();
    if det.is_nan() || det <= 1e-9 {
        return None;
    }
    // The nearest rotation is the polar factor U V^T of the SVD.
    let svd = r.svd(true, true);
    let nearest = svd.u? * svd.v_t?;
    if !(nearest.iter().all(|v| v.is_finite()) && nearest.determinant() > 0.0) {
        return None;
    }
    let mut out = *m;
    out.fixed_view_mut::<3, 3>(0, 0).copy_from(&nearest);
    out.fixed_view_mut::<1, 4>(3, 0)
        .copy_from(&nalgebra::RowVector4::new(0.0, 0.0, 0.0, 1.0));
    Some(out)
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::Vector4;

    #[test]
    fn quaternion_scalar_last_rotates_as_expected() {
        // 90 degrees about +y: camera z (forward) maps to world +x.
        let h = std::f64::consts::FRAC_1_SQRT_2;
        let m = pose_from_translation_quaternion([1.0, 2.0, 3.0], [0.0, h, 0.0, h]).unwrap();
        let fwd = m * Vector3::z();
        assert!((fwd - Vector3::x()).norm() < 1e-12);
        assert_eq!(m.to_homogeneous().column(3), Vector4::new(1.0, 2.0, 3.0, 1.0));
        // Unnormalised quaternions are normalised.
        let m2 = pose_from_translation_quaternion([1.0, 2.0, 3.0], [0.0, 2.0, 0.0, 2.0]).unwrap();
        assert!((m2.to_homogeneous() - m.to_homogeneous()).amax() < 1e-12);
        assert!(pose_from_translation_quaternion([0.0; 3], [0.0; 4]).is_none());
        assert!(pose_from_translation_quaternion([0.0; 3], [f64::NAN, 0.0, 0.0, 1.0]).is_none());
    }

    fn pose(rotation: UnitQuaternion<f64>, t: Vector3<f64>) -> Matrix4<f64> {
        Isometry3::from_parts(t.into(), rotation).to_homogeneous()
    }

    #[test]
    fn opengl_flip_maps_forward_axis() {
        // OpenGL camera looks down -z; after conversion OpenCV +z is that same direction.
        let gl = pose(UnitQuaternion::from_euler_angles(0.0, 0.4, 0.0), Vector3::zeros());
        let cv = opengl_to_opencv(&gl);
        assert!((cv.transform_vector(&Vector3::z()) - gl.transform_vector(&-Vector3::z())).norm() < 1e-12);
        assert!((cv.transform_vector(&Vector3::y()) - gl.transform_vector(&-Vector3::y())).norm() < 1e-12);
        assert!((cv.fixed_view::<3, 3>(0, 0).determinant() - 1.0).abs() < 1e-12);
    }

    #[test]
    fn orthonormalize_recovers_rotation() {
        let truth = pose(
            UnitQuaternion::from_euler_angles(0.0, 0.7, 0.0),
            Vector3::new(0.1, 0.2, 0.3),
        );
        let mut noisy = truth;
        noisy[(0, 0)] += 0.004;
        noisy[(2, 1)] -= 0.003;
        assert!(orthonormality_error(&noisy) > 1e-3);
        let fixed = orthonormalize(&noisy).unwrap();
        assert!(orthonormality_error(&fixed) < 1e-12);
        assert!((fixed - truth).amax() < 5e-3);
        assert_eq!(fixed.column(3), truth.column(3));
        let mirror = Matrix4::new_nonuniform_scaling(&Vector3::new(1.0, 1.0, -1.0));
        assert!(orthonormalize(&mirror).is_none());
    }
}
