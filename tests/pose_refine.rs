//! Pose refinement on a scene with known pose errors: a generated tabletop
//! (objects on a table, noisy low-resolution depth) whose written poses were
//! perturbed; the exact ones are in `gt/pose`.

use nalgebra::{IsometryMatrix3, Point3};
use nerflabel::fixture::{generate, Corruptions, FixtureOptions, SceneKind};
use nerflabel::nerf::model_file::Model;
use nerflabel::poses::{pose_difference, refine_poses, trajectory_alignment, RefineOptions};
use nerflabel::scan::{load, LoadOptions, Scan};
use std::path::{Path, PathBuf};
use std::process::Command;

/// A perturbed tabletop scan in `dir/scan` and, in `dir/exact`, the same
/// images with the exact poses.
fn perturbed_tabletop(dir: &Path, frames: usize, sigma_m: f64, sigma_deg: f64) -> (PathBuf, Scan, Scan) {
    let mut options = FixtureOptions::new(SceneKind::Tabletop);
    (options.width, options.height, options.frames, options.seed) = (320, 240, Some(frames), 11);
    options.corruptions = Corruptions {
        pose_noise: true,
        pose_sigma_m: sigma_m,
        pose_sigma_deg: sigma_deg,
        ..Corruptions::default()
    };
    generate_with_exact_copy(dir, &options)
}

/// The fixture `options` describe in `dir/scan` and, in `dir/exact`, the
/// same images with the exact poses.
fn generate_with_exact_copy(dir: &Path, options: &FixtureOptions) -> (PathBuf, Scan, Scan) {
    let scan_dir = dir.join("scan");
    generate(&scan_dir, options).unwrap();
    let exact_dir = dir.join("exact");
    std::fs::create_dir_all(&exact_dir).unwrap();
    for entry in ["rgb", "depth", "intrinsics.txt"] {
        std::os::unix::fs::symlink(scan_dir.join(entry), exact_dir.join(entry)).unwrap();
    }
    std::os::unix::fs::symlink(scan_dir.join("gt/pose"), exact_dir.join("pose")).unwrap();
    let scan = load(&scan_dir, &LoadOptions::default()).unwrap();
    let exact = load(&exact_dir, &LoadOptions::default()).unwrap();
    (scan_dir, scan, exact)
}

/// Root-mean-square reprojection error, pixels, of each frame's surface
/// points (placed by the exact pose and depth) seen through `poses`, once the
/// trajectory as a whole is aligned to the exact one (where the scene sits
/// as a whole is not what refinement can know); and the RMS rotation error.
fn rms_error(poses: &[IsometryMatrix3<f64>], exact: &Scan) -> (f64, f64) {
    let truth = exact.poses();
    let align = trajectory_alignment(poses, &truth, 0.7);
    let (mut px, mut count, mut rot) = (0.0, 0usize, 0.0);
    for (p, f) in poses.iter().zip(&exact.frames) {
        let pose = align * p;
        rot += pose_difference(&f.camera_to_world, &pose).1.powi(2);
        let (Some(depth), k) = (&f.depth, f.intrinsics) else {
            continue;
        };
        let world_to_camera = pose.inverse();
        for v in (0..depth.height).step_by(8) {
            for u in (0..depth.width).step_by(8) {
                let z = depth.get(u, v);
                if z <= 0.0 {
                    continue;
                }
                let world = f.camera_to_world * Point3::from(k.unproject(u as f64, v as f64) * z as f64);
                if let Some((x, y)) = k.project(&(world_to_camera * world)) {
                    px += (x - u as f64).powi(2) + (y - v as f64).powi(2);
                    count += 1;
                }
            }
        }
    }
    ((px / count.max(1) as f64).sqrt(), (rot / poses.len() as f64).sqrt())
}

#[test]
fn refinement_recovers_known_pose_perturbations() {
    let dir = tempfile::tempdir().unwrap();
    let (_, scan, exact) = perturbed_tabletop(dir.path(), 36, 0.006, 0.3);
    let (px0, deg0) = rms_error(&scan.poses(), &exact);
    let refined = refine_poses(&scan, &RefineOptions::default())
        .unwrap()
        .expect("the scan has depth");
    let (px1, deg1) = rms_error(&refined.camera_to_world, &exact);
    eprintln!("reprojection error {px0:.2} px, {deg0:.3} deg -> {px1:.2} px, {deg1:.3} deg");
    // Measured: 1.75 px, 0.32 deg -> 0.63 px, 0.14 deg.
    assert!(px1 < 0.45 * px0, "reprojection RMS error {px0:.2} px -> {px1:.2} px");
    assert!(deg1 < 0.55 * deg0, "rotation RMS error {deg0:.3} deg -> {deg1:.3} deg");
    assert!(
        refined.refined_count() * 10 >= scan.frames.len() * 9,
        "{} of {} frames refined",
        refined.refined_count(),
        scan.frames.len()
    );
    let (before, after) = refined.median_residuals();
    assert!(
        after < 0.5 * before,
        "median disagreement {:.2} mm -> {:.2} mm",
        before * 1e3,
        after * 1e3
    );
}

/// SLAM-like pose error (1 cm and 0.5 deg per frame, 2 cm slow drift) on a
/// realistic tabletop (JPEG colour, exposure drift, low-resolution noisy
/// depth): depth alone leaves groups of frames slid apart along the table;
/// aligning the frames to each other by colour removes that slide.
#[test]
fn colour_pins_what_depth_leaves_free_on_slam_like_poses() {
    let dir = tempfile::tempdir().unwrap();
    let mut options = FixtureOptions::new(SceneKind::Tabletop);
    (options.width, options.height, options.frames, options.seed) = (320, 240, Some(48), 4);
    options.corruptions = Corruptions {
        pose_sigma_m: 0.01,
        pose_sigma_deg: 0.5,
        pose_drift_m: 0.02,
        ..Corruptions::realistic()
    };
    let (_, scan, exact) = generate_with_exact_copy(dir.path(), &options);
    let depth_only = RefineOptions {
        align_colour: false,
        ..RefineOptions::default()
    };
    let (px0, _) = rms_error(&scan.poses(), &exact);
    let by_depth = refine_poses(&scan, &depth_only).unwrap().expect("the scan has depth");
    let (px_depth, _) = rms_error(&by_depth.camera_to_world, &exact);
    let by_both = refine_poses(&scan, &RefineOptions::default())
        .unwrap()
        .expect("the scan has depth");
    let (px_both, _) = rms_error(&by_both.camera_to_world, &exact);
    eprintln!("reprojection error {px0:.2} px; aligned to the depth {px_depth:.2} px; and by colour {px_both:.2} px");
    // Measured: 4.64 px; 2.51 px by depth alone; 0.09 px with colour.
    assert!(
        px_both < 0.25 * px_depth,
        "depth {px_depth:.2} px, and colour {px_both:.2} px"
    );
    assert!(px_both < 0.3, "reprojection RMS error {px_both:.2} px with colour");
}

/// `fit` refines by default, stores the poses in the model (which `label`
/// and `synth` then use) and reports each frame's correction;
/// `--no-pose-refine` keeps the captured poses.
#[test]
fn fit_stores_refined_poses_and_reports_them() {
    let dir = tempfile::tempdir().unwrap();
    let (scan_dir, scan, exact) = perturbed_tabletop(dir.path(), 24, 0.004, 0.2);
    let fit = |model: &Path, extra: &[&str]| {
        let out = Command::new(env!("CARGO_BIN_EXE_nerflabel"))
            .args([
                "fit",
                scan_dir.to_str().unwrap(),
                "--steps",
                "3",
                "--preset",
                "fast",
                "--holdout",
                "0",
                "--model",
            ])
            .arg(model)
            .args(extra)
            .output()
            .unwrap();
        assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
        String::from_utf8_lossy(&out.stderr).into_owned()
    };
    let refined_path = dir.path().join("refined.nlf");
    let stderr = fit(&refined_path, &[]);
    assert!(
        stderr.contains("aligned") && stderr.contains("poses to the depth and to each other by colour"),
        "{stderr}"
    );
    let model = Model::load(&refined_path).unwrap();
    let mut labelled = scan.clone();
    let changed = model.apply_fitted_poses(&mut labelled);
    assert!(
        changed * 10 >= scan.frames.len() * 9,
        "{changed} of {} poses changed",
        scan.frames.len()
    );
    let (px0, _) = rms_error(&scan.poses(), &exact);
    let (px1, _) = rms_error(&labelled.poses(), &exact);
    assert!(
        px1 < 0.7 * px0,
        "the model's poses: reprojection error {px0:.2} px -> {px1:.2} px"
    );
    let report: serde_json::Value =
        serde_json::from_slice(&std::fs::read(dir.path().join("refined.report.json")).unwrap()).unwrap();
    let corrections = report["pose_refinement"]["frames"]
        .as_array()
        .expect("the report lists the corrections");
    assert_eq!(corrections.len(), scan.frames.len());
    assert!(corrections
        .iter()
        .all(|c| c["translation_m"].as_f64().is_some_and(|t| t.is_finite() && t < 0.05)));
    // The model still belongs to the scan as captured.
    assert_eq!(model.matches_scan(&scan), nerflabel::nerf::model_file::ScanMatch::Same);

    let captured_path = dir.path().join("captured.nlf");
    let stderr = fit(&captured_path, &["--no-pose-refine"]);
    assert!(!stderr.contains("poses to the depth"), "{stderr}");
    let model = Model::load(&captured_path).unwrap();
    assert!(model.header.fitted_poses.is_none());
    let report: serde_json::Value =
        serde_json::from_slice(&std::fs::read(dir.path().join("captured.report.json")).unwrap()).unwrap();
    assert!(report.get("pose_refinement").is_none());
    assert!(report.get("pose_alignment").is_none());
    assert!(report.get("pose_learning").is_none());
}

/// How the number of rounds trades off (`cargo test --release --test
/// pose_refine -- --ignored --nocapture`): the error falls for two or three
/// rounds, then the trajectory wanders; refinement stops on its own.
#[test]
#[ignore]
fn sweep_rounds() {
    let dir = tempfile::tempdir().unwrap();
    let (_, scan, exact) = perturbed_tabletop(dir.path(), 36, 0.006, 0.3);
    for rounds in [0, 1, 2, 4, 8, 16, 32] {
        let refined = refine_poses(
            &scan,
            &RefineOptions {
                rounds,
                ..RefineOptions::default()
            },
        )
        .unwrap()
        .unwrap();
        let (px, deg) = rms_error(&refined.camera_to_world, &exact);
        let (before, after) = refined.median_residuals();
        eprintln!(
            "at most {rounds:>2} rounds: {px:.3} px, {deg:.3} deg; disagreement {:.3} -> {:.3} mm",
            before * 1e3,
            after * 1e3
        );
    }
}

/// A copy of `scan_dir` whose poses' camera positions are multiplied by
/// `factor` (native pose files: the translation column scales with them).
fn scaled_copy(scan_dir: &Path, out: &Path, factor: f64) {
    std::fs::create_dir_all(out.join("pose")).unwrap();
    for entry in ["rgb", "depth", "intrinsics.txt"] {
        std::os::unix::fs::symlink(scan_dir.join(entry), out.join(entry)).unwrap();
    }
    for file in std::fs::read_dir(scan_dir.join("pose")).unwrap() {
        let path = file.unwrap().path();
        let text = std::fs::read_to_string(&path).unwrap();
        let rows: Vec<String> = text
            .lines()
            .enumerate()
            .map(|(r, line)| {
                let mut v: Vec<f64> = line.split_whitespace().map(|x| x.parse().unwrap()).collect();
                if r < 3 {
                    v[3] *= factor;
                }
                v.iter().map(|x| format!("{x:.17}")).collect::<Vec<_>>().join(" ")
            })
            .collect();
        std::fs::write(out.join("pose").join(path.file_name().unwrap()), rows.join("\n") + "\n").unwrap();
    }
}

/// Poses known only up to scale: `info` says so with the factor, and `fit`
/// finds it within 1 % and fits in metres (boxes stay metric).
#[test]
fn up_to_scale_poses_are_found_and_made_metric() {
    let dir = tempfile::tempdir().unwrap();
    let (scan_dir, _, _) = perturbed_tabletop(dir.path(), 24, 0.0015, 0.075);
    for factor in [0.4, 2.5] {
        let scaled = dir.path().join(format!("scaled-{factor}"));
        scaled_copy(&scan_dir, &scaled, factor);
        let info = Command::new(env!("CARGO_BIN_EXE_nerflabel"))
            .args(["info", scaled.to_str().unwrap()])
            .output()
            .unwrap();
        let stdout = String::from_utf8_lossy(&info.stdout);
        assert!(stdout.contains("poses are up to scale"), "x{factor}: {stdout}");
        let model = scaled.join("model.nlf");
        let out = Command::new(env!("CARGO_BIN_EXE_nerflabel"))
            .args([
                "fit",
                scaled.to_str().unwrap(),
                "--steps",
                "2",
                "--preset",
                "fast",
                "--holdout",
                "0",
                "--model",
            ])
            .arg(&model)
            .output()
            .unwrap();
        assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
        let report: serde_json::Value =
            serde_json::from_slice(&std::fs::read(scaled.join("model.report.json")).unwrap()).unwrap();
        let applied = report["pose_scale"]["applied"]
            .as_f64()
            .expect("the report gives the applied scale");
        assert!((applied * factor - 1.0).abs() < 0.01, "x{factor}: applied {applied}");
    }
    // The metric original is left as it is.
    let info = Command::new(env!("CARGO_BIN_EXE_nerflabel"))
        .args(["info", scan_dir.to_str().unwrap()])
        .output()
        .unwrap();
    assert!(String::from_utf8_lossy(&info.stdout).contains("poses look metric"));
}

/// Regression: with poses off by centimetres (SLAM-like), too few planes
/// were found at any scale and `info` said no frame had depth. The rough
/// estimate stands instead, and says the poses are metric.
#[test]
fn centimetre_pose_error_still_gives_a_scale_verdict() {
    let dir = tempfile::tempdir().unwrap();
    let (_, scan, _) = perturbed_tabletop(dir.path(), 36, 0.02, 1.0);
    let e = nerflabel::poses::estimate_pose_scale(&scan)
        .unwrap()
        .expect("the scan has depth");
    assert!(
        e.looks_metric() && (e.scale - 1.0).abs() < 0.05,
        "{e:?}: {}",
        e.verdict()
    );
}

/// Part-way through the fit and at its end, the frames' images are aligned
/// to the field: on a scan whose depth alignment already leaves well under a
/// pixel, the poses the model stores stay as good (measured: 0.63 px RMS
/// aligned to the depth, 0.65 px stored), the report lists the passes with
/// each frame's correction, and most frames keep theirs. (That a known error
/// is undone is pinned by the unit tests of `nerf::train::photometric`.)
/// Fits the 36-frame tabletop with 6 mm / 0.3 deg pose error put in (400
/// steps, aligned to the depth only, `extra` flags added), checks that the poses the model stores are
/// about as good as those aligned to the depth (within 15 %), and returns
/// the fit's messages, its report and the scan's frame count.
fn fit_perturbed_tabletop(extra: &[&str]) -> (String, serde_json::Value, usize) {
    let dir = tempfile::tempdir().unwrap();
    let (scan_dir, scan, exact) = perturbed_tabletop(dir.path(), 36, 0.006, 0.3);
    let model_path = dir.path().join("model.nlf");
    let out = Command::new(env!("CARGO_BIN_EXE_nerflabel"))
        .args(["fit", scan_dir.to_str().unwrap(), "--steps", "400", "--seed", "1"])
        // Frames aligned to each other by colour skip the field passes.
        .arg("--no-colour-align")
        .args(extra)
        .arg("--model")
        .arg(&model_path)
        .output()
        .unwrap();
    let stderr = String::from_utf8_lossy(&out.stderr).to_string();
    assert!(out.status.success(), "{stderr}");
    let depth_only = RefineOptions {
        align_colour: false,
        ..RefineOptions::default()
    };
    let depth_aligned = refine_poses(&scan, &depth_only).unwrap().unwrap();
    let mut fitted = scan.clone();
    Model::load(&model_path).unwrap().apply_fitted_poses(&mut fitted);
    let (px_depth, _) = rms_error(&depth_aligned.camera_to_world, &exact);
    let (px_fitted, _) = rms_error(&fitted.poses(), &exact);
    eprintln!("reprojection RMS: aligned to the depth {px_depth:.2} px, stored {px_fitted:.2} px");
    assert!(px_fitted < 1.15 * px_depth, "{px_depth:.2} px -> {px_fitted:.2} px");
    let report = serde_json::from_slice(&std::fs::read(dir.path().join("model.report.json")).unwrap()).unwrap();
    (stderr, report, scan.frames.len())
}

#[test]
fn fit_aligns_the_images_to_the_field() {
    let (stderr, report, frame_count) = fit_perturbed_tabletop(&[]);
    assert!(stderr.contains("images to the field"), "{stderr}");
    let passes = report["pose_alignment"]
        .as_array()
        .expect("the report lists the passes");
    // One to four passes part-way (training frames), one at the end (every
    // frame); a pass part-way follows another only if that one moved at
    // least a quarter of its frames by over a pixel.
    assert!((2..=5).contains(&passes.len()), "{} passes", passes.len());
    let last = passes.len() - 1;
    for (i, pass) in passes[..last].iter().enumerate() {
        let aligned = pass["frames_aligned"].as_u64().unwrap();
        assert!(aligned < frame_count as u64);
        let moved = pass["frames"]
            .as_array()
            .unwrap()
            .iter()
            .filter(|f| f["refined"] == true && f["shift_px"].as_f64().unwrap() > 1.0)
            .count() as u64;
        if i + 1 < last {
            assert!(
                4 * moved >= aligned,
                "pass {i} moved {moved} of {aligned} frames, yet another followed"
            );
        }
    }
    let frames = passes[last]["frames"]
        .as_array()
        .expect("the pass lists the corrections");
    assert_eq!(frames.len(), frame_count);
    // Learning the poses with the field is asked for with --learn-poses.
    assert!(report.get("pose_learning").is_none());
    // No correction beyond twice the error put in (6 mm RMS; measured:
    // largest 10.2 mm, most under 5 mm).
    assert!(frames
        .iter()
        .all(|f| f["translation_m"].as_f64().is_some_and(|t| t < 0.012)));
}

/// With `--learn-poses` the training frames' poses also learn with the
/// field: the report lists every training frame's learnt correction, none
/// beyond twice the error put in, and the stored poses are about as good as
/// those aligned to the depth (measured: 0.63 px -> 0.67 px RMS; largest
/// learnt correction 3.4 mm).
#[test]
fn fit_learns_the_poses_with_the_field_when_asked() {
    let (stderr, report, _) = fit_perturbed_tabletop(&["--learn-poses"]);
    assert!(stderr.contains("poses with the field"), "{stderr}");
    let learnt = report["pose_learning"]["frames"]
        .as_array()
        .expect("the report lists the poses learnt with the field");
    assert_eq!(learnt.len() as u64, report["train_frames"].as_u64().unwrap());
    let largest = learnt
        .iter()
        .map(|f| f["translation_m"].as_f64().unwrap())
        .fold(0.0, f64::max);
    assert!(largest < 0.012, "a frame learnt a {:.1} mm correction", largest * 1e3);
}
