//! Read an RGB-D scan in any supported layout into one in-memory [`Scan`]:
//! colour frames, optional metric depth on the colour grid, camera-to-world
//! poses (f64, OpenCV axes) and intrinsics for the colour resolution.
//!
//! Each layout (`native`, `tum`, `nerfstudio`, `scannet`, `stray`) only lists
//! its frames; `assemble` checks poses and decodes every frame in parallel
//! (`image_io`, `depth`), `validate` holds the checks, `summary` the report.
//!
//! Must never depend on `nerf`, `boxes` or `synth`: it only reads and checks
//! outside data.

mod assemble;
mod colmap;
mod colour_border;
mod depth;
mod depth_noise;
mod detect;
mod error;
mod files;
pub mod fingerprint;
mod image_io;
mod native;
mod nerfstudio;
mod rigid;
mod scannet;
mod stray;
mod summary;
mod text;
mod tum;
mod validate;

pub use colour_border::{colour_borders, dead_colour_border, ColourBorder};
pub use depth::{resample_depth_to, vouched_free_distance, vouched_start, DepthMap, EDGE_RELATIVE_GAP, FREE_FRACTION};
pub use depth_noise::{depth_noise, DepthNoise};
pub use detect::{detect_layout, Layout, ParseLayoutError};
pub use error::ScanError;
pub use rigid::isometry;
pub use summary::{summarize, DepthRange, ScanSummary};
pub use validate::{check_intrinsics, check_pose, PoseCheck, POSE_TOLERANCE};

use nalgebra::{IsometryMatrix3, Point3, Vector3};
use std::path::{Path, PathBuf};

/// Largest accepted image side, in pixels (guards against absurd headers).
pub const MAX_IMAGE_SIDE: u32 = 16_384;
/// Largest accepted number of frames in one scan.
pub const MAX_FRAMES: usize = 100_000;

/// Pinhole intrinsics for one image resolution (pixels, OpenCV convention:
/// pixel centres at integer + 0.5 in continuous coordinates is NOT assumed;
/// `u = fx * x / z + cx` addresses pixel centres at integers).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Intrinsics {
    pub fx: f64,
    pub fy: f64,
    pub cx: f64,
    pub cy: f64,
}

impl Intrinsics {
    /// Intrinsics for the same camera imaged at another resolution.
    pub fn scaled(&self, from: (u32, u32), to: (u32, u32)) -> Intrinsics {
        let sx = to.0 as f64 / from.0 as f64;
        let sy = to.1 as f64 / from.1 as f64;
        // Pixel centres stay aligned: continuous coordinate c maps to (c + 0.5) * s - 0.5.
        Intrinsics {
            fx: self.fx * sx,
            fy: self.fy * sy,
            cx: (self.cx + 0.5) * sx - 0.5,
            cy: (self.cy + 0.5) * sy - 0.5,
        }
    }

    /// Squared tangent of the angle off the optical axis at the farthest
    /// pixel centre of a `width` x `height` image (its corners).
    pub fn corner_tan2(&self, width: u32, height: u32) -> f64 {
        let (right, bottom) = (width.saturating_sub(1) as f64, height.saturating_sub(1) as f64);
        [(0.0, 0.0), (right, 0.0), (0.0, bottom), (right, bottom)]
            .into_iter()
            .map(|(u, v)| self.unproject(u, v).xy().norm_squared())
            .fold(0.0, f64::max)
    }

    /// Camera-frame direction (z = 1) through pixel (u, v).
    #[inline]
    pub fn unproject(&self, u: f64, v: f64) -> Vector3<f64> {
        Vector3::new((u - self.cx) / self.fx, (v - self.cy) / self.fy, 1.0)
    }

    /// Pixel of a camera-frame point; `None` behind the camera.
    #[inline]
    pub fn project(&self, p: &Point3<f64>) -> Option<(f64, f64)> {
        if p.z <= 0.0 {
            return None;
        }
        Some((self.fx * p.x / p.z + self.cx, self.fy * p.y / p.z + self.cy))
    }
}

/// Colour image, 8-bit RGB, row-major.
pub type RgbImage = image::RgbImage;

/// One captured frame.
#[derive(Clone, Debug)]
pub struct Frame {
    /// Integer id from the file stem (frames are paired by it).
    pub id: u64,
    /// Name used for outputs of this frame, e.g. `000012`.
    pub name: String,
    /// Colour image.
    pub rgb: RgbImage,
    /// Depth in metres on the colour grid; 0 = no measurement. `None` when
    /// the frame has no depth file.
    pub depth: Option<DepthMap>,
    /// Resolution of the depth image as stored on disk, before resampling
    /// to the colour grid; `None` when the frame has no depth file.
    pub depth_size: Option<(u32, u32)>,
    /// Camera-to-world pose, OpenCV camera axes, scan world frame.
    pub camera_to_world: IsometryMatrix3<f64>,
    /// Intrinsics for the colour resolution.
    pub intrinsics: Intrinsics,
}

impl Frame {
    /// A frame whose depth (if any) is already on the colour grid.
    pub fn new(
        id: u64,
        name: impl Into<String>,
        rgb: RgbImage,
        depth: Option<DepthMap>,
        camera_to_world: IsometryMatrix3<f64>,
        intrinsics: Intrinsics,
    ) -> Frame {
        let depth_size = depth.as_ref().map(|d| (d.width, d.height));
        Frame {
            id,
            name: name.into(),
            rgb,
            depth,
            depth_size,
            camera_to_world,
            intrinsics,
        }
    }

    /// Width and height of the colour image.
    pub fn size(&self) -> (u32, u32) {
        self.rgb.dimensions()
    }

    /// Camera centre in world coordinates.
    pub fn camera_center(&self) -> Point3<f64> {
        Point3::from(self.camera_to_world.translation.vector)
    }
}

/// Scene bounds given by the user (`bbox.txt`), world frame, metres.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Bounds {
    pub min: Point3<f64>,
    pub max: Point3<f64>,
}

/// A whole scan, every layout read into the same form.
#[derive(Clone, Debug)]
pub struct Scan {
    /// Folder the scan was read from.
    pub root: PathBuf,
    /// Layout it was read as.
    pub layout: Layout,
    /// Frames sorted by id.
    pub frames: Vec<Frame>,
    /// Optional user-supplied bounds (`bbox.txt`).
    pub bounds: Option<Bounds>,
    /// Non-fatal findings (skipped frames, re-orthonormalised poses, ...).
    pub warnings: Vec<String>,
    /// Every file the scan was read from (images, poses, intrinsics, lists).
    pub inputs: Vec<PathBuf>,
}

impl Scan {
    /// Colour resolution shared by all frames.
    pub fn size(&self) -> (u32, u32) {
        self.frames.first().map(|f| f.size()).unwrap_or((0, 0))
    }

    /// Every frame's camera-to-world pose, in frame order.
    pub fn poses(&self) -> Vec<IsometryMatrix3<f64>> {
        self.frames.iter().map(|f| f.camera_to_world).collect()
    }

    /// Each frame's dead colour border ([`colour_borders`]).
    pub fn colour_borders(&self) -> Vec<ColourBorder> {
        colour_borders(&self.frames)
    }

    /// Replace the frames' poses, in frame order.
    pub fn set_poses(&mut self, poses: &[IsometryMatrix3<f64>]) {
        for (frame, pose) in self.frames.iter_mut().zip(poses) {
            frame.camera_to_world = *pose;
        }
    }
}

/// How to read a scan.
#[derive(Clone, Debug, Default)]
pub struct LoadOptions {
    /// Force a layout instead of detecting it.
    pub layout: Option<Layout>,
    /// Re-orthonormalise slightly bad rotations (with a warning) instead of failing.
    pub fix_poses: bool,
}

/// Load and fully validate a scan (every image decoded, every pose checked):
/// detect or take the layout, list its frames, decode them in parallel.
pub fn load(root: &Path, options: &LoadOptions) -> Result<Scan, ScanError> {
    if !root.exists() {
        return Err(ScanError::MissingFolder(root.to_path_buf()));
    }
    if !root.is_dir() {
        return Err(ScanError::NotAFolder(root.to_path_buf()));
    }
    let layout = match options.layout {
        Some(layout) => layout,
        None => detect_layout(root)?,
    };
    let listing = match layout {
        Layout::Native => native::list(root)?,
        Layout::Tum => tum::list(root)?,
        Layout::Nerfstudio => nerfstudio::list(root)?,
        Layout::Scannet => scannet::list(root)?,
        Layout::Stray => stray::list(root)?,
        Layout::Colmap => colmap::list(root)?,
    };
    let mut scan = assemble::assemble(listing, options)?;
    scan.frames.sort_by_key(|f| f.id);
    validate::check_scan(&scan)?;
    validate::exclude_outlier_poses(&mut scan)?;
    Ok(scan)
}
