//! A COLMAP text model (as `colmap model_converter --output_type TXT`
//! writes it): `cameras.txt` and `images.txt` in `sparse/0/`, `sparse/` or
//! the scan folder, colour images in `images/` (or the scan folder) under
//! the names `images.txt` gives, and optionally a `depth/` folder of 16-bit
//! PNGs in millimetres named by the colour image's stem.
//!
//! `images.txt` holds world-to-camera poses (`QW QX QY QZ TX TY TZ`, OpenCV
//! axes) in any order; frames are numbered by image name, so the same
//! reconstruction listed in another order gives the same scan. Structure
//! from motion recovers poses up to scale: `fit` finds the metric scale
//! from the depth images (`src/poses/scale.rs`).
//!
//! Cameras: SIMPLE_PINHOLE, PINHOLE, and the distorting SIMPLE_RADIAL,
//! RADIAL and OPENCV when their distortion moves no image corner by half a
//! pixel or more (nerflabel models no lens distortion: undistort first with
//! `colmap image_undistorter`, which writes PINHOLE cameras).

use super::assemble::{check_frame_count, FrameSpec, Listing, PoseKind};
use super::files::stem;
use super::rigid::pose_from_translation_quaternion;
use super::text::{read_text, TextError};
use super::{Intrinsics, Layout, ScanError};
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

/// Largest displacement (pixels, at an image corner) that a camera's lens
/// distortion may cause before the camera is refused.
const MAX_DISTORTION_PX: f64 = 0.5;

/// Folders, relative to the scan, where the text model may be.
const MODEL_DIRS: [&str; 3] = ["sparse/0", "sparse", "."];

/// The folder of the text model in `root`, if any.
pub(crate) fn model_dir(root: &Path) -> Option<PathBuf> {
    MODEL_DIRS
        .iter()
        .map(|d| root.join(d))
        .find(|d| d.join("cameras.txt").is_file() && d.join("images.txt").is_file())
}

/// One camera of `cameras.txt`: pinhole intrinsics at its image size.
#[derive(Clone, Copy, Debug, PartialEq)]
struct Camera {
    intrinsics: Intrinsics,
    size: (u32, u32),
}

/// One image of `images.txt`.
#[derive(Clone, Debug, PartialEq)]
struct Image {
    world_to_camera: nalgebra::Isometry3<f64>,
    camera_id: u64,
    name: String,
    line: usize,
}

/// List the frames of a COLMAP text model.
pub(crate) fn list(root: &Path) -> Result<Listing, ScanError> {
    let Some(model) = model_dir(root) else {
        return Err(ScanError::MissingFile {
            path: root.join("sparse/0/cameras.txt"),
            what: "COLMAP text model (cameras.txt and images.txt in sparse/0/, sparse/ or the scan folder)".into(),
        });
    };
    let cameras_path = model.join("cameras.txt");
    let images_path = model.join("images.txt");
    let cameras = parse_cameras(&read_text(&cameras_path)?).map_err(|e| ScanError::parse(&cameras_path, e))?;
    let mut images = parse_images(&read_text(&images_path)?).map_err(|e| ScanError::parse(&images_path, e))?;
    check_frame_count(&images_path, images.len())?;
    if images.is_empty() {
        return Err(ScanError::NoFrames(
            root.to_path_buf(),
            format!("{} lists no image", images_path.display()),
        ));
    }
    // Frames numbered in name order, whatever order images.txt lists them in.
    images.sort_by(|a, b| a.name.cmp(&b.name));
    let image_dir = if root.join("images").is_dir() {
        root.join("images")
    } else {
        root.to_path_buf()
    };
    let depth_dir = root.join("depth");
    let mut listing = Listing::new(root, Layout::Colmap, PoseKind::WorldToCamera, cameras_path.clone());
    listing.inputs.push(images_path.clone());
    if depth_dir.is_dir() {
        listing.inputs.push(depth_dir.clone());
    } else {
        listing.warnings.push(format!(
            "{}: no depth folder, frames have no depth supervision",
            depth_dir.display()
        ));
    }
    let mut missing_depth = 0;
    for (id, image) in images.iter().enumerate() {
        let camera = cameras.get(&image.camera_id).ok_or_else(|| ScanError::Parse {
            path: images_path.clone(),
            line: image.line,
            reason: format!(
                "image {} uses camera {}, which cameras.txt does not list",
                image.name, image.camera_id
            ),
        })?;
        let rgb = image_dir.join(&image.name);
        if !rgb.is_file() {
            return Err(ScanError::MissingFile {
                path: rgb,
                what: format!("colour image of {} (images.txt line {})", image.name, image.line),
            });
        }
        let name = stem(&rgb);
        let depth = depth_dir
            .is_dir()
            .then(|| depth_dir.join(format!("{name}.png")))
            .filter(|d| d.is_file());
        missing_depth += usize::from(depth.is_none() && depth_dir.is_dir());
        listing.frames.push(FrameSpec {
            id: id as u64,
            name,
            rgb,
            depth,
            pose: image.world_to_camera.to_homogeneous(),
            pose_source: format!("{} line {}", images_path.display(), image.line),
            intrinsics: camera.intrinsics,
            intrinsics_size: Some(camera.size),
        });
    }
    if missing_depth > 0 {
        listing.warnings.push(format!(
            "{}: {missing_depth} of {} images have no depth image of the same stem (no depth supervision for them)",
            depth_dir.display(),
            images.len()
        ));
    }
    let mut names = std::collections::HashSet::new();
    if let Some(f) = listing.frames.iter().find(|f| !names.insert(f.name.as_str())) {
        return Err(ScanError::Invalid(
            images_path,
            format!("two images share the stem '{}' (frames are named by stem)", f.name),
        ));
    }
    Ok(listing)
}

/// `CAMERA_ID MODEL WIDTH HEIGHT PARAMS...` per line.
fn parse_cameras(text: &str) -> Result<BTreeMap<u64, Camera>, TextError> {
    let mut cameras = BTreeMap::new();
    for (line, body) in super::text::content_lines(text) {
        let t: Vec<&str> = body.split_whitespace().collect();
        let err = |reason: String| TextError { line, reason };
        if t.len() < 4 {
            return Err(err(format!(
                "expected CAMERA_ID MODEL WIDTH HEIGHT PARAMS..., found {} fields",
                t.len()
            )));
        }
        let id: u64 = t[0]
            .parse()
            .map_err(|_| err(format!("camera id '{}' is not a whole number", t[0])))?;
        let size = |s: &str| s.parse::<u32>().ok().filter(|&v| v > 0);
        let (Some(w), Some(h)) = (size(t[2]), size(t[3])) else {
            return Err(err(format!(
                "image size '{} {}' is not two positive whole numbers",
                t[2], t[3]
            )));
        };
        let p = t[4..]
            .iter()
            .map(|s| super::text::number(s, line))
            .collect::<Result<Vec<f64>, _>>()?;
        let model = t[1].to_ascii_uppercase();
        // (fx, fy, cx, cy, radial k1, k2, tangential p1, p2)
        let expect = |n: usize| {
            if p.len() == n {
                Ok(())
            } else {
                Err(err(format!(
                    "camera model {model} has {n} parameters, found {}",
                    p.len()
                )))
            }
        };
        let (fx, fy, cx, cy, k1, k2, p1, p2) = match model.as_str() {
            "SIMPLE_PINHOLE" => expect(3).map(|_| (p[0], p[0], p[1], p[2], 0.0, 0.0, 0.0, 0.0))?,
            "PINHOLE" => expect(4).map(|_| (p[0], p[1], p[2], p[3], 0.0, 0.0, 0.0, 0.0))?,
            "SIMPLE_RADIAL" => expect(4).map(|_| (p[0], p[0], p[1], p[2], p[3], 0.0, 0.0, 0.0))?,
            "RADIAL" => expect(5).map(|_| (p[0], p[0], p[1], p[2], p[3], p[4], 0.0, 0.0))?,
            "OPENCV" => expect(8).map(|_| (p[0], p[1], p[2], p[3], p[4], p[5], p[6], p[7]))?,
            other => {
                return Err(err(format!(
                    "camera model {other} is not supported (SIMPLE_PINHOLE, PINHOLE, SIMPLE_RADIAL, RADIAL, OPENCV): undistort the images with `colmap image_undistorter` first"
                )))
            }
        };
        // Written so that NaN fails too.
        let positive = fx > 0.0 && fy > 0.0;
        if !positive || ![cx, cy, k1, k2, p1, p2].iter().all(|v| v.is_finite()) {
            return Err(err(format!(
                "camera {id}: focal lengths must be positive and all parameters finite"
            )));
        }
        // Displacement at the farthest image corner, in pixels.
        let (x, y) = (
            (w as f64 - cx).abs().max(cx.abs()) / fx,
            (h as f64 - cy).abs().max(cy.abs()) / fy,
        );
        let r2 = x * x + y * y;
        let radial = (k1 * r2 + k2 * r2 * r2).abs() * r2.sqrt();
        let tangential = 2.0 * (p1.abs() + p2.abs()) * r2;
        let shift = (radial + tangential) * fx.max(fy);
        if shift >= MAX_DISTORTION_PX {
            return Err(err(format!(
                "camera {id} ({model}) distorts the image corners by {shift:.1} px; nerflabel needs undistorted images: run `colmap image_undistorter` and use its PINHOLE model"
            )));
        }
        if cameras
            .insert(
                id,
                Camera {
                    intrinsics: Intrinsics { fx, fy, cx, cy },
                    size: (w, h),
                },
            )
            .is_some()
        {
            return Err(err(format!("camera {id} is listed twice")));
        }
    }
    if cameras.is_empty() {
        return Err(TextError {
            line: 0,
            reason: "no camera listed".into(),
        });
    }
    Ok(cameras)
}

/// `IMAGE_ID QW QX QY QZ TX TY TZ CAMERA_ID NAME` lines, each followed by a
/// line of 2D points (possibly empty), which is skipped.
fn parse_images(text: &str) -> Result<Vec<Image>, TextError> {
    let mut images = Vec::new();
    let mut lines = text.lines().enumerate().map(|(i, l)| (i + 1, l.trim()));
    while let Some((line, body)) = lines.next() {
        if body.is_empty() || body.starts_with('#') {
            continue;
        }
        let err = |reason: String| TextError { line, reason };
        let t: Vec<&str> = body.split_whitespace().collect();
        if t.len() < 10 {
            return Err(err(format!(
                "expected IMAGE_ID QW QX QY QZ TX TY TZ CAMERA_ID NAME, found {} fields",
                t.len()
            )));
        }
        let v = t[1..8]
            .iter()
            .map(|s| super::text::number(s, line))
            .collect::<Result<Vec<f64>, _>>()?;
        let camera_id: u64 = t[8]
            .parse()
            .map_err(|_| err(format!("camera id '{}' is not a whole number", t[8])))?;
        // Names may hold spaces: everything after the camera id.
        let name = t[9..].join(" ");
        let world_to_camera = pose_from_translation_quaternion([v[4], v[5], v[6]], [v[1], v[2], v[3], v[0]])
            .ok_or_else(|| {
                err(format!(
                    "image {name}: the quaternion or translation is not finite or has zero length"
                ))
            })?;
        images.push(Image {
            world_to_camera,
            camera_id,
            name,
            line,
        });
        // The image's 2D points (possibly an empty line).
        lines.next();
    }
    Ok(images)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn cameras_parse_and_distortion_is_checked() {
        let text = "# Camera list\n1 PINHOLE 640 480 500 502 320 240\n2 SIMPLE_RADIAL 640 480 500 320 240 0.00001\n";
        let cams = parse_cameras(text).unwrap();
        assert_eq!(
            cams[&1].intrinsics,
            Intrinsics {
                fx: 500.0,
                fy: 502.0,
                cx: 320.0,
                cy: 240.0
            }
        );
        assert_eq!(cams[&2].size, (640, 480));
        let bad = parse_cameras("1 SIMPLE_RADIAL 640 480 500 320 240 0.05\n").unwrap_err();
        assert!(bad.reason.contains("image_undistorter") && bad.line == 1, "{bad:?}");
        let fisheye = parse_cameras("1 OPENCV_FISHEYE 640 480 500 500 320 240 0 0 0 0\n").unwrap_err();
        assert!(fisheye.reason.contains("not supported"), "{fisheye:?}");
        assert!(parse_cameras("1 PINHOLE 640 480 500 320 240\n")
            .unwrap_err()
            .reason
            .contains("4 parameters"));
        assert!(parse_cameras("1 PINHOLE 640 0 500 500 320 240\n").is_err());
    }

    #[test]
    fn images_alternate_with_point_lines_which_may_be_empty() {
        let text = "# Image list\n# two lines per image\n\
            3 1 0 0 0 0.5 0 0 1 b.jpg\n\
            100.0 200.0 -1 110.0 210.0 7\n\
            7 0.7071067811865476 0 0.7071067811865476 0 0 0 2 1 a name.jpg\n\
            \n";
        let images = parse_images(text).unwrap();
        assert_eq!(images.len(), 2);
        assert_eq!(
            (images[0].name.as_str(), images[0].camera_id, images[0].line),
            ("b.jpg", 1, 3)
        );
        assert_eq!(
            images[0].world_to_camera.translation.vector,
            nalgebra::Vector3::new(0.5, 0.0, 0.0)
        );
        assert_eq!(images[1].name, "a name.jpg");
        // 90 degrees about y: the world x axis becomes the camera's -z.
        let x = images[1].world_to_camera * nalgebra::Vector3::x();
        assert!((x - nalgebra::Vector3::new(0.0, 0.0, -1.0)).norm() < 1e-12, "{x}");
        assert!(parse_images("1 1 0 0 0 0 0 0 1\n")
            .unwrap_err()
            .reason
            .contains("found 9 fields"));
        assert!(parse_images("1 0 0 0 0 0 0 0 1 z.jpg\n\n")
            .unwrap_err()
            .reason
            .contains("quaternion"));
    }
}
