//! Stray Scanner exports with extracted frames: images in `rgb/` or
//! `frames/` (named by frame number), `depth/N.png` (16-bit, mm, usually
//! 256x192), `odometry.csv` (`timestamp, frame, x, y, z, qx, qy, qz, qw`,
//! camera-to-world) and `camera_matrix.csv` (3x3 K of the 1920x1440 video,
//! scaled here to the extracted image size). `confidence/` is ignored.

use super::assemble::{check_frame_count, FrameSpec, Listing, PoseKind};
use super::files::{files_by_id, optional_depth_files, stem};
use super::image_io::RGB_EXTENSIONS;
use super::native::require_file;
use super::rigid::pose_from_translation_quaternion;
use super::text::{self, read_text, Table, TextError};
use super::{Layout, ScanError};
use nalgebra::Matrix4;
use std::collections::HashMap;
use std::path::Path;

/// Resolution of the video `camera_matrix.csv` was calibrated for.
const STRAY_VIDEO_SIZE: (u32, u32) = (1920, 1440);

/// List the frames of a Stray Scanner export.
pub(crate) fn list(root: &Path) -> Result<Listing, ScanError> {
    let odometry_path = require_file(
        root,
        "odometry.csv",
        "camera poses 'timestamp, frame, x, y, z, qx, qy, qz, qw'",
    )?;
    let k_path = require_file(root, "camera_matrix.csv", "3x3 camera matrix of the 1920x1440 video")?;
    let image_dir = ["rgb", "frames"]
        .iter()
        .map(|d| root.join(d))
        .find(|d| d.is_dir())
        .ok_or_else(|| ScanError::MissingFile {
            path: root.join("rgb"),
            what: "folder of extracted frames (rgb/ or frames/)".into(),
        })?;
    let intrinsics = text::intrinsics(&read_text(&k_path)?).map_err(|e| ScanError::parse(&k_path, e))?;
    let mut listing = Listing::new(root, Layout::Stray, PoseKind::CameraToWorld, k_path);
    listing.inputs.push(odometry_path.clone());

    let images = files_by_id(&image_dir, &RGB_EXTENSIONS, &mut listing.warnings)?;
    if images.is_empty() {
        return Err(ScanError::NoFrames(
            image_dir,
            "no extracted frame images (N.jpg / N.png)".into(),
        ));
    }
    check_frame_count(&image_dir, images.len())?;
    let depth = optional_depth_files(root, &mut listing.warnings)?;
    listing.inputs.extend(Some(root.join("depth")).filter(|d| d.is_dir()));
    let odometry = read_odometry(&odometry_path)?;

    for (id, rgb) in &images {
        let Some((pose, line)) = odometry.get(id) else {
            return Err(ScanError::Frame {
                frame: stem(rgb),
                reason: format!("{} has no pose row in odometry.csv", rgb.display()),
            });
        };
        listing.frames.push(FrameSpec {
            id: *id,
            name: stem(rgb),
            rgb: rgb.clone(),
            depth: depth.get(id).cloned(),
            pose: *pose,
            pose_source: format!("{} line {line}", odometry_path.display()),
            intrinsics,
            intrinsics_size: Some(STRAY_VIDEO_SIZE),
        });
    }
    Ok(listing)
}

/// Camera-to-world pose and line number of every frame in `odometry.csv`.
fn read_odometry(path: &Path) -> Result<HashMap<u64, (Matrix4<f64>, usize)>, ScanError> {
    let table = text::csv(&read_text(path)?);
    parse_odometry(&table).map_err(|e| ScanError::parse(path, e))
}

fn parse_odometry(table: &Table) -> Result<HashMap<u64, (Matrix4<f64>, usize)>, TextError> {
    let names = ["x", "y", "z", "qx", "qy", "qz", "qw"];
    // Columns by header name, else by position (9 columns with timestamp and
    // frame, or 7 without, one row per frame).
    let (frame_col, value_cols): (Option<usize>, Vec<usize>) = match &table.header {
        Some(_) => {
            let cols = names
                .iter()
                .map(|n| table.column(n))
                .collect::<Option<Vec<_>>>()
                .ok_or_else(|| TextError {
                    line: 1,
                    reason: "header must name columns frame, x, y, z, qx, qy, qz, qw".into(),
                })?;
            (table.column("frame"), cols)
        }
        None => match table.rows.first().map(|(_, r)| r.len()) {
            Some(9) => (Some(1), (2..9).collect()),
            _ => (None, (0..7).collect()),
        },
    };
    let mut poses = HashMap::with_capacity(table.rows.len());
    for (index, (line, row)) in table.rows.iter().enumerate() {
        let line = *line;
        let field = |c: usize| -> Result<f64, TextError> {
            let token = row.get(c).ok_or_else(|| TextError {
                line,
                reason: format!("expected at least {} fields", c + 1),
            })?;
            text::number(token, line)
        };
        let frame = match frame_col {
            Some(c) => {
                let v = field(c)?;
                if !(v >= 0.0 && v.fract() == 0.0 && v < 1e15) {
                    return Err(TextError {
                        line,
                        reason: format!("frame number {v} is not a whole number"),
                    });
                }
                v as u64
            }
            None => index as u64,
        };
        let v = value_cols.iter().map(|&c| field(c)).collect::<Result<Vec<f64>, _>>()?;
        let [x, y, z, qx, qy, qz, qw] = v[..] else {
            return Err(TextError {
                line,
                reason: "expected x, y, z, qx, qy, qz, qw".into(),
            });
        };
        let pose = pose_from_translation_quaternion([x, y, z], [qx, qy, qz, qw]).ok_or_else(|| TextError {
            line,
            reason: "pose has NaN/infinite values or a zero quaternion".into(),
        })?;
        poses.insert(frame, (pose.to_homogeneous(), line));
    }
    Ok(poses)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn odometry_with_and_without_header() {
        let with = text::csv("timestamp, frame, x, y, z, qx, qy, qz, qw\n0.1, 3, 1, 2, 3, 0, 0, 0, 1\n");
        let poses = parse_odometry(&with).unwrap();
        assert_eq!(poses[&3].0.fixed_view::<3, 1>(0, 3).as_slice(), [1.0, 2.0, 3.0]);
        assert_eq!(poses[&3].1, 2);
        let plain = text::csv("0.1,5,1,2,3,0,0,0,1\n");
        assert!(parse_odometry(&plain).unwrap().contains_key(&5));
        let old = text::csv("1,2,3,0,0,0,1\n4,5,6,0,0,0,1\n");
        assert_eq!(parse_odometry(&old).unwrap()[&1].0[(0, 3)], 4.0);
        let bad = text::csv("timestamp, frame, x, y\n0,0,0,0\n");
        assert_eq!(parse_odometry(&bad).unwrap_err().line, 1);
        let short = text::csv("timestamp, frame, x, y, z, qx, qy, qz, qw\n0.1, 3, 1\n");
        assert_eq!(parse_odometry(&short).unwrap_err().line, 2);
    }
}
