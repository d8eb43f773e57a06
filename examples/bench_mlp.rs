//! Single-thread throughput of the fused MLP against the machine's FMA peak.
//!
//! `cargo run --release --example bench_mlp [seconds_per_case]`
//!
//! Prints the measured FMA peak, then for the density (32->64->16) and colour
//! (32->64->64->3) networks at n = 4096: forward+backward (with d_input)
//! GFLOP/s and its share of the peak, forward-only GFLOP/s, and the portable
//! kernel for comparison; then forward+backward at other batch sizes.
//! Each figure is from the best single call, with the median in brackets:
//! on a shared machine the best call is the one that ran undisturbed.

use std::hint::black_box;
use std::time::Instant;

use nerflabel::nerf::field::mlp::{Mlp, MlpConfig, MlpKernel, MlpWorkspace};
use nerflabel::nerf::field::simd;
use nerflabel::rng::Rng;

/// Best and median seconds of one call of `f` over about `budget` seconds.
fn time_calls(budget: f64, mut f: impl FnMut()) -> (f64, f64) {
    f();
    let start = Instant::now();
    let mut times = Vec::new();
    while times.len() < 3 || start.elapsed().as_secs_f64() < budget {
        let t = Instant::now();
        f();
        times.push(t.elapsed().as_secs_f64());
    }
    times.sort_by(f64::total_cmp);
    (times[0], times[times.len() / 2])
}

/// GFLOP/s from the best and the median call.
#[derive(Clone, Copy)]
struct Rate {
    best: f64,
    median: f64,
}

impl Rate {
    fn new(flops: f64, (best, median): (f64, f64)) -> Rate {
        Rate {
            best: flops / best * 1e-9,
            median: flops / median * 1e-9,
        }
    }

    fn show(self, peak: f64) -> String {
        let pct = if peak > 0.0 { 100.0 * self.best / peak } else { f64::NAN };
        format!("{:6.1} ({:5.1}) {:5.1}%", self.best, self.median, pct)
    }
}

/// (forward+backward, forward only) rates of `mlp` at batch size `n`.
fn measure(mlp: &Mlp, n: usize, budget: f64) -> (Rate, Rate) {
    let mut rng = Rng::new(1, 0);
    let c = &mlp.config;
    let input: Vec<f32> = (0..c.input * n).map(|_| rng.f32()).collect();
    let d_out: Vec<f32> = (0..c.output * n).map(|_| rng.f32() - 0.5).collect();
    let mut out = vec![0.0; c.output * n];
    let mut d_in = vec![0.0; c.input * n];
    let mut grad = vec![0.0; mlp.param_count()];
    let mut ws = MlpWorkspace::new();
    let train = time_calls(budget, || {
        mlp.forward_train(&input, n, &mut ws, &mut out);
        mlp.backward(&mut ws, &d_out, n, &mut grad, Some(&mut d_in));
        black_box((&out, &grad, &d_in));
    });
    let forward = time_calls(budget / 2.0, || {
        mlp.forward(&input, n, &mut ws, &mut out);
        black_box(&out);
    });
    let f = (mlp.flops_forward_per_sample() * n) as f64;
    let b = (mlp.flops_backward_per_sample() * n) as f64;
    (Rate::new(f + b, train), Rate::new(f, forward))
}

fn main() {
    let budget: f64 = std::env::args().nth(1).and_then(|s| s.parse().ok()).unwrap_or(1.0);
    let peak = simd::measure_fma_peak_gflops(budget);
    println!("AVX2+FMA available: {}", simd::avx2_fma_available());
    println!("FMA peak, 1 thread, register-only loop: {peak:.1} GFLOP/s");
    println!("1 thread; GFLOP/s of the best call (median call), % of peak from the best call;");
    println!("backward includes d_input; fwd+bwd FLOPs = 3 x forward.");
    let nets = [
        (
            "density 32->64->16",
            MlpConfig {
                input: 32,
                hidden: vec![64],
                output: 16,
            },
        ),
        (
            "colour 32->64->64->3",
            MlpConfig {
                input: 32,
                hidden: vec![64, 64],
                output: 3,
            },
        ),
    ];
    println!("\nn = 4096");
    println!("{:<22} {:<9} {:<24} {:<24}", "network", "kernel", "fwd+bwd", "fwd only");
    for (name, config) in &nets {
        let mut mlp = Mlp::new(config.clone(), &mut Rng::new(7, 0));
        for kernel in [MlpKernel::best(), MlpKernel::Scalar] {
            if mlp.set_kernel(kernel) != kernel {
                continue;
            }
            let share = if kernel == MlpKernel::Scalar { 0.5 } else { 1.0 };
            let (train, fwd) = measure(&mlp, 4096, budget * share);
            println!(
                "{name:<22} {:<9} {:<24} {:<24}",
                kernel.name(),
                train.show(peak),
                fwd.show(peak)
            );
        }
    }
    println!("\nfwd+bwd by batch size ({})", MlpKernel::best().name());
    println!(
        "{:<22} {:<24} {:<24} {:<24}",
        "network", "n = 1024", "n = 16384", "n = 1000 (tail)"
    );
    for (name, config) in &nets {
        let mlp = Mlp::new(config.clone(), &mut Rng::new(7, 0));
        let row: Vec<String> = [1024, 16384, 1000]
            .iter()
            .map(|&n| measure(&mlp, n, budget * 0.5).0.show(peak))
            .collect();
        println!("{name:<22} {:<24} {:<24} {:<24}", row[0], row[1], row[2]);
    }
}
