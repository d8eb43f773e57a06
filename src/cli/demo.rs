//! `nerflabel demo`: generate a fixture scan, run every stage on it and
//! print the accuracy against its exact ground truth.

use super::DemoArgs;
use anyhow::Context;
use nerflabel::boxes::coco::CocoInfo;
use nerflabel::boxes::metrics::MaskScores;
use nerflabel::boxes::{read_boxes, write_labels, DepthSource, LabelOptions, Labeler, OutputOptions, DEFAULT_SOURCE};
use nerflabel::evaluate::score_holdout;
use nerflabel::fixture::{generate, FixtureOptions, SceneKind};
use nerflabel::nerf::train::fit::{fit, FitEvent, FitOptions};
use nerflabel::scan::{load, LoadOptions};
use nerflabel::synth::{synthesize, SynthOptions};
use std::time::Instant;

pub fn run(args: &DemoArgs) -> anyhow::Result<()> {
    let scan_dir = args.out.join("scan");
    let mut options = FixtureOptions::new(SceneKind::Tabletop);
    options.width = 320;
    options.height = 240;
    options.frames = Some(60);
    options.overwrite = true;
    let t = Instant::now();
    let summary =
        generate(&scan_dir, &options).with_context(|| format!("cannot write the demo scan {}", scan_dir.display()))?;
    println!(
        "1. fixture: {} frames {}x{} of the tabletop scene with {} objects (one without sensor depth) in {} ({:.1} s)",
        summary.frames,
        summary.size.0,
        summary.size.1,
        summary.objects,
        scan_dir.display(),
        t.elapsed().as_secs_f64()
    );

    let mut scan =
        load(&scan_dir, &LoadOptions::default()).with_context(|| format!("cannot read {}", scan_dir.display()))?;
    let fit_options = FitOptions {
        time: Some(args.time),
        ..FitOptions::default()
    };
    let stop = super::common::stop_flag();
    let bar = super::common::progress_bar(1000, "   fitting [{elapsed_precise}] [{bar:30}] {msg}");
    let outcome = fit(&mut scan, &fit_options, stop, &mut |event| {
        if let FitEvent::Step {
            step, stats, progress, ..
        } = event
        {
            bar.set_position((progress * 1000.0) as u64);
            bar.set_message(format!("step {step} loss {:.4}", stats.loss));
        }
    })?;
    bar.finish_and_clear();
    let model_path = super::common::model_path(&scan_dir, None);
    outcome.model.save(&model_path)?;
    let json = serde_json::to_vec_pretty(&outcome.report)?;
    nerflabel::atomic::write_file(&nerflabel::nerf::train::report::report_path(&model_path), &json)?;
    println!(
        "2. fit: {} steps in {:.1} s, {:.0} k samples/s; model {}",
        outcome.report.counters.steps,
        outcome.report.timings.train_s,
        outcome.report.counters.samples as f64 / outcome.report.timings.train_s.max(1e-9) / 1e3,
        model_path.display()
    );
    let score = score_holdout(&outcome.model, &scan_dir).context("cannot score the model on the held-out views")?;
    println!(
        "   held-out views vs exact ground truth: PSNR {:.2} dB, SSIM {:.3}, depth MAE {:.1} mm, surface missing on {:.2} % of pixels",
        score.psnr,
        score.ssim,
        score.depth_mae_m * 1e3,
        score.depth_missing * 100.0
    );

    // 3. Label with raw sensor depth (the paper's baseline) and with the model.
    let boxes_path = scan_dir.join("boxes.json");
    let boxes = read_boxes(&boxes_path)?;
    for source in [DepthSource::Sensor, DEFAULT_SOURCE] {
        let options = LabelOptions {
            source,
            ..LabelOptions::default()
        };
        let mut labeler = Labeler::new(&boxes, Some(&outcome.model), options)?;
        labeler.exclude_supports(&scan)?;
        labeler.fuse_sensor_depth(&scan);
        let t = Instant::now();
        let mut scores = MaskScores::default();
        for frame in &scan.frames {
            let label = labeler.label_frame(frame);
            let truth = read_gt_mask(&scan_dir.join("gt").join("masks").join(format!("{}.png", frame.name)))?;
            scores.add(&label.mask, &truth, frame.size().0 as usize);
        }
        println!(
            "3. label ({source} depth): mean per-object IoU {:.3}, mean per-frame IoU {:.3}, 2D box IoU {:.3} over {} frames ({:.1} s)",
            scores.mean_object_iou(),
            scores.mean_frame_iou(),
            scores.mean_box_iou(),
            scan.frames.len(),
            t.elapsed().as_secs_f64()
        );
    }
    let out = scan_dir.join("nerflabel").join("labels");
    let info = CocoInfo {
        source: DEFAULT_SOURCE.name().into(),
        nerflabel_version: env!("CARGO_PKG_VERSION").into(),
        ..CocoInfo::default()
    };
    let mut labeler = Labeler::new(&boxes, Some(&outcome.model), LabelOptions::default())?;
    labeler.exclude_supports(&scan)?;
    labeler.fuse_sensor_depth(&scan);
    let summary = write_labels(
        &out,
        &scan,
        &boxes,
        &labeler,
        &OutputOptions {
            info,
            ..OutputOptions::default()
        },
        &|_| {},
    )?;
    println!(
        "   wrote masks and coco.json ({} annotations) to {}",
        summary.annotations,
        out.display()
    );

    // 4. Novel views to Parquet.
    let synth_out = scan_dir.join("nerflabel").join("synth.parquet");
    let options = SynthOptions {
        n: 8,
        width: Some(160),
        height: Some(120),
        ..SynthOptions::default()
    };
    let s = synthesize(&scan, &outcome.model, Some(&boxes), &options, &synth_out, &|_| {}, stop)?;
    println!(
        "4. synth: {} novel views (colour, depth, mask, 2D boxes) in {:.1} s -> {}",
        s.views,
        s.seconds,
        synth_out.display()
    );
    Ok(())
}

/// A ground-truth instance mask of the fixture.
fn read_gt_mask(path: &std::path::Path) -> anyhow::Result<Vec<u16>> {
    let img = image::open(path).with_context(|| format!("{}: cannot read the ground-truth mask", path.display()))?;
    Ok(match img {
        image::DynamicImage::ImageLuma16(m) => m.into_raw(),
        other => other.into_luma8().into_raw().into_iter().map(u16::from).collect(),
    })
}
