//! Held-out error of a model with the held-out frames posed two ways: as the
//! fit scores them while it trains (poses aligned to the depth only, never
//! to the field) and as the model stores them (the fit's last pass aligns
//! every frame, held-out ones too, to the final field, as BARF aligns test
//! poses before scoring). The gap tells how much of a held-out PSNR is the
//! held-out poses rather than the field. It also prints how the stored
//! poses differ from the depth-aligned ones in each camera's own frame
//! (x right, y down, z forward): a mean far from zero is a motion all
//! cameras share in their own frame, which no rigid move of the scene
//! explains (a colour image registered off its depth turns every camera
//! the same way).
//!
//! Run: `cargo run --release --example bench_holdout_poses -- SCAN MODEL [HOLDOUT_EVERY]`

use nerflabel::nerf::appearance::NO_VIGNETTING;
use nerflabel::nerf::model_file::Model;
use nerflabel::nerf::train::dataset;
use nerflabel::nerf::train::validation::validate;
use nerflabel::poses::{refine_poses, RefineOptions};
use nerflabel::scan::{load, LoadOptions, Scan};

type Error = Box<dyn std::error::Error>;

fn main() -> Result<(), Error> {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let (scan_dir, model_path, every) = match args.as_slice() {
        [scan, model] => (scan, model, 10),
        [scan, model, every] => (scan, model, every.parse()?),
        _ => return Err("usage: bench_holdout_poses SCAN MODEL [HOLDOUT_EVERY]".into()),
    };
    let captured = load(std::path::Path::new(scan_dir), &LoadOptions::default())?;
    let model = Model::load(std::path::Path::new(model_path))?;
    let mut depth_aligned = captured.clone();
    if let Some(r) = refine_poses(&captured, &RefineOptions::default())? {
        depth_aligned.set_poses(&r.camera_to_world);
    }
    let mut stored = captured.clone();
    model.apply_fitted_poses(&mut stored);
    print_camera_frame_motion(&depth_aligned, &stored);
    println!("| held-out poses | PSNR dB | SSIM | depth MAE mm |");
    println!("|---|---|---|---|");
    for (name, scan) in [
        ("aligned to the depth (as the fit scores them)", &depth_aligned),
        ("stored in the model (aligned to the final field)", &stored),
    ] {
        let (psnr, ssim, mae) = score(&model, scan, every)?;
        println!("| {name} | {psnr:.2} | {ssim:.3} | {mae:.1} |");
    }
    Ok(())
}

/// Mean and RMS over frames of each stored pose's motion from the
/// depth-aligned one, in the depth-aligned camera's frame.
fn print_camera_frame_motion(depth_aligned: &Scan, stored: &Scan) {
    let motions: Vec<[f64; 6]> = depth_aligned
        .poses()
        .iter()
        .zip(stored.poses())
        .map(|(d, s)| {
            let relative = d.inverse() * s;
            let (t, r) = (relative.translation.vector * 1e3, relative.rotation.scaled_axis());
            [t.x, t.y, t.z, r.x.to_degrees(), r.y.to_degrees(), r.z.to_degrees()]
        })
        .collect();
    let n = motions.len().max(1) as f64;
    let mean = |k: usize| motions.iter().map(|m| m[k]).sum::<f64>() / n;
    let rms = |k: usize| (motions.iter().map(|m| m[k] * m[k]).sum::<f64>() / n).sqrt();
    println!(
        "stored poses against the depth-aligned ones, camera frame (x right, y down, z forward), mean / RMS over {} frames:",
        motions.len()
    );
    println!(
        "  translation mm: x {:.2} / {:.2}, y {:.2} / {:.2}, z {:.2} / {:.2}",
        mean(0),
        rms(0),
        mean(1),
        rms(1),
        mean(2),
        rms(2)
    );
    println!(
        "  rotation deg about: x {:.3} / {:.3}, y {:.3} / {:.3}, z {:.3} / {:.3}",
        mean(3),
        rms(3),
        mean(4),
        rms(4),
        mean(5),
        rms(5)
    );
}

fn score(model: &Model, scan: &Scan, every: usize) -> Result<(f64, f64, f64), Error> {
    let transform = model.scene_transform()?;
    let data = dataset::build(scan, &transform, every);
    let render = model.render_options(true);
    let maps = model
        .header
        .appearance
        .as_ref()
        .map(|all| data.holdout_frames.iter().map(|&i| all[i]).collect::<Vec<_>>());
    let v = validate(
        &model.field,
        &model.occupancy,
        &render,
        &data.holdout,
        1.0 / transform.scale(),
        u32::MAX,
        maps.as_deref()
            .map(|m| (m, model.header.vignetting.as_ref().unwrap_or(&NO_VIGNETTING))),
    );
    Ok((v.psnr, v.ssim, v.depth_mae_m.unwrap_or(f64::NAN) * 1e3))
}
