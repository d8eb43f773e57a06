//! Full-frame rendering speed of a fitted model on its own scan's cameras,
//! for each occupancy grid a renderer can march: the model's own, the grid
//! re-estimated from the field at the same resolution (`lattice_pruned`)
//! refined to twice the resolution (`refined`) and refined again at the
//! children's corners (`rendering_grid`, what `label --depth` and `synth`
//! use). For each: set-up time, then per frame the
//! depth-only surface search of `label --depth` (first crossing of opacity
//! 0.5) and the colour + depth render of `synth`, with samples per ray and
//! colour PSNR against the frames' images, and
//! how far each grid's depth lies from the grid before it.
//!
//! Run: `cargo run --release --example bench_render -- SCAN_DIR MODEL [--frames N]`

use nerflabel::boxes::surface::{first_crossings, CrossingOptions, SurfaceWorkspace};
use nerflabel::evaluate::read_gray16;
use nerflabel::nerf::model_file::Model;
use nerflabel::nerf::occupancy::from_field::{lattice_pruned, refined, rendering_grid};
use nerflabel::nerf::occupancy::OccupancyGrid;
use nerflabel::nerf::render::rays::{render_image, RayOutput, RenderRay, PACKET};
use nerflabel::nerf::render::view::ViewRenderer;
use nerflabel::nerf::train::metrics::psnr;
use nerflabel::scan::{load, LoadOptions};
use rayon::prelude::*;
use std::path::PathBuf;
use std::time::Instant;

type Error = Box<dyn std::error::Error>;
/// Builds one of the grids compared.
type GridBuilder<'a> = Box<dyn Fn() -> OccupancyGrid + 'a>;

fn main() -> Result<(), Error> {
    let mut args = std::env::args().skip(1);
    let (mut scan_dir, mut model_path, mut frames) = (None, None, 12usize);
    while let Some(a) = args.next() {
        match a.as_str() {
            "--frames" => frames = args.next().ok_or("--frames needs a value")?.parse()?,
            _ if scan_dir.is_none() => scan_dir = Some(PathBuf::from(a)),
            _ if model_path.is_none() => model_path = Some(PathBuf::from(a)),
            other => return Err(format!("unexpected argument {other}").into()),
        }
    }
    let (Some(scan_dir), Some(model_path)) = (scan_dir, model_path) else {
        return Err("usage: bench_render SCAN_DIR MODEL [--frames N]".into());
    };
    let mut scan = load(&scan_dir, &LoadOptions::default())?;
    let model = Model::load(&model_path)?;
    model.apply_fitted_poses(&mut scan);
    let every = (scan.frames.len() / frames.max(1)).max(1);
    let views: Vec<_> = scan.frames.iter().step_by(every).take(frames).collect();
    let (w, h) = views[0].size();
    let rule = model.render_options(false).rule;
    println!(
        "{} frames of {w}x{h}, {} threads, model grid {}^3, finest hash level {}, steps of 1/{:.0} to 1/{:.0} (cone 1/{:.0})",
        views.len(),
        rayon::current_num_threads(),
        model.occupancy.resolution(),
        model.header.field.grid.finest_resolution,
        1.0 / rule.min_step,
        1.0 / rule.max_step,
        1.0 / rule.cone.max(1e-9),
    );

    let grids: [(&str, GridBuilder); 4] = [
        ("model grid", Box::new(|| model.occupancy.clone())),
        (
            "lattice-pruned",
            Box::new(|| lattice_pruned(&model.field, &model.occupancy)),
        ),
        (
            "pruned + refined",
            Box::new(|| refined(&model.field, &lattice_pruned(&model.field, &model.occupancy))),
        ),
        (
            "rendering grid (refined again at corners)",
            Box::new(|| rendering_grid(&model.field, &model.occupancy)),
        ),
    ];
    let mut previous_depths: Option<Vec<Vec<f32>>> = None;
    // Exact depth of a generated fixture, when present.
    let gt_unit = std::fs::read_to_string(scan_dir.join("gt/meta.json"))
        .ok()
        .and_then(|t| serde_json::from_str::<serde_json::Value>(&t).ok())
        .and_then(|m| m["gt_depth_unit_m"].as_f64())
        .unwrap_or(0.001) as f32;
    let truth: Option<Vec<Vec<f32>>> = views
        .iter()
        .map(|f| {
            let path = scan_dir.join("gt/depth").join(format!("{}.png", f.name));
            let units = read_gray16(&path).ok().filter(|d| d.len() == (w * h) as usize)?;
            Some(units.into_iter().map(|d| f32::from(d) * gt_unit).collect())
        })
        .collect();
    println!("| grid | res | occupied | set-up s | depth s/frame | samples/ray | colour+depth s/frame | samples/ray | colour PSNR vs the frames (dB) | depth vs the grid above: mean / p99 mm, changed > 1 mm | depth vs exact: mean / p99 mm |");
    println!("|---|---|---|---|---|---|---|---|---|---|---|");
    for (name, build) in grids {
        let t = Instant::now();
        let grid = build();
        let setup = t.elapsed().as_secs_f64();
        let renderer = ViewRenderer::with_grid(&model, grid)?;
        let grid = renderer.grid();
        let depth_opts = model.render_options(false);
        let crossing = CrossingOptions {
            rule: depth_opts.rule,
            threshold: 0.5,
            max_samples: depth_opts.max_samples_per_ray,
        };

        // Depth only, as `label --depth` searches for the surface.
        let t = Instant::now();
        let mut depth_samples = 0u64;
        let mut depth_rays = 0u64;
        let mut depths = Vec::new();
        for f in &views {
            let camera = renderer.local_camera(&f.camera_to_world, &f.intrinsics, w, h);
            // Every pixel's ray inside the cube, with its pixel and local t per camera z.
            let (mut marched, mut pixel_of) = (Vec::new(), Vec::new());
            for i in 0..(w * h) as usize {
                let (ray, t_per_z) = camera.ray((i % w as usize) as f32, (i / w as usize) as f32);
                if let Some(r) = RenderRay::through_cube(ray, depth_opts.rule.min_step) {
                    marched.push(r);
                    pixel_of.push((i, t_per_z));
                }
            }
            let mut out = vec![None; marched.len()];
            depth_samples += marched
                .par_chunks(PACKET)
                .zip(out.par_chunks_mut(PACKET))
                .map_init(SurfaceWorkspace::default, |ws, (rays, out)| {
                    first_crossings(&model.field, grid, rays, &crossing, ws, out) as u64
                })
                .sum::<u64>();
            depth_rays += marched.len() as u64;
            // Camera z in metres per pixel, 0 = no surface.
            let mut z = vec![0.0f32; (w * h) as usize];
            for (t, &(i, t_per_z)) in out.iter().zip(&pixel_of) {
                if let Some(t) = t {
                    z[i] = t / t_per_z / renderer.transform.scale() as f32;
                }
            }
            depths.push(z);
        }
        let depth_s = t.elapsed().as_secs_f64() / views.len() as f64;

        // Colour and depth, as `synth` renders a view.
        let colour_opts = model.render_options(true);
        let t = Instant::now();
        let (mut colour_samples, mut colour_rays) = (0u64, 0u64);
        let mut renders = Vec::new();
        for f in &views {
            let camera = renderer.local_camera(&f.camera_to_world, &f.intrinsics, w, h);
            let out = render_image(&model.field, grid, &colour_opts, &camera);
            colour_samples += out.iter().map(|o| o.samples as u64).sum::<u64>();
            colour_rays += out.len() as u64;
            renders.push(out);
        }
        let colour_s = t.elapsed().as_secs_f64() / views.len() as f64;
        let psnr = colour_psnr(&views, &renders);
        let comparison = previous_depths.as_ref().map_or("-".to_string(), |before| {
            let (mean, p99, changed) = compare(before, &depths);
            format!("{mean:.3} / {p99:.2}, {:.3} %", 100.0 * changed)
        });
        let exact = truth.as_ref().map_or("-".to_string(), |truth| {
            let (mean, p99, _) = compare(truth, &depths);
            format!("{mean:.2} / {p99:.1}")
        });
        previous_depths = Some(depths);
        println!(
            "| {name} | {} | {:.2} % | {setup:.2} | {depth_s:.3} | {:.1} | {colour_s:.3} | {:.1} | {psnr:.2} | {comparison} | {exact} |",
            grid.resolution(),
            100.0 * grid.occupied_fraction(),
            depth_samples as f64 / depth_rays.max(1) as f64,
            colour_samples as f64 / colour_rays.max(1) as f64,
        );
    }
    Ok(())
}

/// PSNR of the colour renders against the frames' own images, all frames
/// pooled, as held-out evaluation scores (8-bit colour; no per-frame
/// appearance applied: for comparing renderers, not models).
fn colour_psnr(views: &[&nerflabel::scan::Frame], renders: &[Vec<RayOutput>]) -> f64 {
    let frames: Vec<u8> = views.iter().flat_map(|f| f.rgb.as_raw().iter().copied()).collect();
    let rendered: Vec<u8> = renders
        .iter()
        .flatten()
        .flat_map(|o| o.rgb.map(|c| (c * 255.0).round().clamp(0.0, 255.0) as u8))
        .collect();
    psnr(&frames, &rendered)
}

/// Mean and 99th percentile of |z - reference| over pixels both have a
/// surface in (mm), and the share of pixels that moved by more than 1 mm or
/// have a surface in one image only.
fn compare(reference: &[Vec<f32>], z: &[Vec<f32>]) -> (f64, f64, f64) {
    let mut diffs = Vec::new();
    let (mut changed, mut total) = (0usize, 0usize);
    for (a, b) in reference.iter().zip(z) {
        for (&x, &y) in a.iter().zip(b) {
            total += 1;
            match (x > 0.0, y > 0.0) {
                (true, true) => {
                    let d = f64::from((x - y).abs()) * 1000.0;
                    changed += usize::from(d > 1.0);
                    diffs.push(d);
                }
                (false, false) => {}
                _ => changed += 1,
            }
        }
    }
    diffs.sort_by(f64::total_cmp);
    let mean = diffs.iter().sum::<f64>() / diffs.len().max(1) as f64;
    let p99 = diffs.get(diffs.len() * 99 / 100).copied().unwrap_or(0.0);
    (mean, p99, changed as f64 / total.max(1) as f64)
}
