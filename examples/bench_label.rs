//! Labelling accuracy and speed: sensor vs nerf vs fused depth sources
//! against exact ground-truth masks of a generated fixture (default: the
//! tabletop scene, 640x480, 120 frames), or against the silhouettes of
//! `reference_box.json` on the real cabinet scan (frames 1-57).
//!
//! Run: `cargo run --release --example bench_label -- [FIXTURE_DIR] [--fit-seconds S]`
//! Options: `--scene tabletop|small|cabinet`, `--size WxH`, `--frames N`,
//! `--model PATH` (load if present, else fit and save there),
//! `--cabinet [SCAN]` (real scan; default ../shared/data/scans/cabinet),
//! `--fused-cells C` (fused agreement tolerance in finest grid cells),
//! `--box-cells C` (surface points this many cells in front of a box the ray enters count for it),
//! `--clean` (generate the fixture without sensor corruptions),
//! `--boxes FILE` (boxes to label with, relative to the fixture, e.g. `gt/boxes_loose.json`; default `boxes.json`),
//! `--realistic` (generate the fixture as hard as a handheld scan: JPEG colour, pose error),
//! `--loose M` (boxes grown by M metres on every side, bottom 2 cm into the support),
//! `--exact-boxes` (no support or wall plane excluded from the boxes),
//! `--no-pose-refine` (fit with the poses as captured),
//! `--cleanup F` (mask clean-up fraction, 0 = off),
//! `--no-colour-snap` (silhouettes not moved onto the colour edges),
//! `--opacity A` (accumulated opacity that marks the rendered surface),
//! `--depth-errors` (fixture: rendered depth against exact depth inside each object),
//! `--dump DIR` (error images of every 10th frame: green = right, red =
//! labelled but not in the reference, blue = missed, yellow = wrong id).

use nalgebra::{Point3, Vector3};
use nerflabel::boxes::{read_boxes, BoxClassifier, BoxSet, DepthSource, LabelOptions, Labeler};
use nerflabel::evaluate::{evaluate_labels, fixture_truth, read_gray16};
use nerflabel::fixture::{generate, FixtureOptions, SceneKind};
use nerflabel::nerf::model_file::Model;
use nerflabel::nerf::train::fit::{fit, FitEvent, FitOptions};
use nerflabel::nerf::train::settings::FitSettings;
use nerflabel::scan::{load, Frame, LoadOptions, Scan};
use std::path::{Path, PathBuf};
use std::sync::atomic::AtomicBool;
use std::time::Instant;

type Error = Box<dyn std::error::Error>;

struct Args {
    dir: PathBuf,
    fit_seconds: f64,
    scene: SceneKind,
    size: (u32, u32),
    frames: usize,
    model: Option<PathBuf>,
    cabinet: Option<PathBuf>,
    fused_cells: f64,
    box_cells: f64,
    clean: bool,
    dump: Option<PathBuf>,
    depth_errors: bool,
    opacity: f32,
    cleanup: f64,
    snap_to_colour: bool,
    /// Grow every box by this margin on each side, bottom 2 cm below the original.
    loose: Option<f64>,
    exact_boxes: bool,
    refine_poses: bool,
    boxes: PathBuf,
    realistic: bool,
}

fn shared_data() -> PathBuf {
    std::env::var_os("NERFLABEL_SHARED_DATA")
        .map(PathBuf::from)
        .unwrap_or_else(|| PathBuf::from(concat!(env!("CARGO_MANIFEST_DIR"), "/../shared/data")))
}

fn parse_args() -> Result<Args, Error> {
    let mut args = Args {
        dir: std::env::temp_dir().join("nerflabel-bench-label-tabletop"),
        fit_seconds: 60.0,
        scene: SceneKind::Tabletop,
        size: (640, 480),
        frames: 120,
        model: None,
        cabinet: None,
        fused_cells: LabelOptions::default().fused_tolerance_cells,
        box_cells: LabelOptions::default().box_tolerance_cells,
        clean: false,
        dump: None,
        depth_errors: false,
        opacity: LabelOptions::default().surface_opacity,
        cleanup: LabelOptions::default().cleanup_fraction,
        snap_to_colour: true,
        loose: None,
        exact_boxes: false,
        refine_poses: true,
        boxes: PathBuf::from("boxes.json"),
        realistic: false,
    };
    let mut it = std::env::args().skip(1).peekable();
    while let Some(a) = it.next() {
        let mut value = |name: &str| it.next().ok_or_else(|| format!("{name} needs a value"));
        match a.as_str() {
            "--fit-seconds" => args.fit_seconds = value("--fit-seconds")?.parse()?,
            "--scene" => args.scene = value("--scene")?.parse().map_err(|e| format!("{e:?}"))?,
            "--frames" => args.frames = value("--frames")?.parse()?,
            "--model" => args.model = Some(value("--model")?.into()),
            "--clean" => args.clean = true,
            "--loose" => args.loose = Some(value("--loose")?.parse()?),
            "--exact-boxes" => args.exact_boxes = true,
            "--no-pose-refine" => args.refine_poses = false,
            "--boxes" => args.boxes = value("--boxes")?.into(),
            "--realistic" => args.realistic = true,
            "--cleanup" => args.cleanup = value("--cleanup")?.parse()?,
            "--no-colour-snap" => args.snap_to_colour = false,
            "--opacity" => args.opacity = value("--opacity")?.parse()?,
            "--depth-errors" => args.depth_errors = true,
            "--dump" => args.dump = Some(value("--dump")?.into()),
            "--fused-cells" => args.fused_cells = value("--fused-cells")?.parse()?,
            "--box-cells" => args.box_cells = value("--box-cells")?.parse()?,
            "--size" => {
                let v = value("--size")?;
                let (w, h) = v.split_once('x').ok_or("--size WxH")?;
                args.size = (w.parse()?, h.parse()?);
            }
            "--cabinet" => {
                let next_is_path = it.peek().is_some_and(|p| !p.starts_with("--"));
                args.cabinet = Some(if next_is_path {
                    it.next().unwrap_or_default().into()
                } else {
                    shared_data().join("scans/cabinet")
                });
            }
            other if !other.starts_with("--") => args.dir = other.into(),
            other => return Err(format!("unknown option {other}").into()),
        }
    }
    Ok(args)
}

/// Fit (or load) the model of a scan; the scan takes the poses it was fitted with.
fn model_for(scan: &mut Scan, path: &Path, seconds: f64, refine_poses: bool) -> Result<Model, Error> {
    if path.is_file() {
        eprintln!("loading {}", path.display());
        let model = Model::load(path)?;
        model.apply_fitted_poses(scan);
        return Ok(model);
    }
    eprintln!("fitting for {seconds} s ...");
    let opts = FitOptions {
        settings: FitSettings {
            holdout_every: 0,
            refine_poses,
            ..FitSettings::default()
        },
        time: Some(seconds),
        ..FitOptions::default()
    };
    let t = Instant::now();
    let out = fit(scan, &opts, &AtomicBool::new(false), &mut |e| {
        if let FitEvent::Prepared { train_views, .. } = e {
            eprintln!("  {train_views} training views");
        }
    })?;
    eprintln!(
        "  fitted {} steps in {:.1} s",
        out.model.header.steps,
        t.elapsed().as_secs_f64()
    );
    out.model.save(path)?;
    Ok(out.model)
}

/// Silhouette of a box set in a frame: pixels whose centre ray meets a box.
fn silhouette(frame: &Frame, boxes: &BoxSet) -> Vec<u16> {
    let classifier = BoxClassifier::new(boxes);
    let (w, h) = frame.size();
    let origin = Point3::from(frame.camera_to_world.translation.vector);
    let rot = frame.camera_to_world.rotation;
    let mut mask = vec![0u16; (w * h) as usize];
    for y in 0..h {
        for x in 0..w {
            let dir = rot * frame.intrinsics.unproject(x as f64, y as f64);
            if classifier.ray_interval(&origin, &dir).is_some() {
                mask[(y * w + x) as usize] = 1;
            }
        }
    }
    mask
}

/// Rendered (full-frame) depth against the exact depth on each object's ground-truth pixels.
fn depth_errors(
    dir: &Path,
    boxes: &BoxSet,
    model: &Model,
    frames: &[&Frame],
    truth: &[(usize, Vec<u16>)],
    surface_opacity: f32,
) -> Result<(), Error> {
    let unit = nerflabel::fixture::read_meta(dir)?.gt_depth_unit;
    let opts = LabelOptions {
        source: DepthSource::Nerf,
        full_depth: true,
        surface_opacity,
        ..LabelOptions::default()
    };
    let labeler = Labeler::new(boxes, Some(model), opts)?;
    let t = Instant::now();
    let labels = labeler.label_frames(frames, &|_| {});
    println!(
        "full-frame depth (--depth): {:.1} frames/s",
        frames.len() as f64 / t.elapsed().as_secs_f64()
    );
    let mut per: std::collections::BTreeMap<u16, Vec<f64>> = Default::default();
    for (l, (_, gt)) in labels.iter().zip(truth) {
        let exact = read_gray16(&dir.join("gt/depth").join(format!("{}.png", l.name)))?;
        let depth = l.depth_m.as_ref().ok_or("no depth")?;
        for i in 0..gt.len() {
            if gt[i] != 0 {
                let z = exact[i] as f64 * unit;
                per.entry(gt[i])
                    .or_default()
                    .push(if depth[i] > 0.0 { depth[i] as f64 - z } else { f64::NAN });
            }
        }
    }
    println!("rendered depth minus exact depth on object pixels (mm): none%  p5  p25  median  p75  p95  |err|>5mm%");
    for (id, mut e) in per {
        let n = e.len();
        let none = e.iter().filter(|v| v.is_nan()).count();
        e.retain(|v| !v.is_nan());
        e.sort_by(f64::total_cmp);
        let q = |f: f64| {
            e.get(((e.len() as f64 - 1.0) * f) as usize)
                .map_or(f64::NAN, |v| v * 1000.0)
        };
        let big = e.iter().filter(|v| v.abs() > 0.005).count();
        println!(
            "  {id}: {:5.1} {:7.1} {:6.1} {:6.1} {:6.1} {:7.1} {:5.1}",
            100.0 * none as f64 / n as f64,
            q(0.05),
            q(0.25),
            q(0.5),
            q(0.75),
            q(0.95),
            100.0 * big as f64 / n as f64
        );
    }
    Ok(())
}

/// Error images of every 10th frame.
fn dump_errors(
    dir: &Path,
    source: DepthSource,
    labels: &[nerflabel::boxes::FrameLabel],
    truth: &[(usize, Vec<u16>)],
) -> Result<(), Error> {
    std::fs::create_dir_all(dir)?;
    for (l, (_, gt)) in labels.iter().zip(truth).step_by(10) {
        let rgb: Vec<u8> = l
            .mask
            .iter()
            .zip(gt)
            .flat_map(|(&p, &t)| match (p, t) {
                (0, 0) => [0, 0, 0],
                (p, t) if p == t => [0, 160, 0],
                (p, 0) if p != 0 => [255, 0, 0],
                (0, _) => [0, 80, 255],
                _ => [255, 255, 0],
            })
            .collect();
        let img = image::RgbImage::from_raw(l.width, l.height, rgb).ok_or("image size")?;
        img.save(dir.join(format!("{}_{}.png", source.name(), l.name)))?;
    }
    Ok(())
}

fn main() -> Result<(), Error> {
    let args = parse_args()?;
    let (mut scan, boxes, truth, model_path): (Scan, BoxSet, Vec<(usize, Vec<u16>)>, PathBuf) = match &args.cabinet {
        Some(root) => {
            let scan = load(root, &LoadOptions::default())?;
            let boxes = read_boxes(&root.join("boxes.json"))?;
            let reference = read_boxes(&root.join("reference_box.json"))?;
            let truth = scan
                .frames
                .iter()
                .enumerate()
                .filter(|(_, f)| (1..=57).contains(&f.id))
                .map(|(i, f)| (i, silhouette(f, &reference)))
                .collect();
            let model = args.model.clone().unwrap_or_else(|| {
                std::env::temp_dir().join(format!("nerflabel-bench-cabinet-{}s.nlf", args.fit_seconds))
            });
            (scan, boxes, truth, model)
        }
        None => {
            if !args.dir.join("gt/meta.json").is_file() {
                let mut o = FixtureOptions::new(args.scene);
                (o.width, o.height, o.frames) = (args.size.0, args.size.1, Some(args.frames));
                if args.clean {
                    o.corruptions = nerflabel::fixture::Corruptions::none();
                } else if args.realistic {
                    o.corruptions = nerflabel::fixture::Corruptions::realistic();
                }
                eprintln!("generating {} fixture in {}", args.scene, args.dir.display());
                generate(&args.dir, &o)?;
            }
            let scan = load(&args.dir, &LoadOptions::default())?;
            let boxes = read_boxes(&args.dir.join(&args.boxes))?;
            let truth = fixture_truth(&args.dir, &scan, 1)?;
            let model = args
                .model
                .clone()
                .unwrap_or_else(|| args.dir.join(format!("nerflabel/bench-{}s.nlf", args.fit_seconds)));
            (scan, boxes, truth, model)
        }
    };
    let model = model_for(&mut scan, &model_path, args.fit_seconds, args.refine_poses)?;
    let boxes = match args.loose {
        // Boxes as users draw them: a margin on every side, the bottom 2 cm into the support (boxes stand upright, z up).
        Some(margin) => BoxSet::from_boxes(
            boxes
                .boxes
                .iter()
                .map(|b| {
                    let bottom = b.center.z - b.size.z / 2.0;
                    let height = b.size.z + margin + 0.02;
                    let mut loose = b.clone();
                    loose.size = Vector3::new(b.size.x + 2.0 * margin, b.size.y + 2.0 * margin, height);
                    loose.center.z = bottom - 0.02 + height / 2.0;
                    loose
                })
                .collect(),
        ),
        None => boxes,
    };
    let frames: Vec<&Frame> = truth.iter().map(|(i, _)| &scan.frames[*i]).collect();
    let (w, h) = scan.size();
    println!(
        "{} frames {w}x{h}, {} boxes, model {} steps; {} threads",
        frames.len(),
        boxes.boxes.len(),
        model.header.steps,
        rayon::current_num_threads()
    );
    let mut header = format!("{:<7} {:>8} {:>8} {:>7}", "source", "mIoU/frm", "box IoU", "frm/s");
    for b in &boxes.boxes {
        header.push_str(&format!(
            " {:>9}",
            format!("{}:{}", b.instance_id, b.label)
                .chars()
                .take(9)
                .collect::<String>()
        ));
    }
    println!("{header}   (per-object IoU aggregated over frames)");
    if args.depth_errors && args.cabinet.is_none() {
        depth_errors(&args.dir, &boxes, &model, &frames, &truth, args.opacity)?;
    }
    for source in DepthSource::ALL {
        let opts = LabelOptions {
            source,
            fused_tolerance_cells: args.fused_cells,
            box_tolerance_cells: args.box_cells,
            surface_opacity: args.opacity,
            cleanup_fraction: args.cleanup,
            exact_boxes: args.exact_boxes,
            snap_to_colour: args.snap_to_colour,
            ..LabelOptions::default()
        };
        let e = evaluate_labels(&scan, &boxes, Some(&model), &truth, opts)?;
        if let Some(dir) = &args.dump {
            dump_errors(dir, source, &e.labels, &truth)?;
        }
        let per = e.scores.per_object();
        let mut line = format!(
            "{:<7} {:>8.4} {:>8.4} {:>7.1}",
            source.name(),
            e.scores.mean_frame_iou(),
            e.scores.mean_box_iou(),
            e.frames as f64 / e.seconds
        );
        for b in &boxes.boxes {
            line.push_str(&format!(
                " {:>9.4}",
                per.get(&(b.instance_id as u16)).copied().unwrap_or(0.0)
            ));
        }
        let c = e.scores.total_counts();
        line.push_str(&format!(
            "   ({:.1} s, {:.1} % of pixels rendered, predicted/true pixels {:.3}, FP:FN {:.1}, boundary F {:.3})",
            e.seconds,
            100.0 * e.rendered_fraction,
            c.pixel_ratio(),
            c.false_positives() as f64 / c.false_negatives().max(1) as f64,
            c.boundary_f()
        ));
        println!("{line}");
    }
    Ok(())
}
