//! Silhouettes moved onto the frame's own colour edges. A mask placed from
//! depth and poses is off by the pose error (about a pixel on handheld
//! scans) while the colour image is where the object really is. Each pixel
//! within [`BAND`] pixels of a label change is given the label whose sure
//! pixels nearby (farther from every label change) have the nearest mean
//! colour, when that mean is clearly nearer than its own label's.

use image::RgbImage;

/// Pixels this close to a label change may change label.
pub const BAND: usize = 2;
/// Sure pixels are looked for this far around a band pixel.
const WINDOW: usize = BAND + 3;
/// A pixel changes label only when the other label's mean colour is nearer
/// by this factor in squared distance.
const CLEARLY_NEARER: f32 = 0.25;

/// The mask with band pixels relabelled by colour (see the module doc).
pub fn snap_to_colour(mask: &[u16], rgb: &RgbImage) -> Vec<u16> {
    let (w, h) = (rgb.width() as usize, rgb.height() as usize);
    assert_eq!(mask.len(), w * h, "mask and image sizes differ");
    let band = distance_to_change(mask, w, h, BAND + 1);
    let mut out = mask.to_vec();
    let pixel = |i: usize| {
        let p = rgb.get_pixel((i % w) as u32, (i / w) as u32).0;
        p.map(f32::from)
    };
    // Mean colour of each label's sure pixels in the window (at most a few labels).
    let mut means: Vec<(u16, [f32; 3], u32)> = Vec::new();
    for i in 0..w * h {
        if band[i] > BAND {
            continue;
        }
        let (x, y) = (i % w, i / w);
        means.clear();
        for wy in y.saturating_sub(WINDOW)..(y + WINDOW + 1).min(h) {
            for wx in x.saturating_sub(WINDOW)..(x + WINDOW + 1).min(w) {
                let j = wy * w + wx;
                if band[j] <= BAND {
                    continue;
                }
                let c = pixel(j);
                match means.iter_mut().find(|m| m.0 == mask[j]) {
                    Some(m) => {
                        (0..3).for_each(|k| m.1[k] += c[k]);
                        m.2 += 1;
                    }
                    None => means.push((mask[j], c, 1)),
                }
            }
        }
        let c = pixel(i);
        let distance = |m: &(u16, [f32; 3], u32)| -> f32 { (0..3).map(|k| (m.1[k] / m.2 as f32 - c[k]).powi(2)).sum() };
        let Some(own) = means.iter().find(|m| m.0 == mask[i]).map(distance) else {
            continue;
        };
        if let Some(best) = means
            .iter()
            .filter(|m| m.0 != mask[i] && m.2 >= 3)
            .min_by(|a, b| distance(a).total_cmp(&distance(b)))
        {
            if distance(best) < CLEARLY_NEARER * own {
                out[i] = best.0;
            }
        }
    }
    out
}

/// Chebyshev distance in pixels from each pixel to the nearest pixel with a
/// 4-neighbour of another label (0 on such pixels), capped at `cap`.
fn distance_to_change(mask: &[u16], w: usize, h: usize, cap: usize) -> Vec<usize> {
    let mut dist = vec![cap; w * h];
    for y in 0..h {
        for x in 0..w {
            let i = y * w + x;
            let differs = (x > 0 && mask[i - 1] != mask[i])
                || (x + 1 < w && mask[i + 1] != mask[i])
                || (y > 0 && mask[i - w] != mask[i])
                || (y + 1 < h && mask[i + w] != mask[i]);
            if differs {
                for ny in y.saturating_sub(cap)..(y + cap + 1).min(h) {
                    for nx in x.saturating_sub(cap)..(x + cap + 1).min(w) {
                        let d = (nx.abs_diff(x)).max(ny.abs_diff(y));
                        let j = ny * w + nx;
                        dist[j] = dist[j].min(d);
                    }
                }
            }
        }
    }
    dist
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A bright square on a dark floor, the mask shifted by a pixel: the
    /// snapped mask is the square.
    #[test]
    fn a_mask_off_by_a_pixel_snaps_to_the_colour_edge() {
        let (w, h) = (40u32, 30u32);
        let inside = |x: u32, y: u32| (10..25).contains(&x) && (8..20).contains(&y);
        let rgb = RgbImage::from_fn(w, h, |x, y| {
            if inside(x, y) {
                image::Rgb([200, 180, 40])
            } else {
                image::Rgb([40, 60, 90])
            }
        });
        let shifted: Vec<u16> = (0..w * h)
            .map(|i| u16::from(inside((i % w).saturating_sub(1), (i / w).saturating_sub(1))))
            .collect();
        let truth: Vec<u16> = (0..w * h).map(|i| u16::from(inside(i % w, i / w))).collect();
        let wrong = |m: &[u16]| m.iter().zip(&truth).filter(|(a, b)| a != b).count();
        assert!(wrong(&shifted) > 20);
        assert_eq!(wrong(&snap_to_colour(&shifted, &rgb)), 0);
    }

    /// Where the object and its surroundings have the same colour, nothing moves.
    #[test]
    fn without_a_colour_edge_the_mask_is_kept() {
        let (w, h) = (30u32, 30u32);
        let rgb = RgbImage::from_pixel(w, h, image::Rgb([120, 120, 120]));
        let mask: Vec<u16> = (0..w * h).map(|i| u16::from((i % w) > 12)).collect();
        assert_eq!(snap_to_colour(&mask, &rgb), mask);
    }
}
