//! Error against run time of `fit` on the generated tabletop fixture
//! (640x480, 120 frames, 4 objects): the held-out curve measured during
//! training, then the final model scored against the exact ground truth.
//!
//! cargo run --release --example bench_fit -- [FIXTURE_DIR] [--time SECS | --steps N] [--preset P] [--seed N]

use nerflabel::evaluate::score_holdout;
use nerflabel::fixture::{generate, FixtureOptions, SceneKind};
use nerflabel::nerf::train::dataset::is_holdout;
use nerflabel::nerf::train::fit::{fit, FitEvent, FitOptions};
use nerflabel::nerf::train::settings::FitSettings;
use nerflabel::nerf::train::settings::Preset;
use nerflabel::nerf::train::step::PhaseSeconds;
use nerflabel::scan::{load, LoadOptions};
use std::path::PathBuf;
use std::sync::atomic::AtomicBool;

fn main() -> anyhow::Result<()> {
    let mut args = std::env::args().skip(1);
    let mut dir = PathBuf::from("target/bench/tabletop");
    let (mut time, mut steps, mut preset, mut seed) = (Some(120.0), None, Preset::Default, 0u64);
    while let Some(a) = args.next() {
        match a.as_str() {
            "--time" => time = Some(args.next().unwrap_or_default().parse()?),
            "--steps" => {
                steps = Some(args.next().unwrap_or_default().parse()?);
                time = None;
            }
            "--preset" => {
                preset =
                    clap::ValueEnum::from_str(&args.next().unwrap_or_default(), true).map_err(anyhow::Error::msg)?
            }
            "--seed" => seed = args.next().unwrap_or_default().parse()?,
            other => dir = PathBuf::from(other),
        }
    }
    if !dir.join("gt").join("meta.json").exists() {
        let options = FixtureOptions::new(SceneKind::Tabletop);
        generate(&dir, &options)?;
        println!("generated the tabletop fixture in {}", dir.display());
    }
    let mut scan = load(&dir, &LoadOptions::default())?;
    let options = FitOptions {
        settings: FitSettings {
            seed,
            preset,
            ..FitSettings::default()
        },
        time,
        steps,
        ..FitOptions::default()
    };
    let stop = AtomicBool::new(false);
    // Where training time goes, summed over every step.
    let mut phases = PhaseSeconds::default();
    let (mut samples, mut train_s) = (0usize, 0.0f64);
    let outcome = fit(&mut scan, &options, &stop, &mut |e| {
        if let FitEvent::Step {
            stats, train_seconds, ..
        } = e
        {
            phases.add(&stats.phases);
            samples += stats.samples;
            train_s = train_seconds;
        }
        if let FitEvent::Eval(p) = e {
            eprintln!(
                "  {:6.1} s  step {:5}  PSNR {:5.2}  depth MAE {:?}",
                p.seconds, p.step, p.psnr, p.depth_mae_m
            );
        }
    })?;
    let r = &outcome.report;
    println!(
        "threads {}  params {}  steps {}  skipped {}  samples/ray {:.1}  rays/step {:.0}  finest res {}",
        r.threads,
        r.param_count,
        r.counters.steps,
        r.counters.skipped_batches,
        r.counters.samples as f64 / r.counters.rays.max(1) as f64,
        r.counters.rays as f64 / r.counters.steps.max(1) as f64,
        r.field.grid.finest_resolution
    );
    println!("| seconds | step | PSNR (dB) | SSIM | depth MAE (mm) | samples/s |");
    println!("|---|---|---|---|---|---|");
    for p in &r.curve {
        println!(
            "| {:.0} | {} | {:.2} | {:.3} | {} | {:.0} k |",
            p.seconds,
            p.step,
            p.psnr,
            p.ssim,
            p.depth_mae_m
                .map(|d| format!("{:.1}", d * 1e3))
                .unwrap_or_else(|| "n/a".into()),
            p.samples_per_s / 1e3
        );
    }
    outcome.model.save(&dir.join("nerflabel").join("model.nlf"))?;
    let score = score_holdout(&outcome.model, &dir)?;
    println!(
        "exact ground truth, {} held-out views: PSNR {:.2} dB, SSIM {:.3}, depth MAE {:.1} mm, missing surface {:.2} %",
        score.views,
        score.psnr,
        score.ssim,
        score.depth_mae_m * 1e3,
        score.depth_missing * 100.0
    );
    println!("timings: {:?}", r.timings);
    let total = phases.total().max(1e-9);
    println!(
        "training throughput: {:.0} k samples/s over {:.1} s of training ({} threads); share of thread time: \
         marching {:.0} %, hash grid {:.0} %, MLPs {:.0} %, compositing and losses {:.0} %, optimiser update {:.0} %",
        samples as f64 / train_s.max(1e-9) / 1e3,
        train_s,
        r.threads,
        100.0 * phases.march / total,
        100.0 * phases.grid / total,
        100.0 * phases.mlp / total,
        100.0 * phases.composite / total,
        100.0 * phases.update / total,
    );
    let c = &r.counters;
    let with_depth = (c.rays - c.rays_without_depth).max(1) as f64;
    println!(
        "rays with depth: {:.1} samples each; without depth ({:.0} % of rays): {:.1} samples each",
        (c.samples - c.samples_without_depth) as f64 / with_depth,
        100.0 * c.rays_without_depth as f64 / c.rays.max(1) as f64,
        c.samples_without_depth as f64 / c.rays_without_depth.max(1) as f64
    );
    if let Some(floor) = sensor_noise_floor(&scan, &dir, options.settings.holdout_every)? {
        println!(
            "sensor depth vs exact depth on the same held-out frames (the floor of the depth MAE above): {:.1} mm",
            floor * 1e3
        );
    }
    Ok(())
}

/// Mean absolute difference between the held-out frames' sensor depth and the
/// fixture's exact depth where both exist: a perfect model still shows this
/// error when scored against the sensor.
fn sensor_noise_floor(
    scan: &nerflabel::scan::Scan,
    dir: &std::path::Path,
    every: usize,
) -> anyhow::Result<Option<f64>> {
    let meta: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(dir.join("gt/meta.json"))?)?;
    let Some(unit) = meta["gt_depth_unit_m"].as_f64() else {
        return Ok(None);
    };
    let (mut sum, mut n) = (0.0, 0usize);
    for (_, frame) in scan.frames.iter().enumerate().filter(|(i, _)| is_holdout(*i, every)) {
        let Some(sensor) = &frame.depth else { continue };
        let exact = image::open(dir.join("gt/depth").join(format!("{}.png", frame.name)))?.into_luma16();
        for (x, y, t) in exact.enumerate_pixels() {
            let (t, s) = (t.0[0] as f64 * unit, sensor.get(x, y) as f64);
            if t > 0.0 && s > 0.0 {
                sum += (s - t).abs();
                n += 1;
            }
        }
    }
    Ok((n > 0).then(|| sum / n as f64))
}
