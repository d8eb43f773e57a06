//! Every scan layout, written from one known scene (a tilted plane seen by
//! three known cameras), loads into the same `Scan`: frame count, poses
//! (incl. nerfstudio's OpenGL axes and TUM quaternions), intrinsics scaling,
//! metric depth on the colour grid, and depth that reprojects consistently
//! between frames. Real scans from the shared data folder are checked too
//! when present.

use image::{ImageBuffer, Luma, RgbImage};
use nalgebra::{IsometryMatrix3, Matrix3, Matrix4, Point3, Rotation3, Translation3, Vector3, Vector4};
use nerflabel::scan::{load, summarize, ColourBorder, DepthMap, Frame, Intrinsics, Layout, LoadOptions, Scan};
use std::fmt::Write as _;
use std::path::{Path, PathBuf};

const W: u32 = 80;
const H: u32 = 60;
const K: Intrinsics = Intrinsics {
    fx: 70.0,
    fy: 68.0,
    cx: 39.5,
    cy: 29.5,
};

/// The scene: the plane n . X = PLANE_D (n normalised below).
const PLANE_N: [f64; 3] = [0.1, -0.05, 1.0];
const PLANE_D: f64 = 2.0;

/// Rotation from an axis and angle by Rodrigues' formula (independent of nalgebra's quaternions).
fn rodrigues(axis: Vector3<f64>, angle: f64) -> Matrix3<f64> {
    let a = axis.normalize();
    let k = Matrix3::from_columns(&[
        Vector3::new(0.0, a.z, -a.y),
        Vector3::new(-a.z, 0.0, a.x),
        Vector3::new(a.y, -a.x, 0.0),
    ]);
    Matrix3::identity() + k * angle.sin() + k * k * (1.0 - angle.cos())
}

/// Ground-truth camera: axis, angle, centre; camera-to-world in OpenCV axes.
struct Cam {
    axis: Vector3<f64>,
    angle: f64,
    centre: Vector3<f64>,
}

impl Cam {
    fn c2w(&self) -> IsometryMatrix3<f64> {
        let r = Rotation3::from_matrix_unchecked(rodrigues(self.axis, self.angle));
        IsometryMatrix3::from_parts(Translation3::from(self.centre), r)
    }

    /// Scalar-last quaternion `qx qy qz qw`.
    fn quaternion(&self) -> [f64; 4] {
        let a = self.axis.normalize() * (0.5 * self.angle).sin();
        [a.x, a.y, a.z, (0.5 * self.angle).cos()]
    }
}

fn cams() -> Vec<Cam> {
    vec![
        Cam {
            axis: Vector3::y(),
            angle: 0.0,
            centre: Vector3::zeros(),
        },
        Cam {
            axis: Vector3::y(),
            angle: 0.1,
            centre: Vector3::new(0.2, 0.0, 0.05),
        },
        Cam {
            axis: Vector3::new(1.0, 0.5, 0.2),
            angle: -0.12,
            centre: Vector3::new(-0.1, 0.1, 0.1),
        },
    ]
}

/// Exact depth (camera z) of the plane through pixel (u, v) of a camera.
fn plane_depth(c2w: &IsometryMatrix3<f64>, k: &Intrinsics, u: f64, v: f64) -> f64 {
    let n = Vector3::from(PLANE_N).normalize();
    let dir = c2w * k.unproject(u, v);
    let origin = c2w.translation.vector;
    (PLANE_D - n.dot(&origin)) / n.dot(&dir)
}

/// Depth image of the plane at `w` x `h` in `units_per_metre`.
fn write_depth(path: &Path, c2w: &IsometryMatrix3<f64>, (w, h): (u32, u32), units_per_metre: f64) {
    let k = K.scaled((W, H), (w, h));
    let img = ImageBuffer::<Luma<u16>, Vec<u16>>::from_fn(w, h, |u, v| {
        let z = plane_depth(c2w, &k, u as f64, v as f64);
        Luma([(z * units_per_metre).round() as u16])
    });
    std::fs::create_dir_all(path.parent().unwrap()).unwrap();
    img.save(path).unwrap();
}

fn write_rgb(path: &Path, seed: u8) {
    let img = RgbImage::from_fn(W, H, |u, v| {
        image::Rgb([(u * 3) as u8, (v * 4) as u8, seed.wrapping_mul(60)])
    });
    std::fs::create_dir_all(path.parent().unwrap()).unwrap();
    img.save(path).unwrap();
}

fn write(path: &Path, text: &str) {
    std::fs::create_dir_all(path.parent().unwrap()).unwrap();
    std::fs::write(path, text).unwrap();
}

fn matrix_text(m: &Matrix4<f64>) -> String {
    let mut s = String::new();
    for r in 0..4 {
        writeln!(s, "{} {} {} {}", m[(r, 0)], m[(r, 1)], m[(r, 2)], m[(r, 3)]).unwrap();
    }
    s
}

fn k_text(k: &Intrinsics) -> String {
    format!("{} 0 {}\n0 {} {}\n0 0 1\n", k.fx, k.cx, k.fy, k.cy)
}

/// Depth of a loaded frame sampled bilinearly at a continuous pixel position.
fn sample(depth: &DepthMap, u: f64, v: f64) -> Option<f64> {
    if u < 0.0 || v < 0.0 || u > (depth.width - 1) as f64 || v > (depth.height - 1) as f64 {
        return None;
    }
    let (x0, y0) = (u.floor() as u32, v.floor() as u32);
    let (x1, y1) = ((x0 + 1).min(depth.width - 1), (y0 + 1).min(depth.height - 1));
    let (fx, fy) = (u - x0 as f64, v - y0 as f64);
    let d = [
        depth.get(x0, y0),
        depth.get(x1, y0),
        depth.get(x0, y1),
        depth.get(x1, y1),
    ];
    if d.iter().any(|&z| z <= 0.0) {
        return None;
    }
    let d: Vec<f64> = d.iter().map(|&z| z as f64).collect();
    let top = d[0] + (d[1] - d[0]) * fx;
    let bottom = d[2] + (d[3] - d[2]) * fx;
    Some(top + (bottom - top) * fy)
}

/// |predicted - observed| depth of frame `a`'s depth points seen from `b`,
/// ignoring `margin` pixels at the borders of both images.
fn reprojection_errors(a: &Frame, b: &Frame, step: u32, margin: u32) -> Vec<f64> {
    let (Some(da), Some(db)) = (&a.depth, &b.depth) else {
        return Vec::new();
    };
    let w2c_b = b.camera_to_world.inverse();
    let m = margin as f64;
    let mut out = Vec::new();
    for v in (margin..da.height - margin).step_by(step as usize) {
        for u in (margin..da.width - margin).step_by(step as usize) {
            let z = da.get(u, v) as f64;
            if z <= 0.0 {
                continue;
            }
            let world = a.camera_to_world * Point3::from(a.intrinsics.unproject(u as f64, v as f64) * z);
            let in_b = w2c_b * world;
            let Some((ub, vb)) = b.intrinsics.project(&in_b) else {
                continue;
            };
            if ub < m || vb < m || ub > (db.width - 1) as f64 - m || vb > (db.height - 1) as f64 - m {
                continue;
            }
            if let Some(observed) = sample(db, ub, vb) {
                out.push((observed - in_b.z).abs());
            }
        }
    }
    out
}

fn median(mut v: Vec<f64>) -> f64 {
    assert!(!v.is_empty(), "no overlapping depth");
    v.sort_by(f64::total_cmp);
    v[v.len() / 2]
}

/// Loaded frame `frame` matches ground-truth camera `cam` and the plane.
fn check_frame(frame: &Frame, cam: &Cam, k: &Intrinsics, depth_tolerance: f64) {
    assert_eq!(frame.size(), (W, H), "frame {}", frame.name);
    let truth = cam.c2w();
    assert!(
        (frame.camera_to_world.to_homogeneous() - truth.to_homogeneous()).amax() <= 1e-9,
        "frame {} pose\n{:?}\nvs truth\n{:?}",
        frame.name,
        frame.camera_to_world,
        truth
    );
    for (got, want) in [
        (frame.intrinsics.fx, k.fx),
        (frame.intrinsics.fy, k.fy),
        (frame.intrinsics.cx, k.cx),
        (frame.intrinsics.cy, k.cy),
    ] {
        assert!(
            (got - want).abs() < 1e-9,
            "frame {} intrinsics {:?} vs {:?}",
            frame.name,
            frame.intrinsics,
            k
        );
    }
    let Some(depth) = &frame.depth else { return };
    assert_eq!((depth.width, depth.height), (W, H));
    let mut worst: f64 = 0.0;
    // Skip a 2-pixel border where the low-resolution depth is clamped, not extrapolated.
    for v in 2..H - 2 {
        for u in 2..W - 2 {
            let want = plane_depth(&truth, k, u as f64, v as f64);
            worst = worst.max((depth.get(u, v) as f64 - want).abs());
        }
    }
    assert!(worst < depth_tolerance, "frame {}: depth off by {worst} m", frame.name);
}

/// All three frames reproject onto each other within a few mm.
fn check_reprojection(scan: &Scan) {
    let with_depth: Vec<&Frame> = scan.frames.iter().filter(|f| f.depth.is_some()).collect();
    // Low-resolution depth is clamped, not extrapolated, in the outer 2 colour pixels.
    assert!(with_depth.len() >= 2);
    for a in &with_depth {
        for b in &with_depth {
            if a.id == b.id {
                continue;
            }
            let errors = reprojection_errors(a, b, 1, 2);
            assert!(
                errors.len() > 1200,
                "{} -> {}: only {} points overlap",
                a.name,
                b.name,
                errors.len()
            );
            let worst = errors.iter().cloned().fold(0.0, f64::max);
            assert!(median(errors) < 0.002, "{} -> {}", a.name, b.name);
            assert!(worst < 0.006, "{} -> {}: worst {worst}", a.name, b.name);
        }
    }
}

fn write_native(root: &Path) {
    write(&root.join("intrinsics.txt"), &k_text(&K));
    write(&root.join("bbox.txt"), "-1 -1 0.5 1 1 3 0.01\n");
    for (i, cam) in cams().iter().enumerate() {
        // Unpadded rgb names pair with padded pose names by integer value.
        write_rgb(&root.join(format!("rgb/{i}.png")), i as u8);
        write(
            &root.join(format!("pose/{i:06}.txt")),
            &matrix_text(&cam.c2w().inverse().to_homogeneous()),
        );
        if i < 2 {
            write_depth(&root.join(format!("depth/{i:06}.png")), &cam.c2w(), (32, 24), 1000.0);
        }
    }
}

#[test]
fn native_layout_loads_world_to_camera_and_low_res_depth() {
    let dir = tempfile::tempdir().unwrap();
    write_native(dir.path());
    let scan = load(dir.path(), &LoadOptions::default()).unwrap();
    assert_eq!(scan.layout, Layout::Native);
    assert_eq!(scan.frames.len(), 3);
    assert_eq!(
        scan.frames.iter().map(|f| f.name.as_str()).collect::<Vec<_>>(),
        ["0", "1", "2"]
    );
    for (frame, cam) in scan.frames.iter().zip(cams()) {
        check_frame(frame, &cam, &K, 0.003);
    }
    // Depth at 1/2.5 of the colour resolution, resampled to it.
    assert_eq!(scan.frames[0].depth_size, Some((32, 24)));
    assert!(scan.frames[2].depth.is_none() && scan.frames[2].depth_size.is_none());
    assert!(
        scan.warnings.iter().any(|w| w.contains("no depth")),
        "{:?}",
        scan.warnings
    );
    let bounds = scan.bounds.unwrap();
    assert_eq!((bounds.min.z, bounds.max.z), (0.5, 3.0));
    check_reprojection(&scan);

    let summary = summarize(&scan);
    assert_eq!(summary.frames_with_depth, 2);
    assert_eq!(summary.depth_sizes, vec![((32, 24), 2)]);
    let range = summary.depth_range.unwrap();
    assert!(
        range.min > 1.7 && range.max < 2.4 && range.median > range.min,
        "{range:?}"
    );
    let moved = (cams()[1].centre - cams()[0].centre).norm() + (cams()[2].centre - cams()[1].centre).norm();
    assert!((summary.trajectory_length - moved).abs() < 1e-9);
    assert!(summary.to_string().contains("32x24 (2 frames) on disk") || summary.to_string().contains("32x24 on disk"));
}

/// TUM with intrinsics chosen from the folder name (Freiburg 2 scaled to 80x60).
#[test]
fn tum_layout_associates_timestamps_and_reads_quaternions() {
    let dir = tempfile::tempdir().unwrap();
    let root = dir.path().join("rgbd_dataset_freiburg2_synthetic");
    let k = Intrinsics {
        fx: 520.9,
        fy: 521.0,
        cx: 325.1,
        cy: 249.7,
    }
    .scaled((640, 480), (W, H));
    let (mut rgb_txt, mut depth_txt, mut gt) = (String::from("# color images\n"), String::new(), String::new());
    for (i, cam) in cams().iter().enumerate() {
        let t = 100.0 + i as f64 * 0.1;
        write_rgb(&root.join(format!("rgb/{t:.6}.png")), i as u8);
        writeln!(rgb_txt, "{t:.6} rgb/{t:.6}.png").unwrap();
        let td = t + 0.012;
        writeln!(depth_txt, "{td:.6} depth/{td:.6}.png").unwrap();
        // Render depth with the TUM intrinsics: write_depth uses K, so scale via a custom loop.
        let img = ImageBuffer::<Luma<u16>, Vec<u16>>::from_fn(W, H, |u, v| {
            Luma([(plane_depth(&cam.c2w(), &k, u as f64, v as f64) * 5000.0).round() as u16])
        });
        std::fs::create_dir_all(root.join("depth")).unwrap();
        img.save(root.join(format!("depth/{td:.6}.png"))).unwrap();
        let [qx, qy, qz, qw] = cam.quaternion();
        let c = cam.centre;
        for dt in [-0.005, 0.005] {
            writeln!(gt, "{:.4} {} {} {} {qx} {qy} {qz} {qw}", t + dt, c.x, c.y, c.z).unwrap();
        }
    }
    // Listed but not on disk (a subset of a longer sequence), and an image without depth.
    writeln!(rgb_txt, "100.500000 rgb/100.500000.png").unwrap();
    writeln!(rgb_txt, "99.000000 rgb/99.000000.png").unwrap();
    write_rgb(&root.join("rgb/99.000000.png"), 9);
    write(&root.join("rgb.txt"), &rgb_txt);
    write(&root.join("depth.txt"), &depth_txt);
    write(&root.join("groundtruth.txt"), &gt);

    let scan = load(&root, &LoadOptions::default()).unwrap();
    assert_eq!(scan.layout, Layout::Tum);
    assert_eq!(scan.frames.len(), 3, "{:?}", scan.warnings);
    assert_eq!(scan.frames[1].name, "100.100000");
    for (frame, cam) in scan.frames.iter().zip(cams()) {
        check_frame(frame, &cam, &k, 0.002);
    }
    assert!(
        scan.warnings
            .iter()
            .any(|w| w.contains("1 of 5 listed image(s) are missing")),
        "{:?}",
        scan.warnings
    );
    assert!(
        scan.warnings.iter().any(|w| w.contains("no depth image within 20 ms")),
        "{:?}",
        scan.warnings
    );
    check_reprojection(&scan);
}

#[test]
fn tum_quaternion_is_scalar_last_camera_to_world() {
    let dir = tempfile::tempdir().unwrap();
    let root = dir.path();
    write_rgb(&root.join("rgb/1.000000.png"), 0);
    let depth = ImageBuffer::<Luma<u16>, Vec<u16>>::from_pixel(W, H, Luma([5000]));
    std::fs::create_dir_all(root.join("depth")).unwrap();
    depth.save(root.join("depth/1.000000.png")).unwrap();
    write(&root.join("rgb.txt"), "1.000000 rgb/1.000000.png\n");
    write(&root.join("depth.txt"), "1.000000 depth/1.000000.png\n");
    let h = std::f64::consts::FRAC_1_SQRT_2;
    // 90 degrees about +y, camera at (1, 2, 3).
    write(&root.join("groundtruth.txt"), &format!("1.0 1 2 3 0 {h} 0 {h}\n"));
    write(&root.join("intrinsics.txt"), &k_text(&K));
    let scan = load(root, &LoadOptions::default()).unwrap();
    let f = &scan.frames[0];
    assert_eq!(f.intrinsics, K);
    assert!((f.camera_to_world * Vector3::z() - Vector3::x()).norm() < 1e-12);
    assert!((f.camera_center() - Point3::new(1.0, 2.0, 3.0)).norm() < 1e-12);
    // Depth 1/5000 m units: 5000 -> 1 m.
    assert!((f.depth.as_ref().unwrap().get(10, 10) - 1.0).abs() < 1e-6);
}

/// OpenGL camera-to-world as nerfstudio stores it: flip camera y and z.
fn gl_rows(c2w_cv: &IsometryMatrix3<f64>) -> Vec<Vec<f64>> {
    let gl = c2w_cv.to_homogeneous() * Matrix4::from_diagonal(&Vector4::new(1.0, -1.0, -1.0, 1.0));
    (0..4).map(|r| (0..4).map(|c| gl[(r, c)]).collect()).collect()
}

#[test]
fn nerfstudio_layout_converts_opengl_axes() {
    let dir = tempfile::tempdir().unwrap();
    let root = dir.path();
    let mut frames = Vec::new();
    for (i, cam) in cams().iter().enumerate() {
        write_rgb(&root.join(format!("images/frame_{:05}.png", i + 1)), i as u8);
        write_depth(
            &root.join(format!("depth/frame_{:05}.png", i + 1)),
            &cam.c2w(),
            (W, H),
            1000.0,
        );
        // instant-ngp writes paths without extension.
        let file = if i == 0 {
            format!("images/frame_{:05}", i + 1)
        } else {
            format!("./images/frame_{:05}.png", i + 1)
        };
        frames.push(serde_json::json!({
            "file_path": file,
            "depth_file_path": format!("depth/frame_{:05}.png", i + 1),
            "transform_matrix": gl_rows(&cam.c2w()),
        }));
    }
    // nerfstudio's principal point puts pixel centres at +0.5.
    let json = serde_json::json!({
        "fl_x": K.fx, "fl_y": K.fy, "cx": K.cx + 0.5, "cy": K.cy + 0.5, "w": W, "h": H,
        "camera_model": "OPENCV", "frames": frames,
    });
    write(&root.join("transforms.json"), &json.to_string());
    let scan = load(root, &LoadOptions::default()).unwrap();
    assert_eq!(scan.layout, Layout::Nerfstudio);
    assert_eq!(scan.frames.iter().map(|f| f.id).collect::<Vec<_>>(), [1, 2, 3]);
    assert_eq!(scan.frames[0].name, "frame_00001");
    for (frame, cam) in scan.frames.iter().zip(cams()) {
        check_frame(frame, &cam, &K, 0.001);
    }
    check_reprojection(&scan);
}

#[test]
fn nerfstudio_camera_angle_and_depth_unit_scale() {
    let dir = tempfile::tempdir().unwrap();
    let root = dir.path();
    let cam = &cams()[1];
    let angle_x = 2.0 * (0.5 * W as f64 / K.fx).atan();
    let k = Intrinsics {
        fx: K.fx,
        fy: K.fx,
        cx: K.cx,
        cy: K.cy,
    };
    write_rgb(&root.join("r_0.png"), 0);
    let img = ImageBuffer::<Luma<u16>, Vec<u16>>::from_fn(W, H, |u, v| {
        Luma([(plane_depth(&cam.c2w(), &k, u as f64, v as f64) / 0.0002).round() as u16])
    });
    img.save(root.join("r_0_depth.png")).unwrap();
    let json = serde_json::json!({
        "camera_angle_x": angle_x,
        "depth_unit_scale_factor": 0.0002,
        "frames": [{ "file_path": "r_0", "depth_file_path": "r_0_depth", "transform_matrix": gl_rows(&cam.c2w()) }],
    });
    write(&root.join("transforms.json"), &json.to_string());
    let scan = load(
        root,
        &LoadOptions {
            layout: Some(Layout::Nerfstudio),
            ..LoadOptions::default()
        },
    )
    .unwrap();
    assert_eq!(scan.frames.len(), 1);
    check_frame(&scan.frames[0], cam, &k, 0.0005);
}

/// Images downscaled after calibration (nerfstudio `images_2`): `w`, `h`
/// describe the calibrated size, so intrinsics are scaled to the files.
#[test]
fn nerfstudio_intrinsics_follow_downscaled_images() {
    let dir = tempfile::tempdir().unwrap();
    let root = dir.path();
    let cam = &cams()[2];
    write_rgb(&root.join("images_2/0.png"), 0);
    let big = K.scaled((W, H), (2 * W, 2 * H));
    let json = serde_json::json!({
        "fl_x": big.fx, "fl_y": big.fy, "cx": big.cx + 0.5, "cy": big.cy + 0.5, "w": 2 * W, "h": 2 * H,
        "frames": [{ "file_path": "images_2/0.png", "transform_matrix": gl_rows(&cam.c2w()) }],
    });
    write(&root.join("transforms.json"), &json.to_string());
    let scan = load(root, &LoadOptions::default()).unwrap();
    assert!(scan.frames[0].depth.is_none());
    check_frame(&scan.frames[0], cam, &K, 0.0);
}

#[test]
fn scannet_layout_skips_lost_poses_and_upsamples_quarter_depth() {
    let dir = tempfile::tempdir().unwrap();
    let root = dir.path();
    let k4 = format!("{} 0 {} 0\n0 {} {} 0\n0 0 1 0\n0 0 0 1\n", K.fx, K.cx, K.fy, K.cy);
    write(&root.join("intrinsic/intrinsic_color.txt"), &k4);
    for (i, cam) in cams().iter().enumerate() {
        write_rgb(&root.join(format!("color/{i}.jpg")), i as u8);
        write(
            &root.join(format!("pose/{i}.txt")),
            &matrix_text(&cam.c2w().to_homogeneous()),
        );
        write_depth(&root.join(format!("depth/{i}.png")), &cam.c2w(), (W / 4, H / 4), 1000.0);
    }
    write_rgb(&root.join("color/3.jpg"), 3);
    write(&root.join("pose/3.txt"), &"-inf -inf -inf -inf\n".repeat(4));
    let scan = load(root, &LoadOptions::default()).unwrap();
    assert_eq!(scan.layout, Layout::Scannet);
    assert_eq!(scan.frames.len(), 3);
    assert!(
        scan.warnings.iter().any(|w| w.contains("skipped: 3")),
        "{:?}",
        scan.warnings
    );
    for (frame, cam) in scan.frames.iter().zip(cams()) {
        assert_eq!(frame.depth_size, Some((W / 4, H / 4)));
        check_frame(frame, &cam, &K, 0.003);
    }
    check_reprojection(&scan);
}

#[test]
fn stray_layout_scales_video_intrinsics() {
    let dir = tempfile::tempdir().unwrap();
    let root = dir.path();
    let kv = K.scaled((W, H), (1920, 1440));
    write(
        &root.join("camera_matrix.csv"),
        &format!("{}, 0.0, {}\n0.0, {}, {}\n0.0, 0.0, 1.0\n", kv.fx, kv.cx, kv.fy, kv.cy),
    );
    let mut odometry = String::from("timestamp, frame, x, y, z, qx, qy, qz, qw\n");
    for (i, cam) in cams().iter().enumerate() {
        write_rgb(&root.join(format!("rgb/{i:06}.jpg")), i as u8);
        write_depth(
            &root.join(format!("depth/{i:06}.png")),
            &cam.c2w(),
            (W / 4, H / 4),
            1000.0,
        );
        let [qx, qy, qz, qw] = cam.quaternion();
        let c = cam.centre;
        writeln!(
            odometry,
            "{}, {i}, {}, {}, {}, {qx}, {qy}, {qz}, {qw}",
            0.5 + i as f64,
            c.x,
            c.y,
            c.z
        )
        .unwrap();
    }
    // Odometry has rows for every video frame; only some were extracted.
    writeln!(odometry, "9.0, 7, 0, 0, 0, 0, 0, 0, 1").unwrap();
    write(&root.join("odometry.csv"), &odometry);
    write(&root.join("confidence/000000.png"), "ignored");
    let scan = load(root, &LoadOptions::default()).unwrap();
    assert_eq!(scan.layout, Layout::Stray);
    assert_eq!(scan.frames.len(), 3);
    for (frame, cam) in scan.frames.iter().zip(cams()) {
        check_frame(frame, &cam, &K, 0.003);
    }
    check_reprojection(&scan);
}

#[test]
fn fix_poses_reorthonormalises_with_a_warning() {
    let dir = tempfile::tempdir().unwrap();
    write_native(dir.path());
    let mut bad = cams()[1].c2w().inverse().to_homogeneous();
    bad[(0, 0)] += 0.004;
    write(&dir.path().join("pose/000001.txt"), &matrix_text(&bad));
    assert!(load(dir.path(), &LoadOptions::default()).is_err());
    let scan = load(
        dir.path(),
        &LoadOptions {
            fix_poses: true,
            ..LoadOptions::default()
        },
    )
    .unwrap();
    assert!(scan
        .warnings
        .iter()
        .any(|w| w.contains("000001.txt") && w.contains("re-orthonormalised")));
    assert!((scan.frames[1].camera_to_world.to_homogeneous() - cams()[1].c2w().to_homogeneous()).amax() <= 5e-3);
}

fn shared_data() -> PathBuf {
    std::env::var_os("NERFLABEL_SHARED_DATA")
        .map(PathBuf::from)
        .unwrap_or_else(|| PathBuf::from(concat!(env!("CARGO_MANIFEST_DIR"), "/../shared/data")))
}

/// Median depth disagreement of each neighbouring pair, for real scans.
fn neighbour_medians(scan: &Scan, first: usize) -> Vec<f64> {
    scan.frames[first..]
        .windows(2)
        .filter_map(|pair| {
            let errors = reprojection_errors(&pair[0], &pair[1], 4, 0);
            (errors.len() > 500).then(|| median(errors))
        })
        .collect()
}

#[test]
fn real_cabinet_scan_reprojects_consistently() {
    let root = shared_data().join("scans/cabinet");
    if !root.is_dir() {
        eprintln!("skipping: {} not present", root.display());
        return;
    }
    let scan = load(&root, &LoadOptions::default()).unwrap();
    assert_eq!(scan.frames.len(), 58);
    assert_eq!(scan.size(), (640, 480));
    assert_eq!(scan.frames[5].intrinsics.fx, 535.4);
    // Frame 0's pose is known to be a few cm off: compare frames 1..57.
    let medians = neighbour_medians(&scan, 1);
    assert!(medians.len() >= 50, "{} pairs overlap", medians.len());
    let overall = median(medians.clone());
    let worst = medians.iter().cloned().fold(0.0, f64::max);
    eprintln!("cabinet: median of pair medians {overall:.4} m, worst pair {worst:.4} m");
    assert!(overall < 0.02, "median disagreement {overall} m");
    assert!(worst < 0.06, "worst pair {worst} m");
    let summary = summarize(&scan);
    assert!(
        summary.depth_coverage > 0.3 && summary.trajectory_length > 2.0,
        "{summary}"
    );
    // Its JPEGs end in a dark row and column in every frame (padding).
    let border = ColourBorder {
        bottom: 1,
        right: 1,
        ..Default::default()
    };
    assert!(
        scan.colour_borders().iter().all(|b| *b == border),
        "{:?}",
        scan.colour_borders()[0]
    );
}

#[test]
fn real_tum_desk_loads_and_reprojects_consistently() {
    let root = shared_data().join("real/tum_fr1_desk_first9");
    if !root.is_dir() {
        eprintln!("skipping: {} not present", root.display());
        return;
    }
    let scan = load(&root, &LoadOptions::default()).unwrap();
    assert_eq!(scan.layout, Layout::Tum);
    assert_eq!(scan.frames.len(), 9, "{:?}", scan.warnings);
    assert_eq!(scan.size(), (640, 480));
    // fr1 from the folder name.
    assert_eq!(
        scan.frames[0].intrinsics,
        Intrinsics {
            fx: 517.3,
            fy: 516.5,
            cx: 318.6,
            cy: 255.3
        }
    );
    let medians = neighbour_medians(&scan, 0);
    assert_eq!(medians.len(), 8);
    let worst = medians.iter().cloned().fold(0.0, f64::max);
    eprintln!("tum desk: pair medians {medians:.4?}");
    assert!(worst < 0.01, "worst pair median {worst} m");
    // Its images show the scene to the edge.
    assert!(scan.colour_borders().iter().all(ColourBorder::is_none));
}

/// Speed check (prints, never asserts time): 500 frames of 640x480 PNG.
/// Run with `cargo test --test scan_layouts -- --ignored --nocapture` (the dev profile is optimised).
#[test]
#[ignore]
fn load_500_frames_timing() {
    let dir = tempfile::tempdir().unwrap();
    let root = dir.path();
    let k = Intrinsics {
        fx: 525.0,
        fy: 525.0,
        cx: 319.5,
        cy: 239.5,
    };
    write(&root.join("intrinsics.txt"), &k_text(&k));
    let rgb = RgbImage::from_fn(640, 480, |u, v| {
        image::Rgb([(u % 256) as u8, (v % 256) as u8, ((u * v) % 251) as u8])
    });
    let depth = ImageBuffer::<Luma<u16>, Vec<u16>>::from_fn(640, 480, |u, v| Luma([1000 + ((u + v) % 500) as u16]));
    std::fs::create_dir_all(root.join("rgb")).unwrap();
    std::fs::create_dir_all(root.join("depth")).unwrap();
    rgb.save(root.join("rgb/000000.png")).unwrap();
    depth.save(root.join("depth/000000.png")).unwrap();
    for i in 0..500 {
        if i > 0 {
            std::fs::copy(root.join("rgb/000000.png"), root.join(format!("rgb/{i:06}.png"))).unwrap();
            std::fs::copy(root.join("depth/000000.png"), root.join(format!("depth/{i:06}.png"))).unwrap();
        }
        write(
            &root.join(format!("pose/{i:06}.txt")),
            &matrix_text(&Matrix4::new_translation(&Vector3::new(i as f64 * 0.01, 0.0, 0.0))),
        );
    }
    let start = std::time::Instant::now();
    let scan = load(root, &LoadOptions::default()).unwrap();
    println!(
        "loaded {} frames of 640x480 in {:.2} s",
        scan.frames.len(),
        start.elapsed().as_secs_f64()
    );
    assert_eq!(scan.frames.len(), 500);
}

/// COLMAP's text model: world-to-camera `QW QX QY QZ TX TY TZ`, images in
/// `images/` listed in any order (here reversed, with arbitrary image ids),
/// depth PNGs by stem in `depth/`, an empty 2D-points line after some images.
#[test]
fn colmap_layout_reads_world_to_camera_quaternions_in_any_order() {
    let dir = tempfile::tempdir().unwrap();
    let root = dir.path();
    write(
        &root.join("sparse/0/cameras.txt"),
        &format!(
            "# CAMERA_ID MODEL W H PARAMS\n1 PINHOLE {W} {H} {} {} {} {}\n",
            K.fx, K.fy, K.cx, K.cy
        ),
    );
    let mut images = String::from("# Image list with two lines of data per image:\n");
    for (i, cam) in cams().iter().enumerate().rev() {
        let name = format!("frame_{i:03}");
        write_rgb(&root.join(format!("images/{name}.jpg")), i as u8);
        write_depth(
            &root.join(format!("depth/{name}.png")),
            &cam.c2w(),
            (W / 4, H / 4),
            1000.0,
        );
        // World-to-camera: rotation R^T (quaternion conjugate), translation -R^T c.
        let [qx, qy, qz, qw] = cam.quaternion();
        let t = -(rodrigues(cam.axis, cam.angle).transpose() * cam.centre);
        let points = if i == 1 { "" } else { "12.5 30.5 -1 40.0 20.0 17" };
        writeln!(
            images,
            "{} {qw} {} {} {} {} {} {} 1 {name}.jpg\n{points}",
            40 - i,
            -qx,
            -qy,
            -qz,
            t.x,
            t.y,
            t.z
        )
        .unwrap();
    }
    write(&root.join("sparse/0/images.txt"), &images);
    write(&root.join("sparse/0/points3D.txt"), "# unused\n");
    let scan = load(root, &LoadOptions::default()).unwrap();
    assert_eq!(scan.layout, Layout::Colmap);
    let names: Vec<&str> = scan.frames.iter().map(|f| f.name.as_str()).collect();
    assert_eq!(names, ["frame_000", "frame_001", "frame_002"], "frames in name order");
    for (frame, cam) in scan.frames.iter().zip(cams()) {
        assert_eq!(frame.depth_size, Some((W / 4, H / 4)));
        check_frame(frame, &cam, &K, 0.003);
    }
    check_reprojection(&scan);

    // A distorting camera is refused with the command that fixes it, naming the file.
    write(
        &root.join("sparse/0/cameras.txt"),
        &format!("1 SIMPLE_RADIAL {W} {H} {} {} {} 0.2\n", K.fx, K.cx, K.cy),
    );
    let err = load(root, &LoadOptions::default()).unwrap_err().to_string();
    assert!(
        err.contains("cameras.txt") && err.contains("image_undistorter"),
        "{err}"
    );
}
