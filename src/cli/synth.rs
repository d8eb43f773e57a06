//! `nerflabel synth`: render novel views to one Parquet file.

use super::common::{load_scan, model_path, progress_bar, stop_flag, work_dir};
use super::SynthArgs;
use anyhow::Context;
use nerflabel::boxes::read_boxes;
use nerflabel::nerf::model_file::Model;
use nerflabel::synth::{read_poses, synthesize, SynthOptions, SynthProgress};

pub fn run(args: &SynthArgs) -> anyhow::Result<()> {
    let scan_dir = &args.scan.scan;
    let model_path = model_path(scan_dir, args.model.as_ref());
    let out = args.out.clone().unwrap_or_else(|| work_dir(scan_dir).join("synth.parquet"));
    // Boxes: --boxes, else SCAN/boxes.json when present, else none (scene centre).
    let boxes_path = args.boxes.clone().or_else(|| Some(scan_dir.join("boxes.json")).filter(|p| p.exists()));
    let boxes = boxes_path.as_deref().map(read_boxes).transpose()?;
    let poses = args.poses.as_deref().map(read_poses).transpose()?;
    let model_bytes = std::fs::read(&model_path)
        .with_context(|| format!("{}: cannot read the model (run `nerflabel fit` first)", model_path.display()))?;
    let model_checksum = crc32fast::hash(&model_bytes);
    let model = Model::from_bytes(&model_bytes, &model_path)?;
    drop(model_bytes);
    let scan = load_scan(&args.scan)?;
    let options = SynthOptions {
        n: args.n,
        width: args.width,
        height: args.height,
        seed: args.seed,
        clearance: args.clearance,
        poses,
        model_checksum,
        ..SynthOptions::default()
    };
    let bar = progress_bar(options.poses.as_ref().map_or(args.n, |p| p.len()) as u64, "{spinner} [{elapsed_precise}] [{bar:30}] {pos}/{len} views {msg} (ETA {eta})");
    let progress = |p: SynthProgress| match p {
        SynthProgress::Prepared { views, clearance_m, cloud_points } => bar.suspend(|| {
            let clearance = clearance_m.map(|c| format!(", clearance {c:.3} m")).unwrap_or_default();
            eprintln!("rendering {views} views ({cloud_points} cloud points{clearance})");
        }),
        SynthProgress::Views { done, seconds, .. } => {
            bar.set_position(done as u64);
            bar.set_message(format!("{:.2} views/s", done as f64 / seconds.max(1e-9)));
        }
    };
    let summary = synthesize(&scan, &model, boxes.as_ref(), &options, &out, &progress, stop_flag())?;
    bar.finish_and_clear();
    println!(
        "wrote {} views to {} ({:.1} MB) in {:.1} s ({:.2} views/s)",
        summary.views,
        out.display(),
        summary.bytes as f64 / 1e6,
        summary.seconds,
        summary.views_per_s
    );
    if summary.attempts > 0 {
        println!("sampled {} candidates; rejected: {}", summary.attempts, summary.rejections);
    }
    Ok(())
}
