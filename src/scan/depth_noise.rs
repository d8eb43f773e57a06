//! The depth sensor's noise as a function of depth, measured on the scan's
//! own depth images: structured-light and stereo sensors scatter by a few
//! millimetres at 1 m and by centimetres at 4 m, and training must not
//! hold far surfaces to a tolerance only near ones can meet.
//!
//! Along rows and columns of each depth image (as stored, before
//! resampling to the colour grid), the second difference of three pixels
//! two apart cancels a locally planar surface and leaves the noise; its
//! median absolute value per depth bin gives the noise's scale there.

use super::depth::axis_taps;
use super::Frame;
use serde::{Deserialize, Serialize};

/// Depths of a second difference's three pixels may span at most this
/// fraction of the middle one; wider spans lie across an edge, not a surface.
const MAX_RELATIVE_SPAN: f32 = 0.05;
/// Frames sampled (evenly over the scan): enough pixels, little time.
const MAX_FRAMES: usize = 24;
/// Second differences per depth bin, at least.
const MIN_PER_BIN: usize = 2000;
/// Depth bins, at most.
const MAX_BINS: usize = 8;
/// Median absolute deviation to standard deviation of a normal distribution.
const MAD_TO_SIGMA: f32 = 1.4826;

/// Noise of the depth sensor against depth: standard deviation (metres)
/// at a set of depths (metres, ascending), linear in between and constant
/// beyond the ends.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct DepthNoise {
    pub depths: Vec<f32>,
    pub sigmas: Vec<f32>,
}

impl DepthNoise {
    /// Standard deviation of the depth measured at depth `z`.
    pub fn sigma(&self, z: f32) -> f32 {
        let i = self.depths.partition_point(|&d| d < z);
        if i == 0 {
            return self.sigmas[0];
        }
        if i == self.depths.len() {
            return self.sigmas[i - 1];
        }
        let (z0, z1) = (self.depths[i - 1], self.depths[i]);
        let w = if z1 > z0 { (z - z0) / (z1 - z0) } else { 0.0 };
        self.sigmas[i - 1] + w * (self.sigmas[i] - self.sigmas[i - 1])
    }

    /// The same noise with depths and deviations multiplied by `scale`
    /// (metres to the local units of training).
    pub fn scaled(&self, scale: f32) -> DepthNoise {
        DepthNoise {
            depths: self.depths.iter().map(|d| d * scale).collect(),
            sigmas: self.sigmas.iter().map(|s| s * scale).collect(),
        }
    }
}

/// The noise of the depth sensor that measured `frames`, or `None` when
/// they have too few measured surfaces to tell.
pub fn depth_noise<'a>(frames: impl IntoIterator<Item = &'a Frame>) -> Option<DepthNoise> {
    let with_depth: Vec<&Frame> = frames.into_iter().filter(|f| f.depth.is_some()).collect();
    let step = with_depth.len().div_ceil(MAX_FRAMES).max(1);
    let mut samples: Vec<(f32, f32)> = Vec::new();
    for frame in with_depth.iter().step_by(step) {
        second_differences(frame, &mut samples);
    }
    if samples.len() < MIN_PER_BIN {
        return None;
    }
    samples.sort_by(|a, b| a.0.total_cmp(&b.0));
    let bins = (samples.len() / MIN_PER_BIN).clamp(1, MAX_BINS);
    let (mut depths, mut sigmas) = (Vec::with_capacity(bins), Vec::with_capacity(bins));
    for b in 0..bins {
        let bin = &samples[b * samples.len() / bins..(b + 1) * samples.len() / bins];
        let mut residuals: Vec<f32> = bin.iter().map(|s| s.1.abs()).collect();
        let mid = residuals.len() / 2;
        let (_, median, _) = residuals.select_nth_unstable_by(mid, f32::total_cmp);
        depths.push(bin[bin.len() / 2].0);
        sigmas.push(MAD_TO_SIGMA * *median);
    }
    Some(DepthNoise { depths, sigmas })
}

/// A pixel of the colour grid that sits on a stored depth pixel's centre,
/// and how much of the noise of one stored pixel bilinear resampling left
/// there (the variance of its blend relative to one pixel's).
#[derive(Clone, Copy)]
struct CentreTap {
    pixel: usize,
    variance: f32,
}

/// Per stored depth pixel along one axis, the colour-grid pixel nearest its
/// centre (`None` where no colour pixel lies within half a stored pixel).
fn centre_taps(stored: usize, colour: usize) -> Vec<Option<CentreTap>> {
    let mut best: Vec<Option<(f32, CentreTap)>> = vec![None; stored];
    for (pixel, tap) in axis_taps(stored, colour).iter().enumerate() {
        let (index, offset) = if tap.frac < 0.5 {
            (tap.lo, tap.frac)
        } else {
            (tap.hi, 1.0 - tap.frac)
        };
        let w = 1.0 - offset;
        let candidate = CentreTap {
            pixel,
            variance: w * w + offset * offset,
        };
        if best[index].is_none_or(|(o, _)| offset < o) {
            best[index] = Some((offset, candidate));
        }
    }
    best.into_iter().map(|b| b.map(|(_, t)| t)).collect()
}

/// Push (depth, residual as one pixel's noise) for the frame's second
/// differences along rows and along columns of its stored depth pixels.
fn second_differences(frame: &Frame, out: &mut Vec<(f32, f32)>) {
    let Some(depth) = &frame.depth else { return };
    let (w, h) = (depth.width as usize, depth.height as usize);
    let (sw, sh) = frame.depth_size.map_or((w, h), |(a, b)| (a as usize, b as usize));
    if depth.metres.len() != w * h || sw == 0 || sh == 0 {
        return;
    }
    let cols = centre_taps(sw, w);
    let rows = centre_taps(sh, h);
    let at = |r: CentreTap, c: CentreTap| (depth.metres[r.pixel * w + c.pixel], r.variance * c.variance);
    let mut push = |a: (f32, f32), b: (f32, f32), c: (f32, f32)| {
        let (z0, z1, z2) = (a.0, b.0, c.0);
        if !(z0 > 0.0 && z1 > 0.0 && z2 > 0.0) {
            return;
        }
        if z0.max(z1).max(z2) - z0.min(z1).min(z2) > MAX_RELATIVE_SPAN * z1 {
            return;
        }
        // z1 - (z0 + z2) / 2 has the variance of b + (a + c) / 4 pixels.
        let variance = b.1 + 0.25 * (a.1 + c.1);
        out.push((z1, (z1 - 0.5 * (z0 + z2)) / variance.sqrt()));
    };
    for r in rows.iter().flatten() {
        for k in 0..sw.saturating_sub(4) {
            if let (Some(a), Some(b), Some(c)) = (cols[k], cols[k + 2], cols[k + 4]) {
                push(at(*r, a), at(*r, b), at(*r, c));
            }
        }
    }
    for c in cols.iter().flatten() {
        for k in 0..sh.saturating_sub(4) {
            if let (Some(a), Some(b), Some(d)) = (rows[k], rows[k + 2], rows[k + 4]) {
                push(at(a, *c), at(b, *c), at(d, *c));
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::rng::Rng;
    use crate::scan::Intrinsics;
    use crate::scan::{resample_depth_to, DepthMap};
    use nalgebra::IsometryMatrix3;

    /// A frame looking at a slanted plane from 0.6 to 4.2 m, its stored
    /// depth `stored` pixels wide with noise `a` z^2, resampled to 640x480.
    fn noisy_frame(stored: (u32, u32), a: f32, seed: u64) -> Frame {
        let (sw, sh) = stored;
        let mut rng = Rng::new(seed, 7);
        let metres = (0..sh)
            .flat_map(|y| (0..sw).map(move |x| (x, y)))
            .map(|(x, y)| {
                let z = 0.6 + 3.6 * (y as f32 / sh as f32) + 0.2 * (x as f32 / sw as f32);
                z + a * z * z * rng.normal() as f32
            })
            .collect();
        let depth = resample_depth_to(
            &DepthMap {
                width: sw,
                height: sh,
                metres,
            },
            640,
            480,
        );
        let intrinsics = Intrinsics {
            fx: 525.0,
            fy: 525.0,
            cx: 320.0,
            cy: 240.0,
        };
        let mut frame = Frame::new(
            0,
            "000000",
            image::RgbImage::new(640, 480),
            Some(depth),
            IsometryMatrix3::identity(),
            intrinsics,
        );
        frame.depth_size = Some(stored);
        frame
    }

    #[test]
    fn noise_growing_with_depth_squared_is_measured_at_any_depth_resolution() {
        let a = 0.0015;
        for stored in [(640, 480), (256, 192), (320, 240)] {
            let frames: Vec<Frame> = (0..3).map(|s| noisy_frame(stored, a, s)).collect();
            let noise = depth_noise(&frames).expect("plenty of surface");
            assert!(noise.depths.len() >= 4, "{stored:?}: {} bins", noise.depths.len());
            for (i, (&z, &sigma)) in noise.depths.iter().zip(&noise.sigmas).enumerate() {
                let truth = a * z * z;
                // The nearest bin spans the depths where the noise changes fastest.
                let tolerance = if i == 0 { 0.15 } else { 0.03 };
                assert!(
                    (sigma / truth - 1.0).abs() < tolerance,
                    "{stored:?}: {sigma} m at {z} m, truth {truth}"
                );
            }
        }
    }

    #[test]
    fn edges_and_holes_do_not_count_as_noise() {
        // Noise-free steps every 16 pixels and holes: nothing to measure.
        let mut frame = noisy_frame((640, 480), 0.0, 1);
        let depth = frame.depth.as_mut().unwrap();
        for (i, z) in depth.metres.iter_mut().enumerate() {
            let x = i % 640;
            *z = if x % 97 == 0 { 0.0 } else { 1.0 + 0.5 * (x / 16) as f32 };
        }
        let noise = depth_noise([&frame]).unwrap();
        assert!(noise.sigmas.iter().all(|&s| s < 1e-4), "{noise:?}");
    }

    #[test]
    fn scans_without_depth_have_no_noise_and_lookups_interpolate() {
        let mut frame = noisy_frame((64, 48), 0.001, 2);
        frame.depth = None;
        assert_eq!(depth_noise([&frame]), None);
        let noise = DepthNoise {
            depths: vec![1.0, 3.0],
            sigmas: vec![0.002, 0.010],
        };
        assert_eq!(noise.sigma(0.5), 0.002);
        assert!((noise.sigma(2.0) - 0.006).abs() < 1e-7);
        assert_eq!(noise.sigma(5.0), 0.010);
        assert!((noise.scaled(0.5).sigma(1.0) - 0.003).abs() < 1e-7);
    }
}
