//! Score a `label` output folder against a generated fixture's exact masks
//! (`gt/masks`): mean per-frame mIoU, predicted/true pixel ratio, boundary
//! F-score (2 px) and each object's mean IoU, over the frames both hold.
//!
//! Run: `cargo run --release --example score_labels -- FIXTURE_DIR LABEL_DIR`

use nerflabel::boxes::metrics::MaskScores;
use nerflabel::evaluate::read_gray16;
use std::path::PathBuf;

type Error = Box<dyn std::error::Error>;

fn main() -> Result<(), Error> {
    let args: Vec<PathBuf> = std::env::args().skip(1).map(PathBuf::from).collect();
    let [fixture, labels] = args.as_slice() else {
        return Err("usage: score_labels FIXTURE_DIR LABEL_DIR".into());
    };
    let mut names: Vec<_> = std::fs::read_dir(labels.join("masks"))?
        .filter_map(|e| e.ok().map(|e| e.file_name()))
        .collect();
    names.sort();
    let mut scores = MaskScores::default();
    let mut frames = 0;
    for name in names {
        let truth_path = fixture.join("gt/masks").join(&name);
        if !truth_path.exists() {
            continue;
        }
        let (predicted, truth) = (
            read_gray16(&labels.join("masks").join(&name))?,
            read_gray16(&truth_path)?,
        );
        let width = image::image_dimensions(&truth_path)?.0 as usize;
        if predicted.len() != truth.len() {
            return Err(format!("{}: size differs from the truth", name.to_string_lossy()).into());
        }
        scores.add(&predicted, &truth, width);
        frames += 1;
    }
    let total = scores.total_counts();
    println!(
        "{frames} frames: mIoU {:.4}, predicted/true px {:.3}, boundary F {:.3}",
        scores.mean_frame_iou(),
        total.pixel_ratio(),
        total.boundary_f()
    );
    for (id, iou) in scores.per_object_mean_frame() {
        println!("  object {id}: IoU {iou:.4}");
    }
    Ok(())
}
