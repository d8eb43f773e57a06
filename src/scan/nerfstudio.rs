//! The nerfstudio / instant-ngp layout: `transforms.json` with
//! `frames[].file_path` (relative to the json's folder, extension optional as
//! instant-ngp writes them), optional `depth_file_path` (16-bit PNG, mm unless
//! `depth_unit_scale_factor` gives metres per unit), `transform_matrix`
//! (camera-to-world, OpenGL camera axes: converted to OpenCV here), and
//! intrinsics `fl_x fl_y cx cy w h` or `camera_angle_x` given globally or per
//! frame. nerfstudio puts pixel centres at +0.5, so `cx`, `cy` are shifted by
//! -0.5 to this crate's integer-centre convention.

use super::assemble::{check_frame_count, FrameSpec, Listing, PoseKind};
use super::files::stem;
use super::image_io::{dimensions, has_extension, RGB_EXTENSIONS};
use super::native::require_file;
use super::rigid::opengl_to_opencv;
use super::text::read_text;
use super::{Intrinsics, Layout, ScanError};
use nalgebra::Matrix4;
use serde::Deserialize;
use std::collections::HashSet;
use std::path::{Path, PathBuf};

/// Camera fields that may appear at the top level or per frame.
#[derive(Clone, Debug, Default, Deserialize)]
struct Camera {
    fl_x: Option<f64>,
    fl_y: Option<f64>,
    cx: Option<f64>,
    cy: Option<f64>,
    w: Option<f64>,
    h: Option<f64>,
    camera_angle_x: Option<f64>,
    camera_angle_y: Option<f64>,
    k1: Option<f64>,
    k2: Option<f64>,
    p1: Option<f64>,
    p2: Option<f64>,
}

impl Camera {
    /// Per-frame values override the global ones.
    fn or(&self, global: &Camera) -> Camera {
        Camera {
            fl_x: self.fl_x.or(global.fl_x),
            fl_y: self.fl_y.or(global.fl_y),
            cx: self.cx.or(global.cx),
            cy: self.cy.or(global.cy),
            w: self.w.or(global.w),
            h: self.h.or(global.h),
            camera_angle_x: self.camera_angle_x.or(global.camera_angle_x),
            camera_angle_y: self.camera_angle_y.or(global.camera_angle_y),
            k1: self.k1.or(global.k1),
            k2: self.k2.or(global.k2),
            p1: self.p1.or(global.p1),
            p2: self.p2.or(global.p2),
        }
    }

    fn has_distortion(&self) -> bool {
        [self.k1, self.k2, self.p1, self.p2]
            .iter()
            .flatten()
            .any(|v| v.abs() > 1e-9)
    }
}

#[derive(Debug, Deserialize)]
struct FrameJson {
    file_path: Option<String>,
    depth_file_path: Option<String>,
    transform_matrix: Option<Vec<Vec<f64>>>,
    #[serde(flatten)]
    camera: Camera,
}

#[derive(Debug, Deserialize)]
struct Transforms {
    frames: Option<Vec<FrameJson>>,
    depth_unit_scale_factor: Option<f64>,
    #[serde(flatten)]
    camera: Camera,
}

/// List the frames of a `transforms.json` scan.
pub(crate) fn list(root: &Path) -> Result<Listing, ScanError> {
    let json_path = require_file(root, "transforms.json", "nerfstudio / instant-ngp camera file")?;
    let text = read_text(&json_path)?;
    let invalid = |reason: String| ScanError::Invalid(json_path.clone(), reason);
    if text.trim().is_empty() {
        return Err(invalid("empty file, expected a JSON object with 'frames'".into()));
    }
    let parsed: Transforms = serde_json::from_str(&text).map_err(|e| invalid(format!("malformed JSON: {e}")))?;
    let Some(frames) = parsed.frames else {
        return Err(invalid("no 'frames' list".into()));
    };
    if frames.is_empty() {
        return Err(ScanError::NoFrames(json_path.clone(), "'frames' is empty".into()));
    }
    check_frame_count(&json_path, frames.len())?;
    let base = json_path.parent().unwrap_or(root).to_path_buf();

    let mut listing = Listing::new(root, Layout::Nerfstudio, PoseKind::CameraToWorld, json_path.clone());
    if let Some(scale) = parsed.depth_unit_scale_factor {
        if !(scale.is_finite() && scale > 0.0) {
            return Err(invalid(format!(
                "depth_unit_scale_factor must be positive, found {scale}"
            )));
        }
        listing.depth_metres_per_unit = scale as f32;
    }
    let mut distortion_seen = false;
    for (index, frame) in frames.iter().enumerate() {
        let frame_err = |reason: String| ScanError::Frame {
            frame: format!("{index} of transforms.json"),
            reason,
        };
        let Some(file) = &frame.file_path else {
            return Err(frame_err("has no file_path".into()));
        };
        let rgb = resolve(&base, file, &RGB_EXTENSIONS).ok_or_else(|| frame_err(format!("image {file} not found")))?;
        let depth = match &frame.depth_file_path {
            Some(d) => {
                Some(resolve(&base, d, &["png"]).ok_or_else(|| frame_err(format!("depth image {d} not found")))?)
            }
            None => None,
        };
        let Some(rows) = &frame.transform_matrix else {
            return Err(frame_err("has no transform_matrix".into()));
        };
        let pose = opengl_to_opencv(&matrix_from_rows(rows).map_err(frame_err)?);
        let camera = frame.camera.or(&parsed.camera);
        distortion_seen |= camera.has_distortion();
        let (intrinsics, size) = intrinsics(&camera, &rgb).map_err(|reason| ScanError::Intrinsics {
            path: json_path.clone(),
            reason: format!("frame {index} ({file}): {reason}"),
        })?;
        listing.frames.push(FrameSpec {
            id: index as u64,
            name: stem(&rgb),
            rgb,
            depth,
            pose,
            pose_source: format!("{} frame {index} ({file})", json_path.display()),
            intrinsics,
            intrinsics_size: Some(size),
        });
    }
    if distortion_seen {
        listing.warnings.push(format!(
            "{}: lens distortion is ignored (pinhole model)",
            json_path.display()
        ));
    }
    name_frames(&mut listing.frames);
    Ok(listing)
}

/// Ids from the numbers at the end of the file names when they are unique
/// (`frame_00012.png` -> 12), else the json order; names from the stems
/// when unique, else the zero-padded id.
fn name_frames(frames: &mut [FrameSpec]) {
    let numbers: Vec<Option<u64>> = frames.iter().map(|f| trailing_number(&f.name)).collect();
    let unique_numbers = numbers.iter().flatten().collect::<HashSet<_>>().len() == frames.len();
    if unique_numbers {
        for (frame, n) in frames.iter_mut().zip(numbers) {
            frame.id = n.unwrap_or(frame.id);
        }
    }
    let unique_names = frames.iter().map(|f| &f.name).collect::<HashSet<_>>().len() == frames.len();
    if !unique_names {
        for frame in frames.iter_mut() {
            frame.name = format!("{:06}", frame.id);
        }
    }
}

fn trailing_number(name: &str) -> Option<u64> {
    let digits = name.len() - name.trim_end_matches(|c: char| c.is_ascii_digit()).len();
    name.get(name.len() - digits..)
        .filter(|d| !d.is_empty() && d.len() <= 18)?
        .parse()
        .ok()
}

/// `base/file`, or with an image extension appended when the json omits it.
fn resolve(base: &Path, file: &str, exts: &[&str]) -> Option<PathBuf> {
    let path = base.join(file);
    if path.is_file() {
        return Some(path);
    }
    if has_extension(&path, exts) {
        return None;
    }
    exts.iter()
        .flat_map(|e| [e.to_string(), e.to_ascii_uppercase()])
        .map(|e| PathBuf::from(format!("{}.{e}", path.display())))
        .find(|p| p.is_file())
}

/// A 4x4 (or 3x4) row-major matrix from JSON rows.
fn matrix_from_rows(rows: &[Vec<f64>]) -> Result<Matrix4<f64>, String> {
    let shape_ok = (rows.len() == 4 || rows.len() == 3) && rows.iter().all(|r| r.len() == 4);
    if !shape_ok {
        return Err(format!("transform_matrix must be 4x4, found {} rows", rows.len()));
    }
    let at = |r: usize, c: usize| {
        rows.get(r)
            .and_then(|row| row.get(c))
            .copied()
            .unwrap_or(if r == c { 1.0 } else { 0.0 })
    };
    Ok(Matrix4::from_fn(at))
}

/// Intrinsics (integer pixel centres) and the resolution they refer to.
fn intrinsics(camera: &Camera, rgb: &Path) -> Result<(Intrinsics, (u32, u32)), String> {
    let (w, h) = match (camera.w, camera.h) {
        (Some(w), Some(h)) if w >= 1.0 && h >= 1.0 && w <= f64::from(u32::MAX) && h <= f64::from(u32::MAX) => {
            (w.round() as u32, h.round() as u32)
        }
        (Some(w), Some(h)) => return Err(format!("bad image size w {w} h {h}")),
        _ => dimensions(rgb).map_err(|e| e.to_string())?,
    };
    let (wf, hf) = (f64::from(w), f64::from(h));
    let fx = match (camera.fl_x, camera.camera_angle_x) {
        (Some(f), _) => f,
        (None, Some(angle)) => 0.5 * wf / (0.5 * angle).tan(),
        (None, None) => return Err("no focal length (fl_x or camera_angle_x)".into()),
    };
    let fy = match (camera.fl_y, camera.camera_angle_y) {
        (Some(f), _) => f,
        (None, Some(angle)) => 0.5 * hf / (0.5 * angle).tan(),
        (None, None) => fx,
    };
    let cx = camera.cx.unwrap_or(0.5 * wf) - 0.5;
    let cy = camera.cy.unwrap_or(0.5 * hf) - 0.5;
    Ok((Intrinsics { fx, fy, cx, cy }, (w, h)))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn trailing_numbers() {
        assert_eq!(trailing_number("frame_00012"), Some(12));
        assert_eq!(trailing_number("r_7"), Some(7));
        assert_eq!(trailing_number("img"), None);
        assert_eq!(trailing_number("12345678901234567890123"), None);
    }

    #[test]
    fn field_of_view_gives_focal_length() {
        let camera = Camera {
            camera_angle_x: Some(std::f64::consts::FRAC_PI_2),
            w: Some(100.0),
            h: Some(50.0),
            ..Camera::default()
        };
        let (k, size) = intrinsics(&camera, Path::new("unused")).unwrap();
        assert_eq!(size, (100, 50));
        assert!((k.fx - 50.0).abs() < 1e-9 && (k.fy - 50.0).abs() < 1e-9);
        assert_eq!((k.cx, k.cy), (49.5, 24.5));
    }

    #[test]
    fn matrices_need_four_columns() {
        assert!(matrix_from_rows(&[vec![1.0, 0.0, 0.0]]).is_err());
        let m = matrix_from_rows(&[
            vec![1.0, 0.0, 0.0, 2.0],
            vec![0.0, 1.0, 0.0, 3.0],
            vec![0.0, 0.0, 1.0, 4.0],
        ])
        .unwrap();
        assert_eq!(m.column(3), nalgebra::Vector4::new(2.0, 3.0, 4.0, 1.0));
    }
}
