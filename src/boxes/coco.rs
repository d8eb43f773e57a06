//! COCO instances JSON and YOLO text from per-frame labels: images,
//! one category per label, annotations with RLE segmentation, tight bbox,
//! area, `instance_id` and `object_to_camera` (row-major 4x4).

use super::label::FrameLabel;
use super::parse::BoxSet;
use super::rle::encode_instances;
use nalgebra::IsometryMatrix3;
use serde::Serialize;

/// Provenance recorded in `info`.
#[derive(Clone, Debug, Default, Serialize)]
pub struct CocoInfo {
    pub description: String,
    pub nerflabel_version: String,
    /// Depth source: nerf, sensor or fused.
    pub source: String,
    /// Which box a point in several boxes went to: smallest or deepest.
    pub overlap: String,
    /// Silhouettes moved onto the colour edges (`label --no-colour-snap` = false).
    pub colour_snap: bool,
    /// Seed of the model's fit (`None` without a model).
    pub seed: Option<u64>,
    /// The scan folder, absolute.
    pub scan: String,
    /// Folder the images' `file_name`s are relative to, absolute (the scan
    /// folder unless `label --image-root` names another).
    pub image_root: String,
    pub boxes: String,
    /// Folder of given masks carried to every frame (`label --masks`).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub masks: Option<String>,
    pub model: Option<String>,
    /// Training steps of the model.
    pub model_steps: Option<u64>,
    /// Frame range labelled (`A..B`), `None` = all frames.
    pub frames: Option<String>,
}

#[derive(Clone, Debug, Serialize)]
pub struct CocoImage {
    pub id: u64,
    /// The colour frame, relative to `info.image_root` (`/`-separated, with
    /// `..` where the image lies outside that folder).
    pub file_name: String,
    pub width: u32,
    pub height: u32,
    /// Frame id of the scan (integer file stem).
    pub frame_id: u64,
    /// Instance mask, relative to the output folder.
    pub mask_file: String,
}

#[derive(Clone, Debug, Serialize)]
pub struct CocoCategory {
    pub id: u32,
    pub name: String,
    pub supercategory: String,
}

#[derive(Clone, Debug, Serialize)]
pub struct CocoRle {
    /// `[height, width]`.
    pub size: [u32; 2],
    /// Compressed counts string as pycocotools writes it.
    pub counts: String,
}

#[derive(Clone, Debug, Serialize)]
pub struct CocoAnnotation {
    pub id: u64,
    pub image_id: u64,
    pub category_id: u32,
    /// `[x, y, width, height]` in pixels, tight around the mask.
    pub bbox: [f64; 4],
    pub area: f64,
    pub segmentation: CocoRle,
    pub iscrowd: u8,
    pub instance_id: u32,
    /// Box pose in the camera frame (OpenCV axes), 4 rows of 4.
    pub object_to_camera: [[f64; 4]; 4],
}

/// A whole `coco.json`.
#[derive(Clone, Debug, Serialize)]
pub struct CocoFile {
    pub info: CocoInfo,
    pub licenses: Vec<serde_json::Value>,
    pub images: Vec<CocoImage>,
    pub categories: Vec<CocoCategory>,
    pub annotations: Vec<CocoAnnotation>,
}

/// One frame's share of the COCO file (image without its final id).
#[derive(Clone, Debug)]
pub struct FrameRecord {
    pub image: CocoImage,
    pub annotations: Vec<CocoAnnotation>,
    /// YOLO lines for `labels/<stem>.txt`.
    pub yolo: String,
}

/// Rows of a rigid transform's 4x4 matrix.
pub fn rows4(m: &IsometryMatrix3<f64>) -> [[f64; 4]; 4] {
    let m = m.to_homogeneous();
    std::array::from_fn(|r| std::array::from_fn(|c| m[(r, c)]))
}

/// COCO entries and YOLO lines of one labelled frame (ids filled in later by [`assemble`]).
pub fn frame_record(label: &FrameLabel, boxes: &BoxSet, file_name: String) -> FrameRecord {
    let rles = encode_instances(&label.mask, label.width, label.height);
    let (w, h) = (label.width as f64, label.height as f64);
    let mut annotations = Vec::new();
    let mut yolo = String::new();
    for inst in &label.instances {
        let (Some(rle), Some(b)) = (
            rles.get(&(inst.instance_id as u16)),
            boxes.by_instance(inst.instance_id),
        ) else {
            continue;
        };
        let category_id = boxes.category_id(&b.label).unwrap_or(0);
        let r = inst.bbox;
        let (bw, bh) = ((r.x1 - r.x0) as f64, (r.y1 - r.y0) as f64);
        annotations.push(CocoAnnotation {
            id: 0,
            image_id: 0,
            category_id,
            bbox: [r.x0 as f64, r.y0 as f64, bw, bh],
            area: inst.area as f64,
            segmentation: CocoRle {
                size: [label.height, label.width],
                counts: rle.to_coco_string(),
            },
            iscrowd: 0,
            instance_id: inst.instance_id,
            object_to_camera: rows4(&inst.object_to_camera),
        });
        yolo.push_str(&format!(
            "{} {:.6} {:.6} {:.6} {:.6}\n",
            category_id.saturating_sub(1),
            (r.x0 as f64 + 0.5 * bw) / w,
            (r.y0 as f64 + 0.5 * bh) / h,
            bw / w,
            bh / h
        ));
    }
    FrameRecord {
        image: CocoImage {
            id: 0,
            file_name,
            width: label.width,
            height: label.height,
            frame_id: label.frame_id,
            mask_file: format!("masks/{}.png", label.name),
        },
        annotations,
        yolo,
    }
}

/// The COCO file from frame records in output order: image ids 1.. in that
/// order, annotation ids 1.. (COCO tools treat id 0 as "none").
pub fn assemble(info: CocoInfo, boxes: &BoxSet, records: &[FrameRecord]) -> CocoFile {
    let mut images = Vec::with_capacity(records.len());
    let mut annotations = Vec::new();
    for (i, rec) in records.iter().enumerate() {
        let image_id = i as u64 + 1;
        images.push(CocoImage {
            id: image_id,
            ..rec.image.clone()
        });
        for a in &rec.annotations {
            annotations.push(CocoAnnotation {
                id: annotations.len() as u64 + 1,
                image_id,
                ..a.clone()
            });
        }
    }
    let categories = boxes
        .categories
        .iter()
        .enumerate()
        .map(|(i, name)| CocoCategory {
            id: i as u32 + 1,
            name: name.clone(),
            supercategory: String::new(),
        })
        .collect();
    CocoFile {
        info,
        licenses: Vec::new(),
        images,
        categories,
        annotations,
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::boxes::label::instances_of;
    use crate::boxes::parse::Box3;
    use nalgebra::{Point3, Rotation3, Translation3, Vector3};

    fn set() -> BoxSet {
        let b = |label: &str, id: u32| Box3 {
            label: label.into(),
            instance_id: id,
            center: Point3::new(id as f64, 0.0, 2.0),
            size: Vector3::repeat(1.0),
            rotation: Rotation3::identity(),
        };
        BoxSet::from_boxes(vec![b("mug", 1), b("book", 2), b("mug", 3)])
    }

    #[test]
    fn record_has_tight_boxes_areas_rle_and_yolo_lines() {
        let boxes = set();
        let (w, h) = (8u32, 4u32);
        let mut mask = vec![0u16; 32];
        // Instance 3 on rows 1..3, columns 2..5; instance 2 a single pixel at (7, 0).
        for y in 1..3 {
            for x in 2..5 {
                mask[y * 8 + x] = 3;
            }
        }
        mask[7] = 2;
        let w2c = IsometryMatrix3::from_parts(Translation3::new(0.0, 0.0, 1.0), Rotation3::identity());
        let instances = instances_of(&mask, w, h, &boxes, &w2c);
        let label = FrameLabel {
            frame_id: 12,
            name: "000012".into(),
            width: w,
            height: h,
            mask,
            depth_m: None,
            instances,
            in_view: vec![1, 2, 3],
            box_pixels: 0,
            rendered_rays: 0,
        };
        let rec = frame_record(&label, &boxes, "rgb/000012.png".into());
        assert_eq!(rec.annotations.len(), 2);
        let book = &rec.annotations[0];
        assert_eq!(
            (book.instance_id, book.category_id, book.bbox, book.area),
            (2, 2, [7.0, 0.0, 1.0, 1.0], 1.0)
        );
        let mug = &rec.annotations[1];
        assert_eq!(
            (mug.instance_id, mug.category_id, mug.bbox, mug.area),
            (3, 1, [2.0, 1.0, 3.0, 2.0], 6.0)
        );
        // Column-major runs [9, 2, 2, 2, 2, 2, 13]; from the fourth on, deltas to two back: 0 0 0 11.
        assert_eq!(mug.segmentation.size, [4, 8]);
        assert_eq!(mug.segmentation.counts, "922000;");
        assert_eq!(
            mug.object_to_camera[2][3], 3.0,
            "box 3 sits at z = 2 m, camera shifted by +1"
        );
        assert_eq!(mug.object_to_camera[0][3], 3.0);
        let lines: Vec<&str> = rec.yolo.lines().collect();
        assert_eq!(
            lines,
            vec![
                "1 0.937500 0.125000 0.125000 0.250000",
                "0 0.437500 0.500000 0.375000 0.500000"
            ]
        );
        let coco = assemble(CocoInfo::default(), &boxes, &[rec.clone(), rec]);
        assert_eq!(coco.images.iter().map(|i| i.id).collect::<Vec<_>>(), vec![1, 2]);
        assert_eq!(
            coco.annotations.iter().map(|a| (a.id, a.image_id)).collect::<Vec<_>>(),
            vec![(1, 1), (2, 1), (3, 2), (4, 2)]
        );
        assert_eq!(coco.categories.len(), 2);
        let json = serde_json::to_value(&coco).unwrap();
        assert_eq!(
            json["annotations"][1]["segmentation"]["counts"],
            serde_json::json!(coco.annotations[1].segmentation.counts)
        );
        assert_eq!(
            json["annotations"][1]["object_to_camera"][0],
            serde_json::json!([1.0, 0.0, 0.0, 3.0])
        );
        assert_eq!(json["annotations"][1]["iscrowd"], 0);
    }
}
