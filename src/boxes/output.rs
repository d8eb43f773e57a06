//! Write a labelling run into an output folder exactly as FORMATS.md
//! section 3: `masks/`, `depth/` (full depth), `coco.json`, and with YOLO
//! the ultralytics dataset `yolo/` ([`super::yolo`]). Everything is
//! written into a staging folder inside the output folder and swapped in
//! at the end, so a failed run keeps the previous outputs and a re-run
//! never leaves a mix of old and new.
//! A marker file says the folder is ours: entries of a folder without it
//! are never replaced. A run over some frames (`--frames`) into a labelled
//! folder keeps every other frame's files and their COCO records.

use super::coco::{assemble, frame_record, CocoInfo, FrameRecord};
use super::label::{FrameLabel, Labeler};
use super::options::{FrameRange, LabelError, LabelOptions};
use super::parse::BoxSet;
use super::yolo::{self, ImageMode, YoloOptions};
use crate::atomic;
use crate::png_encode::{encode_depth, encode_mask, encode_rgb, quantise_depth, MILLIMETRE};
use crate::scan::{Frame, Scan};
use image::ImageError;
use rayon::prelude::*;
use std::collections::BTreeSet;
use std::fs;
use std::path::{Path, PathBuf};

/// Entries of the output folder a run owns; replaced as a whole, `coco.json`
/// last. `labels` and `classes.txt` are where earlier versions wrote YOLO
/// files: a run removes them.
const OWNED: [&str; 6] = ["masks", "depth", "labels", "classes.txt", yolo::DIR, "coco.json"];
/// Per-frame folders among [`OWNED`] (one file per frame, named by its stem).
const PER_FRAME: [&str; 5] = ["masks", "depth", "labels", "yolo/images", "yolo/labels"];
/// Marks a folder whose owned entries `label` wrote and may replace.
pub const MARKER: &str = ".nerflabel-labels";

/// Labels one frame at a time: boxes ([`Labeler`]) or carried masks.
pub trait FrameLabelling: Sync {
    fn label_frame(&self, frame: &Frame) -> FrameLabel;
    fn options(&self) -> &LabelOptions;
}

impl FrameLabelling for Labeler<'_> {
    fn label_frame(&self, frame: &Frame) -> FrameLabel {
        Labeler::label_frame(self, frame)
    }
    fn options(&self) -> &LabelOptions {
        Labeler::options(self)
    }
}

/// What to write besides masks and COCO.
#[derive(Clone, Debug, Default)]
pub struct OutputOptions {
    /// Only frames with ids in this range.
    pub frames: Option<FrameRange>,
    /// Also write the ultralytics YOLO dataset `yolo/`.
    pub yolo: Option<YoloOptions>,
    /// Provenance for `coco.json` (`source` is filled in from the labeler,
    /// `scan` and `image_root` as absolute paths from the scan and `image_root`).
    pub info: CocoInfo,
    /// Folder the COCO `file_name`s are relative to; `None` = the scan folder.
    pub image_root: Option<PathBuf>,
}

/// What a run produced.
#[derive(Clone, Debug, PartialEq)]
pub struct LabelSummary {
    pub out: PathBuf,
    pub frames: usize,
    pub annotations: usize,
    /// Per box (instance-id order): frames in which it got mask pixels.
    pub frames_visible: Vec<usize>,
    /// Fraction of all pixels whose ray meets a box (the part that was rendered).
    pub box_pixel_fraction: f64,
    /// Rays handed to the renderer.
    pub rendered_rays: usize,
    /// Non-fatal findings (boxes no frame sees, depth beyond 65.535 m).
    pub warnings: Vec<String>,
    /// With YOLO: frames in `train.txt` and in `val.txt`.
    pub yolo_split: Option<(usize, usize)>,
}

fn io_err(path: &Path) -> impl FnOnce(std::io::Error) -> LabelError + '_ {
    move |source| LabelError::Io {
        path: path.to_path_buf(),
        source,
    }
}

/// Write an encoder's PNG atomically.
fn write_png(path: &Path, encoded: Result<Vec<u8>, ImageError>) -> Result<(), LabelError> {
    let png = encoded.map_err(|source| LabelError::Encode {
        path: path.to_path_buf(),
        source,
    })?;
    atomic::write_file(path, &png).map_err(io_err(path))
}

/// Instance mask: 8-bit when every instance id is at most 255, else 16-bit.
pub fn write_mask(path: &Path, mask: &[u16], w: u32, h: u32, max_id: usize) -> Result<(), LabelError> {
    write_png(path, encode_mask(mask, max_id, w, h))
}

/// Depth in millimetres as 16-bit PNG (0 = no surface); returns how many
/// depths beyond 65.535 m were written as 0.
pub fn write_depth_mm(path: &Path, depth_m: &[f32], w: u32, h: u32) -> Result<usize, LabelError> {
    let (mm, overflow) = quantise_depth(depth_m, MILLIMETRE);
    write_png(path, encode_depth(&mm, w, h))?;
    Ok(overflow)
}

/// The colour file of a frame relative to the scan folder, where a usual
/// layout keeps it.
fn rgb_file(scan: &Scan, frame: &Frame) -> Option<String> {
    for dir in ["rgb", "images", "color"] {
        for ext in ["png", "jpg", "jpeg"] {
            let rel = format!("{dir}/{}.{ext}", frame.name);
            if scan.root.join(&rel).is_file() {
                return Some(rel);
            }
        }
    }
    None
}

/// The colour file of a frame relative to the scan folder, where a usual
/// layout keeps it; the frame name with `.png` otherwise.
fn rgb_file_name(scan: &Scan, frame: &Frame) -> String {
    rgb_file(scan, frame).unwrap_or_else(|| format!("{}.png", frame.name))
}

/// `path` relative to `base` (both absolute), `/`-separated, with a `..`
/// for each folder of `base` that `path` does not lie in; `None` when they
/// share no root (another drive).
pub(crate) fn relative_path(path: &Path, base: &Path) -> Option<String> {
    let (p, b): (Vec<_>, Vec<_>) = (path.components().collect(), base.components().collect());
    let common = p.iter().zip(&b).take_while(|(x, y)| x == y).count();
    if common == 0 {
        return None;
    }
    let up = std::iter::repeat_n("..".to_string(), b.len() - common);
    let down = p[common..].iter().map(|c| c.as_os_str().to_string_lossy().into_owned());
    Some(up.chain(down).collect::<Vec<_>>().join("/"))
}

/// The scan folder and the COCO image root, both canonical (absolute).
fn image_roots(scan: &Scan, options: &OutputOptions) -> Result<(PathBuf, PathBuf), LabelError> {
    let scan_root = fs::canonicalize(&scan.root).map_err(io_err(&scan.root))?;
    let image_root = match &options.image_root {
        Some(dir) => fs::canonicalize(dir).map_err(io_err(dir))?,
        None => scan_root.clone(),
    };
    Ok((scan_root, image_root))
}

/// A frame's COCO `file_name`: its colour file relative to `image_root`.
fn image_file_name(scan: &Scan, scan_root: &Path, image_root: &Path, frame: &Frame) -> Result<String, LabelError> {
    let image = scan_root.join(rgb_file_name(scan, frame));
    relative_path(&image, image_root).ok_or_else(|| {
        LabelError::Option(format!(
            "{}: no path leads from the image root {} to it (another drive?); choose an --image-root on its drive",
            image.display(),
            image_root.display()
        ))
    })
}

/// Put the frame's colour image into `images/` of the YOLO folder: the
/// scan's own file, hard-linked or copied, or (a layout that keeps it
/// elsewhere) the decoded frame as PNG.
fn place_image(images: &Path, scan: &Scan, frame: &Frame, mode: ImageMode) -> Result<(), LabelError> {
    fs::create_dir_all(images).map_err(io_err(images))?;
    let Some(rel) = rgb_file(scan, frame) else {
        let path = images.join(format!("{}.png", frame.name));
        let (w, h) = frame.rgb.dimensions();
        return write_png(&path, encode_rgb(frame.rgb.as_raw(), w, h));
    };
    let source = scan.root.join(&rel);
    let ext = source
        .extension()
        .map(|e| e.to_string_lossy().into_owned())
        .unwrap_or_default();
    let target = images.join(format!("{}.{ext}", frame.name));
    if mode == ImageMode::Link && fs::hard_link(&source, &target).is_ok() {
        return Ok(());
    }
    fs::copy(&source, &target).map(|_| ()).map_err(io_err(&source))
}

/// Per-frame results kept after the mask is written.
struct Written {
    record: FrameRecord,
    visible: Vec<u32>,
    in_view: Vec<u32>,
    box_pixels: usize,
    pixels: usize,
    rendered_rays: usize,
    depth_overflow: usize,
}

/// Label the selected frames of `scan` and write every output into `out`.
pub fn write_labels(
    out: &Path,
    scan: &Scan,
    boxes: &BoxSet,
    labeler: &dyn FrameLabelling,
    options: &OutputOptions,
    progress: &(dyn Fn(usize) + Sync),
) -> Result<LabelSummary, LabelError> {
    let frames: Vec<&Frame> = scan
        .frames
        .iter()
        .filter(|f| options.frames.is_none_or(|r| r.contains(f.id)))
        .collect();
    if frames.is_empty() {
        return Err(LabelError::NoFrames(
            options.frames.unwrap_or(FrameRange { start: None, end: None }),
        ));
    }
    let labelled_before = claim(out)?;
    let staging = out.join(format!(".staging-{}", std::process::id()));
    if staging.exists() {
        fs::remove_dir_all(&staging).map_err(io_err(&staging))?;
    }
    let partial = options.frames.is_some() && labelled_before && out.join("coco.json").is_file();
    if partial {
        if let Some(yolo) = &options.yolo {
            check_yolo_kind(out, yolo)?;
        }
    }
    let result = stage(&staging, scan, boxes, labeler, options, &frames, progress).and_then(|mut summary| {
        if partial {
            let names: BTreeSet<&str> = frames.iter().map(|f| f.name.as_str()).collect();
            let dropped = carry_over(out, &staging, &names)?;
            merge_coco(&out.join("coco.json"), &staging.join("coco.json"), &frames)?;
            if !dropped.is_empty() {
                summary.warnings.push(format!(
                    "the relabelled frames' old {} files were removed: this run did not write them (add --depth / --yolo to rewrite them)",
                    dropped.join(" and ")
                ));
            }
        }
        summary.yolo_split = match &options.yolo {
            Some(yolo) => Some(write_yolo_lists(out, &staging, boxes, yolo)?),
            None if partial => keep_yolo_lists(out, &staging)?,
            None => None,
        };
        swap_in(out, &staging)?;
        Ok(LabelSummary { out: out.to_path_buf(), ..summary })
    });
    if staging.exists() {
        let _ = fs::remove_dir_all(&staging);
    }
    result
}

/// Make `out` a label folder: refuse one that holds an owned entry without
/// the marker (a scan, another tool's output), create it and its marker
/// otherwise. Returns whether it held labels before.
fn claim(out: &Path) -> Result<bool, LabelError> {
    let marked = out.join(MARKER).is_file();
    if !marked {
        if let Some(entry) = OWNED.iter().find(|name| out.join(name).exists()) {
            return Err(LabelError::NotOurs {
                path: out.to_path_buf(),
                entry: entry.to_string(),
            });
        }
    }
    fs::create_dir_all(out).map_err(io_err(out))?;
    if !marked {
        let marker = out.join(MARKER);
        atomic::write_file(
            &marker,
            b"written by `nerflabel label`: its masks, depth, yolo and coco.json are replaced by the next run\n",
        )
        .map_err(io_err(&marker))?;
    }
    Ok(marked)
}

/// Partial run: bring every other frame's files from `out` into `staging`
/// (hard links, so they stay byte-identical), and `classes.txt` when this
/// run wrote none. Returns the per-frame kinds whose files of the
/// relabelled frames were dropped because this run did not rewrite them.
fn carry_over(out: &Path, staging: &Path, relabelled: &BTreeSet<&str>) -> Result<Vec<&'static str>, LabelError> {
    let mut dropped = Vec::new();
    for dir in PER_FRAME {
        let (old, new) = (out.join(dir), staging.join(dir));
        if !old.is_dir() {
            continue;
        }
        fs::create_dir_all(&new).map_err(io_err(&new))?;
        for entry in fs::read_dir(&old).map_err(io_err(&old))? {
            let entry = entry.map_err(io_err(&old))?;
            let path = entry.path();
            let stem = path
                .file_stem()
                .map(|s| s.to_string_lossy().into_owned())
                .unwrap_or_default();
            let target = new.join(entry.file_name());
            if target.exists() {
                continue;
            }
            if relabelled.contains(stem.as_str()) {
                let kind = if dir.starts_with(yolo::DIR) { "YOLO" } else { dir };
                if !dropped.contains(&kind) {
                    dropped.push(kind);
                }
                continue;
            }
            if fs::hard_link(&path, &target).is_err() {
                fs::copy(&path, &target).map_err(io_err(&path))?;
            }
        }
    }
    let (old, new) = (out.join("classes.txt"), staging.join("classes.txt"));
    if old.is_file() && !new.exists() {
        fs::copy(&old, &new).map_err(io_err(&old))?;
    }
    Ok(dropped)
}

/// Partial run with YOLO into a folder whose YOLO labels are of the other
/// kind (boxes against polygons): refused, the two would be mixed.
fn check_yolo_kind(out: &Path, options: &YoloOptions) -> Result<(), LabelError> {
    let Ok(yaml) = fs::read_to_string(out.join(yolo::DIR).join("data.yaml")) else {
        return Ok(());
    };
    let segments = yaml.lines().next().is_some_and(|l| l.contains("--yolo-seg"));
    if segments == options.segments {
        return Ok(());
    }
    let kind = |s: bool| if s { "outline polygons (--yolo-seg)" } else { "boxes" };
    Err(LabelError::Merge {
        path: out.to_path_buf(),
        reason: format!(
            "its YOLO labels are {}, this run writes {}",
            kind(segments),
            kind(options.segments)
        ),
    })
}

/// Images of the staged YOLO folder as (frame order key, file name).
fn yolo_images(staging: &Path) -> Result<Vec<(u64, String)>, LabelError> {
    let dir = staging.join(yolo::DIR).join("images");
    let mut images = Vec::new();
    if !dir.is_dir() {
        return Ok(images);
    }
    for entry in fs::read_dir(&dir).map_err(io_err(&dir))? {
        let name = entry.map_err(io_err(&dir))?.file_name().to_string_lossy().into_owned();
        let stem = Path::new(&name)
            .file_stem()
            .map(|s| s.to_string_lossy().into_owned())
            .unwrap_or_default();
        images.push((stem.parse::<u64>().unwrap_or(u64::MAX), name));
    }
    images.sort();
    Ok(images)
}

/// Write `train.txt`, `val.txt` and `data.yaml` for every image of the
/// staged YOLO folder (this run's and, after `--frames`, the earlier
/// ones'); the split is over those frames in frame order. Returns the
/// train and val counts.
fn write_yolo_lists(
    out: &Path,
    staging: &Path,
    boxes: &BoxSet,
    options: &YoloOptions,
) -> Result<(usize, usize), LabelError> {
    let images = yolo_images(staging)?;
    let val = yolo::val_frames(images.len(), options.val_fraction, options.seed);
    let (mut train_list, mut val_list) = (String::new(), String::new());
    for ((_, name), is_val) in images.iter().zip(&val) {
        let list = if *is_val { &mut val_list } else { &mut train_list };
        list.push_str(&format!("./images/{name}\n"));
    }
    let dir = staging.join(yolo::DIR);
    for (name, text) in [("train.txt", &train_list), ("val.txt", &val_list)] {
        let path = dir.join(name);
        atomic::write_file(&path, text.as_bytes()).map_err(io_err(&path))?;
    }
    let n_val = val.iter().filter(|&&v| v).count();
    let root = fs::canonicalize(out).map_err(io_err(out))?.join(yolo::DIR);
    let yaml = yolo::data_yaml(&root, boxes, options, images.len() - n_val, n_val).ok_or_else(|| {
        LabelError::Option(format!(
            "{}: the YOLO data.yaml needs the dataset's path as UTF-8 text; choose an --out path without non-UTF-8 names",
            root.display()
        ))
    })?;
    let path = dir.join("data.yaml");
    atomic::write_file(&path, yaml.as_bytes()).map_err(io_err(&path))?;
    Ok((images.len() - n_val, n_val))
}

/// Partial run without YOLO into a folder with a YOLO dataset: the other
/// frames' files were carried over, the relabelled frames' dropped; keep
/// `data.yaml` and the lists without the dropped frames.
fn keep_yolo_lists(out: &Path, staging: &Path) -> Result<Option<(usize, usize)>, LabelError> {
    let (old, new) = (out.join(yolo::DIR), staging.join(yolo::DIR));
    if !old.join("data.yaml").is_file() {
        return Ok(None);
    }
    fs::create_dir_all(&new).map_err(io_err(&new))?;
    let yaml = old.join("data.yaml");
    fs::copy(&yaml, new.join("data.yaml")).map_err(io_err(&yaml))?;
    let mut counts = [0usize; 2];
    for (name, count) in ["train.txt", "val.txt"].into_iter().zip(&mut counts) {
        let path = old.join(name);
        let text = fs::read_to_string(&path).unwrap_or_default();
        let kept: String = text
            .lines()
            .filter(|line| line.strip_prefix("./").is_some_and(|rel| new.join(rel).is_file()))
            .map(|line| format!("{line}\n"))
            .collect();
        *count = kept.lines().count();
        let target = new.join(name);
        atomic::write_file(&target, kept.as_bytes()).map_err(io_err(&target))?;
    }
    Ok(Some((counts[0], counts[1])))
}

/// Partial run: the staged `coco.json` gains the images and annotations of
/// every frame of the old one that this run did not relabel; image and
/// annotation ids are renumbered in frame order.
fn merge_coco(old_path: &Path, staged_path: &Path, relabelled: &[&Frame]) -> Result<(), LabelError> {
    let merge_err = |reason: String| LabelError::Merge {
        path: old_path.to_path_buf(),
        reason,
    };
    let read = |path: &Path| -> Result<serde_json::Value, LabelError> {
        let bytes = fs::read(path).map_err(io_err(path))?;
        serde_json::from_slice(&bytes).map_err(|e| merge_err(format!("its coco.json is not valid JSON ({e})")))
    };
    let (old, mut new) = (read(old_path)?, read(staged_path)?);
    if old.get("categories") != new.get("categories") {
        return Err(merge_err(
            "the boxes' labels (COCO categories) changed since it was written".into(),
        ));
    }
    // A file written before `image_root` was recorded is relative to the scan folder.
    let info = |doc: &serde_json::Value, key: &str| doc["info"][key].as_str().map(str::to_string);
    let old_root = info(&old, "image_root").or_else(|| info(&new, "scan"));
    let new_root = info(&new, "image_root");
    if old_root != new_root {
        return Err(merge_err(format!(
            "its images' file_names are relative to {}, this run's to {} (give --image-root {0} to keep them)",
            old_root.as_deref().unwrap_or("?"),
            new_root.as_deref().unwrap_or("?")
        )));
    }
    let ids: BTreeSet<u64> = relabelled.iter().map(|f| f.id).collect();
    let frame_of = |image: &serde_json::Value| image.get("frame_id").and_then(|v| v.as_u64());
    let array =
        |doc: &serde_json::Value, key: &str| doc.get(key).and_then(|v| v.as_array()).cloned().unwrap_or_default();
    // (frame id, image, its annotations) from both files.
    let mut frames: Vec<(u64, serde_json::Value, Vec<serde_json::Value>)> = Vec::new();
    for (doc, keep) in [(&old, false), (&new, true)] {
        let annotations = array(doc, "annotations");
        for image in array(doc, "images") {
            let frame = frame_of(&image).ok_or_else(|| merge_err("an image has no frame_id".into()))?;
            if ids.contains(&frame) != keep {
                continue;
            }
            let id = image
                .get("id")
                .and_then(|v| v.as_u64())
                .ok_or_else(|| merge_err("an image has no id".into()))?;
            let own = annotations
                .iter()
                .filter(|a| a.get("image_id").and_then(|v| v.as_u64()) == Some(id))
                .cloned()
                .collect();
            frames.push((frame, image, own));
        }
    }
    frames.sort_by_key(|(frame, _, _)| *frame);
    let (mut images, mut annotations) = (Vec::new(), Vec::new());
    for (i, (_, mut image, own)) in frames.into_iter().enumerate() {
        let image_id = i as u64 + 1;
        image["id"] = image_id.into();
        images.push(image);
        for mut a in own {
            a["id"] = (annotations.len() as u64 + 1).into();
            a["image_id"] = image_id.into();
            annotations.push(a);
        }
    }
    new["images"] = images.into();
    new["annotations"] = annotations.into();
    let json = serde_json::to_vec(&new).map_err(|source| LabelError::Json {
        path: staged_path.to_path_buf(),
        source,
    })?;
    atomic::write_file(staged_path, &json).map_err(io_err(staged_path))
}

/// Write everything into `staging`.
fn stage(
    staging: &Path,
    scan: &Scan,
    boxes: &BoxSet,
    labeler: &dyn FrameLabelling,
    options: &OutputOptions,
    frames: &[&Frame],
    progress: &(dyn Fn(usize) + Sync),
) -> Result<LabelSummary, LabelError> {
    let max_id = boxes.max_instance_id() as usize;
    let (scan_root, image_root) = image_roots(scan, options)?;
    let done = std::sync::atomic::AtomicUsize::new(0);
    let written: Vec<Written> = frames
        .par_iter()
        .map(|frame| {
            let label: FrameLabel = labeler.label_frame(frame);
            let (w, h) = (label.width, label.height);
            write_mask(
                &staging.join("masks").join(format!("{}.png", label.name)),
                &label.mask,
                w,
                h,
                max_id,
            )?;
            let depth_overflow = match &label.depth_m {
                Some(d) => write_depth_mm(&staging.join("depth").join(format!("{}.png", label.name)), d, w, h)?,
                None => 0,
            };
            let file_name = image_file_name(scan, &scan_root, &image_root, frame)?;
            let record = frame_record(&label, boxes, file_name);
            if let Some(yolo) = &options.yolo {
                let dir = staging.join(yolo::DIR);
                let path = dir.join("labels").join(format!("{}.txt", label.name));
                let lines = if yolo.segments {
                    yolo::segment_lines(&label, boxes)
                } else {
                    record.yolo.clone()
                };
                atomic::write_file(&path, lines.as_bytes()).map_err(io_err(&path))?;
                place_image(&dir.join("images"), scan, frame, yolo.images)?;
            }
            progress(done.fetch_add(1, std::sync::atomic::Ordering::Relaxed) + 1);
            Ok(Written {
                visible: label.instances.iter().map(|i| i.instance_id).collect(),
                in_view: label.in_view,
                box_pixels: label.box_pixels,
                pixels: w as usize * h as usize,
                rendered_rays: label.rendered_rays,
                depth_overflow,
                record,
            })
        })
        .collect::<Result<_, LabelError>>()?;

    let mut warnings = boxes.warnings();
    let n = boxes.boxes.len();
    let mut frames_visible = vec![0usize; n];
    let mut frames_in_view = vec![0usize; n];
    for w in &written {
        for &id in &w.visible {
            if let Some(c) = boxes.position(id).and_then(|i| frames_visible.get_mut(i)) {
                *c += 1;
            }
        }
        for &id in &w.in_view {
            if let Some(c) = boxes.position(id).and_then(|i| frames_in_view.get_mut(i)) {
                *c += 1;
            }
        }
    }
    for (i, b) in boxes.boxes.iter().enumerate() {
        if frames_in_view[i] == 0 {
            warnings.push(format!(
                "box {} (`{}`) is outside the view of every labelled frame",
                b.instance_id, b.label
            ));
        } else if frames_visible[i] == 0 {
            warnings.push(format!(
                "box {} (`{}`) is in view of {} frames but no surface point falls inside it (empty box, or hidden)",
                b.instance_id, b.label, frames_in_view[i]
            ));
        }
    }
    let overflow: usize = written.iter().map(|w| w.depth_overflow).sum();
    if overflow > 0 {
        warnings.push(format!("{overflow} depth pixels beyond 65.535 m were written as 0"));
    }

    let records: Vec<FrameRecord> = written.iter().map(|w| w.record.clone()).collect();
    let info = CocoInfo {
        source: labeler.options().source.name().to_string(),
        overlap: labeler.options().overlap.name().to_string(),
        colour_snap: labeler.options().snap_to_colour,
        scan: scan_root.display().to_string(),
        image_root: image_root.display().to_string(),
        ..options.info.clone()
    };
    let coco = assemble(info, boxes, &records);
    let path = staging.join("coco.json");
    let json = serde_json::to_vec(&coco).map_err(|source| LabelError::Json {
        path: path.clone(),
        source,
    })?;
    atomic::write_file(&path, &json).map_err(io_err(&path))?;

    let pixels: usize = written.iter().map(|w| w.pixels).sum();
    Ok(LabelSummary {
        out: PathBuf::new(),
        frames: written.len(),
        annotations: coco.annotations.len(),
        frames_visible,
        box_pixel_fraction: written.iter().map(|w| w.box_pixels).sum::<usize>() as f64 / pixels.max(1) as f64,
        rendered_rays: written.iter().map(|w| w.rendered_rays).sum(),
        warnings,
        yolo_split: None,
    })
}

/// Replace the owned entries of `out` by those in `staging`: old ones are
/// moved aside first (and deleted after). `coco.json` goes aside first and
/// comes in last, so whenever `out/coco.json` exists the folder holds one
/// complete run, old or new, even if the process is killed mid-swap.
fn swap_in(out: &Path, staging: &Path) -> Result<(), LabelError> {
    let old = out.join(format!(".replaced-{}", std::process::id()));
    if old.exists() {
        fs::remove_dir_all(&old).map_err(io_err(&old))?;
    }
    fs::create_dir_all(&old).map_err(io_err(&old))?;
    for name in OWNED.iter().rev() {
        let p = out.join(name);
        if p.exists() {
            fs::rename(&p, old.join(name)).map_err(io_err(&p))?;
        }
    }
    for name in OWNED {
        let p = staging.join(name);
        if p.exists() {
            fs::rename(&p, out.join(name)).map_err(io_err(&p))?;
        }
    }
    fs::remove_dir_all(&old).map_err(io_err(&old))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn relative_paths_climb_with_dot_dot_out_of_the_base() {
        let rel = |p: &str, b: &str| relative_path(Path::new(p), Path::new(b));
        assert_eq!(rel("/d/scan/rgb/1.png", "/d/scan").as_deref(), Some("rgb/1.png"));
        assert_eq!(rel("/d/scan/rgb/1.png", "/d").as_deref(), Some("scan/rgb/1.png"));
        assert_eq!(
            rel("/d/scan/rgb/1.png", "/d/scan/depth").as_deref(),
            Some("../rgb/1.png")
        );
        assert_eq!(
            rel("/d/scan/rgb/1.png", "/e/f").as_deref(),
            Some("../../d/scan/rgb/1.png")
        );
    }

    #[test]
    fn masks_are_8_or_16_bit_and_depth_is_millimetres() {
        let dir = tempfile::tempdir().unwrap();
        let mask = [0u16, 3, 300, 65535];
        let p8 = dir.path().join("m8.png");
        write_mask(&p8, &mask[..2], 2, 1, 255).unwrap();
        let img = image::open(&p8).unwrap();
        assert_eq!(img.as_luma8().unwrap().as_raw(), &vec![0u8, 3]);
        let p16 = dir.path().join("m16.png");
        write_mask(&p16, &mask, 2, 2, 256).unwrap();
        assert_eq!(image::open(&p16).unwrap().as_luma16().unwrap().as_raw(), &mask.to_vec());
        let pd = dir.path().join("d.png");
        let overflow = write_depth_mm(&pd, &[0.0, 1.2344, 70.0, f32::NAN], 2, 2).unwrap();
        assert_eq!(overflow, 1);
        assert_eq!(
            image::open(&pd).unwrap().as_luma16().unwrap().as_raw(),
            &vec![0u16, 1234, 0, 0]
        );
    }

    #[test]
    fn swap_replaces_owned_entries_and_keeps_the_rest() {
        let dir = tempfile::tempdir().unwrap();
        let out = dir.path().join("labels");
        for (rel, text) in [
            ("masks/000001.png", "old"),
            ("depth/000001.png", "old"),
            ("coco.json", "old"),
            ("notes.txt", "mine"),
        ] {
            atomic::write_file(&out.join(rel), text.as_bytes()).unwrap();
        }
        let staging = out.join(".staging-test");
        for rel in ["masks/000002.png", "coco.json"] {
            atomic::write_file(&staging.join(rel), b"new").unwrap();
        }
        swap_in(&out, &staging).unwrap();
        let mut names: Vec<String> = fs::read_dir(&out)
            .unwrap()
            .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
            .collect();
        names.sort();
        assert_eq!(names, vec![".staging-test", "coco.json", "masks", "notes.txt"]);
        assert_eq!(fs::read_to_string(out.join("coco.json")).unwrap(), "new");
        assert!(out.join("masks/000002.png").is_file() && !out.join("masks/000001.png").exists());
        assert_eq!(fs::read_to_string(out.join("notes.txt")).unwrap(), "mine");
    }
}
