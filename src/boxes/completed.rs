//! Depth completed by the fitted model for the point cloud (`nerflabel
//! cloud`): the sensor's depth where it agrees with the rendered surface,
//! the rendered depth elsewhere, so objects the sensor missed (glass, dark,
//! shiny) appear. Rendered on a sub-grid of every `stride`-th pixel: the
//! cloud is voxel-averaged, so full frames would only cost time.

use super::label::Labeler;
use super::options::{DepthSource, LabelError, LabelOptions};
use super::parse::BoxSet;
use crate::nerf::model_file::Model;
use crate::poses::{fuse_depth_maps, CloudOptions, GeometryError, PointCloud};
use crate::scan::{DepthMap, Frame, Intrinsics, Scan};
use std::borrow::Cow;
use std::sync::atomic::{AtomicUsize, Ordering};

/// Rays rendered for a whole cloud at most: the cloud is voxel-averaged, so
/// a sub-grid of pixels gives the same points in a fraction of the time.
pub const CLOUD_RAYS: u64 = 6_000_000;

/// Why a completed cloud could not be made.
#[derive(Debug, thiserror::Error)]
pub enum CloudError {
    #[error(transparent)]
    Model(#[from] LabelError),
    #[error(transparent)]
    Fuse(#[from] GeometryError),
}

/// The cloud of every frame's depth completed by `model` (the sensor's
/// depth where it agrees with the rendered surface), rendered on a pixel
/// sub-grid sized to [`CLOUD_RAYS`]; `progress` hears frames finished.
pub fn completed_cloud(
    scan: &Scan,
    model: &Model,
    options: &CloudOptions,
    progress: &(dyn Fn(usize) + Sync),
) -> Result<PointCloud, CloudError> {
    let no_boxes = BoxSet::from_boxes(Vec::new());
    let labeler = Labeler::new(
        &no_boxes,
        Some(model),
        LabelOptions {
            source: DepthSource::Fused,
            full_depth: true,
            ..LabelOptions::default()
        },
    )?;
    let pixels: u64 = scan
        .frames
        .iter()
        .map(|f| u64::from(f.size().0) * u64::from(f.size().1))
        .sum();
    let stride = stride_for(pixels, CLOUD_RAYS);
    let done = AtomicUsize::new(0);
    let depth_of = |frame| {
        let (depth, k) = completed_depth(&labeler, frame, stride);
        progress(done.fetch_add(1, Ordering::Relaxed) + 1);
        Some((Cow::Owned(depth), k))
    };
    Ok(fuse_depth_maps(scan, options, &depth_of)?)
}

/// The odd pixel stride that renders at most `budget` rays over `pixels`
/// in all (odd, so every sample is an rgb pixel's centre).
pub fn stride_for(pixels: u64, budget: u64) -> u32 {
    let mut stride = 1u32;
    while pixels / u64::from(stride).pow(2) > budget.max(1) && stride < 255 {
        stride += 2;
    }
    stride
}

/// `frame`'s depth on every `stride`-th pixel from `labeler` (built with
/// full depth and no boxes), with the intrinsics of that sub-grid.
pub fn completed_depth(labeler: &Labeler, frame: &Frame, stride: u32) -> (DepthMap, Intrinsics) {
    let stride = stride.max(1);
    let (w, h) = frame.size();
    // Samples sit on pixel centres offset/2 in from each block's corner.
    let offset = (stride - 1) / 2;
    let (gw, gh) = (
        w.saturating_sub(offset).div_ceil(stride),
        h.saturating_sub(offset).div_ceil(stride),
    );
    let on_grid = |x: u32, y: u32| x % stride == offset && y % stride == offset;
    let surface = labeler.surface_where(frame, &on_grid);
    let mut metres = vec![0.0f32; gw as usize * gh as usize];
    for (x, y, z) in surface.points() {
        let (gx, gy) = ((x / stride) as usize, (y / stride) as usize);
        if let Some(d) = metres.get_mut(gy * gw as usize + gx) {
            *d = z as f32;
        }
    }
    let grid_k = sub_grid_intrinsics(&frame.intrinsics, stride);
    let depth = DepthMap {
        width: gw,
        height: gh,
        metres,
    };
    (depth, grid_k)
}

/// Intrinsics of the grid of every `stride`-th pixel, starting at pixel
/// `(stride - 1) / 2`: grid pixel g sees what rgb pixel `g * stride + offset` sees.
fn sub_grid_intrinsics(k: &Intrinsics, stride: u32) -> Intrinsics {
    let (s, offset) = (f64::from(stride), f64::from((stride - 1) / 2));
    Intrinsics {
        fx: k.fx / s,
        fy: k.fy / s,
        cx: (k.cx - offset) / s,
        cy: (k.cy - offset) / s,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_grid_pixel_sees_what_its_rgb_pixel_sees() {
        let k = Intrinsics {
            fx: 500.0,
            fy: 510.0,
            cx: 319.5,
            cy: 241.0,
        };
        for stride in [1u32, 3, 5] {
            let g = sub_grid_intrinsics(&k, stride);
            let offset = f64::from((stride - 1) / 2);
            for (gx, gy) in [(0.0, 0.0), (7.0, 11.0), (100.0, 3.0)] {
                let s = f64::from(stride);
                let want = k.unproject(gx * s + offset, gy * s + offset);
                assert!((g.unproject(gx, gy) - want).norm() < 1e-12, "stride {stride}");
            }
        }
    }

    #[test]
    fn stride_is_odd_and_keeps_the_budget() {
        assert_eq!(stride_for(1000, 5000), 1);
        assert_eq!(stride_for(36_864_000, 6_000_000), 3);
        for (pixels, budget) in [(36_864_000u64, 1_000_000u64), (10_000_000, 999), (1 << 40, 1)] {
            let s = stride_for(pixels, budget);
            assert_eq!(s % 2, 1);
            assert!(
                pixels / u64::from(s).pow(2) <= budget || s >= 255,
                "{pixels} {budget} {s}"
            );
        }
    }
}
