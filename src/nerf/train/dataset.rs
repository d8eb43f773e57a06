//! Scan frames turned into training and held-out views in local
//! coordinates, plus the depth rays that seed the occupancy grid.

use crate::mask::{components, dilate_mask};
use crate::nerf::camera::LocalCamera;
use crate::nerf::occupancy::{CameraSpace, DepthRay};
use crate::poses::SceneTransform;
use crate::scan::{vouched_free_distance, ColourBorder, Frame, Scan};
use rayon::prelude::*;

/// One training or evaluation view: camera, colour and optional depth.
#[derive(Clone, Debug)]
pub struct View {
    pub camera: LocalCamera,
    /// RGB8, row-major.
    pub rgb: Vec<u8>,
    /// Z-depth in local units per pixel, 0 = no measurement.
    pub depth: Option<Vec<f32>>,
    /// Pixels where the sensor returned nothing, away from any measured
    /// pixel (not a speck or an edge dropout): something the sensor cannot
    /// see may be there. `None` when the view's missing depth says nothing.
    pub no_return: Option<Vec<bool>>,
    /// Lines at the image's edges that show no scene: not scored
    /// ([`crate::scan::dead_colour_border`]).
    pub colour_border: ColourBorder,
}

/// Views of a scan split into training and held-out sets.
pub struct Dataset {
    pub train: Vec<View>,
    pub holdout: Vec<View>,
    /// Scan frame index of each training view.
    pub train_frames: Vec<usize>,
    /// Scan frame index of each held-out view.
    pub holdout_frames: Vec<usize>,
    /// Mean colour of the training images, used behind empty rays.
    pub background: [f32; 3],
}

/// Whether frame `index` is held out when every `every`-th frame is (0 = none).
/// The held-out frames are the last of each group of `every`, so the first
/// frame of a scan always trains.
pub fn is_holdout(index: usize, every: usize) -> bool {
    every > 1 && (index + 1).is_multiple_of(every)
}

/// The camera of a scan frame in local coordinates.
pub fn local_camera(frame: &crate::scan::Frame, transform: &SceneTransform) -> LocalCamera {
    let (w, h) = frame.size();
    LocalCamera::new(
        &transform.world_to_local_pose(&frame.camera_to_world),
        &frame.intrinsics,
        w,
        h,
    )
}

/// Build the views of `scan` in the local frame of `transform`.
pub fn build(scan: &Scan, transform: &SceneTransform, holdout_every: usize) -> Dataset {
    let borders = scan.colour_borders();
    let views: Vec<View> = scan
        .frames
        .par_iter()
        .zip(&borders)
        .map(|(frame, &colour_border)| {
            let depth = frame.depth.as_ref().map(|d| {
                let scale = transform.scale() as f32;
                d.metres
                    .iter()
                    .map(|&m| if m > 0.0 && m.is_finite() { m * scale } else { 0.0 })
                    .collect()
            });
            View {
                camera: local_camera(frame, transform),
                rgb: frame.rgb.as_raw().clone(),
                depth,
                no_return: None,
                colour_border,
            }
        })
        .collect();
    let mut data = Dataset {
        train: Vec::new(),
        holdout: Vec::new(),
        train_frames: Vec::new(),
        holdout_frames: Vec::new(),
        background: [0.5; 3],
    };
    let single = views.len() < 2;
    for (i, view) in views.into_iter().enumerate() {
        // A one-frame scan trains on its only frame.
        if !single && is_holdout(i, holdout_every) {
            data.holdout.push(view);
            data.holdout_frames.push(i);
        } else {
            data.train.push(view);
            data.train_frames.push(i);
        }
    }
    data.background = mean_colour(&data.train);
    data
}

/// Mark the "no return" pixels of the training views (see
/// [`View::no_return`]); only the no-return term of training reads them.
pub fn mark_no_return(data: &mut Dataset, scan: &Scan) {
    data.train
        .par_iter_mut()
        .zip(&data.train_frames)
        .for_each(|(view, &i)| {
            let frame = &scan.frames[i];
            let (w, h) = frame.size();
            view.no_return = view
                .depth
                .as_deref()
                .and_then(|d| no_return_mask(d, w, h, depth_pixel_ratio(frame)));
        });
}

/// A view's depth is evidence of absence only when most of it was measured
/// (a sensor that failed on the whole frame says nothing about any pixel).
const NO_RETURN_MIN_COVERAGE: f64 = 0.2;

/// Colour pixels per pixel of the frame's depth image (as stored).
fn depth_pixel_ratio(frame: &Frame) -> f64 {
    let (w, _) = frame.size();
    frame.depth_size.map_or(1.0, |(dw, _)| w as f64 / dw.max(1) as f64)
}

/// Pixels without depth inside the silhouette of something the sensor
/// cannot see (see [`View::no_return`]), more than one depth pixel
/// (`ratio` colour pixels) from any measured one. A region without depth
/// is such a silhouette when it holds a pixel more than two depth pixels
/// from any measured one (wider than a speck or an edge dropout), does not
/// reach the image border (the depth camera's field of view or range
/// running out) and is not a projector shadow. Within it, the band between
/// one and two depth pixels from the measured depth is the object too:
/// left to colour alone, long fits let a glass's lower rim go transparent
/// and painted it on the table behind.
pub fn no_return_mask(depth: &[f32], w: u32, h: u32, ratio: f64) -> Option<Vec<bool>> {
    let valid: Vec<bool> = depth.iter().map(|&z| z > 0.0 && z.is_finite()).collect();
    let measured = valid.iter().filter(|&&v| v).count();
    if (measured as f64) < NO_RETURN_MIN_COVERAGE * valid.len() as f64 {
        return None;
    }
    let one_depth_pixel = ratio.ceil().max(1.0) as usize;
    let two_depth_pixels = (2.0 * ratio).round().max(2.0) as usize;
    // Regions without depth (value 0) that touch the border are open.
    let regions = components(
        &valid.iter().map(|&v| v as u16).collect::<Vec<_>>(),
        w as usize,
        h as usize,
    );
    let shadow = shadow_regions(depth, &valid, &regions.label, regions.value.len(), w as usize);
    let mut silhouette = vec![false; regions.value.len()];
    let within_two = dilate_mask(&valid, w, h, two_depth_pixels);
    for (&region, _) in regions.label.iter().zip(&within_two).filter(|(_, &near)| !near) {
        let r = region as usize;
        silhouette[r] |= !regions.border[r] && !shadow[r];
    }
    let within_one = dilate_mask(&valid, w, h, one_depth_pixel);
    Some(
        regions
            .label
            .iter()
            .zip(&within_one)
            .map(|(&r, &near)| silhouette[r as usize] && !near)
            .collect(),
    )
}

/// Relative depth step across a region without depth above which its row
/// runs from a near surface to a far one.
const SHADOW_DEPTH_STEP: f32 = 0.1;

/// Regions without depth that are the shadow of a structured-light
/// projector: in most of their rows the measured depth just left and just
/// right of the gap differs by more than [`SHADOW_DEPTH_STEP`] (the gap lies
/// beside a depth edge, the projector's baseline being horizontal). Rays
/// there see the far surface, which other views measured; an object the
/// sensor cannot see sits in front of one surface instead. A shadow whose
/// step is smaller is narrower than the two-pixel margin anyway.
fn shadow_regions(depth: &[f32], valid: &[bool], label: &[u32], regions: usize, w: usize) -> Vec<bool> {
    let (mut rows, mut steps) = (vec![0usize; regions], vec![0usize; regions]);
    let mut left = vec![0.0f32; w];
    for (row_depth, (row_valid, row_label)) in depth
        .chunks_exact(w)
        .zip(valid.chunks_exact(w).zip(label.chunks_exact(w)))
    {
        let mut last = 0.0;
        for x in 0..w {
            if row_valid[x] {
                last = row_depth[x];
            }
            left[x] = last;
        }
        let mut right = 0.0;
        for x in (0..w).rev() {
            if row_valid[x] {
                right = row_depth[x];
                continue;
            }
            if left[x] > 0.0 && right > 0.0 {
                let region = row_label[x] as usize;
                rows[region] += 1;
                if (left[x] - right).abs() > SHADOW_DEPTH_STEP * left[x].min(right) {
                    steps[region] += 1;
                }
            }
        }
    }
    rows.iter().zip(&steps).map(|(&n, &s)| 2 * s > n).collect()
}

fn mean_colour(views: &[View]) -> [f32; 3] {
    let mut sum = [0.0f64; 3];
    let mut n = 0u64;
    for v in views {
        for px in v.rgb.chunks_exact(3).step_by(7) {
            for c in 0..3 {
                sum[c] += px[c] as f64;
            }
            n += 1;
        }
    }
    if n == 0 {
        return [0.5; 3];
    }
    sum.map(|s| (s / n as f64 / 255.0) as f32)
}

/// Each view's camera and the distance within which it measured nothing.
pub fn camera_spaces(views: &[View]) -> Vec<CameraSpace> {
    views
        .iter()
        .map(|view| CameraSpace {
            origin: view.camera.origin,
            free_distance: view.depth.as_deref().map_or(0.0, vouched_free_distance),
        })
        .collect()
}

/// Depth rays of the training views (every `stride`-th pixel both ways).
pub fn depth_rays(views: &[View], stride: usize) -> Vec<DepthRay> {
    strided_rays(views, stride, |view, i| {
        let z = view.depth.as_deref()?[i];
        (z > 0.0 && z.is_finite()).then_some(z)
    })
}

/// Rays of every `stride`-th pixel (in both directions) that the views'
/// no-return masks mark (see [`View::no_return`]); `t_hit` is infinite.
pub fn no_return_rays(views: &[View], stride: usize) -> Vec<DepthRay> {
    strided_rays(views, stride, |view, i| {
        view.no_return.as_deref()?[i].then_some(f32::INFINITY)
    })
}

/// Rays of every `stride`-th pixel (in both directions) where `depth_at`
/// (a view and a pixel index) gives a depth along the optical axis.
fn strided_rays<F>(views: &[View], stride: usize, depth_at: F) -> Vec<DepthRay>
where
    F: Fn(&View, usize) -> Option<f32> + Sync,
{
    let stride = stride.max(1);
    let depth_at = &depth_at;
    views
        .par_iter()
        .flat_map_iter(|view| {
            let cam = view.camera;
            let width = cam.width as usize;
            let height = cam.height as usize;
            (0..height).step_by(stride).flat_map(move |y| {
                (0..width).step_by(stride).filter_map(move |x| {
                    let z = depth_at(view, y * width + x)?;
                    let (ray, t_per_z) = cam.ray(x as f32, y as f32);
                    Some(DepthRay {
                        origin: ray.origin,
                        dir: ray.dir,
                        t_hit: z * t_per_z,
                    })
                })
            })
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn depth_and_no_return_rays_start_at_the_strided_pixels_they_mark() {
        let (w, h) = (8u32, 6u32);
        let camera = LocalCamera {
            rotation: [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]],
            origin: [0.5, 0.5, 0.1],
            fx: 10.0,
            fy: 10.0,
            cx: 4.0,
            cy: 3.0,
            width: w,
            height: h,
        };
        // Depth 0.4 on the left half, nothing on the right; the right half's
        // pixels marked as no return.
        let depth: Vec<f32> = (0..w * h).map(|i| if i % w < 4 { 0.4 } else { 0.0 }).collect();
        let no_return: Vec<bool> = (0..w * h).map(|i| i % w >= 4).collect();
        let view = View {
            camera,
            rgb: vec![0; (w * h * 3) as usize],
            depth: Some(depth),
            no_return: Some(no_return),
            colour_border: ColourBorder::default(),
        };
        let views = [view];
        // Stride 2: columns 0, 2, 4, 6 and rows 0, 2, 4.
        let measured = depth_rays(&views, 2);
        let unseen = no_return_rays(&views, 2);
        assert_eq!((measured.len(), unseen.len()), (6, 6));
        for ray in &measured {
            // The surface lies at depth 0.4 along the optical axis (+z here).
            let z = ray.t_hit * ray.dir[2];
            assert!((z - 0.4).abs() < 1e-5, "{z}");
            assert!(ray.dir[0] < 0.0, "left half");
        }
        assert!(unseen.iter().all(|r| r.t_hit == f32::INFINITY && r.dir[0] >= 0.0));
        assert!(unseen.iter().all(|r| r.origin == [0.5, 0.5, 0.1]));
    }

    #[test]
    fn no_return_marks_only_wide_regions_without_depth() {
        let (w, h) = (64u32, 48u32);
        let mut depth = vec![1.5f32; (w * h) as usize];
        let mut clear = |x0: u32, x1: u32, y0: u32, y1: u32| {
            for y in y0..y1 {
                for x in x0..x1 {
                    depth[(y * w + x) as usize] = 0.0;
                }
            }
        };
        clear(10, 30, 10, 30); // an object the sensor cannot see
        clear(45, 47, 5, 7); // a speck
        clear(50, 51, 2, 46); // a one-pixel dropout line
        clear(36, 40, 20, 40); // a dropout band four pixels wide
        clear(0, 8, 30, 48); // the depth camera's field of view ending
        let mask = no_return_mask(&depth, w, h, 1.0).expect("mostly measured");
        let at = |x: u32, y: u32| mask[(y * w + x) as usize];
        // A region with a pixel two pixels from the measured ones (native
        // resolution) is a silhouette: all of it but its outermost pixel.
        assert!(at(11, 11) && at(20, 20) && at(28, 28));
        assert!(!at(10, 20) && !at(29, 20) && !at(5, 5));
        assert!(!at(45, 5) && !at(46, 6) && !at(50, 20));
        assert!(
            (36..40).all(|x| !at(x, 30)),
            "a band no wider than four pixels is a dropout"
        );
        assert!(!at(3, 40) && !at(5, 45), "regions open to the border are not evidence");
        assert_eq!(mask.iter().filter(|&&m| m).count(), 18 * 18);
        // Depth 2.5x coarser than the colour: three colour pixels in.
        let coarse = no_return_mask(&depth, w, h, 2.5).unwrap();
        assert_eq!(coarse.iter().filter(|&&m| m).count(), 14 * 14);
        // A frame the sensor mostly failed on says nothing.
        let failed: Vec<f32> = (0..w * h).map(|i| if i % 10 == 0 { 1.0 } else { 0.0 }).collect();
        assert!(no_return_mask(&failed, w, h, 1.0).is_none());
    }

    #[test]
    fn no_return_skips_projector_shadows_beside_depth_edges() {
        // A near box (1 m) on a far wall (2 m), with the gap a
        // structured-light projector leaves on its left, and an enclosed
        // gap in the wall that an unseen object would leave.
        let (w, h) = (80u32, 60u32);
        let mut depth = vec![2.0f32; (w * h) as usize];
        for y in 10..50 {
            for x in 30..60 {
                depth[(y * w + x) as usize] = 1.0;
            }
            for x in 22..30 {
                depth[(y * w + x) as usize] = 0.0;
            }
        }
        for y in 20..30 {
            for x in 5..15 {
                depth[(y * w + x) as usize] = 0.0;
            }
        }
        let mask = no_return_mask(&depth, w, h, 1.0).unwrap();
        let at = |x: u32, y: u32| mask[(y * w + x) as usize];
        assert!((22..30).all(|x| !at(x, 30)), "the shadow is not evidence");
        assert!(at(9, 24) && at(10, 25), "the enclosed gap in one surface is");
        // The same gap between surfaces 5 % apart is not a shadow.
        for y in 10..50 {
            for x in 30..60 {
                depth[(y * w + x) as usize] = 1.9;
            }
        }
        let mask = no_return_mask(&depth, w, h, 1.0).unwrap();
        assert!(mask[(30 * w + 25) as usize]);
    }
}
