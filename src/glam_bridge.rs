//! Temporary: exact element-for-element conversions between glam and
//! nalgebra while the crate moves to nalgebra module by module (issue 16).
//! Deleted with the glam dependency.
use glam::{DMat3, DMat4, DVec3};
use nalgebra::{IsometryMatrix3, Matrix3, Matrix4, Point3, Rotation3, Translation3, Vector3};

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

impl ToGlam for Matrix4<f64> {
    type Glam = DMat4;
    fn to_glam(&self) -> DMat4 {
        DMat4::from_cols_slice(self.as_slice())
    }
}

impl ToGlam for Point3<f64> {
    type Glam = DVec3;
    fn to_glam(&self) -> DVec3 {
        DVec3::new(self.x, self.y, self.z)
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

impl ToGlam for Matrix3<f64> {
    type Glam = DMat3;
    fn to_glam(&self) -> DMat3 {
        DMat3::from_cols_slice(self.as_slice())
    }
}

impl ToNalgebra for DMat3 {
    type Nalgebra = Matrix3<f64>;
    fn to_na(&self) -> Matrix3<f64> {
        Matrix3::from_column_slice(&self.to_cols_array())
    }
}

/// A glam vector as a nalgebra one (an offset, not a point).
pub fn vector(v: DVec3) -> Vector3<f64> {
    Vector3::new(v.x, v.y, v.z)
}

/// Points as glam vectors.
pub fn points_to_glam(points: &[Point3<f64>]) -> Vec<DVec3> {
    points.iter().map(ToGlam::to_glam).collect()
}

/// Camera-to-world poses as glam 4x4s.
pub fn poses_to_glam(poses: &[IsometryMatrix3<f64>]) -> Vec<DMat4> {
    poses.iter().map(ToGlam::to_glam).collect()
}

impl ToNalgebra for DVec3 {
    type Nalgebra = Point3<f64>;
    fn to_na(&self) -> Point3<f64> {
        Point3::new(self.x, self.y, self.z)
    }
}

/// A glam 4x4 as a nalgebra one, element for element.
pub fn matrix4(m: &DMat4) -> Matrix4<f64> {
    Matrix4::from_column_slice(&m.to_cols_array())
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
