//! Speed and quality of `synth` on the generated tabletop fixture.
//!
//! `cargo run --release --example bench_synth [-- --time 120 --views 500 --width 320 --height 240 --fixture DIR --reuse --speed-only]`
//!
//! Generates the tabletop fixture (320x240, 120 frames, 12 held out) unless
//! it exists, fits a model for `--time` seconds (or loads the saved one with
//! `--reuse`), then prints:
//! - speed: `--views` sampled views at `--width` x `--height` written to
//!   Parquet (seconds, views/s, rejections, file size);
//! - quality on the held-out frames rendered through a `--poses` file,
//!   against the fixture's exact ground truth: PSNR, SSIM, depth MAE and
//!   mask mIoU; and the mask mIoU of the first 50 sampled views
//!   (skipped with `--speed-only`).
//!
//! Besides wall-clock seconds it prints the CPU seconds the process used
//! (user + system, from /proc/self/stat) and the load average, since the
//! machine is shared: compare runs by ratios taken in one session.

use arrow_array::cast::AsArray;
use arrow_array::types::{Float64Type, Int32Type};
use image::DynamicImage;
use nalgebra::Matrix4;
use nerflabel::boxes::read_boxes;
use nerflabel::boxes::BoxClassifier;
use nerflabel::fixture::{generate, read_meta, trajectory, FixtureOptions, SceneKind};
use nerflabel::nerf::model_file::Model;
use nerflabel::nerf::render::rays::render_image;
use nerflabel::nerf::render::view::ViewRenderer;
use nerflabel::nerf::train::fit::{fit, FitOptions};
use nerflabel::nerf::train::metrics::{depth_mae, psnr, ssim};
use nerflabel::png_encode::{depth_mm_saturating, encode_depth, encode_mask, encode_rgb};
use nerflabel::scan::{load, Intrinsics, LoadOptions};
use nerflabel::synth::triplet::{clean_instances, instance_mask};
use nerflabel::synth::{read_poses, synthesize, Instances, SynthOptions, SynthProgress, SynthSummary, ViewSpec};
use parquet::arrow::arrow_reader::ParquetRecordBatchReaderBuilder;
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::sync::atomic::AtomicBool;
use std::time::Instant;

struct Args {
    fixture: PathBuf,
    time: f64,
    views: usize,
    width: u32,
    height: u32,
    reuse: bool,
    speed_only: bool,
}

fn parse_args() -> Result<Args, String> {
    let mut a = Args {
        fixture: PathBuf::from("target/bench_synth/tabletop"),
        time: 120.0,
        views: 500,
        width: 320,
        height: 240,
        reuse: false,
        speed_only: false,
    };
    let mut it = std::env::args().skip(1);
    while let Some(flag) = it.next() {
        let mut value = || it.next().ok_or(format!("{flag} needs a value"));
        match flag.as_str() {
            "--fixture" => a.fixture = PathBuf::from(value()?),
            "--time" => a.time = value()?.parse().map_err(|e| format!("--time: {e}"))?,
            "--views" => a.views = value()?.parse().map_err(|e| format!("--views: {e}"))?,
            "--width" => a.width = value()?.parse().map_err(|e| format!("--width: {e}"))?,
            "--height" => a.height = value()?.parse().map_err(|e| format!("--height: {e}"))?,
            "--reuse" => a.reuse = true,
            "--speed-only" => a.speed_only = true,
            other => return Err(format!("unknown argument {other}")),
        }
    }
    Ok(a)
}

/// One decoded row of a synth file.
struct Row {
    spec: ViewSpec,
    rgb: Vec<u8>,
    depth_m: Vec<f32>,
    mask: Vec<u16>,
}

fn read_rows(path: &Path, limit: usize) -> Result<Vec<Row>, Box<dyn std::error::Error>> {
    let reader = ParquetRecordBatchReaderBuilder::try_new(std::fs::File::open(path)?)?.build()?;
    let mut rows = Vec::new();
    for batch in reader {
        let b = batch?;
        let col = |name: &str| b.column_by_name(name).cloned().ok_or(format!("no column {name}"));
        let (w, h) = (col("width")?, col("height")?);
        let (k, pose) = (col("intrinsics")?, col("camera_to_world")?);
        let (rgb, depth, mask) = (col("rgb")?, col("depth")?, col("mask")?);
        for i in 0..b.num_rows() {
            if rows.len() >= limit {
                return Ok(rows);
            }
            let kv = k.as_fixed_size_list().value(i);
            let kv = kv.as_primitive::<Float64Type>().values().to_vec();
            let m = pose.as_fixed_size_list().value(i);
            let m: [f64; 16] = m
                .as_primitive::<Float64Type>()
                .values()
                .to_vec()
                .try_into()
                .map_err(|_| "pose")?;
            let spec = ViewSpec {
                camera_to_world: nerflabel::scan::isometry(&Matrix4::from_row_slice(&m)),
                intrinsics: Intrinsics {
                    fx: kv[0],
                    fy: kv[1],
                    cx: kv[2],
                    cy: kv[3],
                },
                width: w.as_primitive::<Int32Type>().value(i) as u32,
                height: h.as_primitive::<Int32Type>().value(i) as u32,
            };
            let decode = |c: &arrow_array::ArrayRef| {
                let png = c
                    .as_struct()
                    .column_by_name("bytes")
                    .ok_or_else(|| "no bytes field".to_string())?;
                image::load_from_memory(png.as_binary::<i32>().value(i)).map_err(|e| e.to_string())
            };
            let rgb = decode(&rgb)?.into_rgb8().into_raw();
            let depth_m = match decode(&depth)? {
                DynamicImage::ImageLuma16(d) => d.into_raw().into_iter().map(|v| f32::from(v) / 1000.0).collect(),
                _ => return Err("depth PNG is not 16-bit".into()),
            };
            let mask = match decode(&mask)? {
                DynamicImage::ImageLuma8(m) => m.into_raw().into_iter().map(u16::from).collect(),
                DynamicImage::ImageLuma16(m) => m.into_raw(),
                _ => return Err("mask PNG is not single-channel".into()),
            };
            rows.push(Row {
                spec,
                rgb,
                depth_m,
                mask,
            });
        }
    }
    Ok(rows)
}

/// Per-instance (intersection, predicted, true) pixel counts.
type IouCounts = BTreeMap<u16, (u64, u64, u64)>;

fn add_iou(counts: &mut IouCounts, pred: &[u16], truth: &[u16]) {
    for (&p, &g) in pred.iter().zip(truth) {
        if p > 0 {
            counts.entry(p).or_default().1 += 1;
        }
        if g > 0 {
            counts.entry(g).or_default().2 += 1;
        }
        if p > 0 && p == g {
            counts.entry(p).or_default().0 += 1;
        }
    }
}

fn mean_iou(counts: &IouCounts) -> f64 {
    let ious: Vec<f64> = counts
        .values()
        .map(|&(i, p, g)| i as f64 / (p + g - i).max(1) as f64)
        .collect();
    ious.iter().sum::<f64>() / ious.len().max(1) as f64
}

/// CPU seconds (user + system) used by this process so far; 0 where /proc is missing.
fn cpu_seconds() -> f64 {
    let Ok(stat) = std::fs::read_to_string("/proc/self/stat") else {
        return 0.0;
    };
    // Fields after the parenthesised command name; utime and stime are fields 14 and 15.
    let Some(rest) = stat.rsplit_once(')').map(|(_, r)| r) else {
        return 0.0;
    };
    let f: Vec<&str> = rest.split_whitespace().collect();
    let ticks = |i: usize| f.get(i).and_then(|v| v.parse::<f64>().ok()).unwrap_or(0.0);
    (ticks(11) + ticks(12)) / 100.0
}

/// The 1-minute load average.
fn load_average() -> String {
    std::fs::read_to_string("/proc/loadavg")
        .ok()
        .and_then(|l| l.split_whitespace().next().map(str::to_string))
        .unwrap_or_default()
}

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let args = parse_args()?;
    let scan_dir = &args.fixture;
    if !scan_dir.join("gt/meta.json").exists() {
        let mut o = FixtureOptions::new(SceneKind::Tabletop);
        o.width = 320;
        o.height = 240;
        let t = Instant::now();
        generate(scan_dir, &o)?;
        eprintln!("generated {} in {:.1} s", scan_dir.display(), t.elapsed().as_secs_f64());
    }
    let mut scan = load(scan_dir, &LoadOptions::default())?;
    let boxes = read_boxes(&scan_dir.join("boxes.json"))?;
    let model_path = scan_dir.join("nerflabel/model.nlf");
    let model = if args.reuse && model_path.exists() {
        let model = Model::load(&model_path)?;
        model.apply_fitted_poses(&mut scan);
        model
    } else {
        let t = Instant::now();
        let opts = FitOptions {
            time: Some(args.time),
            ..FitOptions::default()
        };
        let outcome = fit(&mut scan, &opts, &AtomicBool::new(false), &mut |_| {})?;
        eprintln!(
            "fitted {} steps in {:.1} s",
            outcome.report.counters.steps,
            t.elapsed().as_secs_f64()
        );
        outcome.model.save(&model_path)?;
        outcome.model
    };
    let checksum = crc32fast::hash(&std::fs::read(&model_path)?);
    let out_dir = scan_dir.join("nerflabel");
    let stop = AtomicBool::new(false);

    // Speed: sampled views.
    let sampled_path = out_dir.join("bench_synth.parquet");
    let opts = SynthOptions {
        n: args.views,
        width: Some(args.width),
        height: Some(args.height),
        seed: 0,
        model_checksum: checksum,
        ..SynthOptions::default()
    };
    let load_before = load_average();
    let cpu = cpu_seconds();
    let t = Instant::now();
    let prepared = std::sync::Mutex::new(0.0);
    let on_progress = |p: SynthProgress| {
        if let SynthProgress::Prepared { .. } = p {
            if let Ok(mut s) = prepared.lock() {
                *s = t.elapsed().as_secs_f64();
            }
        }
    };
    let speed: SynthSummary = synthesize(&scan, &model, Some(&boxes), &opts, &sampled_path, &on_progress, &stop)?;
    let prepare_s = prepared.into_inner().unwrap_or(0.0);
    let cpu_s = cpu_seconds() - cpu;
    let load_after = load_average();
    println!(
        "| synth on the tabletop fixture ({} frames, model {:.0} s) | value |",
        scan.frames.len(),
        args.time
    );
    println!("|---|---|");
    println!("| sampled views {}x{} | {} |", args.width, args.height, speed.views);
    println!("| seconds (incl. cloud, k-d tree, probes) | {:.1} |", speed.seconds);
    println!("| views/s | {:.2} |", speed.views_per_s);
    println!(
        "| CPU seconds (user + system) | {cpu_s:.1} ({:.2} per view) |",
        cpu_s / speed.views.max(1) as f64
    );
    println!("| load average before / after | {load_before} / {load_after} |");
    println!("| of which set-up (cloud, k-d tree, clearance) | {prepare_s:.1} s |");
    println!(
        "| candidates / rejected | {} / {} ({}) |",
        speed.attempts,
        speed.rejections.total(),
        speed.rejections
    );
    println!("| clearance | {:.3} m |", speed.clearance_m.unwrap_or(0.0));
    println!("| file size | {:.1} MB |", speed.bytes as f64 / 1e6);
    if args.speed_only {
        return Ok(());
    }

    // Quality: held-out frames through a poses file.
    let meta = read_meta(scan_dir)?;
    let scene = meta.build_scene();
    let holdout = trajectory(&scene, meta.frames, meta.holdout, meta.seed).holdout;
    let k = meta.intrinsics;
    let views: Vec<serde_json::Value> = holdout
        .iter()
        .map(|p| {
            let m = p.to_homogeneous();
            let rows: Vec<[f64; 4]> = (0..4).map(|r| [0, 1, 2, 3].map(|c| m[(r, c)])).collect();
            serde_json::json!({ "camera_to_world": rows, "intrinsics": [k.fx, k.fy, k.cx, k.cy],
                                "width": meta.width, "height": meta.height })
        })
        .collect();
    let poses_path = out_dir.join("bench_holdout_poses.json");
    std::fs::write(&poses_path, serde_json::json!({ "views": views }).to_string())?;
    let held_path = out_dir.join("bench_holdout.parquet");
    let opts = SynthOptions {
        poses: Some(read_poses(&poses_path)?),
        model_checksum: checksum,
        ..SynthOptions::default()
    };
    let held: SynthSummary = synthesize(&scan, &model, Some(&boxes), &opts, &held_path, &|_| {}, &stop)?;

    let (mut p, mut s, mut mae, mut mae_n) = (0.0, 0.0, 0.0, 0);
    let mut held_iou = IouCounts::new();
    let rows = read_rows(&held_path, usize::MAX)?;
    for row in &rows {
        let gt = scene.render(
            &row.spec.camera_to_world,
            &row.spec.intrinsics,
            row.spec.width,
            row.spec.height,
        );
        p += psnr(&row.rgb, gt.rgb.as_raw());
        s += ssim(
            &row.rgb,
            gt.rgb.as_raw(),
            row.spec.width as usize,
            row.spec.height as usize,
        );
        if let Some(e) = depth_mae(&row.depth_m, &gt.depth) {
            mae += e;
            mae_n += 1;
        }
        add_iou(&mut held_iou, &row.mask, &gt.instance);
    }
    let n = rows.len().max(1) as f64;
    let mut sampled_iou = IouCounts::new();
    let sampled = read_rows(&sampled_path, 50)?;
    for row in &sampled {
        let gt = scene.render(
            &row.spec.camera_to_world,
            &row.spec.intrinsics,
            row.spec.width,
            row.spec.height,
        );
        add_iou(&mut sampled_iou, &row.mask, &gt.instance);
    }

    // Where the time of one view goes, on the first sampled poses (one thread each stage).
    let t = Instant::now();
    let renderer = ViewRenderer::pruned(&model)?;
    let t_prune = t.elapsed().as_secs_f64();
    let classifier = BoxClassifier::new(&boxes);
    let instances = Instances {
        classify: &|p, _| classifier.classify(&p),
        labels: boxes.boxes.iter().map(|b| b.label.clone()).collect(),
    };
    let (mut t_render, mut t_mask, mut t_png, mut rays, mut opaque, mut samples) =
        (0.0, 0.0, 0.0, 0usize, 0usize, 0u64);
    for row in sampled.iter().take(16) {
        let spec = &row.spec;
        let t = Instant::now();
        let view = renderer.render_view(&spec.camera_to_world, &spec.intrinsics, spec.width, spec.height, true);
        t_render += t.elapsed().as_secs_f64();
        let t = Instant::now();
        let mut mask = instance_mask(
            &view.depth_m,
            &spec.camera_to_world,
            &spec.intrinsics,
            spec.width,
            instances.classify,
        );
        clean_instances(&mut mask, spec.width, spec.height);
        t_mask += t.elapsed().as_secs_f64();
        let t = Instant::now();
        encode_rgb(&view.rgb, spec.width, spec.height)?;
        encode_depth(&depth_mm_saturating(&view.depth_m), spec.width, spec.height)?;
        encode_mask(&mask, instances.max_id() as usize, spec.width, spec.height)?;
        t_png += t.elapsed().as_secs_f64();
        rays += view.depth_m.len();
        let camera = renderer.local_camera(&spec.camera_to_world, &spec.intrinsics, spec.width, spec.height);
        let out = render_image(&model.field, renderer.grid(), &model.render_options(true), &camera);
        samples += out.iter().map(|o| u64::from(o.samples)).sum::<u64>();
        opaque += view.opacity.iter().filter(|&&a| a > 0.5).count();
    }
    let per = 1.0 / sampled.len().clamp(1, 16) as f64;

    println!(
        "| per view: render (all threads) | {:.0} ms ({:.2} M rays/s, {:.0} % opaque) |",
        t_render * per * 1e3,
        rays as f64 / t_render / 1e6,
        100.0 * opaque as f64 / rays.max(1) as f64
    );
    println!("| mean samples per ray | {:.1} |", samples as f64 / rays.max(1) as f64);
    println!("| set-up: pruned grid (all threads) | {t_prune:.1} s |");
    println!("| per view: mask (1 thread) | {:.1} ms |", t_mask * per * 1e3);
    println!("| per view: 3 PNGs (1 thread) | {:.1} ms |", t_png * per * 1e3);
    println!(
        "| held-out views via --poses | {} ({:.1} s) |",
        held.views, held.seconds
    );
    println!("| PSNR | {:.2} dB |", p / n);
    println!("| SSIM | {:.3} |", s / n);
    println!("| depth MAE | {:.1} mm |", mae / f64::from(mae_n.max(1)) * 1e3);
    println!("| mask mIoU (held-out) | {:.3} |", mean_iou(&held_iou));
    for (id, &(i, p, g)) in &held_iou {
        let label = boxes
            .boxes
            .get(usize::from(*id).saturating_sub(1))
            .map_or("?", |b| b.label.as_str());
        println!(
            "| mask IoU (held-out) of {id} ({label}) | {:.3} |",
            i as f64 / (p + g - i).max(1) as f64
        );
    }
    println!(
        "| mask mIoU (first {} sampled views) | {:.3} |",
        sampled.len(),
        mean_iou(&sampled_iou)
    );
    Ok(())
}
