//! Rigid-transform helpers for reading poses: quaternions to matrices,
//! rigid inverse, axis-convention flips and re-orthonormalisation.

use glam::{DMat3, DMat4, DQuat, DVec3};

/// Camera-to-world from a translation and a scalar-last quaternion
/// (`qx qy qz qw`, Hamilton); `None` when the quaternion is not finite or
/// has (near) zero norm. The quaternion is normalised.
pub fn pose_from_translation_quaternion(t: [f64; 3], q: [f64; 4]) -> Option<DMat4> {
    let quat = DQuat::from_xyzw(q[0], q[1], q[2], q[3]);
    let norm = quat.length();
    if !norm.is_finite() || norm < 1e-6 || !t.iter().all(|v| v.is_finite()) {
        return None;
    }
    Some(DMat4::from_rotation_translation(quat / norm, DVec3::from_array(t)))
}

/// Inverse of a rigid transform `[R t; 0 1]` as `[R^T -R^T t; 0 1]`.
pub fn rigid_inverse(m: &DMat4) -> DMat4 {
    let r = DMat3::from_mat4(*m);
    let rt = r.transpose();
    let t = m.w_axis.truncate();
    let mut out = DMat4::from_mat3(rt);
    out.w_axis = (-(rt * t)).extend(1.0);
    out
}

/// Convert a camera-to-world pose with OpenGL camera axes (y up, z back)
/// to OpenCV axes (y down, z forward): right-multiply by diag(1, -1, -1, 1).
pub fn opengl_to_opencv(c2w: &DMat4) -> DMat4 {
    let mut out = *c2w;
    out.y_axis = -out.y_axis;
    out.z_axis = -out.z_axis;
    out
}

/// Largest entry of `|R^T R - I|` for the rotation block.
pub fn orthonormality_error(m: &DMat4) -> f64 {
    let r = DMat3::from_mat4(*m);
    let e = r.transpose() * r - DMat3::IDENTITY;
    e.to_cols_array().iter().fold(0.0f64, |acc, v| acc.max(v.abs()))
}

/// Nearest rotation to the rotation block (its polar factor, from the
/// SVD), keeping the translation. `None` when the block is singular or a
/// reflection.
pub fn orthonormalize(m: &DMat4) -> Option<DMat4> {
    let r = DMat3::from_mat4(*m);
    let det = r.determinant();
    if det.is_nan() || det <= 1e-9 {
        return None;
    }
    // The nearest rotation is the polar factor U V^T of the SVD.
    let svd = nalgebra::Matrix3::from_column_slice(&r.to_cols_array()).svd(true, true);
    let nearest = svd.u? * svd.v_t?;
    let r = DMat3::from_cols_slice(nearest.as_slice());
    if !(r.is_finite() && r.determinant() > 0.0) {
        return None;
    }
    let mut out = DMat4::from_mat3(r);
    out.w_axis = m.w_axis.truncate().extend(1.0);
    Some(out)
}

#[cfg(test)]
mod tests {
    use super::*;
    use glam::DVec4;

    #[test]
    fn quaternion_scalar_last_rotates_as_expected() {
        // 90 degrees about +y: camera z (forward) maps to world +x.
        let h = std::f64::consts::FRAC_1_SQRT_2;
        let m = pose_from_translation_quaternion([1.0, 2.0, 3.0], [0.0, h, 0.0, h]).unwrap();
        let fwd = m.transform_vector3(DVec3::Z);
        assert!((fwd - DVec3::X).length() < 1e-12);
        assert_eq!(m.w_axis, DVec4::new(1.0, 2.0, 3.0, 1.0));
        // Unnormalised quaternions are normalised.
        let m2 = pose_from_translation_quaternion([1.0, 2.0, 3.0], [0.0, 2.0, 0.0, 2.0]).unwrap();
        assert!(m2.abs_diff_eq(m, 1e-12));
        assert!(pose_from_translation_quaternion([0.0; 3], [0.0; 4]).is_none());
        assert!(pose_from_translation_quaternion([0.0; 3], [f64::NAN, 0.0, 0.0, 1.0]).is_none());
    }

    #[test]
    fn rigid_inverse_inverts() {
        let m = DMat4::from_rotation_translation(
            DQuat::from_rotation_x(0.3) * DQuat::from_rotation_z(1.1),
            DVec3::new(1.0, -2.0, 0.5),
        );
        assert!((rigid_inverse(&m) * m).abs_diff_eq(DMat4::IDENTITY, 1e-12));
    }

    #[test]
    fn opengl_flip_maps_forward_axis() {
        // OpenGL camera looks down -z; after conversion OpenCV +z is that same direction.
        let gl = DMat4::from_rotation_translation(DQuat::from_rotation_y(0.4), DVec3::ZERO);
        let cv = opengl_to_opencv(&gl);
        assert!((cv.transform_vector3(DVec3::Z) - gl.transform_vector3(-DVec3::Z)).length() < 1e-12);
        assert!((cv.transform_vector3(DVec3::Y) - gl.transform_vector3(-DVec3::Y)).length() < 1e-12);
        assert!((DMat3::from_mat4(cv).determinant() - 1.0).abs() < 1e-12);
    }

    #[test]
    fn orthonormalize_recovers_rotation() {
        let truth = DMat4::from_rotation_translation(DQuat::from_rotation_y(0.7), DVec3::new(0.1, 0.2, 0.3));
        let mut noisy = truth;
        noisy.x_axis.x += 0.004;
        noisy.y_axis.z -= 0.003;
        assert!(orthonormality_error(&noisy) > 1e-3);
        let fixed = orthonormalize(&noisy).unwrap();
        assert!(orthonormality_error(&fixed) < 1e-12);
        assert!(fixed.abs_diff_eq(truth, 5e-3));
        assert_eq!(fixed.w_axis, truth.w_axis);
        let mirror = DMat4::from_scale(DVec3::new(1.0, 1.0, -1.0));
        assert!(orthonormalize(&mirror).is_none());
    }
}
