//! The Euler-angle conventions of the tools boxes come from: labelCloud
//! rotates a box about x, then y, then z of the world (R = Rz Ry Rx);
//! CVAT's 3D canvas keeps three.js Euler angles in their default `XYZ`
//! order (R = Rx Ry Rz); KITTI turns a box about the camera's y axis.
//! Angles in radians; rotations are box-to-world, columns the box axes.

use nalgebra::{Matrix3, Rotation3, Vector3};

/// Rows of a 3x3 matrix.
pub fn rows(m: &Rotation3<f64>) -> [[f64; 3]; 3] {
    let m = m.matrix();
    std::array::from_fn(|r| std::array::from_fn(|c| m[(r, c)]))
}

/// A matrix from its rows.
pub fn from_rows(r: [[f64; 3]; 3]) -> Matrix3<f64> {
    Matrix3::from_fn(|i, j| r[i][j])
}

/// labelCloud: rotate about world x by `x`, then y by `y`, then z by `z`.
pub fn zyx(x: f64, y: f64, z: f64) -> Rotation3<f64> {
    about(&Vector3::z_axis(), z) * about(&Vector3::y_axis(), y) * about(&Vector3::x_axis(), x)
}

/// three.js `Euler(x, y, z, 'XYZ')`, as CVAT stores a cuboid's rotation.
pub fn xyz(x: f64, y: f64, z: f64) -> Rotation3<f64> {
    about(&Vector3::x_axis(), x) * about(&Vector3::y_axis(), y) * about(&Vector3::z_axis(), z)
}

/// Rotation by `angle` about a coordinate axis.
fn about(axis: &nalgebra::Unit<Vector3<f64>>, angle: f64) -> Rotation3<f64> {
    Rotation3::from_axis_angle(axis, angle)
}

/// The angles `(x, y, z)` with `zyx(x, y, z) == r`, each in (-pi, pi]
/// (y in [-pi/2, pi/2]); at y = +-pi/2 (gimbal lock) x is 0.
pub fn to_zyx(r: &Rotation3<f64>) -> (f64, f64, f64) {
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

    #[test]
    fn conventions_turn_the_axes_as_their_tools_do() {
        let q = std::f64::consts::FRAC_PI_2;
        // labelCloud: z = 90 degrees takes the box's x (length) axis to world +y.
        assert!((zyx(0.0, 0.0, q) * Vector3::x() - Vector3::y()).norm() < 1e-15);
        // x first, then z: the box's y axis goes to world z (by x), stays there (z).
        assert!((zyx(q, 0.0, q) * Vector3::y() - Vector3::z()).norm() < 1e-15);
        // three.js XYZ: z first in the object's frame, then y, then x.
        assert!((xyz(q, 0.0, q) * Vector3::x() - Vector3::z()).norm() < 1e-15);
        let m = from_rows([[1.0, 2.0, 3.0], [4.0, 5.0, 6.0], [7.0, 8.0, 9.0]]);
        assert_eq!(rows(&Rotation3::from_matrix_unchecked(m))[1], [4.0, 5.0, 6.0]);
    }

    #[test]
    fn zyx_angles_round_trip_including_gimbal_lock() {
        let mut rng = Rng::new(5, 0);
        for _ in 0..1000 {
            let (x, y, z) = (rng.range(-3.1, 3.1), rng.range(-1.5, 1.5), rng.range(-3.1, 3.1));
            let r = zyx(x, y, z);
            let (a, b, c) = to_zyx(&r);
            assert!((zyx(a, b, c).matrix() - r.matrix()).amax() < 1e-12);
            assert!((a - x).abs() < 1e-9 && (b - y).abs() < 1e-9 && (c - z).abs() < 1e-9);
        }
        for y in [std::f64::consts::FRAC_PI_2, -std::f64::consts::FRAC_PI_2] {
            let r = zyx(0.4, y, -1.1);
            let (a, b, c) = to_zyx(&r);
            assert!((zyx(a, b, c).matrix() - r.matrix()).amax() < 1e-12, "{a} {b} {c}");
        }
    }
}
