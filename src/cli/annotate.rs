//! `nerflabel annotate`: serve the box annotation page for a scan.

use super::common::{check_model_scan, load_scan, model_path, progress_bar, read_model};
use super::verbosity::note;
use super::AnnotateArgs;
use anyhow::Context;
use nerflabel::annotate::{serve, Session};
use nerflabel::boxes::completed::CLOUD_RAYS;
use std::io::Write;
use std::sync::Arc;

pub fn run(args: &AnnotateArgs) -> anyhow::Result<()> {
    let scan_dir = &args.scan.scan;
    let boxes = args.boxes.clone().unwrap_or_else(|| scan_dir.join("boxes.json"));
    let path = model_path(scan_dir, args.model.as_ref());
    // The default model is used when it exists; a given one must.
    let model = if args.model.is_some() || path.exists() {
        Some(read_model(&path)?.0)
    } else {
        None
    };
    let mut scan = load_scan(&args.scan)?;
    if let Some(model) = &model {
        check_model_scan(model, &path, &mut scan, args.force)?;
    }
    let frames = scan.frames.len();
    let bar = match &model {
        Some(_) => {
            note!(
                "rendering the model's depth in {frames} frames to complete the cloud where the sensor saw nothing (at most {} M rays; ~8 s for 120 VGA frames in release)...",
                CLOUD_RAYS / 1_000_000
            );
            Some(progress_bar(
                frames as u64,
                "rendering depth {bar:30} {pos}/{len} frames {elapsed}",
            ))
        }
        None => {
            note!("preparing the point cloud of {frames} frames...");
            None
        }
    };
    let progress = |done: usize| {
        if let Some(bar) = &bar {
            bar.set_position(done as u64);
        }
    };
    let session = Session::open_reporting(scan, scan_dir.clone(), boxes.clone(), model, &progress)
        .with_context(|| format!("cannot annotate {}", scan_dir.display()))?;
    if let Some(bar) = bar {
        bar.finish_and_clear();
    }
    let source = session.source_name();
    if session.model.is_some() {
        note!(
            "{} fit points from the model's surface where the sensor saw nothing",
            session.fit.unseen()
        );
    }
    serve(Arc::new(session), &args.host, args.port, |addr| {
        note!(
            "boxes file: {}{}; previews from {source} depth; Ctrl-C stops",
            boxes.display(),
            if boxes.exists() {
                ""
            } else {
                " (created on the first save)"
            }
        );
        println!("http://{addr}/");
        let _ = std::io::stdout().flush();
    })?;
    Ok(())
}
