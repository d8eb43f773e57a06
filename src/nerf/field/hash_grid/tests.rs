//! Tests of the hash grid against a plain per-sample reference, finite
//! differences, the SIMD kernels and the gradient buffer's bookkeeping.

use super::*;
use crate::nerf::field::simd::grid as simd;

/// Grid with parameters U(-1, 1) so outputs are far from rounding noise.
fn grid(config: HashGridConfig, seed: u64) -> HashGrid {
    let mut rng = Rng::new(seed, 1);
    let params = (0..config.param_count()).map(|_| rng.f32() * 2.0 - 1.0).collect();
    HashGrid::from_params(config, params).expect("valid test grid")
}

fn positions(n: usize, seed: u64) -> Vec<[f32; 3]> {
    let mut rng = Rng::new(seed, 2);
    (0..n).map(|_| [rng.f32(), rng.f32(), rng.f32()]).collect()
}

/// Points along random rays, 48 per ray and 1/200 apart, in ray order: many
/// consecutive samples share a cell (the pattern training produces).
fn ray_positions(n: usize, seed: u64) -> Vec<[f32; 3]> {
    let mut rng = Rng::new(seed, 3);
    let mut out = Vec::with_capacity(n);
    while out.len() < n {
        let mid = [rng.f32(), rng.f32(), rng.f32()];
        let d = [rng.normal() as f32, rng.normal() as f32, rng.normal() as f32];
        let norm = (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt().max(1e-6);
        for k in 0..48 {
            let t = (k as f32 - 24.0) / 200.0;
            out.push(std::array::from_fn(|a| mid[a] + t * d[a] / norm));
        }
    }
    out.truncate(n);
    out
}

fn small_mixed(features_per_level: usize) -> HashGridConfig {
    // Levels 4..40 with a 2^12 table: the coarse ones dense, the fine ones hashed.
    HashGridConfig {
        levels: 5,
        features_per_level,
        log2_table_size: 12,
        base_resolution: 4,
        finest_resolution: 40,
    }
}

/// Plain reference: per sample, per level, per corner, in f64, from the config alone.
fn reference_encode(config: &HashGridConfig, params: &[f32], pos: &[[f32; 3]]) -> Vec<f64> {
    let fpl = config.features_per_level;
    let table = 1u64 << config.log2_table_size;
    let n = pos.len();
    let mut out = vec![0.0; n * config.output_dim()];
    let mut offset = 0u64;
    for (l, &res) in config.resolutions().iter().enumerate() {
        let side = res as u64 + 1;
        let dense = side.pow(3) <= table;
        for (b, p) in pos.iter().enumerate() {
            let mut cell = [0u64; 3];
            let mut frac = [0f64; 3];
            for a in 0..3 {
                let x = if p[a].is_nan() {
                    0.0
                } else {
                    (p[a] as f64).clamp(0.0, 1.0)
                };
                let q = x * res as f64;
                cell[a] = (q.floor() as u64).min(res as u64 - 1);
                frac[a] = q - cell[a] as f64;
            }
            for c in 0..8u64 {
                let v = [cell[0] + (c & 1), cell[1] + ((c >> 1) & 1), cell[2] + (c >> 2)];
                let w: f64 = (0..3)
                    .map(|a| if (c >> a) & 1 == 1 { frac[a] } else { 1.0 - frac[a] })
                    .product();
                let entry = if dense {
                    v[0] + side * (v[1] + side * v[2])
                } else {
                    ((v[0] as u32)
                        ^ (v[1] as u32).wrapping_mul(2_654_435_761)
                        ^ (v[2] as u32).wrapping_mul(805_459_861)) as u64
                        % table
                };
                for f in 0..fpl {
                    let i = (offset + entry) as usize * fpl + f;
                    out[(l * fpl + f) * n + b] += w * params[i] as f64;
                }
            }
        }
        offset += if dense { side.pow(3) } else { table };
    }
    out
}

/// Plain reference gradient of sum(d_out * out) (the adjoint of
/// `reference_encode`) and the params reached: the corners of every sample
/// with a non-zero gradient on the level, even where a weight is 0.
fn reference_backward(config: &HashGridConfig, pos: &[[f32; 3]], d_out: &[f32]) -> (Vec<f64>, Vec<bool>) {
    // The same loops as `reference_encode`, scattering instead of gathering.
    let fpl = config.features_per_level;
    let table = 1u64 << config.log2_table_size;
    let n = pos.len();
    let mut grad = vec![0.0; config.param_count()];
    let mut reached = vec![false; config.param_count()];
    let mut offset = 0u64;
    for (l, &res) in config.resolutions().iter().enumerate() {
        let side = res as u64 + 1;
        let dense = side.pow(3) <= table;
        for (b, p) in pos.iter().enumerate() {
            let mut cell = [0u64; 3];
            let mut frac = [0f64; 3];
            for a in 0..3 {
                let x = if p[a].is_nan() {
                    0.0
                } else {
                    (p[a] as f64).clamp(0.0, 1.0)
                };
                let q = x * res as f64;
                cell[a] = (q.floor() as u64).min(res as u64 - 1);
                frac[a] = q - cell[a] as f64;
            }
            for c in 0..8u64 {
                let v = [cell[0] + (c & 1), cell[1] + ((c >> 1) & 1), cell[2] + (c >> 2)];
                let w: f64 = (0..3)
                    .map(|a| if (c >> a) & 1 == 1 { frac[a] } else { 1.0 - frac[a] })
                    .product();
                let entry = if dense {
                    v[0] + side * (v[1] + side * v[2])
                } else {
                    ((v[0] as u32)
                        ^ (v[1] as u32).wrapping_mul(2_654_435_761)
                        ^ (v[2] as u32).wrapping_mul(805_459_861)) as u64
                        % table
                };
                let live = (0..fpl).any(|f| d_out[(l * fpl + f) * n + b] != 0.0);
                for f in 0..fpl {
                    let i = (offset + entry) as usize * fpl + f;
                    grad[i] += w * d_out[(l * fpl + f) * n + b] as f64;
                    reached[i] |= live;
                }
            }
        }
        offset += if dense { side.pow(3) } else { table };
    }
    (grad, reached)
}

fn encode(g: &HashGrid, pos: &[[f32; 3]]) -> Vec<f32> {
    let mut out = vec![0.0; pos.len() * g.output_dim()];
    g.encode(pos, &mut out);
    out
}

#[test]
fn encode_matches_plain_reference() {
    let configs = [
        HashGridConfig::for_scene(2.0, 0.015),
        small_mixed(1),
        small_mixed(2),
        small_mixed(4),
        small_mixed(8),
    ];
    for (k, config) in configs.iter().enumerate() {
        let g = grid(*config, k as u64);
        let pos = positions(1000 + 3, 10 + k as u64); // not a multiple of 8 or of the block
        let got = encode(&g, &pos);
        let want = reference_encode(config, &g.params, &pos);
        let worst = got
            .iter()
            .zip(&want)
            .map(|(a, b)| (*a as f64 - b).abs())
            .fold(0.0, f64::max);
        // f32 rounding of x * res moves the fraction by ~res * 2^-24 per axis.
        let tol = 1e-6 + 2e-7 * config.finest_resolution as f64;
        assert!(worst < tol, "config {config:?}: max |encode - reference| = {worst}");
    }
}

#[test]
fn simd_and_scalar_paths_are_bit_identical() {
    if !simd::available() {
        eprintln!("skipping: no AVX2+FMA on this CPU");
        return;
    }
    let config = HashGridConfig::for_scene(2.0, 0.015);
    let g = grid(config, 3);
    for (k, mut pos) in [positions(777, 4), ray_positions(1000, 5)].into_iter().enumerate() {
        pos.extend([
            [1.0, 1.0, 1.0],
            [0.0, 0.0, 0.0],
            [-0.5, 2.0, f32::NAN],
            [f32::INFINITY, f32::NEG_INFINITY, 0.5],
        ]);
        let n = pos.len();
        let (mut fast, mut plain) = (vec![0.0; n * g.output_dim()], vec![0.0; n * g.output_dim()]);
        g.encode_with(&pos, &mut fast, true);
        g.encode_with(&pos, &mut plain, false);
        assert!(
            fast.iter().zip(&plain).all(|(a, b)| a.to_bits() == b.to_bits()),
            "set {k}: SIMD encode differs"
        );

        // Random d_out with every 5th sample's gradient zero (skipped inside runs).
        let mut rng = Rng::new(6, k as u64);
        let d_out: Vec<f32> = (0..n * g.output_dim())
            .map(|i| if i % n % 5 == 0 { 0.0 } else { rng.f32() - 0.5 })
            .collect();
        let (mut ga, mut gb) = (GridGrad::new(g.param_count()), GridGrad::new(g.param_count()));
        g.backward_with(&pos, &d_out, &mut ga, true);
        g.backward_with(&pos, &d_out, &mut gb, false);
        assert!(
            ga.values
                .iter()
                .zip(&gb.values)
                .all(|(a, b)| a.to_bits() == b.to_bits()),
            "set {k}: SIMD backward differs"
        );
        assert!(ga.touched().eq(gb.touched()));
    }
}

#[test]
fn backward_along_rays_matches_reference_gradient() {
    // Consecutive samples share cells, so the scatter sums runs before writing.
    for config in [HashGridConfig::for_scene(2.0, 0.015), small_mixed(1), small_mixed(4)] {
        let g = grid(config, 30);
        let pos = ray_positions(2000 + 5, 31);
        let mut rng = Rng::new(32, 0);
        let d_out: Vec<f32> = (0..pos.len() * g.output_dim()).map(|_| rng.f32() - 0.5).collect();
        let mut grad = GridGrad::new(g.param_count());
        g.backward(&pos, &d_out, &mut grad);
        let (want, reached) = reference_backward(&config, &pos, &d_out);
        let scale = want.iter().fold(0.0f64, |m, v| m.max(v.abs()));
        let worst = grad
            .values
            .iter()
            .zip(&want)
            .map(|(a, b)| (*a as f64 - b).abs())
            .fold(0.0, f64::max);
        assert!(
            worst < 1e-5 * scale.max(1.0),
            "{config:?}: max gradient error {worst} (largest {scale})"
        );
        // Rays leave the cube, and clamped samples on a face have zero-weight corners: touched
        // is every corner reached, a superset of the non-zero gradients.
        let reached: Vec<usize> = (0..want.len()).filter(|&i| reached[i]).collect();
        assert!(
            grad.touched().eq(reached.iter().copied()),
            "{config:?}: touched set differs from the corners reached"
        );
        assert!(want
            .iter()
            .enumerate()
            .all(|(i, v)| *v == 0.0 || reached.binary_search(&i).is_ok()));
        assert!(reached.iter().filter(|&&i| want[i] == 0.0).count() < reached.len() / 10);
    }
}

/// Loss = sum(c * out); returns (loss in f64, gradient from backward).
fn loss_and_grad(g: &HashGrid, pos: &[[f32; 3]], c: &[f32]) -> (f64, GridGrad) {
    let out = encode(g, pos);
    let loss = out.iter().zip(c).map(|(o, c)| *o as f64 * *c as f64).sum();
    let mut grad = GridGrad::new(g.param_count());
    g.backward(pos, c, &mut grad);
    (loss, grad)
}

#[test]
fn backward_matches_central_differences_and_touched_is_exact() {
    let config = small_mixed(2);
    let mut g = grid(config, 8);
    let pos = positions(50, 9);
    let mut rng = Rng::new(10, 0);
    let c: Vec<f32> = (0..pos.len() * g.output_dim()).map(|_| rng.f32() * 2.0 - 1.0).collect();
    let (_, grad) = loss_and_grad(&g, &pos, &c);

    let touched: Vec<usize> = grad.touched().collect();
    let nonzero: Vec<usize> = (0..g.param_count()).filter(|&i| grad.values[i] != 0.0).collect();
    assert_eq!(
        touched, nonzero,
        "touched set must be exactly the params with a gradient"
    );
    assert!(
        touched.windows(2).all(|w| w[0] < w[1]),
        "touched must be ascending and unique"
    );
    assert!(touched.len() > 100);

    // Central differences on touched params and a few untouched ones.
    let untouched = (0..g.param_count())
        .filter(|i| grad.values[*i] == 0.0)
        .step_by(97)
        .take(5);
    let probe: Vec<usize> = touched.iter().copied().step_by(7).chain(untouched).collect();
    let eps = 1e-2;
    for i in probe {
        let keep = g.params[i];
        g.params[i] = keep + eps;
        let (up, _) = loss_and_grad(&g, &pos, &c);
        g.params[i] = keep - eps;
        let (down, _) = loss_and_grad(&g, &pos, &c);
        g.params[i] = keep;
        let fd = (up - down) / (2.0 * eps as f64);
        let err = (fd - grad.values[i] as f64).abs();
        assert!(
            err < 1e-3 * (1.0 + fd.abs()),
            "param {i}: backward {} vs finite difference {fd}",
            grad.values[i]
        );
    }
}

#[test]
fn gradient_is_exact_because_encoding_is_linear_in_params() {
    // d(sum c*out)/d(param) = sum over samples of c * corner weight: compare with an f64 reference
    // built from unit parameter vectors' encodings.
    let config = HashGridConfig {
        levels: 2,
        features_per_level: 2,
        log2_table_size: 6,
        base_resolution: 2,
        finest_resolution: 5,
    };
    let g = grid(config, 11);
    let pos = positions(40, 12);
    let mut rng = Rng::new(13, 0);
    let c: Vec<f32> = (0..pos.len() * g.output_dim()).map(|_| rng.f32() - 0.5).collect();
    let (_, grad) = loss_and_grad(&g, &pos, &c);
    for i in 0..g.param_count() {
        let mut unit = vec![0.0f32; g.param_count()];
        unit[i] = 1.0;
        let basis = reference_encode(&config, &unit, &pos);
        let want: f64 = basis.iter().zip(&c).map(|(b, c)| b * *c as f64).sum();
        assert!(
            (grad.values[i] as f64 - want).abs() < 1e-5,
            "param {i}: {} vs exact {want}",
            grad.values[i]
        );
    }
}

#[test]
fn for_scene_sizes_tabletop_room_and_tiny() {
    let table = HashGridConfig::for_scene(2.0, 0.015);
    let room = HashGridConfig::for_scene(8.0, 0.04);
    let tiny = HashGridConfig::for_scene(0.3, 0.01);
    assert_eq!(table.finest_resolution, 134);
    assert_eq!(room.finest_resolution, 200);
    assert_eq!(tiny.finest_resolution, 30);
    for c in [table, room, tiny] {
        c.validate().expect("for_scene gives a valid config");
        assert_eq!(c.features_per_level, 2);
        assert_eq!(c.output_dim(), 2 * c.levels);
        let res = c.resolutions();
        assert_eq!(res.first(), Some(&c.base_resolution));
        assert_eq!(res.last(), Some(&c.finest_resolution));
        assert!(
            res.windows(2).all(|w| w[1] > w[0]),
            "levels must grow strictly: {res:?}"
        );
        let growth = (c.finest_resolution as f64 / c.base_resolution as f64).powf(1.0 / (c.levels - 1) as f64);
        assert!((1.2..=1.45 + 1e-9).contains(&growth), "growth {growth}");
        assert!(c.log2_table_size <= 19);
    }
    assert_eq!(table.base_resolution, 16);
    // Tiny scene: every level dense (no collisions) and a far smaller model.
    let tiny_grid = HashGrid::new(tiny, &mut Rng::new(0, 0));
    assert!(tiny_grid.levels().iter().all(|l| l.dense));
    let p = |c: HashGridConfig| c.param_count();
    assert!(p(tiny) * 5 < p(table), "tiny {} vs tabletop {}", p(tiny), p(table));
    assert!(p(table) < p(room), "tabletop {} vs room {}", p(table), p(room));
    // A huge scene hits the caps.
    let huge = HashGridConfig::for_scene(1000.0, 0.01);
    assert_eq!((huge.finest_resolution, huge.log2_table_size), (4096, 19));
    // Unusable inputs still give a usable config.
    for (e, t) in [(f64::NAN, 0.01), (2.0, 0.0), (-1.0, 0.01), (f64::INFINITY, 1.0)] {
        HashGridConfig::for_scene(e, t).validate().expect("fallback config");
    }
}

#[test]
fn dense_levels_are_detected_and_laid_out_back_to_back() {
    let config = HashGridConfig::for_scene(2.0, 0.015);
    let g = HashGrid::new(config, &mut Rng::new(1, 0));
    let levels = g.levels();
    let table = 1usize << config.log2_table_size;
    let mut offset = 0;
    for l in levels {
        let side = l.resolution as usize + 1;
        assert_eq!(l.dense, side.pow(3) <= table);
        assert_eq!(l.entries, if l.dense { side.pow(3) } else { table });
        assert_eq!(l.param_offset, offset);
        offset += l.entries * 2;
    }
    assert_eq!(offset, g.param_count());
    assert!(levels.iter().filter(|l| l.dense).count() >= 2 && levels.iter().any(|l| !l.dense));
    // Dense levels come first: once a level is hashed, all finer ones are.
    assert!(levels.windows(2).all(|w| w[0].dense || !w[1].dense));
    assert!(g.params.iter().all(|p| p.abs() <= 1e-4));
}

#[test]
fn clear_zeroes_everything_touched() {
    let g = grid(HashGridConfig::for_scene(2.0, 0.015), 14);
    let pos = positions(3000, 15);
    let d = vec![0.5; pos.len() * g.output_dim()];
    let mut grad = GridGrad::new(g.param_count());
    g.backward(&pos, &d, &mut grad);
    assert!(grad.touched_count() > 1000);
    assert_eq!(grad.touched_count(), grad.touched().count());
    grad.clear();
    assert_eq!(grad.touched().count(), 0);
    assert!(grad.values.iter().all(|v| *v == 0.0));
    // And the buffer is fully reusable.
    g.backward(&pos, &d, &mut grad);
    let mut fresh = GridGrad::new(g.param_count());
    g.backward(&pos, &d, &mut fresh);
    assert_eq!(grad.values, fresh.values);
    assert!(grad.touched().eq(fresh.touched()));
}

#[test]
fn touched_in_a_block_range_is_the_touched_set_cut_to_it() {
    let g = grid(HashGridConfig::for_scene(2.0, 0.015), 14);
    let pos = positions(3000, 15);
    let mut grad = GridGrad::new(g.param_count());
    g.backward(&pos, &vec![0.5; pos.len() * g.output_dim()], &mut grad);
    let all: Vec<usize> = grad.touched().collect();
    let block = GridGrad::BLOCK;
    let len = 3 * block;
    let mut joined = Vec::new();
    for start in (0..g.param_count()).step_by(len) {
        let part: Vec<usize> = grad.touched_in(start, len).collect();
        assert!(part.iter().all(|&i| (start..start + len).contains(&i)));
        joined.extend(part);
    }
    assert_eq!(joined, all);
    assert!(grad
        .touched_in(g.param_count().next_multiple_of(block), block)
        .next()
        .is_none());
}

#[test]
fn touched_rms_is_over_the_touched_values_and_refuses_a_nan() {
    let g = grid(HashGridConfig::for_scene(2.0, 0.015), 14);
    let pos = positions(3000, 15);
    let mut rng = Rng::new(3, 0);
    let d: Vec<f32> = (0..pos.len() * g.output_dim()).map(|_| rng.f32() - 0.5).collect();
    let mut grad = GridGrad::new(g.param_count());
    g.backward(&pos, &d, &mut grad);
    let n = grad.touched_count() as f64;
    let reference = (grad.touched().map(|i| (grad.values[i] as f64).powi(2)).sum::<f64>() / n).sqrt();
    let rms = grad.touched_rms().unwrap() as f64;
    assert!((rms - reference).abs() < 1e-5 * reference, "{rms} vs {reference}");
    let i = grad.touched().nth(100).unwrap();
    grad.values[i] = f32::NAN;
    assert_eq!(grad.touched_rms(), None);
}

#[test]
fn zero_gradient_samples_touch_nothing() {
    let g = grid(small_mixed(2), 16);
    let pos = positions(100, 17);
    let mut grad = GridGrad::new(g.param_count());
    g.backward(&pos, &vec![0.0; pos.len() * g.output_dim()], &mut grad);
    assert_eq!(grad.touched_count(), 0);
}

#[test]
fn merge_is_deterministic_and_matches_one_buffer() {
    let g = grid(HashGridConfig::for_scene(2.0, 0.015), 18);
    let pos = positions(2000, 19);
    let mut rng = Rng::new(20, 0);
    let d: Vec<f32> = (0..pos.len() * g.output_dim()).map(|_| rng.f32() - 0.5).collect();
    // Two "threads", each with half the samples (d_out re-sliced per half).
    let half = |r: std::ops::Range<usize>| -> GridGrad {
        let sub: Vec<f32> = (0..g.output_dim())
            .flat_map(|f| d[f * pos.len() + r.start..f * pos.len() + r.end].to_vec())
            .collect();
        let mut gg = GridGrad::new(g.param_count());
        g.backward(&pos[r], &sub, &mut gg);
        gg
    };
    let (a, b) = (half(0..1000), half(1000..2000));
    let merged = |first: &GridGrad, second: &GridGrad| {
        let mut m = GridGrad::new(g.param_count());
        m.drain_from(&mut first.clone());
        m.drain_from(&mut second.clone());
        m
    };
    let (m1, m2) = (merged(&a, &b), merged(&a, &b));
    assert!(m1
        .values
        .iter()
        .zip(&m2.values)
        .all(|(x, y)| x.to_bits() == y.to_bits()));
    let mut whole = GridGrad::new(g.param_count());
    g.backward(&pos, &d, &mut whole);
    assert!(m1.touched().eq(whole.touched()), "merged touched set = union");
    let worst = m1
        .values
        .iter()
        .zip(&whole.values)
        .map(|(x, y)| (x - y).abs())
        .fold(0.0, f32::max);
    assert!(worst < 1e-5, "merged vs single buffer: {worst}");
    assert!(a.touched_count() < m1.touched_count());
}

#[test]
fn positions_outside_the_cube_or_nan_are_clamped() {
    let g = grid(small_mixed(2), 21);
    let wild = [
        [-0.5, 0.3, 2.0],
        [f32::NAN, 0.7, 0.2],
        [f32::INFINITY, f32::NEG_INFINITY, 0.5],
        [1.0, 1.0, 1.0],
        [1e30, -1e30, f32::NAN],
    ];
    let tame = [
        [0.0, 0.3, 1.0],
        [0.0, 0.7, 0.2],
        [1.0, 0.0, 0.5],
        [1.0, 1.0, 1.0],
        [1.0, 0.0, 0.0],
    ];
    let (a, b) = (encode(&g, &wild), encode(&g, &tame));
    assert_eq!(a, b);
    assert!(a.iter().all(|v| v.is_finite()));
    // At (1,1,1) each dense level returns its last vertex exactly.
    for (l, level) in g.levels().iter().enumerate().filter(|(_, l)| l.dense) {
        let last = level.param_offset + (level.entries - 1) * 2;
        assert_eq!(a[(2 * l) * wild.len() + 3], g.params[last]);
        assert_eq!(a[(2 * l + 1) * wild.len() + 3], g.params[last + 1]);
    }
    let mut grad = GridGrad::new(g.param_count());
    g.backward(&wild, &vec![1.0; wild.len() * g.output_dim()], &mut grad);
    assert!(grad.values.iter().all(|v| v.is_finite()));
}

#[test]
fn no_reallocation_after_warm_up() {
    let g = grid(HashGridConfig::for_scene(2.0, 0.015), 22);
    let pos = positions(1500, 23);
    let d = vec![0.25; pos.len() * g.output_dim()];
    let mut main = GridGrad::new(g.param_count());
    let mut other = GridGrad::new(g.param_count());
    let fingerprint = |gg: &GridGrad| {
        (
            gg.values.as_ptr(),
            gg.values.capacity(),
            gg.bits.as_ptr(),
            gg.summary.as_ptr(),
        )
    };
    let before = (fingerprint(&main), fingerprint(&other));
    for _ in 0..3 {
        main.clear();
        other.clear();
        g.backward(&pos[..700], &d[..700 * g.output_dim()], &mut main);
        g.backward(&pos[..700], &d[..700 * g.output_dim()], &mut other);
        main.drain_from(&mut other);
    }
    assert_eq!(before, (fingerprint(&main), fingerprint(&other)));
    assert_eq!(main.values.len(), g.param_count());
}

#[test]
fn from_params_rejects_bad_input() {
    let config = small_mixed(2);
    let n = config.param_count();
    assert!(matches!(
        HashGrid::from_params(config, vec![0.0; n - 1]),
        Err(GridError::ParamCount { .. })
    ));
    let mut p = vec![0.0; n];
    p[5] = f32::NAN;
    assert!(matches!(
        HashGrid::from_params(config, p),
        Err(GridError::NonFinite { index: 5, .. })
    ));
    let bad = HashGridConfig {
        features_per_level: 3,
        ..config
    };
    assert!(matches!(HashGrid::from_params(bad, vec![]), Err(GridError::Config(_))));
    let bad = HashGridConfig {
        finest_resolution: 2,
        ..config
    };
    assert!(bad.validate().is_err());
    assert!(HashGrid::from_params(config, vec![0.0; n]).is_ok());
}

#[test]
fn level_split_across_threads_matches_one_thread_exactly() {
    let g = grid(HashGridConfig::for_scene(2.0, 0.015), 50);
    let pos = ray_positions(3001, 51);
    let (n, rows) = (pos.len(), 2 * pos.len());
    let mut rng = Rng::new(52, 0);
    let d_out: Vec<f32> = (0..n * g.output_dim()).map(|_| rng.f32() - 0.5).collect();
    let whole_out = encode(&g, &pos);
    let mut whole = GridGrad::new(g.param_count());
    g.backward(&pos, &d_out, &mut whole);
    let levels = g.levels().len();
    for split in [1, 3, levels - 1] {
        let mut out = vec![0.0; n * g.output_dim()];
        let (a, b) = out.split_at_mut(split * rows);
        let (mut ga, mut gb) = (GridGrad::new(g.param_count()), GridGrad::new(g.param_count()));
        std::thread::scope(|s| {
            s.spawn(|| {
                g.encode_levels(&pos, 0..split, a);
                g.backward_levels(&pos, 0..split, &d_out[..split * rows], &mut ga);
            });
            g.encode_levels(&pos, split..levels, b);
            g.backward_levels(&pos, split..levels, &d_out[split * rows..], &mut gb);
        });
        assert_eq!(out, whole_out, "split {split}: encode differs");
        // Disjoint parameters: merging in either order is exact.
        let mut merged = GridGrad::new(g.param_count());
        merged.drain_from(&mut gb.clone());
        merged.drain_from(&mut ga.clone());
        assert!(
            merged
                .values
                .iter()
                .zip(&whole.values)
                .all(|(x, y)| x.to_bits() == y.to_bits()),
            "split {split}"
        );
        assert!(merged.touched().eq(whole.touched()));
        assert!(ga.touched().all(|i| i < g.levels()[split].param_offset));
    }
}

#[test]
fn buffers_shorter_than_a_word_work() {
    let mut empty = GridGrad::new(0);
    let mut other = GridGrad::new(0);
    other.drain_from(&mut empty);
    other.clear();
    assert_eq!(other.touched().count(), 0);

    // 27 parameters (one dense 3x3x3-vertex level, 1 feature): the last word is partial.
    let config = HashGridConfig {
        levels: 1,
        features_per_level: 1,
        log2_table_size: 5,
        base_resolution: 2,
        finest_resolution: 2,
    };
    let g = grid(config, 60);
    assert_eq!(g.param_count(), 27);
    let pos = [[1.0, 1.0, 1.0], [0.9, 0.2, 0.6]];
    let mut grad = GridGrad::new(27);
    g.backward(&pos, &[1.0, 2.0], &mut grad);
    let touched: Vec<usize> = grad.touched().collect();
    // Cells (1,1,1) and (1,0,1) of the 3x3x3 vertices (index x + 3y + 9z) share 4 corners.
    assert_eq!(touched, [10, 11, 13, 14, 16, 17, 19, 20, 22, 23, 25, 26]);
    let mut sum = GridGrad::new(27);
    let (mut first, mut second) = (grad.clone(), grad.clone());
    sum.drain_from(&mut first);
    sum.drain_from(&mut second);
    assert!(touched.iter().all(|&i| sum.values[i] == 2.0 * grad.values[i]));
    // Drained buffers are empty and zero, ready for the next step.
    for drained in [&first, &second] {
        assert!(drained.values.iter().all(|v| *v == 0.0) && drained.touched_count() == 0);
    }
    assert_eq!(sum.touched().collect::<Vec<_>>(), touched);
    // Zeroed by a consumer, the set is forgotten without another pass.
    let (values, _) = first.values_and_touched();
    assert!(values.iter().all(|v| *v == 0.0));
    sum.values.iter_mut().for_each(|v| *v = 0.0);
    sum.forget_zeroed();
    assert_eq!(sum.touched_count(), 0);
    sum.clear();
    assert!(sum.values.iter().all(|v| *v == 0.0) && sum.touched_count() == 0);
}

#[test]
fn position_gradient_matches_central_differences_of_the_reference() {
    for fpl in [1, 2, 4] {
        let config = small_mixed(fpl);
        let g = grid(config, 21);
        // Inside the cube, away from its faces (the encoding is clamped there).
        let pos: Vec<[f32; 3]> = positions(64, 22)
            .into_iter()
            .map(|p| p.map(|x| 0.05 + 0.9 * x))
            .collect();
        let mut rng = Rng::new(23, 4);
        let d_out: Vec<f32> = (0..pos.len() * config.output_dim())
            .map(|_| rng.f32() * 2.0 - 1.0)
            .collect();
        let every: Vec<usize> = (0..pos.len()).collect();
        let mut analytic = vec![[0f32; 3]; pos.len()];
        g.position_gradient(&pos, &d_out, config.levels, &every, &mut analytic);
        let loss = |p: [f32; 3], b: usize| -> f64 {
            let enc = reference_encode(&config, &g.params, &[p]);
            (0..config.output_dim())
                .map(|k| enc[k] * d_out[k * pos.len() + b] as f64)
                .sum()
        };
        let h = 1e-4f32;
        let resolutions = config.resolutions();
        // An interval across a cell face bends the slope: skipped.
        let crosses = |lo: f32, hi: f32| {
            resolutions
                .iter()
                .any(|&r| (lo * r as f32).floor() != (hi * r as f32).floor())
        };
        let (mut worst, mut checked) = (0f64, 0);
        for (b, p) in pos.iter().enumerate() {
            for a in 0..3 {
                let (mut lo, mut hi) = (*p, *p);
                lo[a] -= h;
                hi[a] += h;
                if crosses(lo[a], hi[a]) {
                    continue;
                }
                let numeric = (loss(hi, b) - loss(lo, b)) / (hi[a] - lo[a]) as f64;
                worst = worst.max((analytic[b][a] as f64 - numeric).abs() / (1.0 + numeric.abs()));
                checked += 1;
            }
        }
        assert!(checked > 150, "features {fpl}: only {checked} components checked");
        assert!(worst < 1e-3, "features {fpl}: worst relative error {worst}");
    }
}

#[test]
fn position_gradient_over_the_coarse_levels_only_ignores_the_fine_ones() {
    let config = small_mixed(2);
    let g = grid(config, 31);
    let pos = positions(16, 32);
    let n = pos.len();
    let mut d_out = vec![0f32; n * config.output_dim()];
    // Gradient only on the last (finest) level.
    let last = (config.levels - 1) * 2 * n;
    d_out[last..].iter_mut().for_each(|d| *d = 1.0);
    let every: Vec<usize> = (0..n).collect();
    let mut coarse = vec![[0f32; 3]; n];
    g.position_gradient(&pos, &d_out, config.levels - 1, &every, &mut coarse);
    assert!(coarse.iter().all(|v| *v == [0.0; 3]));
    let mut all = vec![[0f32; 3]; n];
    g.position_gradient(&pos, &d_out, config.levels, &[3], &mut all);
    assert!(all[3] != [0.0; 3]);
    assert!(all.iter().enumerate().all(|(b, v)| b == 3 || *v == [0.0; 3]));
}
