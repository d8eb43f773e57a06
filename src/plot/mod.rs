//! Line charts to PNG for `nerflabel report --plot`: the error-against-run-time
//! curve of a fit (held-out PSNR, SSIM and depth MAE against training
//! seconds), on linear or logarithmic y axes.
//!
//! Self-contained: a built-in bitmap font, 1-2-5 ticks and a pixel canvas on
//! top of `image::RgbImage`. Knows nothing of NeRFs or reports; the CLI turns
//! a fit report into [`Panel`]s. Any input renders without panicking.
//!
//! Why not `plotters`: its bitmap text needs either the system font stack
//! (font-kit, with fontconfig and FreeType as C libraries) or a TrueType
//! font shipped in the binary plus a rasteriser (ab_glyph), about six crates
//! for two line charts; the bitmap font here gives the same PNG on every
//! machine, with no font installed, in about 300 lines.

mod canvas;
mod font;
mod panel;
mod ticks;

use std::path::{Path, PathBuf};

use image::RgbImage;

use canvas::{Canvas, Rect};

/// Smallest image side in pixels; requested sizes are raised to it.
pub const MIN_SIZE: u32 = 64;
/// Largest image side in pixels; requested sizes are capped to it.
pub const MAX_SIZE: u32 = 4096;
/// Panels shorter than this are not drawn (the rest of the image stays blank).
const MIN_PANEL_HEIGHT: u32 = 48;

/// One named curve: (x, y) points joined in order; non-finite points are skipped.
#[derive(Clone, Debug, PartialEq)]
pub struct Series {
    pub name: String,
    pub points: Vec<(f64, f64)>,
    pub color: [u8; 3],
}

/// One chart: a title, axis labels and the series drawn on shared axes.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Panel {
    pub title: String,
    pub x_label: String,
    pub y_label: String,
    pub series: Vec<Series>,
    /// Logarithmic y axis (decades, ticks at 1, 2 and 5 of each); points
    /// with `y <= 0` are not drawn.
    pub log_y: bool,
}

/// Failure to save a rendered plot.
#[derive(Debug, thiserror::Error)]
pub enum PlotError {
    /// The PNG encoder rejected the image.
    #[error("{path}: cannot encode the plot as PNG: {source}")]
    Encode { path: PathBuf, source: image::ImageError },
    /// The file could not be written.
    #[error("{path}: cannot write the plot: {source}")]
    Write { path: PathBuf, source: std::io::Error },
}

/// Text scale (pixels per font pixel) for an image `width` wide with panels
/// `panel_h` tall: 2 for ordinary report sizes, 1 when small, 3 when huge.
fn text_scale(width: u32, panel_h: u32) -> i64 {
    if width >= 2000 && panel_h >= 700 {
        3
    } else if width >= 480 && panel_h >= 220 {
        2
    } else {
        1
    }
}

/// Render panels stacked vertically (e.g. PSNR on top, depth MAE below) into an RGB image of the given size.
pub fn render_panels(panels: &[Panel], width: u32, height: u32) -> RgbImage {
    let width = width.clamp(MIN_SIZE, MAX_SIZE);
    let height = height.clamp(MIN_SIZE, MAX_SIZE);
    let mut canvas = Canvas::new(width, height, [255, 255, 255]);
    let empty = [Panel::default()];
    let panels = if panels.is_empty() { &empty[..] } else { panels };
    let fit = (height / MIN_PANEL_HEIGHT).max(1) as usize;
    let n = panels.len().min(fit);
    let panel_h = height / n as u32;
    let scale = text_scale(width, panel_h);
    let line_w = scale.max(2);
    let y_labels_w = panels
        .iter()
        .take(n)
        .map(|p| panel::y_labels_width(p, scale))
        .max()
        .unwrap_or(0);
    for (i, panel) in panels.iter().take(n).enumerate() {
        let y0 = i64::from(height) * i as i64 / n as i64;
        let y1 = i64::from(height) * (i as i64 + 1) / n as i64;
        let rect = Rect {
            x: 0,
            y: y0,
            w: i64::from(width),
            h: y1 - y0,
        };
        panel::draw_panel(&mut canvas, panel, rect, scale, line_w, y_labels_w);
    }
    canvas.into_image()
}

/// Encode and write atomically with crate::atomic::write_file.
pub fn write_png(path: &Path, img: &RgbImage) -> Result<(), PlotError> {
    let bytes =
        crate::png_encode::encode_rgb(img.as_raw(), img.width(), img.height()).map_err(|source| PlotError::Encode {
            path: path.to_path_buf(),
            source,
        })?;
    crate::atomic::write_file(path, &bytes).map_err(|source| PlotError::Write {
        path: path.to_path_buf(),
        source,
    })
}

#[cfg(test)]
mod tests;
