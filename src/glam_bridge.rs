//! Temporary: exact element-for-element conversions between glam and
//! nalgebra at the edge of the fixture generator, the one module still on
//! glam (issue 16). Deleted with the glam dependency.
use glam::{DMat4, DVec3};
use nalgebra::{IsometryMatrix3, Matrix3, Point3, Rotation3, Translation3, Vector3};

/// nalgebra value to its glam twin.
pub trait ToGlam {
    type Glam;
    fn to_glam(&self) -> Self::Glam;
}

/// glam value to its nalgebra twin.
pub trait ToNalgebra {
    type Nalgebra;
    fn to_na(&self) -> Self::Nalgebra;
}

impl ToGlam for IsometryMatrix3<f64> {
    type Glam = DMat4;
    fn to_glam(&self) -> DMat4 {
        DMat4::from_cols_slice(self.to_homogeneous().as_slice())
    }
}

impl ToGlam for Vector3<f64> {
    type Glam = DVec3;
    fn to_glam(&self) -> DVec3 {
        DVec3::new(self.x, self.y, self.z)
    }
}

/// A rigid (or nearly rigid) 4x4 as an isometry, keeping every element.
impl ToNalgebra for DMat4 {
    type Nalgebra = IsometryMatrix3<f64>;
    fn to_na(&self) -> IsometryMatrix3<f64> {
        let c = self.to_cols_array();
        let r = Matrix3::new(c[0], c[4], c[8], c[1], c[5], c[9], c[2], c[6], c[10]);
        IsometryMatrix3::from_parts(
            Translation3::new(c[12], c[13], c[14]),
            Rotation3::from_matrix_unchecked(r),
        )
    }
}

impl ToNalgebra for DVec3 {
    type Nalgebra = Point3<f64>;
    fn to_na(&self) -> Point3<f64> {
        Point3::new(self.x, self.y, self.z)
    }
}

/// A glam vector as a nalgebra one (an offset, not a point).
pub fn vector(v: DVec3) -> Vector3<f64> {
    Vector3::new(v.x, v.y, v.z)
}

/// Inverse of a rigid transform `[R t; 0 1]` as `[R^T -R^T t; 0 1]`.
pub fn rigid_inverse(m: &DMat4) -> DMat4 {
    let r = glam::DMat3::from_mat4(*m);
    let rt = r.transpose();
    let t = m.w_axis.truncate();
    let mut out = DMat4::from_mat3(rt);
    out.w_axis = (-(rt * t)).extend(1.0);
    out
}
