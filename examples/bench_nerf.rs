//! One-run performance figures of the NeRF core on this machine:
//! FMA peak, fused MLP forward+backward GFLOP/s (share of peak), hash-grid
//! encode+backprop samples/s, whole training step samples/s and depth-only
//! rendering samples/s (both threads), on the committed small fixture.
//!
//! cargo run --release --example bench_nerf

use nerflabel::nerf::field::hash_grid::{GridGrad, HashGrid, HashGridConfig};
use nerflabel::nerf::field::mlp::{Mlp, MlpConfig, MlpWorkspace};
use nerflabel::nerf::field::simd;
use nerflabel::nerf::render::rays::render_pixels;
use nerflabel::nerf::render::view::ViewRenderer;
use nerflabel::nerf::train::fit::{fit, FitOptions};
use nerflabel::nerf::train::settings::FitSettings;
use nerflabel::rng::Rng;
use std::sync::atomic::AtomicBool;
use std::time::Instant;

fn best_of<F: FnMut()>(reps: usize, mut f: F) -> f64 {
    (0..reps)
        .map(|_| {
            let t = Instant::now();
            f();
            t.elapsed().as_secs_f64()
        })
        .fold(f64::INFINITY, f64::min)
}

fn main() -> anyhow::Result<()> {
    let mut rng = Rng::new(0, 0);
    let peak = simd::measure_fma_peak_gflops(0.5);
    println!("AVX2+FMA available: {}", simd::avx2_fma_available());
    println!("FMA peak, 1 thread: {peak:.1} GFLOP/s");

    let n = 4096;
    for (name, cfg) in [
        (
            "density 32-64-16",
            MlpConfig {
                input: 32,
                hidden: vec![64],
                output: 16,
            },
        ),
        (
            "colour 32-64-64-3",
            MlpConfig {
                input: 32,
                hidden: vec![64, 64],
                output: 3,
            },
        ),
    ] {
        let mlp = Mlp::new(cfg.clone(), &mut rng);
        let input: Vec<f32> = (0..cfg.input * n).map(|_| rng.f32() - 0.5).collect();
        let d_out: Vec<f32> = (0..cfg.output * n).map(|_| rng.f32() - 0.5).collect();
        let mut out = vec![0.0; cfg.output * n];
        let mut d_in = vec![0.0; cfg.input * n];
        let mut grad = vec![0.0; mlp.param_count()];
        let mut ws = MlpWorkspace::new();
        let secs = best_of(30, || {
            mlp.forward_train(&input, n, &mut ws, &mut out);
            mlp.backward(&mut ws, &d_out, n, &mut grad, Some(&mut d_in));
        });
        let flops = (mlp.flops_forward_per_sample() + mlp.flops_backward_per_sample()) as f64 * n as f64;
        let gflops = flops / secs / 1e9;
        println!(
            "MLP {name} fwd+bwd, n={n}, 1 thread: {gflops:.1} GFLOP/s = {:.0} % of peak",
            100.0 * gflops / peak
        );
    }

    let grid = HashGrid::new(HashGridConfig::for_scene(2.0, 0.015), &mut rng);
    let m = 16384;
    let pos: Vec<[f32; 3]> = (0..m).map(|_| [rng.f32(), rng.f32(), rng.f32()]).collect();
    let mut enc = vec![0.0; grid.output_dim() * m];
    let d_enc: Vec<f32> = (0..grid.output_dim() * m).map(|_| rng.f32() - 0.5).collect();
    let mut g = GridGrad::new(grid.param_count());
    let secs = best_of(20, || {
        grid.encode(&pos, &mut enc);
        grid.backward(&pos, &d_enc, &mut g);
        g.clear();
    });
    println!(
        "hash grid encode+backward (tabletop size, random points), 1 thread: {:.2} M samples/s",
        m as f64 / secs / 1e6
    );

    let fixture = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("fixtures/small");
    let mut scan = nerflabel::scan::load(&fixture, &Default::default())?;
    let options = FitOptions {
        settings: FitSettings {
            holdout_every: 0,
            ..FitSettings::default()
        },
        steps: Some(200),
        time: None,
        ..FitOptions::default()
    };
    let outcome = fit(&mut scan, &options, &AtomicBool::new(false), &mut |_| {})?;
    let r = &outcome.report;
    println!(
        "training step ({} threads, {} samples/step): {:.0} k samples/s over {} steps ({:.1} samples/ray)",
        r.threads,
        r.train.samples_per_step,
        r.counters.samples as f64 / r.timings.train_s / 1e3,
        r.counters.steps,
        r.counters.samples as f64 / r.counters.rays.max(1) as f64
    );
    let renderer = ViewRenderer::new(&outcome.model)?;
    let frame = &scan.frames[0];
    let (w, h) = frame.size();
    let cam = renderer.local_camera(&frame.camera_to_world, &frame.intrinsics, w, h);
    let pixels: Vec<(f32, f32)> = (0..h).flat_map(|v| (0..w).map(move |u| (u as f32, v as f32))).collect();
    let opts = outcome.model.render_options(false);
    let mut samples = 0u64;
    let secs = best_of(5, || {
        let out = render_pixels(&outcome.model.field, &outcome.model.occupancy, &opts, &cam, &pixels);
        samples = out.iter().map(|o| o.samples as u64).sum();
    });
    println!(
        "depth-only rendering ({} threads): {:.2} M samples/s, {:.0} k rays/s",
        rayon::current_num_threads(),
        samples as f64 / secs / 1e6,
        pixels.len() as f64 / secs / 1e3
    );
    Ok(())
}
