//! `nerflabel synth`: render novel views to one Parquet file.

use super::common::{
    check_model_scan, load_scan, model_path, progress_bar, read_model, stop_flag, work_dir, PlainProgress,
};
use super::label::lift_masks;
use super::verbosity::{note, say};
use super::SynthArgs;
use anyhow::bail;
use nalgebra::{Point3, Vector3};
use nerflabel::boxes::{read_boxes, BoxClassifier, LabelOptions};
use nerflabel::masks::{objects_and_boxes, PointLabels};
use nerflabel::outputs::{check_outputs, lock_output, Output, ProtectedInputs};
use nerflabel::synth::{
    read_poses, support_planes, synthesize, synthesize_objects, Objects, SynthOptions, SynthProgress,
};

pub fn run(args: &SynthArgs) -> anyhow::Result<()> {
    let scan_dir = &args.scan.scan;
    let model_path = model_path(scan_dir, args.model.as_ref());
    let out = args
        .out
        .clone()
        .unwrap_or_else(|| work_dir(scan_dir).join("synth.parquet"));
    let outputs = [Output::file(&out, "the synthetic views")];
    check_outputs(&outputs, None)?;
    // Boxes: --boxes, else SCAN/boxes.json when present and no masks are
    // given (they would label the masks' objects twice), else none.
    let boxes_path = args
        .boxes
        .clone()
        .or_else(|| Some(scan_dir.join("boxes.json")).filter(|p| p.exists() && args.masks.is_none()));
    let boxes = boxes_path.as_deref().map(read_boxes).transpose()?;
    let poses = args.poses.as_deref().map(read_poses).transpose()?;
    let (model, model_checksum) = read_model(&model_path)?;
    if boxes.is_none() && args.masks.is_none() {
        eprintln!(
            "warning: no boxes (no --boxes, no {}): every mask will be empty",
            scan_dir.join("boxes.json").display()
        );
    }
    let mut scan = load_scan(&args.scan)?;
    check_outputs(&outputs, Some(&ProtectedInputs::of(&scan)))?;
    check_model_scan(&model, &model_path, &mut scan, args.force)?;
    // Two runs writing one file would each replace the other's at its end.
    let _lock = lock_output(&out, "the synthetic views")?;
    if out.exists() && !args.overwrite {
        bail!(
            "{}: exists; pass --overwrite to replace it, or choose another --out",
            out.display()
        );
    }
    let appearance = match args.appearance.as_str() {
        "neutral" => None,
        stem => Some(scan.frames.iter().position(|f| f.name == stem).ok_or_else(|| {
            anyhow::anyhow!(
                "--appearance {stem}: no frame of {} has that stem (use `neutral` or a frame's stem such as {})",
                scan_dir.display(),
                scan.frames.first().map_or("000000", |f| f.name.as_str())
            )
        })?),
    };
    let options = SynthOptions {
        appearance,
        n: args.n,
        width: args.width,
        height: args.height,
        seed: args.seed,
        clearance: args.clearance,
        poses,
        model_checksum,
        exact_boxes: args.exact_boxes,
        ..SynthOptions::default()
    };
    let views = options.poses.as_ref().map_or(args.n, |p| p.len());
    let log = PlainProgress::new();
    let bar = progress_bar(
        views as u64,
        "{spinner} [{elapsed_precise}] [{bar:30}] {pos}/{len} views {msg} (ETA {eta})",
    );
    let progress = |p: SynthProgress| match p {
        SynthProgress::Prepared {
            views,
            clearance_m,
            cloud_points,
        } => bar.suspend(|| {
            let clearance = clearance_m.map(|c| format!(", clearance {c:.3} m")).unwrap_or_default();
            note!("rendering {views} views ({cloud_points} cloud points{clearance})");
        }),
        SynthProgress::Views { done, seconds, .. } => {
            bar.set_position(done as u64);
            bar.set_message(format!("{:.2} views/s", done as f64 / seconds.max(1e-9)));
            log.tick(done as f64 / views.max(1) as f64, || {
                format!(
                    "{done} of {views} views, {:.2} views/s",
                    done as f64 / seconds.max(1e-9)
                )
            });
        }
    };
    let summary = match &args.masks {
        None => synthesize(&scan, &model, boxes.as_ref(), &options, &out, &progress, stop_flag())?,
        Some(dir) => {
            let (_, lifted) = lift_masks(dir, &scan, Some(&model), LabelOptions::default())?;
            let (all, first_box_id) = objects_and_boxes(&lifted, boxes.as_ref())?;
            let from_masks = PointLabels::new(&lifted);
            let region_of = lifted.region_of();
            let object_supports = support_planes(&lifted.regions, &model, &scan, args.exact_boxes)?;
            let from_boxes = boxes.as_ref().map(BoxClassifier::new);
            let box_supports = boxes
                .as_ref()
                .map(|b| support_planes(b, &model, &scan, args.exact_boxes))
                .transpose()?;
            // A mask object's surface first; the boxes label the rest. Each
            // loses the support and wall planes `label` excludes from it.
            let classify = |p: Point3<f64>, normal: &dyn Fn(f64) -> Option<Vector3<f64>>| -> u32 {
                let p = &p;
                let id = from_masks.classify(p);
                if id > 0 {
                    let on_support = region_of
                        .get(&id)
                        .is_some_and(|&r| object_supports.excluded_at(r, p, normal));
                    return if on_support { 0 } else { id as u32 };
                }
                let b = from_boxes.as_ref().map_or(0, |c| c.classify(p));
                let on_support = b > 0
                    && box_supports
                        .as_ref()
                        .is_some_and(|s| s.excluded_at(b as usize - 1, p, normal));
                if b == 0 || on_support {
                    0
                } else {
                    b + first_box_id as u32 - 1
                }
            };
            let objects = Objects::of(&all, &classify);
            synthesize_objects(&scan, &model, &objects, &options, &out, &progress, stop_flag())?
        }
    };
    bar.finish_and_clear();
    say!(
        "wrote {} views to {} ({:.1} MB) in {:.1} s ({:.2} views/s)",
        summary.views,
        out.display(),
        summary.bytes as f64 / 1e6,
        summary.seconds,
        summary.views_per_s
    );
    if summary.attempts > 0 {
        say!(
            "sampled {} candidates; rejected: {}",
            summary.attempts,
            summary.rejections
        );
    }
    Ok(())
}
