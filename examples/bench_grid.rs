//! Hash grid throughput: encode and encode+backward samples/s for the small
//! fixture's grid (2.4 MiB, in cache) and for a 640x480 scan's (31 MiB, far
//! beyond it), on uniformly random positions and on points along
//! rays (the access pattern of training): one thread, SIMD and scalar, then
//! two threads splitting the levels (`encode_levels` / `backward_levels`).
//! Last, the time to build an occupancy grid for rendering (its bits, group
//! bits and group distances) at 128 / 256 / 512 cells per axis.
//!
//! Run: `cargo run --release --example bench_grid`

use nerflabel::nerf::field::hash_grid::{GridGrad, HashGrid, HashGridConfig};
use nerflabel::nerf::field::simd::grid as simd;
use nerflabel::nerf::occupancy::OccupancyGrid;
use nerflabel::rng::Rng;
use std::time::Instant;

/// Samples per encode/backward call (a training chunk of one thread).
const CHUNK: usize = 16_384;
/// Samples per pass.
const TOTAL: usize = 32 * CHUNK;
/// Levels given to the first of two threads (coarse levels are cheaper).
const SPLIT: usize = 4;
/// Samples per ray for the coherent pattern.
const PER_RAY: usize = 64;

fn random_positions(rng: &mut Rng) -> Vec<[f32; 3]> {
    (0..TOTAL).map(|_| [rng.f32(), rng.f32(), rng.f32()]).collect()
}

/// Points along random rays: 64 samples 1/160 apart (~1.25 cm in a 2 m cube)
/// around a random point, in ray order.
fn ray_positions(rng: &mut Rng) -> Vec<[f32; 3]> {
    let mut out = Vec::with_capacity(TOTAL);
    while out.len() < TOTAL {
        let mid = [0.2 + 0.6 * rng.f32(), 0.2 + 0.6 * rng.f32(), 0.2 + 0.6 * rng.f32()];
        let d = [rng.normal() as f32, rng.normal() as f32, rng.normal() as f32];
        let norm = (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt().max(1e-6);
        let step = 1.0 / 160.0;
        for k in 0..PER_RAY {
            let t = (k as f32 - PER_RAY as f32 / 2.0) * step;
            out.push(std::array::from_fn(|a| mid[a] + t * d[a] / norm));
        }
    }
    out.truncate(TOTAL);
    out
}

/// Samples per second of `run` (one call per chunk), from the fastest and
/// the median chunk over 5 passes. On a shared machine the fastest chunk is
/// the uncontended figure; the median shows what contention costs.
fn rates(pos: &[[f32; 3]], mut run: impl FnMut(&[[f32; 3]])) -> (f64, f64) {
    let mut times: Vec<f64> = Vec::with_capacity(5 * pos.len() / CHUNK);
    for _ in 0..5 {
        for chunk in pos.chunks(CHUNK) {
            let t = Instant::now();
            run(chunk);
            times.push(t.elapsed().as_secs_f64());
        }
    }
    times.sort_by(f64::total_cmp);
    (CHUNK as f64 / times[0], CHUNK as f64 / times[times.len() / 2])
}

fn main() {
    // The small fixture's grid (fits in cache) and a 640x480 scan's (finest
    // resolution 695, as the realistic tabletop: tables far beyond cache).
    for (name, cell) in [
        ("small fixture (2 m, 1.5 cm)", 0.015),
        ("640x480 scan (2 m, finest 695)", 2.0 / 695.0),
    ] {
        grid_rates(name, HashGridConfig::for_scene(2.0, cell));
    }
    occupancy_build_times();
}

/// Encode and backward rates of one grid, on one thread and on two.
fn grid_rates(name: &str, config: HashGridConfig) {
    let grid = HashGrid::new(config, &mut Rng::new(1, 0));
    let dim = grid.output_dim();
    println!("{name}: {config:?}");
    for (l, level) in grid.levels().iter().enumerate() {
        let kind = if level.dense { "dense" } else { "hashed" };
        println!(
            "  level {l}: res {:4} {kind:6} {:7} entries",
            level.resolution, level.entries
        );
    }
    println!(
        "  {} params ({:.1} MiB), output dim {dim}, AVX2 kernels: {}",
        grid.param_count(),
        grid.param_count() as f64 * 4.0 / 1048576.0,
        simd::available()
    );

    let mut rng = Rng::new(2, 0);
    let mut d_rng = Rng::new(3, 0);
    let d_out: Vec<f32> = (0..CHUNK * dim).map(|_| d_rng.f32() - 0.5).collect();
    let mut out = vec![0.0f32; CHUNK * dim];
    let mut grad = GridGrad::new(grid.param_count());
    println!("\n1 thread, {CHUNK} samples per call, Msamples/s as fastest chunk (median chunk):");
    println!(
        "{:<10} {:<7} {:>16} {:>16} {:>18}  touched params/chunk",
        "positions", "path", "encode", "backward", "encode+backward"
    );
    for (name, pos) in [
        ("random", random_positions(&mut rng)),
        ("rays", ray_positions(&mut rng)),
    ] {
        for simd in [true, false] {
            let enc = rates(&pos, |chunk| grid.encode_with(chunk, &mut out, simd));
            let bwd = rates(&pos, |chunk| {
                grid.backward_with(chunk, &d_out, &mut grad, simd);
                grad.clear();
            });
            let both = rates(&pos, |chunk| {
                grid.encode_with(chunk, &mut out, simd);
                grid.backward_with(chunk, &d_out, &mut grad, simd);
                grad.clear();
            });
            grid.backward_with(&pos[..CHUNK], &d_out, &mut grad, simd);
            let touched = grad.touched_count();
            grad.clear();
            let path = if simd { "avx2" } else { "scalar" };
            let fmt = |(best, median): (f64, f64)| format!("{:.2} ({:.2})", best / 1e6, median / 1e6);
            println!(
                "{name:<10} {path:<7} {:>16} {:>16} {:>18}  {touched}",
                fmt(enc),
                fmt(bwd),
                fmt(both)
            );
        }
    }

    // Two threads, each owning a contiguous range of levels and its own gradient buffer.
    let split = SPLIT.min(grid.levels().len());
    let rows = split * config.features_per_level * CHUNK;
    let levels = grid.levels().len();
    let mut other = GridGrad::new(grid.param_count());
    println!("\n2 threads (levels 0..{split} | {split}..{levels}), AVX2, Msamples/s as fastest chunk (median chunk):");
    println!("{:<10} {:>16} {:>18}", "positions", "encode", "encode+backward");
    for (name, pos) in [
        ("random", random_positions(&mut rng)),
        ("rays", ray_positions(&mut rng)),
    ] {
        let fmt = |(best, median): (f64, f64)| format!("{:.2} ({:.2})", best / 1e6, median / 1e6);
        let (d_a, d_b) = d_out.split_at(rows);
        let enc = rates(&pos, |chunk| {
            let (a, b) = out.split_at_mut(rows);
            rayon::join(
                || grid.encode_levels(chunk, 0..split, a),
                || grid.encode_levels(chunk, split..levels, b),
            );
        });
        let both = rates(&pos, |chunk| {
            let (a, b) = out.split_at_mut(rows);
            let (ga, gb) = (&mut grad, &mut other);
            rayon::join(
                || {
                    grid.encode_levels(chunk, 0..split, a);
                    grid.backward_levels(chunk, 0..split, d_a, ga);
                    ga.clear();
                },
                || {
                    grid.encode_levels(chunk, split..levels, b);
                    grid.backward_levels(chunk, split..levels, d_b, gb);
                    gb.clear();
                },
            );
        });
        println!("{name:<10} {:>16} {:>18}", fmt(enc), fmt(both));
    }
    println!();
}

/// Milliseconds to build a rendering occupancy grid (`from_occupied_bits`:
/// group bits and group distances) from a shell of surfaces filling about
/// 1 % of the cells, as a scanned room does; fastest of 5.
fn occupancy_build_times() {
    println!("\noccupancy grid build (from_occupied_bits), fastest of 5:");
    for res in [128usize, 256, 512] {
        let cells = res * res * res;
        let mut bits = vec![0u64; cells.div_ceil(64)];
        let shell = 0.5 / res as f32;
        for cell in 0..cells {
            let p = [cell % res, (cell / res) % res, cell / (res * res)].map(|i| (i as f32 + 0.5) / res as f32 - 0.5);
            let wall = p.iter().any(|v| (v.abs() - 0.45).abs() < shell);
            let ball = ((p[0] * p[0] + p[1] * p[1] + p[2] * p[2]).sqrt() - 0.2).abs() < shell;
            if wall || ball {
                bits[cell >> 6] |= 1 << (cell & 63);
            }
        }
        let mut best = f64::INFINITY;
        let mut occupied = 0.0;
        for _ in 0..5 {
            let input = bits.clone();
            let t = Instant::now();
            let grid = OccupancyGrid::from_occupied_bits(res, input).expect("sizes match");
            best = best.min(t.elapsed().as_secs_f64());
            occupied = grid.occupied_fraction();
        }
        println!(
            "  res {res:3}: {:7.1} ms ({:.2} % of cells occupied)",
            best * 1e3,
            occupied * 100.0
        );
    }
}
