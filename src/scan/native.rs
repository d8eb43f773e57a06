//! The native (autolabel-compatible) layout: `rgb/`, optional `depth/`
//! (16-bit PNG, mm), `pose/` (4x4 world-to-camera), `intrinsics.txt` and
//! optional `bbox.txt`. Frames pair by the integer value of the file stem.

use super::assemble::{check_frame_count, FrameSpec, Listing, PoseKind};
use super::files::{files_by_id, id_list, optional_depth_files, rel, stem};
use super::image_io::RGB_EXTENSIONS;
use super::text::{self, read_text};
use super::{Layout, ScanError};
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

/// A folder the layout needs, or an error saying it is missing.
pub(crate) fn require_dir(root: &Path, name: &str, what: &str) -> Result<PathBuf, ScanError> {
    let dir = root.join(name);
    if !dir.is_dir() {
        return Err(ScanError::MissingFile {
            path: dir,
            what: what.into(),
        });
    }
    Ok(dir)
}

/// A file the layout needs, or an error saying it is missing.
pub(crate) fn require_file(root: &Path, name: &str, what: &str) -> Result<PathBuf, ScanError> {
    let path = root.join(name);
    if !path.is_file() {
        return Err(ScanError::MissingFile {
            path,
            what: what.into(),
        });
    }
    Ok(path)
}

/// List the frames of a native scan.
pub(crate) fn list(root: &Path) -> Result<Listing, ScanError> {
    let rgb_dir = require_dir(root, "rgb", "folder of colour frames")?;
    let pose_dir = require_dir(root, "pose", "folder of 4x4 world-to-camera poses")?;
    let k_path = require_file(root, "intrinsics.txt", "3x3 camera matrix for the rgb resolution")?;
    let intrinsics = text::intrinsics(&read_text(&k_path)?).map_err(|e| ScanError::parse(&k_path, e))?;
    let mut listing = Listing::new(root, Layout::Native, PoseKind::WorldToCamera, k_path);
    listing.inputs.extend([rgb_dir.clone(), pose_dir.clone()]);

    let bbox = root.join("bbox.txt");
    if bbox.is_file() {
        listing.inputs.push(bbox.clone());
        listing.bounds = Some(text::bounds(&read_text(&bbox)?).map_err(|e| ScanError::parse(&bbox, e))?);
    }

    let rgb = files_by_id(&rgb_dir, &RGB_EXTENSIONS, &mut listing.warnings)?;
    let poses = files_by_id(&pose_dir, &["txt"], &mut listing.warnings)?;
    let depth = optional_depth_files(root, &mut listing.warnings)?;
    listing.inputs.extend(Some(root.join("depth")).filter(|d| d.is_dir()));
    if rgb.is_empty() && poses.is_empty() {
        return Err(ScanError::NoFrames(
            root.to_path_buf(),
            "rgb/ and pose/ hold no frame files".into(),
        ));
    }
    check_frame_count(&rgb_dir, rgb.len())?;
    pair_parts(root, &rgb, &poses)?;
    let orphans: Vec<u64> = depth.keys().filter(|id| !rgb.contains_key(id)).copied().collect();
    if !orphans.is_empty() {
        listing.warnings.push(format!(
            "depth/ has files for frames without rgb, ignored: {}",
            id_list(&orphans)
        ));
    }
    let no_depth: Vec<u64> = rgb.keys().filter(|id| !depth.contains_key(id)).copied().collect();
    if !no_depth.is_empty() && !depth.is_empty() {
        listing.warnings.push(format!(
            "{} frame(s) have no depth: {}",
            no_depth.len(),
            id_list(&no_depth)
        ));
    }

    for (id, rgb_path) in &rgb {
        let Some(pose_path) = poses.get(id) else { continue };
        let pose = text::matrix4(&read_text(pose_path)?).map_err(|e| ScanError::parse(pose_path, e))?;
        listing.inputs.push(pose_path.clone());
        listing.frames.push(FrameSpec {
            id: *id,
            name: stem(rgb_path),
            rgb: rgb_path.clone(),
            depth: depth.get(id).cloned(),
            pose,
            pose_source: pose_path.display().to_string(),
            intrinsics,
            intrinsics_size: None,
        });
    }
    Ok(listing)
}

/// Every rgb needs a pose and every pose an rgb; the error names the frame.
pub(crate) fn pair_parts(
    root: &Path,
    rgb: &BTreeMap<u64, PathBuf>,
    poses: &BTreeMap<u64, PathBuf>,
) -> Result<(), ScanError> {
    if let Some((_, path)) = rgb.iter().find(|(id, _)| !poses.contains_key(id)) {
        return Err(ScanError::Frame {
            frame: stem(path),
            reason: format!(
                "{} has no pose file (expected pose/{}.txt)",
                rel(root, path),
                stem(path)
            ),
        });
    }
    if let Some((_, path)) = poses.iter().find(|(id, _)| !rgb.contains_key(id)) {
        return Err(ScanError::Frame {
            frame: stem(path),
            reason: format!("{} has no rgb image", rel(root, path)),
        });
    }
    Ok(())
}
