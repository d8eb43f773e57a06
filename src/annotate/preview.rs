//! The live check: one frame's colour image with the masks and 2D boxes
//! the current boxes would produce, drawn over it as a PNG.

use crate::boxes::{BoxSet, DepthSource, LabelError, LabelOptions, Labeler};
use crate::nerf::model_file::Model;
use crate::scan::Frame;
use nalgebra::Point3;

/// Share of the mask colour in a masked pixel.
const TINT: f32 = 0.5;
/// Width of a drawn 2D box edge, pixels.
const EDGE_PX: u32 = 2;

/// The display colour of an instance id (the page draws its boxes alike):
/// hues a golden angle apart.
pub fn instance_colour(id: u32) -> [u8; 3] {
    let hue = (f64::from(id) * 0.618_033_988_749_895).fract();
    let (s, v) = (0.75, 1.0);
    let h6 = hue * 6.0;
    let f = h6.fract();
    let (p, q, t) = (v * (1.0 - s), v * (1.0 - s * f), v * (1.0 - s * (1.0 - f)));
    let (r, g, b) = match h6 as u32 {
        0 => (v, t, p),
        1 => (q, v, p),
        2 => (p, v, t),
        3 => (p, q, v),
        4 => (t, p, v),
        _ => (v, p, q),
    };
    [r, g, b].map(|c| (c * 255.0).round() as u8)
}

/// The frame's labels under `boxes` drawn over its colour image: pixels
/// tinted by instance, 2D boxes outlined. `support_points` are the scan's
/// surface points (world metres) the support planes are found among, seen
/// from the camera centres `cameras`.
pub fn render_preview(
    frame: &Frame,
    boxes: &BoxSet,
    model: Option<&Model>,
    support_points: &[Point3<f64>],
    cameras: &[Point3<f64>],
) -> Result<image::RgbImage, LabelError> {
    let mut img = frame.rgb.clone();
    if boxes.boxes.is_empty() {
        return Ok(img);
    }
    let source = if model.is_some() {
        DepthSource::Nerf
    } else {
        DepthSource::Sensor
    };
    let options = LabelOptions {
        source,
        few_frames: true,
        ..LabelOptions::default()
    };
    let mut labeler = Labeler::new(boxes, model, options)?;
    labeler.exclude_supports_among(support_points, cameras);
    let label = labeler.label_frame(frame);
    if (label.width, label.height) != img.dimensions() {
        return Ok(img);
    }
    for (pixel, &id) in img.pixels_mut().zip(&label.mask) {
        if id > 0 {
            let c = instance_colour(u32::from(id));
            for (channel, tint) in pixel.0.iter_mut().zip(c) {
                *channel = (f32::from(*channel) * (1.0 - TINT) + f32::from(tint) * TINT).round() as u8;
            }
        }
    }
    let (w, h) = img.dimensions();
    for inst in &label.instances {
        let colour = image::Rgb(instance_colour(inst.instance_id));
        let r = inst.bbox;
        for y in r.y0..r.y1.min(h) {
            for x in r.x0..r.x1.min(w) {
                let edge = x < r.x0 + EDGE_PX || x + EDGE_PX >= r.x1 || y < r.y0 + EDGE_PX || y + EDGE_PX >= r.y1;
                if edge {
                    img.put_pixel(x, y, colour);
                }
            }
        }
    }
    Ok(img)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn neighbouring_ids_get_distinct_colours() {
        for id in 1..20 {
            let (a, b) = (instance_colour(id), instance_colour(id + 1));
            let d: i32 = (0..3).map(|k| (i32::from(a[k]) - i32::from(b[k])).abs()).sum();
            assert!(d > 60, "{id}: {a:?} {b:?}");
        }
    }
}
