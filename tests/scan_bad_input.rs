//! One row per kind of broken scan: each builds the scan in a tempdir,
//! `load` must fail, and the one-line message must name the offending file
//! (or frame) and say what is wrong.

mod common;

use common::{copy_dir, small_fixture};
use image::{ImageBuffer, Luma, Rgb, RgbImage};
use nerflabel::scan::{load, LoadOptions, MAX_FRAMES};
use std::fmt::Write as _;
use std::path::{Path, PathBuf};

const W: u32 = 8;
const H: u32 = 6;

fn write(path: &Path, bytes: impl AsRef<[u8]>) {
    std::fs::create_dir_all(path.parent().unwrap()).unwrap();
    std::fs::write(path, bytes).unwrap();
}

fn rgb_png(path: &Path, w: u32, h: u32) {
    std::fs::create_dir_all(path.parent().unwrap()).unwrap();
    RgbImage::from_pixel(w, h, Rgb([10, 20, 30])).save(path).unwrap();
}

fn depth_png(path: &Path) {
    std::fs::create_dir_all(path.parent().unwrap()).unwrap();
    ImageBuffer::<Luma<u16>, Vec<u16>>::from_pixel(W, H, Luma([1500]))
        .save(path)
        .unwrap();
}

fn pose_text(tx: f64) -> String {
    format!("1 0 0 {tx}\n0 1 0 0\n0 0 1 0\n0 0 0 1\n")
}

/// A valid two-frame native scan.
fn native(root: &Path) {
    write(&root.join("intrinsics.txt"), "8 0 3.5\n0 8 2.5\n0 0 1\n");
    for i in 0..2 {
        rgb_png(&root.join(format!("rgb/{i:06}.png")), W, H);
        depth_png(&root.join(format!("depth/{i:06}.png")));
        write(&root.join(format!("pose/{i:06}.txt")), pose_text(i as f64 * 0.1));
    }
}

fn jpeg_bytes() -> Vec<u8> {
    let mut out = Vec::new();
    let img = RgbImage::from_fn(32, 32, |x, y| Rgb([(x * 7) as u8, (y * 5) as u8, 90]));
    image::codecs::jpeg::JpegEncoder::new_with_quality(&mut out, 90)
        .encode_image(&img)
        .unwrap();
    out
}

/// A PNG whose header claims `w` x `h` (no real pixel data).
fn png_header_only(w: u32, h: u32) -> Vec<u8> {
    let mut out = vec![0x89, b'P', b'N', b'G', 0x0D, 0x0A, 0x1A, 0x0A];
    let mut chunk = |kind: &[u8; 4], data: &[u8]| {
        out.extend_from_slice(&(data.len() as u32).to_be_bytes());
        let mut body = kind.to_vec();
        body.extend_from_slice(data);
        out.extend_from_slice(&body);
        out.extend_from_slice(&crc32fast::hash(&body).to_be_bytes());
    };
    let mut ihdr = Vec::new();
    ihdr.extend_from_slice(&w.to_be_bytes());
    ihdr.extend_from_slice(&h.to_be_bytes());
    ihdr.extend_from_slice(&[8, 2, 0, 0, 0]);
    chunk(b"IHDR", &ihdr);
    chunk(b"IDAT", &[]);
    chunk(b"IEND", &[]);
    out
}

/// A valid one-frame TUM sequence with the given lists.
fn tum(root: &Path, rgb_t: f64, depth_t: f64, gt_t: f64) {
    rgb_png(&root.join("rgb/a.png"), W, H);
    depth_png(&root.join("depth/b.png"));
    write(&root.join("rgb.txt"), format!("# color\n{rgb_t} rgb/a.png\n"));
    write(&root.join("depth.txt"), format!("{depth_t} depth/b.png\n"));
    write(&root.join("groundtruth.txt"), format!("{gt_t} 0 0 0 0 0 0 1\n"));
    write(&root.join("intrinsics.txt"), "8 0 3.5\n0 8 2.5\n0 0 1\n");
}

fn nerfstudio(root: &Path, json: &str) {
    rgb_png(&root.join("images/0.png"), W, H);
    write(&root.join("transforms.json"), json);
}

fn stray(root: &Path, odometry: &str) {
    write(&root.join("camera_matrix.csv"), "1440, 0, 960\n0, 1440, 720\n0, 0, 1\n");
    rgb_png(&root.join("rgb/000000.png"), W, H);
    rgb_png(&root.join("rgb/000001.png"), W, H);
    write(&root.join("odometry.csv"), odometry);
}

type Build = fn(&Path) -> PathBuf;

struct Case {
    name: &'static str,
    build: Build,
    /// Every one of these must appear in the message.
    expect: &'static [&'static str],
}

fn depth_png_sized(path: &Path, w: u32, h: u32) {
    std::fs::create_dir_all(path.parent().unwrap()).unwrap();
    ImageBuffer::<Luma<u16>, Vec<u16>>::from_pixel(w, h, Luma([1500]))
        .save(path)
        .unwrap();
}

fn cases() -> Vec<Case> {
    vec![
        Case {
            // Regression: 36x48 depth for 160x120 colour was stretched silently.
            name: "depth of another aspect ratio than colour",
            build: |r| {
                native(r);
                for i in 0..2 {
                    depth_png_sized(&r.join(format!("depth/{i:06}.png")), 3, 8);
                }
                r.to_path_buf()
            },
            expect: &["depth/000000.png", "3x8", "8x6", "stretch"],
        },
        Case {
            name: "one depth image of another size than the rest",
            build: |r| {
                native(r);
                depth_png_sized(&r.join("depth/000001.png"), 4, 3);
                r.to_path_buf()
            },
            expect: &["depth/000001.png", "4x3", "other depth images are 8x6"],
        },
        Case {
            // Regression: reported as a missing image.
            name: "a directory where a frame image should be",
            build: |r| {
                native(r);
                std::fs::remove_file(r.join("rgb/000001.png")).unwrap();
                std::fs::create_dir_all(r.join("rgb/000001.png")).unwrap();
                r.to_path_buf()
            },
            expect: &["rgb/000001.png", "is a directory"],
        },
        Case {
            // Regression: a FIFO among the frames made loading hang.
            name: "a FIFO in a frame folder",
            build: |r| {
                native(r);
                std::fs::remove_file(r.join("depth/000001.png")).unwrap();
                let made = std::process::Command::new("mkfifo")
                    .arg(r.join("depth/000001.png"))
                    .status();
                assert!(
                    made.is_ok_and(|s| s.success()),
                    "mkfifo (coreutils) is needed for this case"
                );
                r.to_path_buf()
            },
            expect: &["depth/000001.png", "not a regular file"],
        },
        Case {
            // Regression: the skew was dropped silently.
            name: "intrinsics with skew",
            build: |r| {
                native(r);
                write(&r.join("intrinsics.txt"), "8 0.5 3.5\n0 8 2.5\n0 0 1\n");
                r.to_path_buf()
            },
            expect: &["intrinsics.txt", "skew 0.5"],
        },
        Case {
            // Regression: fx = 1e-300 loaded and the fit trained nothing.
            name: "focal length 1e-300",
            build: |r| {
                native(r);
                write(&r.join("intrinsics.txt"), "1e-300 0 3.5\n0 8 2.5\n0 0 1\n");
                r.to_path_buf()
            },
            expect: &["intrinsics.txt", "field of view"],
        },
        Case {
            // Regression: 24 frames of 16384x16384 aborted on allocation.
            name: "more pixels than memory",
            build: |r| {
                write(&r.join("intrinsics.txt"), "16000 0 8191.5\n0 16000 8191.5\n0 0 1\n");
                for i in 0..24 {
                    write(&r.join(format!("rgb/{i:06}.png")), png_header_only(16384, 16384));
                    write(&r.join(format!("pose/{i:06}.txt")), pose_text(i as f64 * 0.1));
                }
                r.to_path_buf()
            },
            expect: &["24 frames of 16384x16384", "GB", "memory available"],
        },
        Case {
            name: "missing folder",
            build: |r| r.join("nope"),
            expect: &["nope", "does not exist"],
        },
        Case {
            name: "not a folder",
            build: |r| {
                write(&r.join("file"), "x");
                r.join("file")
            },
            expect: &["file", "not a folder"],
        },
        Case {
            name: "unknown layout",
            build: |r| r.to_path_buf(),
            expect: &["cannot tell the scan layout"],
        },
        Case {
            name: "no frames",
            build: |r| {
                write(&r.join("intrinsics.txt"), "8 0 3.5\n0 8 2.5\n0 0 1\n");
                std::fs::create_dir_all(r.join("rgb")).unwrap();
                std::fs::create_dir_all(r.join("pose")).unwrap();
                r.to_path_buf()
            },
            expect: &["no frames"],
        },
        Case {
            name: "missing intrinsics",
            build: |r| {
                native(r);
                std::fs::remove_file(r.join("intrinsics.txt")).unwrap();
                r.to_path_buf()
            },
            expect: &["intrinsics.txt", "missing"],
        },
        Case {
            name: "rgb without pose",
            build: |r| {
                native(r);
                std::fs::remove_file(r.join("pose/000001.txt")).unwrap();
                r.to_path_buf()
            },
            expect: &["frame 000001", "no pose"],
        },
        Case {
            name: "pose without rgb",
            build: |r| {
                native(r);
                write(&r.join("pose/000005.txt"), pose_text(0.0));
                r.to_path_buf()
            },
            expect: &["frame 000005", "no rgb"],
        },
        Case {
            name: "two files for one frame",
            build: |r| {
                native(r);
                rgb_png(&r.join("rgb/1.png"), W, H);
                r.to_path_buf()
            },
            expect: &["frame 1", "two files"],
        },
        Case {
            name: "pose with NaN",
            build: |r| {
                native(r);
                write(&r.join("pose/000001.txt"), "1 0 0 nan\n0 1 0 0\n0 0 1 0\n0 0 0 1\n");
                r.to_path_buf()
            },
            expect: &["pose/000001.txt", "NaN"],
        },
        Case {
            name: "pose with inf",
            build: |r| {
                native(r);
                write(&r.join("pose/000001.txt"), "1 0 0 inf\n0 1 0 0\n0 0 1 0\n0 0 0 1\n");
                r.to_path_buf()
            },
            expect: &["pose/000001.txt", "infinite"],
        },
        Case {
            name: "rotation not orthonormal",
            build: |r| {
                native(r);
                write(&r.join("pose/000001.txt"), "1.1 0 0 0\n0 1 0 0\n0 0 1 0\n0 0 0 1\n");
                r.to_path_buf()
            },
            expect: &["pose/000001.txt", "not orthonormal"],
        },
        Case {
            name: "rotation with det -1",
            build: |r| {
                native(r);
                write(&r.join("pose/000001.txt"), "1 0 0 0\n0 1 0 0\n0 0 -1 0\n0 0 0 1\n");
                r.to_path_buf()
            },
            expect: &["pose/000001.txt", "det"],
        },
        Case {
            name: "pose bottom row",
            build: |r| {
                native(r);
                write(&r.join("pose/000001.txt"), "1 0 0 0\n0 1 0 0\n0 0 1 0\n0 0 1 1\n");
                r.to_path_buf()
            },
            expect: &["pose/000001.txt", "last row"],
        },
        Case {
            name: "pose not a matrix",
            build: |r| {
                native(r);
                write(&r.join("pose/000001.txt"), "1 0 0 0\n0 1 zero 0\n0 0 1 0\n0 0 0 1\n");
                r.to_path_buf()
            },
            expect: &["pose/000001.txt", "line 2", "expected a number"],
        },
        Case {
            name: "depth 8-bit",
            build: |r| {
                native(r);
                image::GrayImage::new(W, H).save(r.join("depth/000001.png")).unwrap();
                r.to_path_buf()
            },
            expect: &[
                "depth/000001.png",
                "expected a 16-bit single-channel PNG, found 8-bit gray",
            ],
        },
        Case {
            name: "depth 8-bit RGB",
            build: |r| {
                native(r);
                rgb_png(&r.join("depth/000001.png"), W, H);
                r.to_path_buf()
            },
            expect: &["depth/000001.png", "found 8-bit RGB"],
        },
        Case {
            name: "depth 16-bit multi-channel",
            build: |r| {
                native(r);
                ImageBuffer::<Rgb<u16>, Vec<u16>>::new(W, H)
                    .save(r.join("depth/000001.png"))
                    .unwrap();
                r.to_path_buf()
            },
            expect: &["depth/000001.png", "found 16-bit RGB"],
        },
        Case {
            name: "truncated JPEG",
            build: |r| {
                native(r);
                std::fs::remove_file(r.join("rgb/000001.png")).unwrap();
                let jpg = jpeg_bytes();
                write(&r.join("rgb/000001.jpg"), &jpg[..jpg.len() * 2 / 3]);
                r.to_path_buf()
            },
            expect: &["rgb/000001.jpg", "cannot decode", "truncated"],
        },
        Case {
            name: "truncated PNG",
            build: |r| {
                native(r);
                let png = std::fs::read(r.join("rgb/000001.png")).unwrap();
                write(&r.join("rgb/000001.png"), &png[..png.len() - 20]);
                r.to_path_buf()
            },
            expect: &["rgb/000001.png", "cannot decode"],
        },
        Case {
            name: "truncated depth PNG",
            build: |r| {
                native(r);
                let png = std::fs::read(r.join("depth/000001.png")).unwrap();
                write(&r.join("depth/000001.png"), &png[..png.len() - 20]);
                r.to_path_buf()
            },
            expect: &["depth/000001.png", "cannot decode"],
        },
        Case {
            name: "not an image",
            build: |r| {
                native(r);
                write(&r.join("rgb/000001.png"), "hello");
                r.to_path_buf()
            },
            expect: &["rgb/000001.png", "not a PNG or JPEG"],
        },
        Case {
            name: "frames of different sizes",
            build: |r| {
                native(r);
                rgb_png(&r.join("rgb/000001.png"), W * 2, H * 2);
                r.to_path_buf()
            },
            expect: &["rgb/000001.png", "16x12", "differs", "8x6"],
        },
        Case {
            name: "absurd dimensions",
            build: |r| {
                native(r);
                write(&r.join("rgb/000001.png"), png_header_only(100_000, 10));
                r.to_path_buf()
            },
            expect: &["rgb/000001.png", "absurd image dimensions 100000x10"],
        },
        Case {
            name: "intrinsics fx <= 0",
            build: |r| {
                native(r);
                write(&r.join("intrinsics.txt"), "-8 0 3.5\n0 8 2.5\n0 0 1\n");
                r.to_path_buf()
            },
            expect: &["intrinsics.txt", "focal lengths must be positive"],
        },
        Case {
            name: "principal point far outside",
            build: |r| {
                native(r);
                write(&r.join("intrinsics.txt"), "8 0 30\n0 8 2.5\n0 0 1\n");
                r.to_path_buf()
            },
            expect: &["intrinsics.txt", "principal point"],
        },
        Case {
            name: "intrinsics not a matrix",
            build: |r| {
                native(r);
                write(&r.join("intrinsics.txt"), "8 0\n0 8\n");
                r.to_path_buf()
            },
            expect: &["intrinsics.txt", "camera matrix"],
        },
        Case {
            name: "bbox malformed",
            build: |r| {
                native(r);
                write(&r.join("bbox.txt"), "0 0 0 1 1\n");
                r.to_path_buf()
            },
            expect: &["bbox.txt", "6 numbers"],
        },
        Case {
            name: "empty transforms.json",
            build: |r| {
                nerfstudio(r, "  \n");
                r.to_path_buf()
            },
            expect: &["transforms.json", "empty"],
        },
        Case {
            name: "malformed transforms.json",
            build: |r| {
                nerfstudio(r, r#"{"frames": [ {"file_path": "images/0.png", }"#);
                r.to_path_buf()
            },
            expect: &["transforms.json", "malformed JSON"],
        },
        Case {
            name: "transforms.json without frames",
            build: |r| {
                nerfstudio(r, r#"{"fl_x": 8, "frames": []}"#);
                r.to_path_buf()
            },
            expect: &["transforms.json", "no frames"],
        },
        Case {
            name: "transforms.json image missing",
            build: |r| {
                nerfstudio(
                    r,
                    r#"{"fl_x": 8, "frames": [{"file_path": "images/7", "transform_matrix": [[1,0,0,0],[0,1,0,0],[0,0,1,0],[0,0,0,1]]}]}"#,
                );
                r.to_path_buf()
            },
            expect: &["frame 0 of transforms.json", "images/7", "not found"],
        },
        Case {
            name: "transforms.json bad matrix",
            build: |r| {
                nerfstudio(
                    r,
                    r#"{"fl_x": 8, "frames": [{"file_path": "images/0.png", "transform_matrix": [[1,0,0],[0,1,0]]}]}"#,
                );
                r.to_path_buf()
            },
            expect: &["frame 0 of transforms.json", "transform_matrix must be 4x4"],
        },
        Case {
            name: "transforms.json without focal length",
            build: |r| {
                nerfstudio(
                    r,
                    r#"{"frames": [{"file_path": "images/0.png", "transform_matrix": [[1,0,0,0],[0,1,0,0],[0,0,1,0],[0,0,0,1]]}]}"#,
                );
                r.to_path_buf()
            },
            expect: &["transforms.json", "no focal length"],
        },
        Case {
            name: "TUM timestamps do not associate",
            build: |r| {
                tum(r, 1.0, 1.5, 1.0);
                r.to_path_buf()
            },
            expect: &["rgb.txt", "could be associated within 20 ms", "1 without depth"],
        },
        Case {
            name: "TUM groundtruth does not associate",
            build: |r| {
                tum(r, 1.0, 1.0, 3.0);
                r.to_path_buf()
            },
            expect: &["rgb.txt", "associated", "1 without a pose"],
        },
        Case {
            name: "TUM groundtruth malformed",
            build: |r| {
                tum(r, 1.0, 1.0, 1.0);
                write(&r.join("groundtruth.txt"), "# gt\n1.0 0 0 0 0 0 0\n");
                r.to_path_buf()
            },
            expect: &["groundtruth.txt", "line 2", "tx ty tz qx qy qz qw"],
        },
        Case {
            name: "TUM zero quaternion",
            build: |r| {
                tum(r, 1.0, 1.0, 1.0);
                write(&r.join("groundtruth.txt"), "1.0 0 0 0 0 0 0 0\n");
                r.to_path_buf()
            },
            expect: &["groundtruth.txt", "line 1", "zero quaternion"],
        },
        Case {
            name: "TUM listed images absent",
            build: |r| {
                tum(r, 1.0, 1.0, 1.0);
                write(&r.join("rgb.txt"), "1.0 rgb/elsewhere.png\n");
                r.to_path_buf()
            },
            expect: &["rgb.txt", "none of the 1 image(s)"],
        },
        Case {
            name: "MAX_FRAMES cap",
            build: |r| {
                tum(r, 1.0, 1.0, 1.0);
                let mut list = String::with_capacity((MAX_FRAMES + 1) * 32);
                for i in 0..=MAX_FRAMES {
                    writeln!(list, "{}.0 rgb/a.png", i).unwrap();
                }
                write(&r.join("rgb.txt"), list);
                r.to_path_buf()
            },
            expect: &["rgb.txt", "too many frames (100001"],
        },
        Case {
            name: "ScanNet every pose lost",
            build: |r| {
                write(
                    &r.join("intrinsic/intrinsic_color.txt"),
                    "8 0 3.5 0\n0 8 2.5 0\n0 0 1 0\n0 0 0 1\n",
                );
                rgb_png(&r.join("color/0.png"), W, H);
                write(&r.join("pose/0.txt"), "-inf -inf -inf -inf\n".repeat(4));
                r.to_path_buf()
            },
            expect: &["no frames", "no valid pose", "inf"],
        },
        Case {
            name: "Stray image without odometry row",
            build: |r| {
                stray(
                    r,
                    "timestamp, frame, x, y, z, qx, qy, qz, qw\n0.0, 0, 0, 0, 0, 0, 0, 0, 1\n",
                );
                r.to_path_buf()
            },
            expect: &["frame 000001", "odometry.csv"],
        },
        Case {
            name: "Stray odometry malformed",
            build: |r| {
                stray(r, "timestamp, frame, x, y, z, qx, qy, qz, qw\n0.0, 0, 0, 0, 0, 0, 0, 0, 1\n0.1, 1, 0, 0, 0, 0, 0, x, 1\n");
                r.to_path_buf()
            },
            expect: &["odometry.csv", "line 3", "'x'"],
        },
    ]
}

#[test]
fn every_bad_input_fails_with_a_message_naming_file_and_problem() {
    let mut failures = Vec::new();
    for case in cases() {
        let dir = tempfile::tempdir().unwrap();
        let root = (case.build)(dir.path());
        match load(&root, &LoadOptions::default()) {
            Ok(scan) => failures.push(format!(
                "{}: loaded {} frames instead of failing",
                case.name,
                scan.frames.len()
            )),
            Err(err) => {
                let message = err.to_string();
                let missing: Vec<&str> = case.expect.iter().copied().filter(|e| !message.contains(e)).collect();
                if !missing.is_empty() {
                    failures.push(format!("{}: message lacks {missing:?}: {message}", case.name));
                }
                if message.contains('\n') {
                    failures.push(format!("{}: message spans several lines: {message}", case.name));
                }
            }
        }
    }
    assert!(
        failures.is_empty(),
        "{} case(s) wrong:\n{}",
        failures.len(),
        failures.join("\n")
    );
}

#[test]
fn the_valid_base_scans_load() {
    // Guards the table: each row must break a scan that is otherwise valid.
    let dir = tempfile::tempdir().unwrap();
    native(dir.path());
    assert_eq!(load(dir.path(), &LoadOptions::default()).unwrap().frames.len(), 2);
    let dir = tempfile::tempdir().unwrap();
    tum(dir.path(), 1.0, 1.0, 1.0);
    assert_eq!(load(dir.path(), &LoadOptions::default()).unwrap().frames.len(), 1);
    let dir = tempfile::tempdir().unwrap();
    stray(
        dir.path(),
        "timestamp, frame, x, y, z, qx, qy, qz, qw\n0, 0, 0, 0, 0, 0, 0, 0, 1\n0, 1, 0, 0, 0, 0, 0, 0, 1\n",
    );
    assert_eq!(load(dir.path(), &LoadOptions::default()).unwrap().frames.len(), 2);
    let dir = tempfile::tempdir().unwrap();
    nerfstudio(
        dir.path(),
        r#"{"fl_x": 8, "frames": [{"file_path": "images/0", "transform_matrix": [[1,0,0,0],[0,1,0,0],[0,0,1,0],[0,0,0,1]]}]}"#,
    );
    assert_eq!(load(dir.path(), &LoadOptions::default()).unwrap().frames.len(), 1);
}

#[test]
fn one_pose_a_hundred_kilometres_off_is_excluded_with_a_warning_naming_it() {
    // Regression: a translation of 1e5 m in one pose file gave `warnings none`,
    // 104 km scene bounds and a fit with a held-out depth error of 63 km.
    let dir = tempfile::tempdir().unwrap();
    copy_dir(&small_fixture(), dir.path());
    let pose = dir.path().join("pose/000007.txt");
    let text = std::fs::read_to_string(&pose).unwrap();
    let mut rows: Vec<Vec<f64>> = text
        .lines()
        .filter(|l| !l.trim().is_empty())
        .map(|l| l.split_whitespace().map(|v| v.parse().unwrap()).collect())
        .collect();
    rows[1][3] += 1e5;
    let text: String = rows
        .iter()
        .map(|r| r.iter().map(|v| format!("{v:.17e}")).collect::<Vec<_>>().join(" ") + "\n")
        .collect();
    std::fs::write(&pose, text).unwrap();
    let scan = load(dir.path(), &LoadOptions::default()).unwrap();
    assert_eq!(scan.frames.len(), 23);
    assert!(scan.frames.iter().all(|f| f.name != "000007"));
    let warning = scan
        .warnings
        .iter()
        .find(|w| w.contains("excluded"))
        .expect("a warning");
    assert!(
        warning.contains("000007") && warning.contains("far from the rest of the trajectory"),
        "{warning}"
    );
    let bounds = nerflabel::poses::scene_bounds(&scan, &Default::default()).unwrap();
    assert!(
        bounds.aabb.max_extent() < 20.0,
        "bounds stay those of the scene: {}",
        bounds.aabb.max_extent()
    );

    // Ten of 24 poses moved is not an outlier to exclude: the trajectory is broken.
    let far = std::fs::read(&pose).unwrap();
    for i in 0..10 {
        std::fs::write(dir.path().join(format!("pose/{i:06}.txt")), &far).unwrap();
    }
    let err = match load(dir.path(), &LoadOptions::default()) {
        Ok(scan) => panic!("loaded {} frames, warnings {:?}", scan.frames.len(), scan.warnings),
        Err(e) => e.to_string(),
    };
    assert!(err.contains("not trustworthy"), "{err}");
}

#[test]
fn generated_and_real_scans_have_no_pose_outliers() {
    let mut scans = vec![small_fixture()];
    let shared = std::env::var_os("NERFLABEL_SHARED_DATA")
        .map(PathBuf::from)
        .unwrap_or_else(|| Path::new(env!("CARGO_MANIFEST_DIR")).join("../shared/data"));
    for real in ["scans/cabinet", "real/tum_fr1_desk_first9", "real/tum_fr1_rpy_every10"] {
        if shared.join(real).is_dir() {
            scans.push(shared.join(real));
        } else {
            eprintln!("{} is absent: skipping that real scan", shared.join(real).display());
        }
    }
    for path in scans {
        let scan = load(&path, &LoadOptions::default()).unwrap();
        assert!(
            !scan.warnings.iter().any(|w| w.contains("excluded")),
            "{}: {:?}",
            path.display(),
            scan.warnings
        );
    }
}
