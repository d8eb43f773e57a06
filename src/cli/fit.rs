//! `nerflabel fit`: train the NeRF of a scan and write the model and report.

use super::common::{load_scan, model_path, progress_bar, stop_flag, PlainProgress};
use super::verbosity::{detail, note, say};
use super::FitArgs;
use anyhow::{bail, Context};
use nerflabel::nerf::train::checkpoint::{checkpoint_path, Checkpoint};
use nerflabel::nerf::train::fit::{fit, resume, FitEvent, FitOptions, DEFAULT_TIME_S};
use nerflabel::nerf::train::report::report_path;
use nerflabel::outputs::{check_outputs, lock_output, Output, ProtectedInputs};
use nerflabel::scan::DepthNoise;

pub fn run(args: &FitArgs) -> anyhow::Result<()> {
    // `--time` is the wall time of the whole command, loading the scan included.
    let started = std::time::Instant::now();
    let model_path = model_path(&args.scan.scan, args.model.as_ref());
    let checkpoint = checkpoint_path(&model_path);
    let options = FitOptions {
        time: args.time,
        steps: args.steps,
        settings: args.settings.clone(),
        checkpoint: Some(checkpoint.clone()),
        started: Some(started),
        ..FitOptions::default()
    };
    // Settings no fit can train with are refused before the scan is read.
    options.validate()?;
    let report_path = report_path(&model_path);
    let outputs = [
        Output::file(&model_path, "the model"),
        Output::file(&report_path, "the fit report"),
        Output::file(&checkpoint, "the checkpoint"),
    ];
    check_outputs(&outputs, None)?;
    let mut scan = load_scan(&args.scan)?;
    check_outputs(&outputs, Some(&ProtectedInputs::of(&scan)))?;
    // Held until the model, report and checkpoint are written.
    let _lock = lock_output(&model_path, "this model")?;
    let from = if args.resume {
        Some(Checkpoint::load(&checkpoint)?)
    } else {
        None
    };
    let (time, steps) = match &from {
        Some(c) if args.time.is_none() && args.steps.is_none() => (c.header.identity.time, c.header.identity.steps),
        _ => (args.time, args.steps),
    };
    if let Some(c) = &from {
        let p = &c.header.progress;
        note!(
            "resuming from step {} ({:.1} s trained) saved in {}",
            c.steps(),
            p.train_seconds,
            checkpoint.display()
        );
    }
    let budget = match (time, steps) {
        (Some(t), Some(s)) => format!("{t} s or {s} steps"),
        (Some(t), None) => format!("{t} s"),
        (None, Some(s)) => format!("{s} steps"),
        (None, None) => format!("{DEFAULT_TIME_S} s"),
    };
    note!(
        "fitting {} frames of {} ({budget}, preset {})",
        scan.frames.len(),
        args.scan.scan.display(),
        args.settings.preset
    );
    let bar = progress_bar(1000, "{spinner} [{elapsed_precise}] [{bar:30}] {msg} (ETA {eta})");
    let log = PlainProgress::new();
    let stop = stop_flag();
    let mut last_eval = String::new();
    let mut on_event = |event: FitEvent| {
        match event {
        FitEvent::PosesScaled(r) => bar.suspend(|| {
            eprintln!(
                "warning: {}; camera positions multiplied by {:.4}",
                r.verdict, r.applied
            )
        }),
        FitEvent::PosesRefined(r) => {
            bar.suspend(|| note!(
                "aligned {} poses to the depth{}: median disagreement {:.2} mm -> {:.2} mm; largest correction {:.1} mm, {:.2} deg",
                r.frames_refined,
                if r.colour_aligned { " and to each other by colour" } else { "" },
                r.median_disagreement_before_m.unwrap_or(f64::NAN) * 1e3,
                r.median_disagreement_after_m.unwrap_or(f64::NAN) * 1e3,
                r.largest_translation_m * 1e3,
                r.largest_rotation_deg
            ));
            bar.suspend(|| note!("poses vs depth: {}", r.verdict));
        }
        FitEvent::PosesAligned(r) => bar.suspend(|| note!(
            "aligned {} of {} frames' images to the field at step {}: median shift {:.2} px; largest correction {:.1} mm, {:.2} deg",
            r.frames_refined,
            r.frames_aligned,
            r.at_step,
            r.median_shift_px,
            r.largest_translation_m * 1e3,
            r.largest_rotation_deg
        )),
        FitEvent::PosesLearnt(r) => bar.suspend(|| note!(
            "learnt {} training frames' poses with the field: median correction {:.1} mm; largest {:.1} mm, {:.2} deg",
            r.frames.len(),
            r.median_translation_m * 1e3,
            r.largest_translation_m * 1e3,
            r.largest_rotation_deg
        )),
        FitEvent::Prepared {
            train_views,
            holdout_views,
            param_count,
            occupied_fraction,
            depth_noise,
            colour_border,
        } => {
            bar.suspend(|| note!(
                "{train_views} training views, {holdout_views} held out; {param_count} parameters; {:.1} % of space occupied after depth carving",
                occupied_fraction * 100.0
            ));
            if let Some(noise) = depth_noise {
                bar.suspend(|| note!("depth noise: {}", describe_noise(noise)));
            }
            if !colour_border.is_none() {
                bar.suspend(|| note!(
                    "colour images: lines at the edges that show no scene ({}) are left out of the held-out scores",
                    colour_border.describe()
                ));
            }
        }
        FitEvent::Step {
            step, stats, progress, ..
        } => {
            bar.set_position((progress * 1000.0) as u64);
            if step % 8 == 0 {
                bar.set_message(format!("step {step}  loss {:.4}  {last_eval}", stats.loss));
            }
            log.tick(progress, || {
                format!("step {step}, loss {:.4}  {last_eval}", stats.loss)
                    .trim_end()
                    .to_string()
            });
        }
        FitEvent::Eval(p) => {
            bar.suspend(|| {
                detail!(
                    "step {}, {:.1} s: held-out PSNR {:.2} dB, SSIM {:.3}, depth MAE {}",
                    p.step,
                    p.seconds,
                    p.psnr,
                    p.ssim,
                    p.depth_mae_m
                        .map_or_else(|| "n/a".into(), |d| format!("{:.1} mm", d * 1e3))
                )
            });
            last_eval = format!(
                "held-out PSNR {:.2} dB, depth MAE {}  {:.0} k samples/s",
                p.psnr,
                p.depth_mae_m
                    .map(|d| format!("{:.1} mm", d * 1e3))
                    .unwrap_or_else(|| "n/a".into()),
                p.samples_per_s / 1e3
            );
        }
        FitEvent::CheckpointSaved { .. } => bar.suspend(|| detail!("checkpoint saved: {}", checkpoint.display())),
        FitEvent::CheckpointFailed(e) => bar.suspend(|| eprintln!("warning: {e}")),
    }
    };
    let outcome = match from {
        Some(c) => resume(&mut scan, &options, c, stop, &mut on_event)?,
        None => fit(&mut scan, &options, stop, &mut on_event)?,
    };
    bar.finish_and_clear();
    if let Some(why) = outcome.report.failure() {
        // Keep the previous model and report; this run's report goes aside for diagnosis.
        let failed = model_path.with_extension("failed.report.json");
        let json = serde_json::to_vec_pretty(&outcome.report).context("cannot serialise the fit report")?;
        nerflabel::atomic::write_file(&failed, &json).with_context(|| format!("cannot write {}", failed.display()))?;
        bail!(
            "the fit trained no usable model: {why}. {} and its report are unchanged; this run's report: {}",
            model_path.display(),
            failed.display()
        );
    }
    outcome.model.save(&model_path)?;
    let json = serde_json::to_vec_pretty(&outcome.report).context("cannot serialise the fit report")?;
    nerflabel::atomic::write_file(&report_path, &json)
        .with_context(|| format!("cannot write {}", report_path.display()))?;
    let r = &outcome.report;
    if r.interrupted {
        eprintln!("interrupted: saved the model trained so far (`nerflabel fit --resume` continues)");
    }
    say!(
        "trained {} steps in {:.1} s ({} batches skipped); model: {}",
        r.counters.steps,
        r.timings.train_s,
        r.counters.skipped_batches,
        model_path.display()
    );
    // A budget spent before the learning rate has ramped up leaves a field
    // too rough to label from (a 30 s fit of a 120-frame scan: 125 of 128
    // steps, held-out depth off by 1.2 m, no label drawn).
    let warmup = r.train.warmup_steps;
    if !r.interrupted && r.counters.steps < warmup {
        let per_step = r.timings.train_s / r.counters.steps.max(1) as f64;
        eprintln!(
            "warning: training stopped after {} steps, inside the {warmup}-step warm-up: the model is too rough to \
             label from; about {:.0} s more of training reach the end of the warm-up (give a larger --time or --steps)",
            r.counters.steps,
            (warmup - r.counters.steps) as f64 * per_step
        );
    }
    if let Some(p) = r.curve.last() {
        say!(
            "held-out: PSNR {:.2} dB, SSIM {:.3}, depth MAE {}",
            p.psnr,
            p.ssim,
            p.depth_mae_m
                .map(|d| format!("{:.1} mm", d * 1e3))
                .unwrap_or_else(|| "n/a".into())
        );
    }
    if let Some(a) = &r.appearance {
        say!(
            "appearance: {} frames, colour change median {:.3}, largest {:.3} (frame {}); lens: {:.0} % of the centre's light in the corners",
            a.frames,
            a.median_strength,
            a.largest_strength,
            a.largest_frame,
            100.0 * a.corner_light
        );
    }
    say!("report: {}", report_path.display());
    Ok(())
}

/// The sensor's depth noise at the nearest, middle and farthest measured depths.
fn describe_noise(noise: &DepthNoise) -> String {
    let n = noise.depths.len();
    let mut picks = vec![0, n / 2, n - 1];
    picks.dedup();
    picks
        .iter()
        .map(|&i| format!("{:.1} mm at {:.1} m", noise.sigmas[i] * 1e3, noise.depths[i]))
        .collect::<Vec<_>>()
        .join(", ")
}
