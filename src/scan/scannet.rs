//! The ScanNet export layout (SensReader output): `color/N.jpg`,
//! `depth/N.png` (mm, usually 640x480 while colour is 1296x968),
//! `pose/N.txt` (camera-to-world 4x4; ScanNet writes `-inf` where tracking
//! was lost: those frames are skipped with a warning) and
//! `intrinsic/intrinsic_color.txt` (4x4). Depth is always resampled to the
//! colour grid; `intrinsic_depth.txt` is only compared for a warning.

use super::assemble::{FrameSpec, Listing, PoseKind};
use super::files::{files_by_id, id_list, optional_depth_files, stem};
use super::image_io::RGB_EXTENSIONS;
use super::native::{pair_parts, require_dir, require_file};
use super::text::{self, read_text};
use super::{Intrinsics, Layout, ScanError};
use std::path::Path;

/// ScanNet's colour resolution, which `intrinsic_color.txt` refers to.
const SCANNET_COLOR_SIZE: (u32, u32) = (1296, 968);

/// List the frames of a ScanNet export.
pub(crate) fn list(root: &Path) -> Result<Listing, ScanError> {
    let color_dir = require_dir(root, "color", "folder of colour frames")?;
    let pose_dir = require_dir(root, "pose", "folder of camera-to-world poses")?;
    let k_path = require_file(root, "intrinsic/intrinsic_color.txt", "4x4 colour camera matrix")?;
    let intrinsics = text::intrinsics(&read_text(&k_path)?).map_err(|e| ScanError::parse(&k_path, e))?;
    let mut listing = Listing::new(root, Layout::Scannet, PoseKind::CameraToWorld, k_path);

    let color = files_by_id(&color_dir, &RGB_EXTENSIONS, &mut listing.warnings)?;
    let poses = files_by_id(&pose_dir, &["txt"], &mut listing.warnings)?;
    let depth = optional_depth_files(root, &mut listing.warnings)?;
    listing.inputs.extend(Some(root.join("depth")).filter(|d| d.is_dir()));
    if color.is_empty() && poses.is_empty() {
        return Err(ScanError::NoFrames(
            root.to_path_buf(),
            "color/ and pose/ hold no frame files".into(),
        ));
    }
    super::assemble::check_frame_count(&color_dir, color.len())?;
    pair_parts(root, &color, &poses)?;
    depth_fov_warning(root, &intrinsics, &mut listing.warnings);

    let intrinsics_size = looks_like_scannet_color(&intrinsics).then_some(SCANNET_COLOR_SIZE);
    let mut lost = Vec::new();
    for (id, rgb) in &color {
        let Some(pose_path) = poses.get(id) else { continue };
        let pose = text::matrix4(&read_text(pose_path)?).map_err(|e| ScanError::parse(pose_path, e))?;
        listing.inputs.push(pose_path.clone());
        if !pose.iter().all(|v| v.is_finite()) {
            lost.push(*id);
            continue;
        }
        listing.frames.push(FrameSpec {
            id: *id,
            name: stem(rgb),
            rgb: rgb.clone(),
            depth: depth.get(id).cloned(),
            pose,
            pose_source: pose_path.display().to_string(),
            intrinsics,
            intrinsics_size,
        });
    }
    if !lost.is_empty() {
        let message = format!(
            "{} frame(s) have no valid pose (inf/nan in pose/N.txt, ScanNet's mark for lost tracking) and were skipped: {}",
            lost.len(),
            id_list(&lost)
        );
        if listing.frames.is_empty() {
            return Err(ScanError::NoFrames(root.to_path_buf(), message));
        }
        listing.warnings.push(message);
    }
    Ok(listing)
}

/// Whether K was calibrated for ScanNet's 1296x968 colour stream (then it is
/// scaled when the exported colour images were resized).
fn looks_like_scannet_color(k: &Intrinsics) -> bool {
    let (w, h) = (f64::from(SCANNET_COLOR_SIZE.0), f64::from(SCANNET_COLOR_SIZE.1));
    (k.cx - 0.5 * w).abs() < 0.1 * w && (k.cy - 0.5 * h).abs() < 0.1 * h
}

/// Warn when the depth camera's field of view differs from the colour
/// camera's, since depth is resampled without reprojection.
fn depth_fov_warning(root: &Path, color: &Intrinsics, warnings: &mut Vec<String>) {
    let path = root.join("intrinsic/intrinsic_depth.txt");
    let Ok(text) = read_text(&path) else { return };
    let Ok(depth) = text::intrinsics(&text) else { return };
    if depth.cx <= 0.0 || color.cx <= 0.0 {
        return;
    }
    // Half-width over focal length is the tangent of the half field of view.
    let fov = |k: &Intrinsics| (k.cx + 0.5) / k.fx;
    let ratio = fov(&depth) / fov(color);
    if (ratio - 1.0).abs() > 0.05 {
        warnings.push(format!(
            "{}: depth field of view differs from colour by {:.0}%; depth is resampled to the colour grid without reprojection",
            path.display(),
            (ratio - 1.0).abs() * 100.0
        ));
    }
}
