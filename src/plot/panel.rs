//! Drawing one panel: title, axis labels, ticks and grid, the series as
//! lines with markers, a legend when there are several series, or "no data".

use super::canvas::{Canvas, Rect};
use super::font::{draw_text, text_height, text_width, Pen};
use super::ticks::{log_axis, nice_axis, Axis};
use super::Panel;

const TEXT: [u8; 3] = [34, 34, 34];
const TICK_TEXT: [u8; 3] = [70, 70, 70];
const AXIS: [u8; 3] = [110, 110, 110];
const GRID: [u8; 3] = [232, 232, 232];
const BACKGROUND: [u8; 3] = [255, 255, 255];
const LEGEND_BORDER: [u8; 3] = [200, 200, 200];
/// Series with more finite points than this are drawn without markers,
/// which would otherwise merge into a thick smear.
const MAX_MARKERS: usize = 60;
/// Smallest plot area (pixels each way) worth drawing axes into.
const MIN_AREA: i64 = 16;

/// Where the data goes in a panel and the axis ranges it maps from.
#[derive(Clone, Debug)]
pub struct Frame {
    /// Plot area: the data range maps onto its first..last column and row.
    pub area: Rect,
    pub x: Axis,
    pub y: Axis,
}

impl Frame {
    /// Pixel position (column, row) of a data point; the x-axis maximum lands
    /// on the area's last column and the y-axis maximum on its first row.
    pub fn to_px(&self, x: f64, y: f64) -> (f64, f64) {
        let (x, y) = (self.x.coord(x), self.y.coord(y));
        let fx = (x - self.x.lo) / (self.x.hi - self.x.lo);
        let fy = (y - self.y.lo) / (self.y.hi - self.y.lo);
        let px = self.area.x as f64 + fx * (self.area.w - 1) as f64;
        let py = self.area.bottom() as f64 - fy * (self.area.h - 1) as f64;
        (px, py)
    }
}

/// Finite points of a series in order; NaN and infinite points are skipped,
/// and with `log_y` those with `y <= 0`, which a log axis cannot show.
pub fn finite_points(points: &[(f64, f64)], log_y: bool) -> impl Iterator<Item = (f64, f64)> + '_ {
    points
        .iter()
        .copied()
        .filter(move |(x, y)| x.is_finite() && y.is_finite() && (!log_y || *y > 0.0))
}

/// The y axis of `panel` over the data range `y0..y1`.
fn y_axis(panel: &Panel, y0: f64, y1: f64) -> Axis {
    if panel.log_y {
        log_axis(y0, y1)
    } else {
        nice_axis(y0, y1)
    }
}

/// Data range over all finite points of all series, `None` when there is none.
fn data_range(panel: &Panel) -> Option<((f64, f64), (f64, f64))> {
    let mut range: Option<((f64, f64), (f64, f64))> = None;
    for (x, y) in panel.series.iter().flat_map(|s| finite_points(&s.points, panel.log_y)) {
        range = Some(match range {
            None => ((x, x), (y, y)),
            Some(((x0, x1), (y0, y1))) => ((x0.min(x), x1.max(x)), (y0.min(y), y1.max(y))),
        });
    }
    range
}

/// Widest tick label of `axis` in pixels.
fn widest_label(axis: &Axis, scale: i64) -> i64 {
    axis.ticks
        .iter()
        .map(|&t| text_width(&axis.label(t), scale))
        .max()
        .unwrap_or(0)
}

/// Width in pixels of the widest y tick label `panel` will have at `scale`,
/// so stacked panels can share one left edge.
pub fn y_labels_width(panel: &Panel, scale: i64) -> i64 {
    data_range(panel).map_or(0, |(_, (y0, y1))| widest_label(&y_axis(panel, y0, y1), scale))
}

/// Plot area and axes of `panel` drawn inside `rect` at text `scale`, with at
/// least `y_labels_w` pixels kept for y tick labels; `None` when the panel
/// has no finite data or the area would be too small.
pub fn layout(panel: &Panel, rect: Rect, scale: i64, y_labels_w: i64) -> Option<Frame> {
    let ((x0, x1), (y0, y1)) = data_range(panel)?;
    let (x, y) = (nice_axis(x0, x1), y_axis(panel, y0, y1));
    let area = plot_area(
        rect,
        scale,
        widest_label(&y, scale).max(y_labels_w),
        widest_label(&x, scale),
    );
    (area.w >= MIN_AREA && area.h >= MIN_AREA).then_some(Frame { area, x, y })
}

/// Plot area left after the margins for title, labels and tick labels.
fn plot_area(rect: Rect, s: i64, y_label_w: i64, x_label_w: i64) -> Rect {
    let pad = 6 * s;
    let th = text_height(s);
    let top = rect.y + pad + th + 2 * pad;
    // y-axis label (rotated), gap, tick labels, tick marks.
    let left = rect.x + pad + th + 3 * s + y_label_w + 6 * s;
    // Half the last x tick label overhangs the right edge of the area.
    let right = rect.x + rect.w - (2 * pad).max(x_label_w / 2 + pad);
    // Tick marks, tick labels, gap, x-axis label.
    let bottom = rect.y + rect.h - (pad + th + 4 * s + th + 6 * s);
    Rect {
        x: left,
        y: top,
        w: right - left,
        h: bottom - top,
    }
}

/// Draw `panel` inside `rect` with text at `scale`, lines `line_w` wide and
/// `y_labels_w` pixels (at least) for the y tick labels.
pub fn draw_panel(canvas: &mut Canvas, panel: &Panel, rect: Rect, scale: i64, line_w: i64, y_labels_w: i64) {
    let s = scale;
    let pad = 6 * s;
    let th = text_height(s);
    canvas.set_clip(Some(rect));
    // Title: centred, made bold by doubling with a one-pixel offset.
    let tw = text_width(&panel.title, s);
    let tx = rect.x + ((rect.w - tw) / 2).max(pad);
    let pen = Pen::new(s, TEXT);
    draw_text(canvas, tx, rect.y + pad, &panel.title, pen);
    draw_text(canvas, tx + 1, rect.y + pad, &panel.title, pen);

    let frame = layout(panel, rect, s, y_labels_w);
    let area = match &frame {
        Some(f) => f.area,
        None => plot_area(rect, s, y_labels_w.max(text_width("0", s)), text_width("0", s)),
    };
    if area.w < MIN_AREA || area.h < MIN_AREA {
        canvas.set_clip(None);
        return;
    }
    // Axis labels centred on the plot area.
    let x = area.x + (area.w - text_width(&panel.x_label, s)) / 2;
    draw_text(canvas, x, rect.y + rect.h - pad - th, &panel.x_label, pen);
    let y = area.y + (area.h - text_width(&panel.y_label, s)) / 2;
    draw_text(canvas, rect.x + pad, y, &panel.y_label, pen.up());

    match frame {
        None => {
            canvas.stroke_rect(area, 1, AXIS);
            let msg = "no data";
            let (x, y) = (area.x + (area.w - text_width(msg, s)) / 2, area.y + (area.h - th) / 2);
            draw_text(canvas, x, y, msg, Pen::new(s, TICK_TEXT));
        }
        Some(frame) => {
            draw_axes(canvas, &frame, s);
            draw_series(canvas, panel, &frame, s, line_w);
            if panel.series.len() > 1 {
                draw_legend(canvas, panel, &frame, s, line_w);
            }
        }
    }
    canvas.set_clip(None);
}

/// Grid lines, frame, tick marks and tick labels.
fn draw_axes(canvas: &mut Canvas, f: &Frame, s: i64) {
    let a = f.area;
    let tick = 3 * s;
    let pen = Pen::new(s, TICK_TEXT);
    // Ticks are axis coordinates: map them as the pixels of the axis range.
    let col = |t: f64| a.x as f64 + (t - f.x.lo) / (f.x.hi - f.x.lo) * (a.w - 1) as f64;
    let row = |t: f64| a.bottom() as f64 - (t - f.y.lo) / (f.y.hi - f.y.lo) * (a.h - 1) as f64;
    for &t in &f.x.ticks {
        let px = col(t).round() as i64;
        canvas.fill_rect(px, a.y, 1, a.h, GRID);
        canvas.fill_rect(px, a.bottom() + 1, 1, tick, AXIS);
        let label = f.x.label(t);
        let x = px - text_width(&label, s) / 2;
        draw_text(canvas, x, a.bottom() + 1 + tick + 2 * s, &label, pen);
    }
    for &t in &f.y.ticks {
        let py = row(t).round() as i64;
        canvas.fill_rect(a.x, py, a.w, 1, GRID);
        canvas.fill_rect(a.x - tick, py, tick, 1, AXIS);
        let label = f.y.label(t);
        let x = a.x - tick - 2 * s - text_width(&label, s);
        // Cap height is 7 of the 8 font rows; centre the digits on the tick.
        draw_text(canvas, x, py - (7 * s) / 2, &label, pen);
    }
    canvas.stroke_rect(a, 1, AXIS);
}

/// Marker radius in pixels for text `scale`.
fn marker_radius(s: i64) -> f64 {
    1.5 * s as f64 + 0.5
}

/// Lines between consecutive finite points, then markers on top.
fn draw_series(canvas: &mut Canvas, panel: &Panel, f: &Frame, s: i64, line_w: i64) {
    let r = marker_radius(s);
    // Let markers on the frame show whole instead of cut in half.
    let m = r.ceil() as i64 + 1;
    let a = f.area;
    let outer = canvas.clip();
    canvas.set_clip(Some(
        Rect {
            x: a.x - m,
            y: a.y - m,
            w: a.w + 2 * m,
            h: a.h + 2 * m,
        }
        .intersect(&outer),
    ));
    for series in &panel.series {
        let mut prev: Option<(f64, f64)> = None;
        for (x, y) in finite_points(&series.points, panel.log_y) {
            let p = f.to_px(x, y);
            if let Some(q) = prev {
                canvas.line(q, p, line_w, series.color);
            }
            prev = Some(p);
        }
    }
    for series in &panel.series {
        let n = finite_points(&series.points, panel.log_y).count();
        if n > MAX_MARKERS {
            continue;
        }
        for (x, y) in finite_points(&series.points, panel.log_y) {
            let (px, py) = f.to_px(x, y);
            canvas.disc(px, py, r + 1.0, BACKGROUND);
            canvas.disc(px, py, r, series.color);
        }
    }
    canvas.set_clip(Some(outer));
}

/// Legend box listing every series, in the corner of the plot area that
/// covers the fewest data points.
fn draw_legend(canvas: &mut Canvas, panel: &Panel, f: &Frame, s: i64, line_w: i64) {
    let a = f.area;
    let pad = 4 * s;
    let th = text_height(s);
    let row = th + 4 * s;
    let swatch = 16 * s;
    // As many rows as fit in the plot area.
    let fit = ((a.h - 2 * pad - 2 * s) / row).max(0) as usize;
    let entries = &panel.series[..panel.series.len().min(fit)];
    if entries.is_empty() {
        return;
    }
    let name_w = entries.iter().map(|e| text_width(&e.name, s)).max().unwrap_or(0);
    let w = (pad + swatch + 2 * pad + name_w + pad).min(a.w - 2 * s);
    let h = 2 * pad + row * entries.len() as i64 - 4 * s;
    let inset = 4 * s;
    let corners = [
        (a.right() - inset - w, a.y + inset),
        (a.x + inset, a.y + inset),
        (a.right() - inset - w, a.bottom() - inset - h),
        (a.x + inset, a.bottom() - inset - h),
    ];
    let covered = |&(x, y): &(i64, i64)| {
        let b = Rect { x, y, w, h };
        panel
            .series
            .iter()
            .flat_map(|s| finite_points(&s.points, panel.log_y))
            .filter(|&(dx, dy)| {
                let (px, py) = f.to_px(dx, dy);
                b.contains(px.round() as i64, py.round() as i64)
            })
            .count()
    };
    let (x, y) = corners.iter().copied().min_by_key(covered).unwrap_or(corners[0]);
    let bx = Rect { x, y, w, h };
    let outer = canvas.clip();
    canvas.set_clip(Some(a.intersect(&outer)));
    canvas.fill_rect(bx.x, bx.y, bx.w, bx.h, BACKGROUND);
    canvas.stroke_rect(bx, 1, LEGEND_BORDER);
    canvas.set_clip(Some(bx.intersect(&outer)));
    for (i, e) in entries.iter().enumerate() {
        let ty = y + pad + row * i as i64;
        let cy = (ty + (7 * s) / 2) as f64;
        let sx = (x + pad) as f64;
        canvas.line((sx, cy), (sx + swatch as f64, cy), line_w, e.color);
        canvas.disc(sx + swatch as f64 / 2.0, cy, marker_radius(s), e.color);
        draw_text(canvas, x + pad + swatch + 2 * pad, ty, &e.name, Pen::new(s, TEXT));
    }
    canvas.set_clip(Some(outer));
}
