//! Turn a layout's frame listing into a [`Scan`]: check poses, decode every
//! frame's images in parallel (one rayon task per frame), bring depth onto
//! the colour grid and intrinsics to the colour resolution.

use super::image_io::{decode_depth, decode_rgb, dimensions};
use super::rigid::isometry;
use super::validate::{accept_pose, check_intrinsics};
use super::{resample_depth_to, Bounds, Frame, Intrinsics, Layout, LoadOptions, Scan, ScanError, MAX_FRAMES};
use nalgebra::{IsometryMatrix3, Matrix4};
use rayon::prelude::*;
use std::path::{Path, PathBuf};

/// Which way the poses of a listing map.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(crate) enum PoseKind {
    /// Camera-to-world, OpenCV camera axes.
    CameraToWorld,
    /// World-to-camera, OpenCV camera axes (inverted on load).
    WorldToCamera,
}

/// One frame as a layout lists it, before any image is decoded.
#[derive(Clone, Debug)]
pub(crate) struct FrameSpec {
    pub id: u64,
    pub name: String,
    pub rgb: PathBuf,
    pub depth: Option<PathBuf>,
    /// Pose as read (direction given by [`Listing::pose_kind`]).
    pub pose: Matrix4<f64>,
    /// Where the pose came from, for messages (`pose/000012.txt`, `groundtruth.txt line 40`).
    pub pose_source: String,
    pub intrinsics: Intrinsics,
    /// Resolution `intrinsics` refer to; `None` = the colour image's own.
    pub intrinsics_size: Option<(u32, u32)>,
}

/// Everything a layout reader found, ready to be decoded.
#[derive(Clone, Debug)]
pub(crate) struct Listing {
    pub root: PathBuf,
    pub layout: Layout,
    pub frames: Vec<FrameSpec>,
    pub pose_kind: PoseKind,
    /// Metres per depth PNG unit (0.001 for millimetres).
    pub depth_metres_per_unit: f32,
    /// File the intrinsics came from, for messages.
    pub intrinsics_source: PathBuf,
    pub bounds: Option<Bounds>,
    pub warnings: Vec<String>,
    /// Files read besides each frame's images and the intrinsics (pose
    /// files, index files, `bbox.txt`): outputs must never touch them.
    pub inputs: Vec<PathBuf>,
}

impl Listing {
    /// An empty listing for `root`.
    pub fn new(root: &Path, layout: Layout, pose_kind: PoseKind, intrinsics_source: PathBuf) -> Listing {
        Listing {
            root: root.to_path_buf(),
            layout,
            frames: Vec::new(),
            pose_kind,
            depth_metres_per_unit: 0.001,
            intrinsics_source,
            bounds: None,
            warnings: Vec::new(),
            inputs: Vec::new(),
        }
    }
}

/// Fail early when a listing is larger than [`MAX_FRAMES`].
pub(crate) fn check_frame_count(path: &Path, count: usize) -> Result<(), ScanError> {
    if count > MAX_FRAMES {
        return Err(ScanError::TooManyFrames {
            path: path.to_path_buf(),
            count,
            max: MAX_FRAMES,
        });
    }
    Ok(())
}

/// Decode and check every frame of `listing`.
pub(crate) fn assemble(mut listing: Listing, options: &LoadOptions) -> Result<Scan, ScanError> {
    if listing.frames.is_empty() {
        return Err(ScanError::NoFrames(
            listing.root.clone(),
            "the layout's file lists are empty".into(),
        ));
    }
    check_frame_count(&listing.root, listing.frames.len())?;
    listing.frames.sort_by_key(|f| f.id);
    for pair in listing.frames.windows(2) {
        if let [a, b] = pair {
            if a.id == b.id {
                return Err(ScanError::Frame {
                    frame: b.name.clone(),
                    reason: format!("listed twice ({} and {})", a.rgb.display(), b.rgb.display()),
                });
            }
        }
    }
    let mut warnings = std::mem::take(&mut listing.warnings);
    let mut camera_to_world = Vec::with_capacity(listing.frames.len());
    for spec in &listing.frames {
        let pose = isometry(&accept_pose(
            spec.pose,
            &spec.pose_source,
            options.fix_poses,
            &mut warnings,
        )?);
        camera_to_world.push(match listing.pose_kind {
            PoseKind::CameraToWorld => pose,
            PoseKind::WorldToCamera => pose.inverse(),
        });
    }
    check_pixel_budget(&listing)?;
    let decoded: Vec<Result<Frame, ScanError>> = listing
        .frames
        .par_iter()
        .zip(&camera_to_world)
        .map(|(spec, pose)| decode_frame(spec, pose, &listing))
        .collect();
    let mut frames = Vec::with_capacity(decoded.len());
    for result in decoded {
        frames.push(result?);
    }
    if let (Some(first), Some(first_spec)) = (frames.first(), listing.frames.first()) {
        let want = first.size();
        for (frame, spec) in frames.iter().zip(&listing.frames) {
            let (w, h) = frame.size();
            if (w, h) != want {
                return Err(ScanError::SizeMismatch {
                    path: spec.rgb.clone(),
                    found_w: w,
                    found_h: h,
                    want_w: want.0,
                    want_h: want.1,
                    first: first_spec.rgb.display().to_string(),
                });
            }
        }
    }
    check_depth_sizes(&frames, &listing)?;
    let mut inputs = std::mem::take(&mut listing.inputs);
    inputs.push(listing.intrinsics_source.clone());
    for spec in &listing.frames {
        inputs.push(spec.rgb.clone());
        inputs.extend(spec.depth.clone());
    }
    Ok(Scan {
        root: listing.root,
        layout: listing.layout,
        frames,
        bounds: listing.bounds,
        warnings,
        inputs,
    })
}

/// Bytes the pipeline holds per colour pixel of a scan: the decoded colour
/// and depth on the colour grid, and the training views' per-pixel colour,
/// depth and ray data (measured order of magnitude, rounded up).
const BYTES_PER_PIXEL: u64 = 32;

/// Refuse a scan whose pixels cannot fit in this machine's available memory,
/// from the first frame's header, before anything is decoded.
fn check_pixel_budget(listing: &Listing) -> Result<(), ScanError> {
    let Some(first) = listing.frames.first() else {
        return Ok(());
    };
    let (w, h) = dimensions(&first.rgb)?;
    let pixels = (w as u64 * h as u64).saturating_mul(listing.frames.len() as u64);
    let needed = pixels.saturating_mul(BYTES_PER_PIXEL);
    let Some(available) = available_memory() else {
        return Ok(());
    };
    if needed > available {
        return Err(ScanError::Invalid(
            listing.root.clone(),
            format!(
                "{} frames of {w}x{h} are {:.1} G pixels; at ~{BYTES_PER_PIXEL} bytes per pixel that needs {:.1} GB, more than the {:.1} GB of memory available; downscale the images or use fewer frames",
                listing.frames.len(),
                pixels as f64 / 1e9,
                needed as f64 / 1e9,
                available as f64 / 1e9
            ),
        ));
    }
    Ok(())
}

/// `MemAvailable` of /proc/meminfo in bytes (Linux); `None` elsewhere.
fn available_memory() -> Option<u64> {
    let text = std::fs::read_to_string("/proc/meminfo").ok()?;
    let line = text.lines().find(|l| l.starts_with("MemAvailable:"))?;
    let kb: u64 = line.split_whitespace().nth(1)?.parse().ok()?;
    Some(kb.saturating_mul(1024))
}

/// Every depth image has one size, and the colour images' aspect ratio
/// (rescaling depth of another shape would stretch it silently).
fn check_depth_sizes(frames: &[Frame], listing: &Listing) -> Result<(), ScanError> {
    let with_depth = frames
        .iter()
        .zip(&listing.frames)
        .filter_map(|(f, spec)| Some((f.depth_size?, f.size(), spec.depth.as_ref()?)));
    let mut first: Option<((u32, u32), &PathBuf)> = None;
    for (size, rgb, path) in with_depth {
        match first {
            None => {
                let (aspect_depth, aspect_rgb) = (size.0 as f64 / size.1 as f64, rgb.0 as f64 / rgb.1 as f64);
                // One pixel of rounding on the depth image's shorter side is tolerated.
                let tolerance = 1.0 / size.0.min(size.1) as f64 + 0.01;
                if (aspect_depth / aspect_rgb - 1.0).abs() > tolerance {
                    return Err(ScanError::Image {
                        path: path.clone(),
                        reason: format!(
                            "depth is {}x{} (aspect {aspect_depth:.3}) but colour is {}x{} (aspect {aspect_rgb:.3}): rescaling would stretch it; crop or register the depth to the colour camera",
                            size.0, size.1, rgb.0, rgb.1
                        ),
                    });
                }
                first = Some((size, path));
            }
            Some((want, first_path)) if size != want => {
                return Err(ScanError::Image {
                    path: path.clone(),
                    reason: format!(
                        "depth image is {}x{}, other depth images are {}x{} ({})",
                        size.0,
                        size.1,
                        want.0,
                        want.1,
                        first_path.display()
                    ),
                });
            }
            Some(_) => {}
        }
    }
    Ok(())
}

/// Decode one frame's colour and depth (one rayon task).
fn decode_frame(
    spec: &FrameSpec,
    camera_to_world: &IsometryMatrix3<f64>,
    listing: &Listing,
) -> Result<Frame, ScanError> {
    let rgb = decode_rgb(&spec.rgb)?;
    let (w, h) = rgb.dimensions();
    let intrinsics = match spec.intrinsics_size {
        Some(size) if size != (w, h) => spec.intrinsics.scaled(size, (w, h)),
        _ => spec.intrinsics,
    };
    check_intrinsics(&intrinsics, w, h).map_err(|reason| ScanError::Intrinsics {
        path: listing.intrinsics_source.clone(),
        reason: format!("{reason} (frame {}, {})", spec.name, spec.rgb.display()),
    })?;
    let (depth, depth_size) = match &spec.depth {
        Some(path) => {
            let raw = decode_depth(path, listing.depth_metres_per_unit)?;
            let size = (raw.width, raw.height);
            let on_grid = if size == (w, h) {
                raw
            } else {
                resample_depth_to(&raw, w, h)
            };
            (Some(on_grid), Some(size))
        }
        None => (None, None),
    };
    Ok(Frame {
        id: spec.id,
        name: spec.name.clone(),
        rgb,
        depth,
        depth_size,
        camera_to_world: *camera_to_world,
        intrinsics,
    })
}
