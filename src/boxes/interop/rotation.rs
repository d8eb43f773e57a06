//! The Euler-angle conventions of the tools boxes come from: labelCloud
//! rotates a box about x, then y, then z of the world (R = Rz Ry Rx);
//! CVAT's 3D canvas keeps three.js Euler angles in their default `XYZ`
//! order (R = Rx Ry Rz); KITTI turns a box about the camera's y axis.
//! Angles in radians; rotations are box-to-world, columns the box axes.

use glam::DMat3;

/// Rows of a 3x3 matrix.
pub fn rows(m: &DMat3) -> [[f64; 3]; 3] {
    let t = m.transpose();
    [t.x_axis.to_array(), t.y_axis.to_array(), t.z_axis.to_array()]
}

/// A matrix from its rows.
pub fn from_rows(r: [[f64; 3]; 3]) -> DMat3 {
    DMat3::from_cols_array_2d(&r).transpose()
}

/// labelCloud: rotate about world x by `x`, then y by `y`, then z by `z`.
pub fn zyx(x: f64, y: f64, z: f64) -> DMat3 {
    DMat3::from_rotation_z(z) * DMat3::from_rotation_y(y) * DMat3::from_rotation_x(x)
}

/// three.js `Euler(x, y, z, 'XYZ')`, as CVAT stores a cuboid's rotation.
pub fn xyz(x: f64, y: f64, z: f64) -> DMat3 {
    DMat3::from_rotation_x(x) * DMat3::from_rotation_y(y) * DMat3::from_rotation_z(z)
}

/// The angles `(x, y, z)` with `zyx(x, y, z) == r`, each in (-pi, pi]
/// (y in [-pi/2, pi/2]); at y = +-pi/2 (gimbal lock) x is 0.
pub fn to_zyx(r: &DMat3) -> (f64, f64, f64) {
    let m = rows(r);
    let cos_y = m[0][0].hypot(m[1][0]);
    let y = (-m[2][0]).atan2(cos_y);
    if cos_y > 1e-12 {
        (m[2][1].atan2(m[2][2]), y, m[1][0].atan2(m[0][0]))
    } else {
        (0.0, y, (-m[0][1]).atan2(m[1][1]))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::rng::Rng;
    use glam::DVec3;

    #[test]
    fn conventions_turn_the_axes_as_their_tools_do() {
        let q = std::f64::consts::FRAC_PI_2;
        // labelCloud: z = 90 degrees takes the box's x (length) axis to world +y.
        assert!((zyx(0.0, 0.0, q) * DVec3::X - DVec3::Y).length() < 1e-15);
        // x first, then z: the box's y axis goes to world z (by x), stays there (z).
        assert!((zyx(q, 0.0, q) * DVec3::Y - DVec3::Z).length() < 1e-15);
        // three.js XYZ: z first in the object's frame, then y, then x.
        assert!((xyz(q, 0.0, q) * DVec3::X - DVec3::Z).length() < 1e-15);
        assert_eq!(
            rows(&from_rows([[1.0, 2.0, 3.0], [4.0, 5.0, 6.0], [7.0, 8.0, 9.0]]))[1],
            [4.0, 5.0, 6.0]
        );
    }

    #[test]
    fn zyx_angles_round_trip_including_gimbal_lock() {
        let mut rng = Rng::new(5, 0);
        for _ in 0..1000 {
            let (x, y, z) = (rng.range(-3.1, 3.1), rng.range(-1.5, 1.5), rng.range(-3.1, 3.1));
            let r = zyx(x, y, z);
            let (a, b, c) = to_zyx(&r);
            assert!((zyx(a, b, c) - r).abs_diff_eq(DMat3::ZERO, 1e-12));
            assert!((a - x).abs() < 1e-9 && (b - y).abs() < 1e-9 && (c - z).abs() < 1e-9);
        }
        for y in [std::f64::consts::FRAC_PI_2, -std::f64::consts::FRAC_PI_2] {
            let r = zyx(0.4, y, -1.1);
            let (a, b, c) = to_zyx(&r);
            assert!((zyx(a, b, c) - r).abs_diff_eq(DMat3::ZERO, 1e-12), "{a} {b} {c}");
        }
    }
}
