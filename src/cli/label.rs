//! `nerflabel label`: 3D boxes to masks, 2D boxes, object poses and COCO.

use super::common::{check_model_scan, load_scan, model_path, progress_bar, read_model, work_dir, PlainProgress};
use super::LabelArgs;
use nerflabel::boxes::coco::CocoInfo;
use nerflabel::boxes::{read_boxes, write_labels, FrameRange, LabelOptions, Labeler, OutputOptions, YoloOptions};
use nerflabel::outputs::{check_outputs, lock_output, Output, ProtectedInputs};

pub fn run(args: &LabelArgs) -> anyhow::Result<()> {
    let scan_dir = &args.scan.scan;
    let source = args.source;
    let frames: Option<FrameRange> = args.frames.as_deref().map(str::parse).transpose()?;
    let yolo = yolo_options(args)?;
    let boxes = read_boxes(&args.boxes)?;
    let model_path = model_path(scan_dir, args.model.as_ref());
    let model = if source.needs_model() {
        Some(read_model(&model_path)?.0)
    } else {
        None
    };
    let out = args.out.clone().unwrap_or_else(|| work_dir(scan_dir).join("labels"));
    let outputs = [Output::folder(&out, "the labels")];
    check_outputs(&outputs, None)?;
    let mut scan = load_scan(&args.scan)?;
    check_outputs(&outputs, Some(&ProtectedInputs::of(&scan)))?;
    if let Some(model) = &model {
        check_model_scan(model, &model_path, &mut scan, args.force)?;
    }
    let _lock = lock_output(&out, "these labels")?;
    let options = LabelOptions {
        source,
        full_depth: args.depth,
        exact_boxes: args.exact_boxes,
        overlap: args.overlap,
        snap_to_colour: !args.no_colour_snap,
        ..LabelOptions::default()
    };
    let mut labeler = Labeler::new(&boxes, model.as_ref(), options)?;
    let planes = labeler.exclude_supports(&scan)?;
    if planes > 0 {
        eprintln!(
            "excluded {planes} support or wall plane(s) from the boxes they run through (--exact-boxes keeps them)"
        );
    }
    labeler.fuse_sensor_depth(&scan);
    let info = CocoInfo {
        description: "nerflabel instance labels".into(),
        nerflabel_version: env!("CARGO_PKG_VERSION").into(),
        source: source.name().into(),
        overlap: args.overlap.name().into(),
        colour_snap: !args.no_colour_snap,
        seed: model.as_ref().map(|m| m.header.seed),
        scan: scan_dir.display().to_string(),
        boxes: args.boxes.display().to_string(),
        model: model.as_ref().map(|_| model_path.display().to_string()),
        model_steps: model.as_ref().map(|m| m.header.steps),
        frames: args.frames.clone(),
    };
    let output = OutputOptions { frames, yolo, info };
    let total = scan
        .frames
        .iter()
        .filter(|f| frames.is_none_or(|r| r.contains(f.id)))
        .count();
    let bar = progress_bar(
        total as u64,
        "{spinner} [{elapsed_precise}] [{bar:30}] {pos}/{len} frames (ETA {eta})",
    );
    let log = PlainProgress::new();
    let summary = write_labels(&out, &scan, &boxes, &labeler, &output, &|done| {
        bar.set_position(done as u64);
        log.tick(done as f64 / total.max(1) as f64, || {
            format!("{done} of {total} frames")
        });
    })?;
    bar.finish_and_clear();
    for warning in &summary.warnings {
        eprintln!("warning: {warning}");
    }
    let work = match (args.depth, source.needs_model()) {
        (true, true) => "rendered every pixel (--depth)".to_string(),
        (true, false) => "wrote every pixel's sensor depth (--depth)".to_string(),
        (false, model) => format!(
            "{} {:.1} % of the pixels (rays that can meet a box)",
            if model { "rendered" } else { "classified" },
            summary.box_pixel_fraction * 100.0
        ),
    };
    println!(
        "labelled {} frames with {} depth: {} annotations in {}; {work}",
        summary.frames,
        source,
        summary.annotations,
        summary.out.display()
    );
    if let Some((train, val)) = summary.yolo_split {
        println!(
            "YOLO dataset for ultralytics: {} ({train} training and {val} validation frames)",
            summary.out.join("yolo").join("data.yaml").display()
        );
    }
    Ok(())
}

/// The YOLO options, or `None` without --yolo / --yolo-seg (whose own
/// options are then refused rather than ignored).
fn yolo_options(args: &LabelArgs) -> anyhow::Result<Option<YoloOptions>> {
    if !(args.yolo || args.yolo_seg) {
        if args.yolo_images.is_some() || args.yolo_val.is_some() {
            anyhow::bail!("--yolo-images and --yolo-val shape the YOLO dataset: add --yolo (or --yolo-seg)");
        }
        return Ok(None);
    }
    let defaults = YoloOptions::default();
    Ok(Some(YoloOptions {
        images: args.yolo_images.unwrap_or(defaults.images),
        segments: args.yolo_seg,
        val_fraction: args.yolo_val.unwrap_or(defaults.val_fraction),
        seed: args.seed,
    }))
}
