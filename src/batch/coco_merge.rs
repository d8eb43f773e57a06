//! The COCO file of one split: the scans' label files joined, ids
//! renumbered, categories joined by name, paths made relative to OUT.

use super::error::BatchError;
use super::manifest::Entry;
use super::merge::{read_json, ID_COLUMN};
use super::stages::ScanOutputs;
use crate::boxes::output::relative_path;
use crate::outputs::resolve;
use serde_json::{json, Value};
use std::collections::{BTreeMap, BTreeSet, HashMap};
use std::path::{Path, PathBuf};

/// One COCO file from the scans' label files: images and annotations
/// renumbered from 1, categories joined by name (ids in name order), each
/// image with its `scan` id and paths relative to OUT (`info.image_root`).
pub(super) fn merge_coco(scans: &[&Entry], out_abs: &Path, split: &str) -> Result<Value, BatchError> {
    let mut files = Vec::new();
    for entry in scans {
        let labels = ScanOutputs::of(entry).labels;
        let path = labels.join("coco.json");
        let coco = read_json(&path).ok_or_else(|| BatchError::Invalid {
            path: path.clone(),
            problem: "not a readable COCO file".into(),
        })?;
        files.push((entry, resolve(&labels), path, coco));
    }
    let names: BTreeSet<String> = files
        .iter()
        .flat_map(|(_, _, _, c)| c["categories"].as_array().cloned().unwrap_or_default())
        .filter_map(|c| c["name"].as_str().map(str::to_string))
        .collect();
    let category_id: BTreeMap<&str, u64> = names.iter().zip(1u64..).map(|(n, i)| (n.as_str(), i)).collect();
    let categories: Vec<Value> = category_id
        .iter()
        .map(|(name, id)| json!({"id": id, "name": name, "supercategory": "object"}))
        .collect();
    let (mut images, mut annotations) = (Vec::new(), Vec::new());
    for (entry, labels_abs, path, coco) in files {
        let bad = |problem: String| BatchError::Invalid {
            path: path.clone(),
            problem,
        };
        let root = coco["info"]["image_root"]
            .as_str()
            .map(PathBuf::from)
            .ok_or_else(|| bad("no info.image_root".into()))?;
        let their_category: HashMap<u64, u64> = coco["categories"]
            .as_array()
            .into_iter()
            .flatten()
            .filter_map(|c| Some((c["id"].as_u64()?, *category_id.get(c["name"].as_str()?)?)))
            .collect();
        let mut their_image: HashMap<u64, u64> = HashMap::new();
        for image in coco["images"].as_array().into_iter().flatten() {
            let mut image = image.clone();
            let old = image["id"]
                .as_u64()
                .ok_or_else(|| bad("an image without an id".into()))?;
            let id = images.len() as u64 + 1;
            their_image.insert(old, id);
            let file = image["file_name"]
                .as_str()
                .map(str::to_string)
                .ok_or_else(|| bad(format!("image {old} has no file_name")))?;
            let from_out = |p: PathBuf| relative_path(&resolve(&p), out_abs);
            image["id"] = json!(id);
            image["file_name"] = json!(from_out(root.join(&file))
                .ok_or_else(|| bad(format!("no path leads from {} to {file}", out_abs.display())))?);
            if let Some(mask) = image["mask_file"].as_str().map(str::to_string) {
                image["mask_file"] = json!(from_out(labels_abs.join(mask)));
            }
            image[ID_COLUMN] = json!(entry.id);
            images.push(image);
        }
        for annotation in coco["annotations"].as_array().into_iter().flatten() {
            let mut a = annotation.clone();
            let image = a["image_id"].as_u64().and_then(|i| their_image.get(&i));
            let category = a["category_id"].as_u64().and_then(|c| their_category.get(&c));
            let (Some(&image), Some(&category)) = (image, category) else {
                return Err(bad(format!(
                    "annotation {} names an image or category the file does not have",
                    a["id"]
                )));
            };
            a["id"] = json!(annotations.len() as u64 + 1);
            a["image_id"] = json!(image);
            a["category_id"] = json!(category);
            annotations.push(a);
        }
    }
    Ok(json!({
        "info": {
            "description": format!("nerflabel merged labels, split {split}"),
            "nerflabel_version": env!("CARGO_PKG_VERSION"),
            "image_root": out_abs.display().to_string(),
            "scans": scans.iter().map(|e| e.id.clone()).collect::<Vec<_>>(),
        },
        "licenses": [],
        "images": images,
        "categories": categories,
        "annotations": annotations,
    }))
}
