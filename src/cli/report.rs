//! `nerflabel report`: print the error-against-run-time curve of a fit.

use super::common::{model_path, work_dir};
use super::ReportArgs;
use anyhow::Context;
use nerflabel::evaluate::{WrittenLabelScore, EVALUATION_FILE};
use nerflabel::nerf::train::report::{legacy_report_path, report_path, CurvePoint, FitReport};
use nerflabel::plot::{render_panels, write_png, Panel, Series};
use std::path::Path;

/// Series colours of the plot's panels.
const PSNR: [u8; 3] = [31, 119, 180];
const SSIM: [u8; 3] = [214, 39, 40];
const DEPTH: [u8; 3] = [44, 160, 44];
const LABELS: [u8; 3] = [148, 103, 189];

pub fn run(args: &ReportArgs) -> anyhow::Result<()> {
    let model = model_path(&args.scan, args.model.as_ref());
    // Reports of earlier versions sit in `fit_report.json` beside the model.
    let path = Some(report_path(&model))
        .filter(|p| p.exists())
        .unwrap_or_else(|| legacy_report_path(&model));
    let bytes = std::fs::read(&path).with_context(|| {
        format!(
            "{}: cannot read the fit report (run `nerflabel fit` first)",
            path.display()
        )
    })?;
    let report: FitReport =
        serde_json::from_slice(&bytes).with_context(|| format!("{}: not a valid fit report", path.display()))?;
    println!(
        "fit of {} ({} training frames, preset {:?}, seed {}, {} threads)",
        report.scan, report.train_frames, report.preset, report.seed, report.threads
    );
    println!(
        "{:>9} {:>7} {:>9} {:>7} {:>14} {:>12}",
        "wall s", "step", "PSNR dB", "SSIM", "depth MAE mm", "k samples/s"
    );
    for p in &report.curve {
        let depth = p
            .depth_mae_m
            .map(|d| format!("{:.1}", d * 1e3))
            .unwrap_or_else(|| "n/a".into());
        println!(
            "{:>9.1} {:>7} {:>9.2} {:>7.3} {:>14} {:>12.0}",
            p.seconds,
            p.step,
            p.psnr,
            p.ssim,
            depth,
            p.samples_per_s / 1e3
        );
    }
    let labels = label_score(&args.scan, &model)?;
    if let Some(l) = &labels {
        println!(
            "labels: mIoU {:.3} against {} over {} frames ({} depth; {})",
            l.miou,
            l.truth,
            l.frames,
            l.source,
            work_dir(&args.scan).join("labels").join(EVALUATION_FILE).display()
        );
    }
    if let Some(plot) = &args.plot {
        let points = |f: fn(&CurvePoint) -> Option<f64>| -> Vec<(f64, f64)> {
            report
                .curve
                .iter()
                .filter_map(|p| f(p).map(|v| (p.seconds, v)))
                .collect()
        };
        let panel = |title: &str, y: &str, points: Vec<(f64, f64)>, color: [u8; 3], log_y: bool| Panel {
            title: title.into(),
            x_label: "wall time of the fit (s)".into(),
            y_label: y.into(),
            series: vec![Series {
                name: "held-out".into(),
                points,
                color,
            }],
            log_y,
        };
        // Depth error on a log axis: the first points (metres) would flatten
        // the millimetres of the converged fit on a linear one.
        let panels = [
            panel("Held-out PSNR", "PSNR (dB)", points(|p| Some(p.psnr)), PSNR, false),
            panel("Held-out SSIM", "SSIM", points(|p| Some(p.ssim)), SSIM, false),
            panel(
                "Held-out depth error",
                "depth MAE (mm, log)",
                points(|p| p.depth_mae_m.map(|d| d * 1e3)),
                DEPTH,
                true,
            ),
        ];
        let mut panels = panels.to_vec();
        // The labels scored by `label`, at the wall time the model was trained for.
        if let (Some(l), Some(last)) = (&labels, report.curve.last()) {
            panels.push(panel(
                "Label mIoU against the ground truth",
                "mIoU",
                vec![(last.seconds, l.miou)],
                LABELS,
                false,
            ));
        }
        let height = 350 * panels.len() as u32;
        write_png(plot, &render_panels(&panels, 1000, height))?;
        println!("plot: {}", plot.display());
    }
    Ok(())
}

/// The score `label` kept beside the default labels when the scan has
/// ground truth and the labels came from this model.
fn label_score(scan: &Path, model: &Path) -> anyhow::Result<Option<WrittenLabelScore>> {
    let path = work_dir(scan).join("labels").join(EVALUATION_FILE);
    if !path.is_file() {
        return Ok(None);
    }
    let bytes = std::fs::read(&path).with_context(|| format!("cannot read {}", path.display()))?;
    let score: WrittenLabelScore =
        serde_json::from_slice(&bytes).with_context(|| format!("{}: not a label score", path.display()))?;
    let this_model = std::fs::canonicalize(model).ok();
    let same = score.model.as_ref().map(|m| std::fs::canonicalize(m).ok()) == Some(this_model);
    Ok(same.then_some(score))
}
