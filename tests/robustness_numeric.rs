//! Issue 6, stiff numbers: compositing at saturated densities, ray/box
//! intervals and marching on degenerate rays, Adam on extreme gradients.
//! Every test asserts bounds on the outcome (no NaN, weights in [0, 1],
//! sample caps respected), never that something merely ran.

use nalgebra::{Point3, Vector3};
use nerflabel::nerf::camera::unit_cube_interval;
use nerflabel::nerf::camera::LocalRay;
use nerflabel::nerf::field::density_activation;
use nerflabel::nerf::occupancy::OccupancyGrid;
use nerflabel::nerf::render::composite::{optical_depth_backward, weights_from_optical_depth};
use nerflabel::nerf::render::march::{march, ray_interval, StepRule};
use nerflabel::nerf::train::adam::Adam;
use nerflabel::poses::Aabb;
use nerflabel::rng::Rng;

/// Composite `tau`, check weights and opacity, backpropagate a seeded
/// upstream gradient and check every tau gradient is finite.
fn check_ray(tau: &[f32], what: &str) -> Vec<f32> {
    let mut w = vec![0.0f32; tau.len()];
    let c = weights_from_optical_depth(tau, &mut w);
    let sum: f64 = w.iter().map(|&x| x as f64).sum();
    assert!(
        w.iter().all(|&x| (0.0..=1.0).contains(&x)),
        "{what}: weight outside [0,1]"
    );
    assert!(sum <= 1.0 + 1e-5, "{what}: weights sum to {sum}");
    assert!((0.0..=1.0).contains(&c.opacity), "{what}: opacity {}", c.opacity);
    assert!(
        (0.0..=1.0).contains(&c.transmittance),
        "{what}: transmittance {}",
        c.transmittance
    );
    assert!(c.used <= tau.len());
    let mut rng = Rng::new(7, 0);
    let grad_w: Vec<f32> = (0..tau.len()).map(|_| rng.range(-1.0, 1.0) as f32).collect();
    let mut grad_tau = vec![f32::NAN; tau.len()];
    optical_depth_backward(tau, &w, &c, &grad_w, 0.5, &mut grad_tau);
    assert!(
        grad_tau.iter().all(|g| g.is_finite()),
        "{what}: non-finite tau gradient"
    );
    // |dL/dtau_i| <= T_{i+1}|g_i| + sum_k w_k |g_k| + T|g_T| <= 1 + 1 + 0.5.
    assert!(
        grad_tau.iter().all(|g| g.abs() <= 2.5),
        "{what}: tau gradient out of bound"
    );
    w
}

#[test]
fn density_activation_of_plus_minus_100_is_finite_and_ordered() {
    for raw in [
        -100.0f32,
        -50.0,
        -1.0,
        0.0,
        1.0,
        50.0,
        100.0,
        1e30,
        -1e30,
        f32::INFINITY,
        f32::NEG_INFINITY,
        f32::NAN,
    ] {
        let s = density_activation(raw);
        assert!(s.is_finite() && s >= 0.0, "raw {raw} gives sigma {s}");
    }
    assert!(density_activation(-100.0) < 1e-30);
    assert!(density_activation(100.0) > 1e3, "saturated density stays large");
    assert!(
        density_activation(-100.0) <= density_activation(0.0) && density_activation(0.0) <= density_activation(100.0)
    );
}

#[test]
fn saturated_densities_composite_to_valid_weights_and_finite_gradients() {
    let delta = 1.0 / 256.0;
    for raw in [-100.0f32, -10.0, 0.0, 10.0, 100.0] {
        let tau = vec![density_activation(raw) * delta; 64];
        let w = check_ray(&tau, &format!("raw {raw}"));
        if raw >= 10.0 {
            assert!(w.iter().sum::<f32>() > 0.999, "opaque ray absorbs: raw {raw}");
        }
        if raw <= -10.0 {
            assert!(w.iter().sum::<f32>() < 1e-3, "empty ray stays transparent: raw {raw}");
        }
    }
}

#[test]
fn optical_depth_from_1e_minus_10_to_1e4_composites_cleanly() {
    let mut tau = 1e-10f32;
    while tau <= 1e4 {
        for n in [1usize, 8, 128] {
            let w = check_ray(&vec![tau; n], &format!("tau {tau} x{n}"));
            // A single sample's weight is alpha = 1 - exp(-tau): no underflow to 0 at tiny tau.
            let alpha = -(-(tau as f64)).exp_m1();
            assert!(
                ((w[0] as f64) - alpha).abs() <= 1e-6 * alpha.max(1e-30) + 1e-7,
                "tau {tau}: w0 {} vs {alpha}",
                w[0]
            );
        }
        tau *= 10.0;
    }
    // Non-finite and negative optical depths are treated as empty, never NaN.
    check_ray(
        &[f32::NAN, f32::INFINITY, -1.0, f32::NEG_INFINITY, 1e30, 0.5],
        "non-finite",
    );
}

#[test]
fn five_thousand_opaque_samples_terminate_without_nan() {
    let mut rng = Rng::new(3, 1);
    let tau: Vec<f32> = (0..5000)
        .map(|_| density_activation(rng.range(-100.0, 100.0) as f32) * 1e-2)
        .collect();
    check_ray(&tau, "5000 random");
    let opaque = vec![50.0f32; 5000];
    let w = check_ray(&opaque, "5000 opaque");
    assert!((w[0] - 1.0).abs() < 1e-6, "the first opaque sample takes all weight");
    let thin = vec![1e-3f32; 5000];
    let w = check_ray(&thin, "5000 thin");
    let sum: f32 = w.iter().sum();
    // 1 - exp(-5) = 0.9933; termination at T < 1e-4 is not reached.
    assert!((sum - 0.99326).abs() < 1e-3, "sum {sum}");
}

#[test]
fn optical_depth_gradient_matches_finite_differences_across_scales() {
    let loss = |tau: &[f32], g: &[f32], g_t: f64| -> f64 {
        let mut log_t = 0.0f64;
        let mut l = 0.0f64;
        for (&t, &gi) in tau.iter().zip(g) {
            l += log_t.exp() * -(-(t as f64)).exp_m1() * gi as f64;
            log_t -= t as f64;
        }
        l + log_t.exp() * g_t
    };
    let mut rng = Rng::new(11, 0);
    for scale in [1e-6f32, 1e-2, 1.0, 3.0] {
        let tau: Vec<f32> = (0..12).map(|_| rng.range(0.1, 1.0) as f32 * scale).collect();
        let g: Vec<f32> = (0..12).map(|_| rng.range(-1.0, 1.0) as f32).collect();
        let mut w = vec![0.0; 12];
        let c = weights_from_optical_depth(&tau, &mut w);
        let mut grad = vec![0.0; 12];
        optical_depth_backward(&tau, &w, &c, &g, 0.3, &mut grad);
        for i in 0..c.used {
            let h = (tau[i] * 1e-2).max(1e-7);
            let (mut up, mut dn) = (tau.clone(), tau.clone());
            up[i] += h;
            dn[i] -= h;
            let fd = (loss(&up, &g, 0.3) - loss(&dn, &g, 0.3)) / ((up[i] - dn[i]) as f64);
            let tol = 2e-3 + 2e-2 * fd.abs();
            assert!(
                (grad[i] as f64 - fd).abs() < tol,
                "scale {scale} i {i}: analytic {} fd {fd}",
                grad[i]
            );
        }
    }
}

fn assert_interval(r: Option<(f32, f32)>, what: &str) {
    if let Some((t0, t1)) = r {
        assert!(t0.is_finite() && t1.is_finite(), "{what}: ({t0}, {t1})");
        assert!(t0 >= 0.0 && t0 <= t1, "{what}: ({t0}, {t1})");
    }
}

#[test]
fn unit_cube_interval_on_degenerate_rays_is_finite_or_a_clean_miss() {
    // Parallel to the z = 0 face, origin on it: a hit along the face.
    let r = unit_cube_interval([0.2, 0.5, 0.0], [1.0, 0.0, 0.0]);
    assert_eq!(r, Some((0.0, 0.8)));
    // Parallel to a face but outside the slab: miss.
    assert_eq!(unit_cube_interval([0.2, 0.5, -0.01], [1.0, 0.0, 0.0]), None);
    // Camera inside: starts at 0.
    let (t0, t1) = unit_cube_interval([0.5, 0.5, 0.5], [0.0, 0.0, -1.0]).unwrap();
    assert_eq!(t0, 0.0);
    assert!((t1 - 0.5).abs() < 1e-6);
    // Looking away from the cube and missing beside it.
    assert_eq!(unit_cube_interval([0.5, 0.5, 2.0], [0.0, 0.0, 1.0]), None);
    assert_eq!(unit_cube_interval([3.0, 3.0, -1.0], [0.0, 0.0, 1.0]), None);
    // Non-finite inputs never produce a non-finite interval.
    let bad = [f32::NAN, f32::INFINITY, f32::NEG_INFINITY];
    for &b in &bad {
        for a in 0..3 {
            let mut o = [0.5f32; 3];
            o[a] = b;
            assert_interval(unit_cube_interval(o, [0.0, 0.0, 1.0]), "bad origin");
            let mut d = [0.0f32, 0.0, 1.0];
            d[a] = b;
            assert_interval(unit_cube_interval([0.5; 3], d), "bad dir");
        }
    }
    assert_interval(unit_cube_interval([0.5; 3], [0.0; 3]), "zero dir");
    // Random rays, including subnormal direction components.
    let mut rng = Rng::new(5, 0);
    for _ in 0..20_000 {
        let o = [
            rng.range(-2.0, 3.0) as f32,
            rng.range(-2.0, 3.0) as f32,
            rng.range(-2.0, 3.0) as f32,
        ];
        let mut d = [
            rng.range(-1.0, 1.0) as f32,
            rng.range(-1.0, 1.0) as f32,
            rng.range(-1.0, 1.0) as f32,
        ];
        if rng.below(4) == 0 {
            d[rng.below(3) as usize] = 1e-40;
        }
        assert_interval(unit_cube_interval(o, d), "random");
    }
}

#[test]
fn aabb_ray_interval_on_degenerate_rays_is_finite_or_a_clean_miss() {
    let b = Aabb::new(Point3::new(-1.0, -1.0, -1.0), Point3::new(1.0, 1.0, 1.0));
    // On a face, parallel to it.
    let (t0, t1) = b.ray_interval(&Point3::new(-1.0, 0.0, 1.0), &Vector3::x()).unwrap();
    assert_eq!((t0, t1), (0.0, 2.0));
    // Inside.
    let (t0, t1) = b.ray_interval(&Point3::origin(), &Vector3::y()).unwrap();
    assert_eq!((t0, t1), (0.0, 1.0));
    // Looking away, missing, zero direction, non-finite.
    assert_eq!(b.ray_interval(&Point3::new(0.0, 0.0, 3.0), &Vector3::z()), None);
    assert_eq!(b.ray_interval(&Point3::new(5.0, 0.0, 0.0), &Vector3::z()), None);
    assert_eq!(b.ray_interval(&Point3::origin(), &Vector3::zeros()), None);
    assert_eq!(b.ray_interval(&Point3::new(f32::NAN, 0.0, 0.0), &Vector3::z()), None);
    assert_eq!(
        b.ray_interval(&Point3::origin(), &Vector3::new(0.0, f32::INFINITY, 0.0)),
        None
    );
    let mut rng = Rng::new(6, 0);
    for _ in 0..20_000 {
        let o = Point3::new(
            rng.range(-4.0, 4.0) as f32,
            rng.range(-4.0, 4.0) as f32,
            rng.range(-4.0, 4.0) as f32,
        );
        let mut d = Vector3::new(
            rng.range(-1.0, 1.0) as f32,
            rng.range(-1.0, 1.0) as f32,
            rng.range(-1.0, 1.0) as f32,
        );
        if rng.below(4) == 0 {
            d.y = 1e-42;
        }
        let r = b.ray_interval(&o, &d);
        assert_interval(r, "random aabb");
        if b.contains(&o) {
            assert!(
                r.is_some_and(|(t0, _)| t0 == 0.0),
                "inside origin {o} must hit at t = 0"
            );
        }
    }
}

#[test]
fn marching_degenerate_rays_respects_the_sample_cap_and_terminates() {
    let grid = OccupancyGrid::full(32);
    let rule = StepRule {
        min_step: 1.0 / 512.0,
        max_step: 1.0 / 16.0,
        cone: 0.004,
    };
    let cases = [
        ([0.0f32, 0.5, 0.0], [1.0f32, 0.0, 0.0]), // on a face, parallel to it
        ([0.5, 0.5, 0.5], [0.0, 0.0, -1.0]),      // inside
        ([0.5, 0.5, 2.0], [0.0, 0.0, 1.0]),       // looking away
        ([3.0, 3.0, -1.0], [0.0, 0.0, 1.0]),      // missing
        ([1.0, 1.0, 1.0], [0.577_350_26, 0.577_350_26, 0.577_350_26]), // corner, leaving
        ([0.5, 0.5, -1e30], [0.0, 0.0, 1.0]),     // far away
        ([f32::NAN, 0.5, 0.5], [1.0, 0.0, 0.0]),
        ([0.5, 0.5, 0.5], [f32::INFINITY, 0.0, 0.0]),
    ];
    for (o, d) in cases {
        let ray = LocalRay { origin: o, dir: d };
        let Some((t0, t1)) = ray_interval(&ray, 0.0) else {
            continue;
        };
        assert!(
            t0.is_finite() && t1.is_finite() && t0 <= t1,
            "{o:?} {d:?}: ({t0}, {t1})"
        );
        for cap in [0usize, 1, 7, 4096] {
            let mut out = Vec::new();
            let t_end = march(&ray, t0, t1, &grid, &rule, 0.5, cap, &mut out);
            assert!(out.len() <= cap, "{o:?}: {} samples over cap {cap}", out.len());
            assert!(t_end.is_finite());
            assert!(out
                .iter()
                .all(|s| s.t.is_finite() && s.dt > 0.0 && s.t >= t0 - 1e-6 && s.t <= t1 + 1e-6));
        }
    }
    // A ray parallel to a face with the origin on it is sampled along its whole length.
    let ray = LocalRay {
        origin: [0.0, 0.5, 0.0],
        dir: [1.0, 0.0, 0.0],
    };
    let (t0, t1) = ray_interval(&ray, 0.0).unwrap();
    let mut out = Vec::new();
    march(
        &ray,
        t0,
        t1,
        &grid,
        &StepRule {
            min_step: 1.0 / 64.0,
            max_step: 1.0 / 64.0,
            cone: 0.0,
        },
        0.0,
        10_000,
        &mut out,
    );
    assert_eq!(out.len(), 64);
}

#[test]
fn marching_with_a_tiny_step_stops_at_the_sample_cap() {
    // 10 000 steps fit the interval; the cap must stop marching at 100.
    let grid = OccupancyGrid::full(16);
    let ray = LocalRay {
        origin: [0.5, 0.5, 0.0],
        dir: [0.0, 0.0, 1.0],
    };
    let rule = StepRule {
        min_step: 1e-4,
        max_step: 1e-4,
        cone: 0.0,
    };
    let mut out = Vec::new();
    march(&ray, 0.0, 1.0, &grid, &rule, 0.0, 100, &mut out);
    assert_eq!(out.len(), 100);
}

#[test]
fn adam_keeps_parameters_finite_under_tiny_huge_and_nan_gradients() {
    let mut rng = Rng::new(9, 0);
    for g in [
        1e-20f32,
        -1e-20,
        1e20,
        -1e20,
        f32::MAX,
        f32::NAN,
        f32::INFINITY,
        f32::NEG_INFINITY,
        0.0,
    ] {
        let mut params: Vec<f32> = (0..64).map(|_| rng.range(-1.0, 1.0) as f32).collect();
        let start = params.clone();
        let mut dense = Adam::new(64);
        let mut sparse = Adam::new(64);
        let mut params_sparse = params.clone();
        for step in 0..500 {
            // Alternate the extreme gradient with ordinary ones so the moments mix.
            let grads: Vec<f32> = (0..64).map(|i| if (i + step) % 3 == 0 { 0.1 } else { g }).collect();
            dense.step_dense(&mut params, &grads, 1e-2, 1e-6);
            sparse.step_sparse(&mut params_sparse, &grads, (0..64).step_by(2), 1e-2);
        }
        for (p, s) in params.iter().zip(&start) {
            assert!(p.is_finite(), "gradient {g}: parameter {p}");
            // Adam moves each parameter by at most ~lr per step.
            assert!(
                (p - s).abs() <= 500.0 * 1e-2 * 1.01 + 1e-3,
                "gradient {g}: moved {}",
                (p - s).abs()
            );
        }
        assert!(params_sparse.iter().all(|p| p.is_finite()), "sparse, gradient {g}");
        let (m, v) = dense.moments();
        assert!(
            m.iter().chain(v).all(|x| x.is_finite()),
            "gradient {g}: non-finite moment"
        );
    }
}
