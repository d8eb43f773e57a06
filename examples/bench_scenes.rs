//! Labelling on realistic scenes: for each scene and seed, a fixture as hard
//! as a handheld scan (`fixture --realistic`: JPEG colour, low-resolution
//! noisy depth with holes, pose error), a timed fit, then labels from the
//! sensor, nerf and fused depth sources with boxes drawn snug (+1 cm) and
//! loose (+2.5 cm, 2 cm into the support), scored against the exact masks.
//!
//! Run: `cargo run --release --example bench_scenes -- [--scenes tabletop,clutter,room]
//! [--seeds 2] [--fit-seconds 120] [--every 1] [--dir DIR] [--objects] [--exact-boxes] [--overlap deepest] [--no-tsdf] [--no-pose-refine] [--no-colour-snap]`
//!
//! Besides the product's sources it labels TSDF fusion (the paper's
//! baseline: sensor depth fused at 5 mm, ray cast into every frame,
//! `support/tsdf.rs`) the same way as sensor depth.
//!
//! Every frame is labelled and scored, as `label` does (`--every N` scores
//! every N-th, quicker; a frame left out can hide a fault such as a floater).
//!
//! Prints one line per scene, seed, box drawing and source (mIoU = mean over
//! frames of the frame's mean object IoU; ratio = predicted / true object
//! pixels; FP:FN = false-positive to false-negative pixels; bF = boundary
//! F-score within 2 px), then the means over scenes as a Markdown table.
//! Fixtures and models are kept in DIR (default: the temp folder) and reused.

use nerflabel::boxes::{read_boxes, DepthSource, LabelOptions, Overlap};
use nerflabel::evaluate::{evaluate_labels, fixture_truth, LabelEvaluation};
use nerflabel::fixture::{generate, Corruptions, FixtureOptions, SceneKind};
use nerflabel::nerf::model_file::Model;
use nerflabel::nerf::train::fit::{fit, FitOptions};
use nerflabel::nerf::train::settings::FitSettings;
use nerflabel::scan::{load, LoadOptions};
use std::collections::BTreeMap;
use std::path::PathBuf;
use std::sync::atomic::AtomicBool;
use std::time::Instant;

#[path = "support/tsdf.rs"]
mod tsdf;

type Error = Box<dyn std::error::Error>;

struct Args {
    scenes: Vec<SceneKind>,
    seeds: Vec<u64>,
    fit_seconds: f64,
    every: usize,
    dir: PathBuf,
    objects: bool,
    exact_boxes: bool,
    overlap: Overlap,
    tsdf: bool,
    refine_poses: bool,
    snap: bool,
}

fn parse_args() -> Result<Args, Error> {
    let mut args = Args {
        scenes: vec![SceneKind::Tabletop, SceneKind::Clutter, SceneKind::Room],
        seeds: vec![2],
        fit_seconds: 120.0,
        every: 1,
        dir: std::env::temp_dir().join("nerflabel-scenes"),
        objects: false,
        exact_boxes: false,
        overlap: Overlap::Smallest,
        tsdf: true,
        refine_poses: true,
        snap: true,
    };
    let mut it = std::env::args().skip(1);
    while let Some(a) = it.next() {
        let mut value = |name: &str| it.next().ok_or_else(|| format!("{name} needs a value"));
        match a.as_str() {
            "--scenes" => {
                args.scenes = (value("--scenes")?.split(','))
                    .map(|s| s.parse::<SceneKind>().map_err(|e| e.to_string()))
                    .collect::<Result<_, _>>()?
            }
            "--seeds" => args.seeds = value("--seeds")?.split(',').map(str::parse).collect::<Result<_, _>>()?,
            "--fit-seconds" => args.fit_seconds = value("--fit-seconds")?.parse()?,
            "--every" => args.every = value("--every")?.parse()?,
            "--dir" => args.dir = value("--dir")?.into(),
            "--objects" => args.objects = true,
            "--exact-boxes" => args.exact_boxes = true,
            "--overlap" => args.overlap = clap::ValueEnum::from_str(&value("--overlap")?, true)?,
            "--no-tsdf" => args.tsdf = false,
            "--no-colour-snap" => args.snap = false,
            "--no-pose-refine" => args.refine_poses = false,
            other => return Err(format!("unknown option {other}").into()),
        }
    }
    Ok(args)
}

/// Running sums for the summary table.
#[derive(Default)]
struct Sums {
    n: usize,
    miou: f64,
    ratio: f64,
    fp: u64,
    fn_: u64,
    bf: f64,
}

fn main() -> Result<(), Error> {
    let args = parse_args()?;
    println!(
        "{:<9} {:>4} {:<6} {:<7} {:>7} {:>7} {:>7} {:>6} {:>7}",
        "scene", "seed", "boxes", "source", "mIoU", "ratio", "FP:FN", "bF", "frm/s"
    );
    let mut summary: BTreeMap<(String, &'static str), Sums> = BTreeMap::new();
    for &scene in &args.scenes {
        for &seed in &args.seeds {
            let dir = args.dir.join(format!("{scene}-s{seed}"));
            if !dir.join("gt/meta.json").is_file() {
                let mut o = FixtureOptions::new(scene);
                o.seed = seed;
                o.corruptions = Corruptions::realistic();
                eprintln!("generating {}", dir.display());
                generate(&dir, &o)?;
            }
            // The paper's baselines (sensor depth, TSDF) take the poses as captured.
            let scan = load(&dir, &LoadOptions::default())?;
            let mut fitted_scan = scan.clone();
            let suffix = if args.refine_poses { "" } else { "-captured-poses" };
            let model_path = dir.join(format!("model-{}s{suffix}.nlf", args.fit_seconds));
            let model = if model_path.is_file() {
                Model::load(&model_path)?
            } else {
                eprintln!("fitting {scene} seed {seed} for {} s", args.fit_seconds);
                let opts = FitOptions {
                    settings: FitSettings {
                        seed,
                        refine_poses: args.refine_poses,
                        ..FitSettings::default()
                    },
                    time: Some(args.fit_seconds),
                    ..FitOptions::default()
                };
                let t = Instant::now();
                let out = fit(&mut fitted_scan, &opts, &AtomicBool::new(false), &mut |_| {})?;
                eprintln!(
                    "  {} steps in {:.0} s",
                    out.model.header.steps,
                    t.elapsed().as_secs_f64()
                );
                out.model.save(&model_path)?;
                out.model
            };
            model.apply_fitted_poses(&mut fitted_scan);
            let h = nerflabel::evaluate::score_holdout(&model, &dir)?;
            println!(
                "{scene} seed {seed}: {} steps; held-out views against exact truth: PSNR {:.2} dB, SSIM {:.3}, depth MAE {:.1} mm",
                model.header.steps,
                h.psnr,
                h.ssim,
                h.depth_mae_m * 1000.0
            );
            let truth = fixture_truth(&dir, &scan, args.every)?;
            // TSDF fused around the loose boxes (they hold the snug ones), ray cast into the scored frames.
            let tsdf_scan = if args.tsdf {
                let t = Instant::now();
                let loose = read_boxes(&dir.join("gt/boxes_loose.json"))?;
                let fused = nerflabel::boxes::tsdf::BoxTsdf::fuse(&scan.frames, &loose, tsdf::VOXEL_M);
                let mut cast = scan.clone();
                for (i, _) in &truth {
                    cast.frames[*i] = tsdf::raycast_frame(&fused, &scan.frames[*i]);
                }
                eprintln!("  TSDF fused and cast in {:.1} s", t.elapsed().as_secs_f64());
                Some(cast)
            } else {
                None
            };
            for (drawing, file) in [("snug", "boxes_user.json"), ("loose", "boxes_loose.json")] {
                let boxes = read_boxes(&dir.join("gt").join(file))?;
                let scan_for = |s: DepthSource| if s.needs_model() { &fitted_scan } else { &scan };
                let runs = DepthSource::ALL
                    .into_iter()
                    .map(|s| (s.name(), s, scan_for(s)))
                    .chain(tsdf_scan.iter().map(|c| ("tsdf", DepthSource::Sensor, c)));
                for (name, source, scan) in runs {
                    let opts = LabelOptions {
                        source,
                        exact_boxes: args.exact_boxes,
                        overlap: args.overlap,
                        snap_to_colour: args.snap,
                        ..LabelOptions::default()
                    };
                    let e = evaluate_labels(scan, &boxes, Some(&model), &truth, opts)?;
                    print_line(&scene.to_string(), seed, drawing, name, &e);
                    if args.objects {
                        print_objects(&e, &boxes);
                    }
                    let c = e.scores.total_counts();
                    let s = summary.entry((drawing.to_string(), name)).or_default();
                    s.n += 1;
                    s.miou += e.scores.mean_frame_iou();
                    s.ratio += c.pixel_ratio();
                    s.fp += c.false_positives();
                    s.fn_ += c.false_negatives();
                    s.bf += c.boundary_f();
                }
            }
        }
    }
    println!(
        "\nMeans over {} scene(s) x {} seed(s), fit {} s:\n",
        args.scenes.len(),
        args.seeds.len(),
        args.fit_seconds
    );
    println!("| boxes | source | mIoU | predicted/true px | FP:FN | boundary F (2 px) |");
    println!("|---|---|---|---|---|---|");
    for ((drawing, source), s) in &summary {
        let n = s.n as f64;
        println!(
            "| {drawing} | {source} | {:.3} | {:.3} | {:.1} | {:.3} |",
            s.miou / n,
            s.ratio / n,
            s.fp as f64 / s.fn_.max(1) as f64,
            s.bf / n
        );
    }
    Ok(())
}

fn print_line(scene: &str, seed: u64, drawing: &str, source: &str, e: &LabelEvaluation) {
    let c = e.scores.total_counts();
    println!(
        "{:<9} {:>4} {:<6} {:<7} {:>7.4} {:>7.3} {:>7.1} {:>6.3} {:>7.1}",
        scene,
        seed,
        drawing,
        source,
        e.scores.mean_frame_iou(),
        c.pixel_ratio(),
        c.false_positives() as f64 / c.false_negatives().max(1) as f64,
        c.boundary_f(),
        e.frames as f64 / e.seconds
    );
}

fn print_objects(e: &LabelEvaluation, boxes: &nerflabel::boxes::BoxSet) {
    for (id, c) in e.scores.object_counts() {
        let label = boxes
            .boxes
            .iter()
            .find(|b| b.instance_id == *id as u32)
            .map_or("?", |b| b.label.as_str());
        println!(
            "    {id}:{label:<8} IoU {:.4}  ratio {:.3}  FP {:>7}  FN {:>7}  bF {:.3}",
            c.iou(),
            c.pixel_ratio(),
            c.false_positives(),
            c.false_negatives(),
            c.boundary_f()
        );
    }
}
