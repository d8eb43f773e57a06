//! The point cloud the page draws, in a compact binary form
//! (`GET /api/cloud.bin`), all little-endian:
//!
//! | bytes | content |
//! |---|---|
//! | 8 | magic `NLCLOUD1` |
//! | 4 | u32 point count N |
//! | 4 | f32 voxel size, metres |
//! | 12 | f32 up axis x, y, z |
//! | 4 | reserved, 0 |
//! | 12 N | f32 x, y, z per point (world metres) |
//! | 3 N | u8 r, g, b per point |
//!
//! Positions come first and the header is 32 bytes, so a `Float32Array`
//! can view them in place.

use crate::poses::PointCloud;
use nalgebra::Vector3;

/// First bytes of the format.
pub const MAGIC: &[u8; 8] = b"NLCLOUD1";
/// Header length in bytes.
pub const HEADER_BYTES: usize = 32;

/// Encode at most `max_points` points of `cloud` (an even subsample when it has more).
pub fn encode(cloud: &PointCloud, up: &Vector3<f64>, max_points: usize) -> Vec<u8> {
    let stride = cloud.len().div_ceil(max_points.max(1)).max(1);
    let kept: Vec<usize> = (0..cloud.len()).step_by(stride).collect();
    let mut out = Vec::with_capacity(HEADER_BYTES + kept.len() * 15);
    out.extend_from_slice(MAGIC);
    out.extend_from_slice(&(kept.len() as u32).to_le_bytes());
    out.extend_from_slice(&((cloud.voxel_size * stride as f64) as f32).to_le_bytes());
    for &c in up.iter() {
        out.extend_from_slice(&(c as f32).to_le_bytes());
    }
    out.extend_from_slice(&0u32.to_le_bytes());
    for &i in &kept {
        for c in cloud.positions[i] {
            out.extend_from_slice(&c.to_le_bytes());
        }
    }
    for &i in &kept {
        out.extend_from_slice(&cloud.colors[i]);
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn layout_matches_the_documented_header() {
        let cloud = PointCloud {
            positions: vec![[1.0, 2.0, 3.0], [4.0, 5.0, 6.0], [7.0, 8.0, 9.0]],
            colors: vec![[1, 2, 3], [4, 5, 6], [7, 8, 9]],
            voxel_size: 0.01,
            ..PointCloud::default()
        };
        let bytes = encode(&cloud, &Vector3::z(), 2);
        assert_eq!(&bytes[..8], MAGIC);
        assert_eq!(u32::from_le_bytes(bytes[8..12].try_into().unwrap()), 2);
        assert_eq!(f32::from_le_bytes(bytes[12..16].try_into().unwrap()), 0.02);
        assert_eq!(f32::from_le_bytes(bytes[24..28].try_into().unwrap()), 1.0);
        assert_eq!(bytes.len(), HEADER_BYTES + 2 * 15);
        assert_eq!(f32::from_le_bytes(bytes[44..48].try_into().unwrap()), 7.0);
        assert_eq!(&bytes[HEADER_BYTES + 24..], &[1, 2, 3, 7, 8, 9]);
    }
}
