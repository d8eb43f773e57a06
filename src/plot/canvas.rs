//! An RGB pixel canvas with a clip rectangle: filled rectangles, thick
//! lines and round markers. Every primitive clips, so any coordinates
//! (huge, negative, non-finite) are safe and cost at most the clip area.

use image::{Rgb, RgbImage};

/// Axis-aligned pixel rectangle: columns `x..x + w`, rows `y..y + h`.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Rect {
    pub x: i64,
    pub y: i64,
    pub w: i64,
    pub h: i64,
}

impl Rect {
    /// Last column inside the rectangle.
    pub fn right(&self) -> i64 {
        self.x + self.w - 1
    }

    /// Last row inside the rectangle.
    pub fn bottom(&self) -> i64 {
        self.y + self.h - 1
    }

    /// Overlap of two rectangles (zero-sized when disjoint).
    pub fn intersect(&self, other: &Rect) -> Rect {
        let x = self.x.max(other.x);
        let y = self.y.max(other.y);
        let x1 = self.x.saturating_add(self.w).min(other.x.saturating_add(other.w));
        let y1 = self.y.saturating_add(self.h).min(other.y.saturating_add(other.h));
        Rect {
            x,
            y,
            w: x1.saturating_sub(x).max(0),
            h: y1.saturating_sub(y).max(0),
        }
    }

    /// Whether the pixel (`x`, `y`) is inside.
    pub fn contains(&self, x: i64, y: i64) -> bool {
        x >= self.x && y >= self.y && x < self.x + self.w && y < self.y + self.h
    }
}

/// Image being drawn on, with the clip that every primitive honours.
#[derive(Clone, Debug, PartialEq)]
pub struct Canvas {
    img: RgbImage,
    clip: Rect,
}

impl Canvas {
    /// A `width` x `height` canvas filled with `bg`; callers cap the size.
    pub fn new(width: u32, height: u32, bg: [u8; 3]) -> Canvas {
        let img = RgbImage::from_pixel(width, height, Rgb(bg));
        Canvas {
            img,
            clip: Rect {
                x: 0,
                y: 0,
                w: i64::from(width),
                h: i64::from(height),
            },
        }
    }

    /// The whole image as a rectangle.
    pub fn bounds(&self) -> Rect {
        Rect {
            x: 0,
            y: 0,
            w: i64::from(self.img.width()),
            h: i64::from(self.img.height()),
        }
    }

    /// Restrict drawing to `rect` (within the image); `None` lifts the clip.
    pub fn set_clip(&mut self, rect: Option<Rect>) {
        self.clip = rect.map_or(self.bounds(), |r| r.intersect(&self.bounds()));
    }

    /// The current clip rectangle.
    pub fn clip(&self) -> Rect {
        self.clip
    }

    /// Colour at (`x`, `y`), or `None` outside the image.
    #[cfg(test)]
    pub fn get(&self, x: i64, y: i64) -> Option<[u8; 3]> {
        let x = u32::try_from(x).ok()?;
        let y = u32::try_from(y).ok()?;
        self.img.get_pixel_checked(x, y).map(|p| p.0)
    }

    /// Fill `w` x `h` pixels from (`x`, `y`), clipped.
    pub fn fill_rect(&mut self, x: i64, y: i64, w: i64, h: i64, color: [u8; 3]) {
        let r = Rect {
            x,
            y,
            w: w.max(0),
            h: h.max(0),
        }
        .intersect(&self.clip);
        for py in r.y..r.y + r.h {
            for px in r.x..r.x + r.w {
                // Inside the clip, which lies inside the image, so both fit in u32.
                self.img.put_pixel(px as u32, py as u32, Rgb(color));
            }
        }
    }

    /// Outline of `rect`, `t` pixels thick, drawn inside it.
    pub fn stroke_rect(&mut self, rect: Rect, t: i64, color: [u8; 3]) {
        self.fill_rect(rect.x, rect.y, rect.w, t, color);
        self.fill_rect(rect.x, rect.y + rect.h - t, rect.w, t, color);
        self.fill_rect(rect.x, rect.y, t, rect.h, color);
        self.fill_rect(rect.x + rect.w - t, rect.y, t, rect.h, color);
    }

    /// Filled disc of radius `r` pixels centred on (`cx`, `cy`).
    pub fn disc(&mut self, cx: f64, cy: f64, r: f64, color: [u8; 3]) {
        if !(cx.is_finite() && cy.is_finite() && r.is_finite()) {
            return;
        }
        let (cx, cy) = (cx.round() as i64, cy.round() as i64);
        let ri = r.ceil().clamp(0.0, 64.0) as i64;
        let r2 = r * r + 0.25;
        for dy in -ri..=ri {
            for dx in -ri..=ri {
                if (dx * dx + dy * dy) as f64 <= r2 {
                    self.fill_rect(cx + dx, cy + dy, 1, 1, color);
                }
            }
        }
    }

    /// Straight line `width` pixels wide between two points, clipped first so
    /// the cost is bounded by the clip size whatever the coordinates.
    pub fn line(&mut self, a: (f64, f64), b: (f64, f64), width: i64, color: [u8; 3]) {
        let width = width.clamp(1, 16);
        let pad = width as f64;
        let c = self.clip;
        let bounds = (
            c.x as f64 - pad,
            c.y as f64 - pad,
            (c.x + c.w) as f64 + pad,
            (c.y + c.h) as f64 + pad,
        );
        let Some((a, b)) = clip_segment(a, b, bounds) else {
            return;
        };
        let (mut x, mut y) = (a.0.round() as i64, a.1.round() as i64);
        let (x1, y1) = (b.0.round() as i64, b.1.round() as i64);
        // Bresenham, stamping a width x width square centred on each step.
        let dx = (x1 - x).abs();
        let dy = -(y1 - y).abs();
        let sx = if x < x1 { 1 } else { -1 };
        let sy = if y < y1 { 1 } else { -1 };
        let mut err = dx + dy;
        let half = width / 2;
        loop {
            self.fill_rect(x - half, y - half, width, width, color);
            if x == x1 && y == y1 {
                break;
            }
            let e2 = 2 * err;
            if e2 >= dy {
                err += dy;
                x += sx;
            }
            if e2 <= dx {
                err += dx;
                y += sy;
            }
        }
    }

    /// Give back the finished image.
    pub fn into_image(self) -> RgbImage {
        self.img
    }
}

/// Liang-Barsky clip of segment `a`-`b` to `(x0, y0, x1, y1)`; `None` when
/// the segment misses the box or has a non-finite end.
fn clip_segment(
    a: (f64, f64),
    b: (f64, f64),
    (x0, y0, x1, y1): (f64, f64, f64, f64),
) -> Option<((f64, f64), (f64, f64))> {
    if ![a.0, a.1, b.0, b.1].iter().all(|v| v.is_finite()) {
        return None;
    }
    let (dx, dy) = (b.0 - a.0, b.1 - a.1);
    if !(dx.is_finite() && dy.is_finite()) {
        return None;
    }
    let (mut t0, mut t1) = (0.0f64, 1.0f64);
    for (p, q) in [(-dx, a.0 - x0), (dx, x1 - a.0), (-dy, a.1 - y0), (dy, y1 - a.1)] {
        if p == 0.0 {
            if q < 0.0 {
                return None;
            }
        } else {
            let t = q / p;
            if p < 0.0 {
                t0 = t0.max(t);
            } else {
                t1 = t1.min(t);
            }
        }
    }
    if t0 > t1 {
        return None;
    }
    Some(((a.0 + t0 * dx, a.1 + t0 * dy), (a.0 + t1 * dx, a.1 + t1 * dy)))
}

#[cfg(test)]
mod tests {
    use super::*;

    const BG: [u8; 3] = [255, 255, 255];
    const RED: [u8; 3] = [200, 0, 0];

    #[test]
    fn line_covers_both_ends_and_midpoint() {
        let mut c = Canvas::new(100, 100, BG);
        c.line((10.0, 10.0), (90.0, 50.0), 2, RED);
        for (x, y) in [(10, 10), (50, 30), (90, 50)] {
            assert_eq!(c.get(x, y), Some(RED), "({x}, {y})");
        }
        assert_eq!(c.get(10, 50), Some(BG));
    }

    #[test]
    fn clip_limits_drawing_and_huge_coordinates_are_cheap() {
        let mut c = Canvas::new(50, 50, BG);
        c.set_clip(Some(Rect {
            x: 10,
            y: 10,
            w: 20,
            h: 20,
        }));
        c.line((-1e300, 20.0), (1e300, 20.0), 2, RED);
        c.fill_rect(i64::MIN / 2, i64::MIN / 2, i64::MAX, i64::MAX, RED);
        c.disc(f64::NAN, 3.0, 2.0, RED);
        c.line((f64::INFINITY, 0.0), (0.0, 0.0), 2, RED);
        assert_eq!(c.get(5, 20), Some(BG));
        assert_eq!(c.get(20, 20), Some(RED));
        assert_eq!(c.get(35, 20), Some(BG));
    }

    #[test]
    fn clip_segment_keeps_inside_part() {
        let (a, b) = clip_segment((-10.0, 5.0), (20.0, 5.0), (0.0, 0.0, 10.0, 10.0)).unwrap();
        assert_eq!((a, b), ((0.0, 5.0), (10.0, 5.0)));
        assert!(clip_segment((-10.0, -5.0), (-1.0, 20.0), (0.0, 0.0, 10.0, 10.0)).is_none());
    }
}
