//! `nerflabel annotate`: serve the box annotation page for a scan.

use super::common::{check_model_scan, load_scan, model_path, read_model};
use super::AnnotateArgs;
use anyhow::Context;
use nerflabel::annotate::{serve, Session};
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
    eprintln!("preparing the point cloud of {} frames...", scan.frames.len());
    let session = Session::open(scan, scan_dir.clone(), boxes.clone(), model)
        .with_context(|| format!("cannot annotate {}", scan_dir.display()))?;
    let source = session.source_name();
    serve(Arc::new(session), &args.host, args.port, |addr| {
        eprintln!(
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
