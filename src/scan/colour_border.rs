//! Lines at the edges of a scan's colour images that show no scene: a
//! converter's padded last row and column (the shared TUM cabinet scan's
//! JPEGs end in a dark row and column), or the black strip an undistortion
//! leaves. Such a line differs from the line next to it in every frame by far
//! more than any two neighbouring lines inside the image do. Training on it
//! teaches the field colours no view of the scene shows, and scoring on it
//! charges the model for them.

use super::Frame;

/// Lines to leave out at each edge of a colour image.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
pub struct ColourBorder {
    pub top: u32,
    pub bottom: u32,
    pub left: u32,
    pub right: u32,
}

impl ColourBorder {
    /// Whether no line is left out.
    pub fn is_none(&self) -> bool {
        *self == ColourBorder::default()
    }

    /// The kept pixels as `(x0, y0, x1, y1)`, ends exclusive (empty when
    /// the border would leave nothing).
    pub fn kept_rect(&self, width: u32, height: u32) -> (u32, u32, u32, u32) {
        let x1 = width.saturating_sub(self.right).max(self.left);
        let y1 = height.saturating_sub(self.bottom).max(self.top);
        (self.left.min(x1), self.top.min(y1), x1, y1)
    }

    /// The edges with lines left out, for messages: "bottom 1, right 1".
    pub fn describe(&self) -> String {
        let sides = [
            ("top", self.top),
            ("bottom", self.bottom),
            ("left", self.left),
            ("right", self.right),
        ];
        let named: Vec<String> = sides
            .iter()
            .filter(|(_, n)| *n > 0)
            .map(|(side, n)| format!("{side} {n}"))
            .collect();
        named.join(", ")
    }
}

/// A dead line must differ from its neighbour this many times more than the
/// most different pair of neighbouring lines inside the image.
const CONTRAST_FACTOR: f64 = 4.0;
/// ... and by at least this many 8-bit grey levels on average (flat,
/// noise-free images would otherwise make any step a border).
const MIN_STEP_LEVELS: f64 = 8.0;
/// At most this fraction of an image's side is looked at from each edge.
const MAX_FRACTION: u32 = 16;
/// Frames sampled for the statistics (evenly spread).
const MAX_FRAMES: usize = 64;

/// The dead lines of `frames` (all of one size): at each edge, the lines up
/// to the strongest step between neighbouring lines within the outer
/// sixteenth, when that step (median over frames of the mean grey-level
/// difference along the line) is far above every step between neighbouring
/// lines inside the image. Lines a scene puts an edge on move with the
/// camera, so only a fixed artefact differs this much in every frame.
pub fn dead_colour_border(frames: &[&Frame]) -> ColourBorder {
    let Some(first) = frames.first() else {
        return ColourBorder::default();
    };
    let (w, h) = first.size();
    if frames.iter().any(|f| f.size() != (w, h)) || w < 4 * MAX_FRACTION || h < 4 * MAX_FRACTION {
        return ColourBorder::default();
    }
    let stride = frames.len().div_ceil(MAX_FRAMES).max(1);
    let sampled: Vec<&Frame> = frames.iter().step_by(stride).copied().collect();
    let lumas: Vec<Vec<i16>> = sampled.iter().map(|f| luma(f)).collect();
    let (w, h) = (w as usize, h as usize);
    // steps[i]: median over frames of the mean difference between row i and i + 1.
    let row_steps = median_steps(&lumas, h - 1, |l, i| {
        (0..w)
            .map(|x| (l[i * w + x] - l[(i + 1) * w + x]).unsigned_abs() as u64)
            .sum::<u64>() as f64
            / w as f64
    });
    let col_steps = median_steps(&lumas, w - 1, |l, i| {
        (0..h)
            .map(|y| (l[y * w + i] - l[y * w + i + 1]).unsigned_abs() as u64)
            .sum::<u64>() as f64
            / h as f64
    });
    let (top, bottom) = dead_lines(&row_steps, h / MAX_FRACTION as usize);
    let (left, right) = dead_lines(&col_steps, w / MAX_FRACTION as usize);
    ColourBorder {
        top,
        bottom,
        left,
        right,
    }
}

/// Each frame's dead colour border: [`dead_colour_border`] over the frames
/// of its size.
pub fn colour_borders(frames: &[Frame]) -> Vec<ColourBorder> {
    let mut sizes: Vec<(u32, u32)> = frames.iter().map(Frame::size).collect();
    sizes.sort_unstable();
    sizes.dedup();
    let per_size: Vec<ColourBorder> = sizes
        .iter()
        .map(|&size| dead_colour_border(&frames.iter().filter(|f| f.size() == size).collect::<Vec<_>>()))
        .collect();
    frames
        .iter()
        .map(|f| per_size[sizes.binary_search(&f.size()).expect("every size is listed")])
        .collect()
}

/// Rec. 601 luma of a frame's colour, in grey levels.
fn luma(frame: &Frame) -> Vec<i16> {
    frame
        .rgb
        .as_raw()
        .chunks_exact(3)
        .map(|p| ((77 * p[0] as i32 + 150 * p[1] as i32 + 29 * p[2] as i32) >> 8) as i16)
        .collect()
}

/// For each of `n` line pairs, the median over frames of `step(luma, pair)`.
fn median_steps(lumas: &[Vec<i16>], n: usize, step: impl Fn(&[i16], usize) -> f64 + Sync) -> Vec<f64> {
    use rayon::prelude::*;
    let per_frame: Vec<Vec<f64>> = lumas.par_iter().map(|l| (0..n).map(|i| step(l, i)).collect()).collect();
    (0..n)
        .map(|i| {
            let mut v: Vec<f64> = per_frame.iter().map(|f| f[i]).collect();
            v.sort_by(f64::total_cmp);
            v[v.len() / 2]
        })
        .collect()
}

/// Dead lines at the start and end of `steps` (steps between neighbouring
/// lines), looking `reach` lines in from each end.
fn dead_lines(steps: &[f64], reach: usize) -> (u32, u32) {
    let n = steps.len();
    if n < 2 * reach + 2 {
        return (0, 0);
    }
    let inside = steps[reach..n - reach].iter().copied().fold(0.0, f64::max);
    let threshold = (CONTRAST_FACTOR * inside).max(MIN_STEP_LEVELS);
    // The strongest step within reach: every line before it is border.
    let strongest = |range: &mut dyn Iterator<Item = (usize, f64)>| {
        range
            .fold(None, |best: Option<(usize, f64)>, (k, s)| match best {
                Some((_, b)) if b >= s => best,
                _ => Some((k, s)),
            })
            .filter(|&(_, s)| s > threshold)
            .map_or(0, |(k, _)| k as u32 + 1)
    };
    let start = strongest(&mut (0..reach).map(|k| (k, steps[k])));
    let end = strongest(&mut (0..reach).map(|k| (k, steps[n - 1 - k])));
    (start, end)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::scan::Intrinsics;
    use image::RgbImage;
    use nalgebra::IsometryMatrix3;

    /// A frame of smooth texture that moves with `shift`, as a handheld
    /// camera sees a scene.
    fn frame(shift: u32, w: u32, h: u32) -> Frame {
        let rgb = RgbImage::from_fn(w, h, |x, y| {
            let v =
                (128.0 + 60.0 * (((x + shift) as f64) * 0.07).sin() * (((y + 2 * shift) as f64) * 0.05).cos()) as u8;
            image::Rgb([v, v / 2 + 40, 255 - v])
        });
        let k = Intrinsics {
            fx: 500.0,
            fy: 500.0,
            cx: w as f64 / 2.0,
            cy: h as f64 / 2.0,
        };
        Frame::new(
            shift as u64,
            format!("{shift:06}"),
            rgb,
            None,
            IsometryMatrix3::identity(),
            k,
        )
    }

    fn detect(frames: &[Frame]) -> ColourBorder {
        dead_colour_border(&frames.iter().collect::<Vec<_>>())
    }

    #[test]
    fn images_that_show_the_scene_to_the_edge_keep_every_line() {
        let frames: Vec<Frame> = (0..12).map(|i| frame(7 * i, 160, 120)).collect();
        assert_eq!(detect(&frames), ColourBorder::default());
    }

    /// The shared TUM cabinet's JPEGs: the last row and column darkened in
    /// every frame; and an undistortion's black strip two lines wide.
    #[test]
    fn a_padded_last_row_and_column_and_a_black_strip_are_found() {
        let mut frames: Vec<Frame> = (0..12).map(|i| frame(7 * i, 160, 120)).collect();
        for f in &mut frames {
            let (w, h) = f.rgb.dimensions();
            for x in 0..w {
                let p = f.rgb.get_pixel_mut(x, h - 1);
                p.0 = p.0.map(|c| c / 5);
            }
            for y in 0..h {
                let p = f.rgb.get_pixel_mut(w - 1, y);
                p.0 = p.0.map(|c| c / 5);
                for x in 0..2 {
                    f.rgb.put_pixel(x, y, image::Rgb([0, 0, 0]));
                }
            }
        }
        let border = detect(&frames);
        assert_eq!(
            border,
            ColourBorder {
                top: 0,
                bottom: 1,
                left: 2,
                right: 1
            }
        );
        assert_eq!(border.describe(), "bottom 1, left 2, right 1");
        assert_eq!(border.kept_rect(160, 120), (2, 0, 159, 119));
    }

    /// A strong edge of the scene (a table's rim, 50 grey levels) that lies
    /// along the border in several frames moves away in the others, so the
    /// median over frames keeps the line.
    #[test]
    fn a_scene_edge_along_the_border_in_some_frames_is_kept() {
        let mut frames: Vec<Frame> = (0..12).map(|i| frame(7 * i, 160, 120)).collect();
        for (i, f) in frames.iter_mut().enumerate().take(5) {
            for x in 0..160 {
                for y in 0..(1 + i as u32) {
                    let p = f.rgb.get_pixel_mut(x, y);
                    p.0 = p.0.map(|c| c.saturating_add(50));
                }
            }
        }
        assert_eq!(detect(&frames), ColourBorder::default());
    }

    #[test]
    fn too_few_pixels_or_mixed_sizes_leave_no_border() {
        assert!(detect(&[]).is_none());
        assert!(detect(&[frame(0, 30, 20)]).is_none());
        assert!(detect(&[frame(0, 160, 120), frame(3, 120, 160)]).is_none());
    }
}
