//! Depth maps in metres and resampling onto the colour grid without
//! blending across depth edges.

/// Depth in metres, row-major, 0 = no measurement.
#[derive(Clone, Debug, PartialEq)]
pub struct DepthMap {
    pub width: u32,
    pub height: u32,
    pub metres: Vec<f32>,
}

/// Neighbours whose depths differ by more than this fraction of the nearest
/// one are treated as lying across an edge and are not blended.
pub const EDGE_RELATIVE_GAP: f32 = 0.03;

/// Share of a frame's nearest measured depth within which it vouches that
/// space is free (margin for flying pixels and depth noise).
pub const FREE_FRACTION: f32 = 0.5;

/// Distance in front of a camera within which its depth image measured
/// nothing, less the [`FREE_FRACTION`] margin, in the depth's own unit; 0
/// without a measurement.
pub fn vouched_free_distance(depth: &[f32]) -> f32 {
    let nearest = depth
        .iter()
        .copied()
        .filter(|&z| z > 0.0 && z.is_finite())
        .fold(f32::INFINITY, f32::min);
    if nearest.is_finite() {
        FREE_FRACTION * nearest
    } else {
        0.0
    }
}

/// Where a ray may start: past `free_z` (from [`vouched_free_distance`])
/// when its pixel measured depth `measured_z`, from the camera otherwise
/// (a pixel without depth vouches for nothing); `t_per_z` turns z-depth
/// into distance along the ray.
pub fn vouched_start(measured_z: f32, free_z: f32, t_per_z: f32) -> f32 {
    if measured_z > 0.0 {
        free_z * t_per_z
    } else {
        0.0
    }
}

impl DepthMap {
    /// Depth at pixel (x, y), 0 outside the map or where missing.
    #[inline]
    pub fn get(&self, x: u32, y: u32) -> f32 {
        if x >= self.width || y >= self.height {
            return 0.0;
        }
        let i = y as usize * self.width as usize + x as usize;
        self.metres.get(i).copied().unwrap_or(0.0)
    }

    /// Number of pixels with a measurement.
    pub fn valid_count(&self) -> usize {
        self.metres.iter().filter(|&&d| d > 0.0).count()
    }
}

/// Bring a depth map to `width` x `height` (the colour grid). Pixel centres
/// are aligned (target pixel u samples source coordinate
/// `(u + 0.5) * dw / W - 0.5`); the four source neighbours are blended
/// bilinearly only when all are valid and agree within
/// [`EDGE_RELATIVE_GAP`], otherwise the nearest source pixel is taken as is,
/// so edges stay sharp and holes stay 0.
pub fn resample_depth_to(depth: &DepthMap, width: u32, height: u32) -> DepthMap {
    let (sw, sh) = (depth.width as usize, depth.height as usize);
    let (tw, th) = (width as usize, height as usize);
    if (sw, sh) == (tw, th) && depth.metres.len() == sw * sh {
        return depth.clone();
    }
    let mut out = vec![0.0f32; tw * th];
    if sw == 0 || sh == 0 || depth.metres.len() != sw * sh {
        return DepthMap {
            width,
            height,
            metres: out,
        };
    }
    let src = &depth.metres;
    let xs = axis_taps(sw, tw);
    let ys = axis_taps(sh, th);
    for (row, ty) in out.chunks_mut(tw.max(1)).zip(&ys) {
        let r0 = ty.lo * sw;
        let r1 = ty.hi * sw;
        for (px, tx) in row.iter_mut().zip(&xs) {
            let d00 = src[r0 + tx.lo];
            let d10 = src[r0 + tx.hi];
            let d01 = src[r1 + tx.lo];
            let d11 = src[r1 + tx.hi];
            let nearest = match (tx.frac < 0.5, ty.frac < 0.5) {
                (true, true) => d00,
                (false, true) => d10,
                (true, false) => d01,
                (false, false) => d11,
            };
            if nearest <= 0.0 {
                continue;
            }
            let lo = d00.min(d10).min(d01).min(d11);
            let hi = d00.max(d10).max(d01).max(d11);
            *px = if lo > 0.0 && hi - lo <= EDGE_RELATIVE_GAP * lo {
                let top = d00 + (d10 - d00) * tx.frac;
                let bottom = d01 + (d11 - d01) * tx.frac;
                top + (bottom - top) * ty.frac
            } else {
                nearest
            };
        }
    }
    DepthMap {
        width,
        height,
        metres: out,
    }
}

/// Source neighbours and weight of one target pixel along one axis.
#[derive(Clone, Copy, Debug)]
pub(super) struct Tap {
    pub lo: usize,
    pub hi: usize,
    pub frac: f32,
}

/// Taps for mapping `target` pixels onto `source` pixels, centres aligned,
/// clamped at the borders.
pub(super) fn axis_taps(source: usize, target: usize) -> Vec<Tap> {
    let scale = source as f64 / target.max(1) as f64;
    let last = source.saturating_sub(1) as f64;
    (0..target)
        .map(|u| {
            let c = ((u as f64 + 0.5) * scale - 0.5).clamp(0.0, last);
            let lo = c.floor();
            let frac = (c - lo) as f32;
            let lo = lo as usize;
            Tap {
                lo,
                hi: (lo + 1).min(source.saturating_sub(1)),
                frac,
            }
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    fn map(width: u32, height: u32, f: impl Fn(u32, u32) -> f32) -> DepthMap {
        let metres = (0..height)
            .flat_map(|y| (0..width).map(move |x| (x, y)))
            .map(|(x, y)| f(x, y))
            .collect();
        DepthMap { width, height, metres }
    }

    #[test]
    fn same_size_is_identity() {
        let d = map(5, 4, |x, y| 1.0 + x as f32 * 0.1 + y as f32);
        assert_eq!(resample_depth_to(&d, 5, 4), d);
    }

    #[test]
    fn upsampling_keeps_pixel_centres_aligned() {
        // Depth linear in the source pixel coordinate: d = 1 + 0.01 * x.
        let d = map(8, 6, |x, _| 1.0 + 0.01 * x as f32);
        let up = resample_depth_to(&d, 32, 24);
        // Target pixel u samples source coordinate (u + 0.5) / 4 - 0.5.
        for u in 2..30u32 {
            let c = (u as f32 + 0.5) / 4.0 - 0.5;
            let want = 1.0 + 0.01 * c;
            assert!(
                (up.get(u, 10) - want).abs() < 1e-5,
                "u {u}: {} vs {want}",
                up.get(u, 10)
            );
        }
        // Integer factor 2.5: centres of target pixels 2 and 7 fall on source centres 0.5 and 2.5.
        let up = resample_depth_to(&d, 20, 15);
        assert!((up.get(2, 5) - (1.0 + 0.01 * 0.5)).abs() < 1e-5);
        assert!((up.get(7, 5) - (1.0 + 0.01 * 2.5)).abs() < 1e-5);
    }

    #[test]
    fn downsampling_by_two_averages_pairs() {
        let d = map(8, 8, |x, _| 2.0 + 0.01 * x as f32);
        let down = resample_depth_to(&d, 4, 4);
        // Target 1 samples source 2.5: average of columns 2 and 3.
        assert!((down.get(1, 1) - 2.025).abs() < 1e-5);
    }

    #[test]
    fn edges_are_not_blended() {
        // A step from 1 m to 3 m between source columns 3 and 4.
        let d = map(8, 4, |x, _| if x < 4 { 1.0 } else { 3.0 });
        let up = resample_depth_to(&d, 32, 16);
        for v in 0..16 {
            for u in 0..32 {
                let z = up.get(u, v);
                assert!(z == 1.0 || z == 3.0, "blended value {z} at {u},{v}");
                // Step at source coordinate 3.5, i.e. target u + 0.5 = 16.
                assert_eq!(z, if u < 16 { 1.0 } else { 3.0 }, "at {u},{v}");
            }
        }
    }

    #[test]
    fn holes_stay_empty_and_do_not_leak() {
        let d = map(8, 8, |x, y| {
            if (3..5).contains(&x) && (3..5).contains(&y) {
                0.0
            } else {
                2.0
            }
        });
        let up = resample_depth_to(&d, 32, 32);
        for v in 0..32 {
            for u in 0..32 {
                let z = up.get(u, v);
                let (sx, sy) = ((u as f32 + 0.5) / 4.0 - 0.5, (v as f32 + 0.5) / 4.0 - 0.5);
                let nearest_in_hole = (2.5..4.5).contains(&sx) && (2.5..4.5).contains(&sy);
                if nearest_in_hole {
                    assert_eq!(z, 0.0, "hole filled at {u},{v}");
                } else {
                    assert_eq!(z, 2.0, "hole leaked at {u},{v}");
                }
            }
        }
    }

    #[test]
    fn smooth_slope_is_interpolated_not_stepped() {
        // 1% per pixel: within the edge gap, so blended.
        let d = map(4, 4, |x, _| 1.0 + 0.01 * x as f32);
        let up = resample_depth_to(&d, 16, 16);
        let distinct: std::collections::BTreeSet<u32> = (0..16).map(|u| up.get(u, 8).to_bits()).collect();
        assert!(distinct.len() >= 12, "only {} distinct values", distinct.len());
    }
}
