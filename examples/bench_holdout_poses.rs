//! Held-out error of a model with the held-out frames posed two ways: as the
//! fit scores them while it trains (poses aligned to the depth only, never
//! to the field) and as the model stores them (the fit's last pass aligns
//! every frame, held-out ones too, to the final field, as BARF aligns test
//! poses before scoring). The gap tells how much of a held-out PSNR is the
//! held-out poses rather than the field.
//!
//! Run: `cargo run --release --example bench_holdout_poses -- SCAN MODEL [HOLDOUT_EVERY]`

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
        maps.as_deref(),
    );
    Ok((v.psnr, v.ssim, v.depth_mae_m.unwrap_or(f64::NAN) * 1e3))
}
