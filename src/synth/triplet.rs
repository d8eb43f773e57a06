//! One synthetic view: colour and depth rendered with the model, the
//! instance mask from back-projecting each pixel's depth into the 3D boxes
//! (cleaned of small holes and specks as `label` does), tight 2D boxes per
//! visible instance, and the three PNG blobs.

use super::error::SynthError;
use super::poses_file::ViewSpec;
use crate::boxes::cleanup::clean_mask;
use crate::boxes::label::surface_normal;
use crate::boxes::LabelOptions;
use crate::nerf::render::view::ViewRenderer;
use crate::png_encode::{depth_mm_saturating, encode_depth, encode_mask, encode_rgb};
use crate::scan::Intrinsics;
use nalgebra::{IsometryMatrix3, Point3, Vector3};

/// Instance id of a world point (0 = none), given the surface normal there
/// on request, where neighbouring pixels give one (a support plane's band
/// keeps the foot of an object, which is steep to it).
pub type PointClassifier<'a> = dyn Fn(Point3<f64>, &dyn Fn(f64) -> Option<Vector3<f64>>) -> u32 + Sync + 'a;

/// Maps world points to instance ids (0 = none) and ids to labels.
pub struct Instances<'a> {
    /// Instance id of a world point, 0 when it lies in no box.
    pub classify: &'a PointClassifier<'a>,
    /// Label of instance id `i` at index `i - 1`.
    pub labels: Vec<String>,
}

impl Instances<'_> {
    /// No boxes: every pixel is background.
    pub fn none() -> Instances<'static> {
        Instances {
            classify: &|_, _| 0,
            labels: Vec::new(),
        }
    }

    /// Largest instance id.
    pub fn max_id(&self) -> u32 {
        u32::try_from(self.labels.len()).unwrap_or(u32::MAX)
    }

    /// Label of an instance id, empty for unknown ids.
    pub fn label(&self, id: u32) -> &str {
        (id as usize)
            .checked_sub(1)
            .and_then(|i| self.labels.get(i))
            .map_or("", String::as_str)
    }
}

/// Tight box of one instance in pixel edges: pixels `x0..x1` by `y0..y1`
/// (so `x1 - x0` is the width in pixels).
#[derive(Clone, Debug, PartialEq)]
pub struct Box2d {
    pub instance_id: u32,
    pub label: String,
    pub x0: f32,
    pub y0: f32,
    pub x1: f32,
    pub y1: f32,
}

/// A rendered view ready to be written as one Parquet row.
#[derive(Clone, Debug)]
pub struct SynthView {
    pub spec: ViewSpec,
    pub rgb_png: Vec<u8>,
    pub depth_png: Vec<u8>,
    pub mask_png: Vec<u8>,
    /// Visible instances, by increasing id.
    pub boxes: Vec<Box2d>,
}

impl SynthView {
    /// Bytes held by the PNG blobs (for row-group budgets).
    pub fn blob_bytes(&self) -> usize {
        self.rgb_png.len() + self.depth_png.len() + self.mask_png.len()
    }
}

/// Instance id of every pixel: its depth back-projected to a world point
/// and classified with the surface normal there; pixels without depth are 0.
pub fn instance_mask(
    depth_m: &[f32],
    camera_to_world: &IsometryMatrix3<f64>,
    k: &Intrinsics,
    width: u32,
    classify: &PointClassifier,
) -> Vec<u16> {
    let w = width.max(1) as usize;
    let h = depth_m.len() / w;
    let z: Vec<f64> = depth_m
        .iter()
        .map(|&z| if z > 0.0 && z.is_finite() { f64::from(z) } else { 0.0 })
        .collect();
    let point_at = |u: u32, v: u32, z: f64| camera_to_world * Point3::from(k.unproject(f64::from(u), f64::from(v)) * z);
    z.iter()
        .enumerate()
        .map(|(i, &depth)| {
            if depth <= 0.0 || i >= w * h {
                return 0;
            }
            let (u, v) = ((i % w) as u32, (i / w) as u32);
            // Computed only where a classifier asks (a point on a support plane's band).
            let normal = |span: f64| surface_normal(&z, w as u32, h as u32, u, v, span, &point_at);
            let id = classify(point_at(u, v, depth), &normal);
            // Ids fit in 16 bits: parsing caps the box count at 65535.
            id.min(65_535) as u16
        })
        .collect()
}

/// Fill small holes in and drop small specks of each instance, with the
/// fraction `label` uses by default; returns the pixels changed.
pub fn clean_instances(mask: &mut [u16], width: u32, height: u32) -> usize {
    clean_mask(mask, width, height, LabelOptions::default().cleanup_fraction)
}

/// Tight pixel boxes of every id in `1..=max_id` present in `mask`.
pub fn tight_boxes(mask: &[u16], width: u32, instances: &Instances) -> Vec<Box2d> {
    let w = width.max(1) as usize;
    let max_id = instances.max_id() as usize;
    // (min x, min y, max x, max y) per id; ids beyond the labels are ignored.
    let mut extent: Vec<Option<[usize; 4]>> = vec![None; max_id + 1];
    for (i, &id) in mask.iter().enumerate() {
        let Some(slot) = extent.get_mut(id as usize).filter(|_| id > 0) else {
            continue;
        };
        let (x, y) = (i % w, i / w);
        let e = slot.get_or_insert([x, y, x, y]);
        *e = [e[0].min(x), e[1].min(y), e[2].max(x), e[3].max(y)];
    }
    extent
        .iter()
        .enumerate()
        .filter_map(|(id, e)| {
            let [x0, y0, x1, y1] = (*e)?;
            let id = id as u32;
            Some(Box2d {
                instance_id: id,
                label: instances.label(id).to_string(),
                x0: x0 as f32,
                y0: y0 as f32,
                x1: (x1 + 1) as f32,
                y1: (y1 + 1) as f32,
            })
        })
        .collect()
}

/// Render view number `index` of `spec`: colour, depth, mask, 2D boxes, PNGs.
pub fn render_view(
    renderer: &ViewRenderer,
    spec: &ViewSpec,
    instances: &Instances,
    index: usize,
) -> Result<SynthView, SynthError> {
    let (w, h) = (spec.width, spec.height);
    let view = renderer.render_view(&spec.camera_to_world, &spec.intrinsics, w, h, true);
    let mut mask = instance_mask(
        &view.depth_m,
        &spec.camera_to_world,
        &spec.intrinsics,
        w,
        instances.classify,
    );
    clean_instances(&mut mask, w, h);
    let png = |what| {
        move |source| SynthError::Png {
            view: index,
            what,
            source,
        }
    };
    Ok(SynthView {
        spec: *spec,
        rgb_png: encode_rgb(&view.rgb, w, h).map_err(png("colour"))?,
        depth_png: encode_depth(&depth_mm_saturating(&view.depth_m), w, h).map_err(png("depth"))?,
        mask_png: encode_mask(&mask, instances.max_id() as usize, w, h).map_err(png("mask"))?,
        boxes: tight_boxes(&mask, w, instances),
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn mask_back_projects_depth_through_the_pose() {
        // Camera at the origin looking along world +x (camera z = world x).
        #[rustfmt::skip]
        let c2w = IsometryMatrix3::from_parts(
            nalgebra::Translation3::identity(),
            nalgebra::Rotation3::from_matrix_unchecked(nalgebra::Matrix3::new(
                0.0, 0.0, 1.0,
                -1.0, 0.0, 0.0,
                0.0, -1.0, 0.0,
            )),
        );
        let k = Intrinsics {
            fx: 4.0,
            fy: 4.0,
            cx: 1.0,
            cy: 1.0,
        };
        // Box 1: world x in [1.5, 2.5] (depth 2 m hits it, depth 1 m does not).
        let classify = |p: Point3<f64>, _: &dyn Fn(f64) -> Option<Vector3<f64>>| {
            u32::from((1.5..2.5).contains(&p.x) && p.y.abs() < 0.6 && p.z.abs() < 0.6)
        };
        let depth = [2.0, 2.0, 2.0, 1.0, 2.0, 0.0, 2.0, 2.0, f32::NAN];
        let mask = instance_mask(&depth, &c2w, &k, 3, &classify);
        // Pixel (u, v) at depth 2 maps to world (2, -(u - 1) / 2, -(v - 1) / 2): inside the box.
        assert_eq!(mask, vec![1, 1, 1, 0, 1, 0, 1, 1, 0]);
    }

    #[test]
    fn cleaning_fills_an_enclosed_hole_and_drops_a_detached_speck() {
        let (w, h) = (40u32, 30u32);
        let mut mask = vec![0u16; (w * h) as usize];
        for y in 5..25 {
            for x in 5..25 {
                mask[y * w as usize + x] = 2;
            }
        }
        mask[15 * w as usize + 15] = 0; // a one-pixel hole inside instance 2
        mask[2 * w as usize + 35] = 2; // a one-pixel speck far from it
        let changed = clean_instances(&mut mask, w, h);
        assert_eq!(changed, 2);
        assert_eq!(mask[15 * w as usize + 15], 2);
        assert_eq!(mask[2 * w as usize + 35], 0);
        assert_eq!(mask.iter().filter(|&&m| m == 2).count(), 400);
    }

    #[test]
    fn tight_boxes_cover_exactly_the_instance_pixels() {
        let instances = Instances {
            classify: &|_, _| 0,
            labels: vec!["mug".into(), "box".into(), "can".into()],
        };
        #[rustfmt::skip]
        let mask = [
            0, 0, 0, 0, 0,
            0, 2, 2, 0, 0,
            0, 2, 0, 0, 9,
            1, 0, 0, 0, 0,
        ];
        let boxes = tight_boxes(&mask, 5, &instances);
        assert_eq!(
            boxes,
            vec![
                Box2d {
                    instance_id: 1,
                    label: "mug".into(),
                    x0: 0.0,
                    y0: 3.0,
                    x1: 1.0,
                    y1: 4.0
                },
                Box2d {
                    instance_id: 2,
                    label: "box".into(),
                    x0: 1.0,
                    y0: 1.0,
                    x1: 3.0,
                    y1: 3.0
                },
            ],
            "id 3 is absent and id 9 has no label"
        );
    }
}
