//! How soft each image's edges are, as colour snapping measures it
//! (`nerflabel::boxes::boundary::edge_width`): the images whose edges spread
//! over more than `SOFT_EDGE_PX` get the mean-colour stage.
//!
//! Run: `cargo run --release --example edge_width -- IMAGE...` (prints each
//! width, then the minimum, median and maximum).

use nerflabel::boxes::boundary::{edge_width, SOFT_EDGE_PX};

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let mut widths = Vec::new();
    for path in std::env::args().skip(1) {
        let image = image::open(&path).map_err(|e| format!("{path}: {e}"))?.to_rgb8();
        let width = edge_width(&image);
        println!("{path} {width:.2}");
        widths.push(width);
    }
    if widths.is_empty() {
        return Err("usage: edge_width IMAGE...".into());
    }
    widths.sort_by(f32::total_cmp);
    let soft = widths.iter().filter(|&&w| w > SOFT_EDGE_PX).count();
    println!(
        "{} images: min {:.2}, median {:.2}, max {:.2} px; {soft} soft (> {SOFT_EDGE_PX} px)",
        widths.len(),
        widths[0],
        widths[widths.len() / 2],
        widths[widths.len() - 1]
    );
    Ok(())
}
