//! Real spherical harmonics up to degree 3 (16 coefficients) for the view
//! direction input of the colour network.

/// Number of coefficients produced by [`encode`].
pub const SH_COEFFS: usize = 16;

/// Spherical-harmonics basis of a unit direction.
#[inline]
pub fn encode(d: [f32; 3], out: &mut [f32; SH_COEFFS]) {
    let [x, y, z] = d;
    let (xx, yy, zz) = (x * x, y * y, z * z);
    out[0] = 0.282_094_8;
    out[1] = -0.488_602_5 * y;
    out[2] = 0.488_602_5 * z;
    out[3] = -0.488_602_5 * x;
    out[4] = 1.092_548_4 * x * y;
    out[5] = -1.092_548_4 * y * z;
    out[6] = 0.315_391_57 * (2.0 * zz - xx - yy);
    out[7] = -1.092_548_4 * x * z;
    out[8] = 0.546_274_2 * (xx - yy);
    out[9] = -0.590_043_6 * y * (3.0 * xx - yy);
    out[10] = 2.890_611_4 * x * y * z;
    out[11] = -0.457_045_8 * y * (4.0 * zz - xx - yy);
    out[12] = 0.373_176_33 * z * (2.0 * zz - 3.0 * xx - 3.0 * yy);
    out[13] = -0.457_045_8 * x * (4.0 * zz - xx - yy);
    out[14] = 1.445_305_7 * z * (xx - yy);
    out[15] = -0.590_043_6 * x * (xx - 3.0 * yy);
}

#[cfg(test)]
#[allow(clippy::needless_range_loop)] // index loops mirror the formulas they check
mod tests {
    use super::*;

    #[test]
    fn basis_is_orthonormal_on_the_sphere() {
        // Monte Carlo integral of Y_i Y_j over the sphere = delta_ij.
        let mut rng = crate::rng::Rng::new(11, 0);
        let n = 200_000;
        let mut gram = [[0.0f64; SH_COEFFS]; SH_COEFFS];
        let mut y = [0.0f32; SH_COEFFS];
        for _ in 0..n {
            let z = rng.f64() * 2.0 - 1.0;
            let phi = rng.f64() * std::f64::consts::TAU;
            let r = (1.0 - z * z).sqrt();
            encode([(r * phi.cos()) as f32, (r * phi.sin()) as f32, z as f32], &mut y);
            for i in 0..SH_COEFFS {
                for j in 0..SH_COEFFS {
                    gram[i][j] += (y[i] * y[j]) as f64;
                }
            }
        }
        let area = 4.0 * std::f64::consts::PI;
        for i in 0..SH_COEFFS {
            for j in 0..SH_COEFFS {
                let v = gram[i][j] * area / n as f64;
                let expect = if i == j { 1.0 } else { 0.0 };
                assert!((v - expect).abs() < 0.03, "({i},{j}) = {v}");
            }
        }
    }
}
