//! `nerflabel label`: 3D boxes (and/or given masks of a few frames) to
//! masks, 2D boxes, object poses and COCO for every frame.

use super::common::{check_model_scan, load_scan, model_path, progress_bar, read_model, work_dir, PlainProgress};
use super::verbosity::{note, say};
use super::LabelArgs;
use anyhow::Context;
use nerflabel::boxes::coco::CocoInfo;
use nerflabel::boxes::output::FrameLabelling;
use nerflabel::boxes::{
    read_boxes, write_labels, BoxSet, FrameRange, LabelOptions, LabelSummary, Labeler, OutputOptions, YoloOptions,
};
use nerflabel::evaluate::{score_written_labels, WrittenLabelScore, EVALUATION_FILE};
use nerflabel::masks::{lift, objects_and_boxes, read_masks, GivenMasks, Lifted, MaskLabeler};
use nerflabel::nerf::model_file::Model;
use nerflabel::outputs::{check_outputs, lock_output, Output, ProtectedInputs};
use nerflabel::scan::Scan;
use std::path::Path;

pub fn run(args: &LabelArgs) -> anyhow::Result<()> {
    let scan_dir = &args.scan.scan;
    let source = args.source;
    let frames: Option<FrameRange> = args.frames.as_deref().map(str::parse).transpose()?;
    let yolo = yolo_options(args)?;
    let boxes = args.boxes.as_deref().map(read_boxes).transpose()?;
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
    let box_labeler = match &boxes {
        Some(boxes) => Some(box_labeler(boxes, model.as_ref(), &scan, options)?),
        None => None,
    };
    let info = CocoInfo {
        description: "nerflabel instance labels".into(),
        nerflabel_version: env!("CARGO_PKG_VERSION").into(),
        source: source.name().into(),
        overlap: args.overlap.name().into(),
        colour_snap: !args.no_colour_snap,
        seed: model.as_ref().map(|m| m.header.seed),
        boxes: args.boxes.as_ref().map(|b| b.display().to_string()).unwrap_or_default(),
        masks: args.masks.as_ref().map(|m| m.display().to_string()),
        model: model.as_ref().map(|_| model_path.display().to_string()),
        model_steps: model.as_ref().map(|m| m.header.steps),
        frames: args.frames.clone(),
        ..CocoInfo::default()
    };
    let image_root = args
        .image_root
        .as_ref()
        .map(|dir| {
            std::fs::canonicalize(dir)
                .with_context(|| format!("{}: --image-root must be an existing folder", dir.display()))
        })
        .transpose()?;
    let output = OutputOptions {
        frames,
        yolo,
        info,
        image_root,
    };
    let summary = match (&args.masks, &boxes, &box_labeler) {
        (Some(dir), _, _) => {
            let boxes = boxes.as_ref().zip(box_labeler.as_ref());
            label_with_masks(dir, &scan, boxes, model.as_ref(), options, &out, &output)?
        }
        (None, Some(boxes), Some(labeler)) => write(&out, &scan, boxes, labeler, &output)?,
        _ => anyhow::bail!("give --boxes FILE, --masks DIR or both"),
    };
    for warning in &summary.warnings {
        eprintln!("warning: {warning}");
    }
    let work = match (args.depth, source.needs_model()) {
        (true, true) => "rendered every pixel (--depth)".to_string(),
        (true, false) => "wrote every pixel's sensor depth (--depth)".to_string(),
        (false, model) => format!(
            "{} {:.1} % of the pixels (rays that can meet {})",
            if model { "rendered" } else { "classified" },
            summary.box_pixel_fraction * 100.0,
            if args.masks.is_some() { "an object" } else { "a box" }
        ),
    };
    say!(
        "labelled {} frames with {} depth: {} annotations in {}; {work}",
        summary.frames,
        source,
        summary.annotations,
        summary.out.display()
    );
    let truth = scan_dir.join("gt").join("masks");
    if truth.is_dir() {
        let model = model
            .as_ref()
            .map(|_| std::fs::canonicalize(&model_path).unwrap_or(model_path.clone()));
        score_against_truth(&summary.out, &truth, model.as_deref(), source.name())?;
    }
    if let Some((train, val)) = summary.yolo_split {
        say!(
            "YOLO dataset for ultralytics: {} ({train} training and {val} validation frames)",
            summary.out.join("yolo").join("data.yaml").display()
        );
    }
    Ok(())
}

/// The boxes' labeler, with the support planes excluded and the sensor depth fused.
fn box_labeler<'a>(
    boxes: &'a BoxSet,
    model: Option<&'a Model>,
    scan: &Scan,
    options: LabelOptions,
) -> anyhow::Result<Labeler<'a>> {
    let mut labeler = Labeler::new(boxes, model, options)?;
    let planes = labeler.exclude_supports(scan)?;
    if planes > 0 {
        note!("excluded {planes} support or wall plane(s) from the boxes they run through (--exact-boxes keeps them)");
    }
    labeler.fuse_sensor_depth(scan);
    Ok(labeler)
}

/// Label and write every selected frame with a progress bar (or plain lines).
fn write(
    out: &Path,
    scan: &Scan,
    objects: &BoxSet,
    labeler: &dyn FrameLabelling,
    output: &OutputOptions,
) -> anyhow::Result<LabelSummary> {
    let total = scan
        .frames
        .iter()
        .filter(|f| output.frames.is_none_or(|r| r.contains(f.id)))
        .count();
    let bar = progress_bar(
        total as u64,
        "{spinner} [{elapsed_precise}] [{bar:30}] {pos}/{len} frames (ETA {eta})",
    );
    let log = PlainProgress::new();
    let summary = write_labels(out, scan, objects, labeler, output, &|done| {
        bar.set_position(done as u64);
        log.tick(done as f64 / total.max(1) as f64, || {
            format!("{done} of {total} frames")
        });
    })?;
    bar.finish_and_clear();
    Ok(summary)
}

/// Fewer given masks than this are lifted through the model's own grid.
const FEW_FRAMES: usize = 20;

/// Read and lift the given masks (`label --masks`, `synth --masks`).
pub(super) fn lift_masks(
    dir: &Path,
    scan: &Scan,
    model: Option<&Model>,
    options: LabelOptions,
) -> anyhow::Result<(GivenMasks, Lifted)> {
    let given = read_masks(dir, scan)?;
    for warning in &given.warnings {
        eprintln!("warning: {warning}");
    }
    let no_boxes = BoxSet::from_boxes(Vec::new());
    let every_pixel = LabelOptions {
        full_depth: true,
        exact_boxes: true,
        few_frames: given.frames.len() < FEW_FRAMES,
        ..options
    };
    let started = std::time::Instant::now();
    let lift_labeler = Labeler::new(&no_boxes, model, every_pixel)?;
    let bar = progress_bar(
        given.frames.len() as u64,
        "{spinner} [{elapsed_precise}] [{bar:30}] {pos}/{len} given masks lifted",
    );
    let lifted = lift(scan, &given, &lift_labeler, &|done| bar.set_position(done as u64))?;
    bar.finish_and_clear();
    for warning in &lifted.warnings {
        eprintln!("warning: {warning}");
    }
    note!(
        "lifted {} masks of {} object(s) in {:.1} s ({} surface points, {:.1} mm voxels)",
        given.frames.len(),
        lifted.objects.boxes.len(),
        started.elapsed().as_secs_f64(),
        lifted.lifted_points,
        lifted.votes.voxel_m() * 1000.0
    );
    const LISTED: usize = 20;
    for b in lifted.objects.boxes.iter().take(LISTED) {
        note!(
            "  object {} (`{}`): {:.3} x {:.3} x {:.3} m at ({:.3}, {:.3}, {:.3})",
            b.instance_id,
            b.label,
            b.size.x,
            b.size.y,
            b.size.z,
            b.center.x,
            b.center.y,
            b.center.z
        );
    }
    if lifted.objects.boxes.len() > LISTED {
        note!("  ... and {} more", lifted.objects.boxes.len() - LISTED);
    }
    Ok((given, lifted))
}

/// `--masks`: lift the given masks, then label every frame from their votes
/// (and the boxes, which take the ids after the largest mask id).
fn label_with_masks(
    dir: &Path,
    scan: &Scan,
    boxes: Option<(&BoxSet, &Labeler)>,
    model: Option<&Model>,
    options: LabelOptions,
    out: &Path,
    output: &OutputOptions,
) -> anyhow::Result<LabelSummary> {
    let (given, lifted) = lift_masks(dir, scan, model, options)?;
    let mut surface = Labeler::new(&lifted.regions, model, options)?;
    surface.fuse_sensor_depth(scan);
    let planes = surface.exclude_supports(scan)?;
    if planes > 0 {
        note!("excluded {planes} support or wall plane(s) from the regions of the masks' objects (--exact-boxes keeps them)");
    }
    let (all, first_box_id) = objects_and_boxes(&lifted, boxes.map(|(b, _)| b))?;
    let boxes = boxes.map(|(_, labeler)| (labeler, first_box_id));
    let labeler = MaskLabeler::new(scan, &given, &lifted, &surface, boxes, &all, options);
    write(out, scan, &all, &labeler, output)
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

/// A generated scan carries its exact masks (`gt/masks`): score the labels
/// against them and keep the score beside the labels (`report --plot` draws it).
fn score_against_truth(out: &Path, truth: &Path, model: Option<&Path>, source: &str) -> anyhow::Result<()> {
    let Some((scores, frames)) = score_written_labels(out, truth).map_err(anyhow::Error::msg)? else {
        return Ok(());
    };
    let score = WrittenLabelScore {
        truth: truth.display().to_string(),
        model: model.map(|m| m.display().to_string()),
        source: source.to_string(),
        frames,
        miou: scores.mean_frame_iou(),
        pixel_ratio: scores.total_counts().pixel_ratio(),
    };
    let path = out.join(EVALUATION_FILE);
    let json = serde_json::to_vec_pretty(&score).context("cannot serialise the label score")?;
    nerflabel::atomic::write_file(&path, &json).with_context(|| format!("cannot write {}", path.display()))?;
    say!(
        "against the scan's ground truth ({}): mIoU {:.3} over {frames} frames, predicted/true pixels {:.3}; {}",
        truth.display(),
        score.miou,
        score.pixel_ratio,
        path.display()
    );
    Ok(())
}
