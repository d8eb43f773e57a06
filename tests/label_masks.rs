//! `label --masks`: the exact masks of a few frames of the small fixture,
//! carried to every other frame through a fitted model, scored against the
//! fixture's exact masks; the layouts, the names, `--boxes` beside masks and
//! bad input through the real binary.

mod common;

use common::{run, s, small_scan, small_scan_fitted, stderr};
use nerflabel::boxes::metrics::MaskScores;
use nerflabel::evaluate::read_gray16;
use serde_json::Value;
use std::path::Path;

/// Write `ids` as an 8-bit grayscale PNG.
fn write_mask(path: &Path, ids: &[u16], w: u32, h: u32) {
    let bytes: Vec<u8> = ids.iter().map(|&v| v as u8).collect();
    image::GrayImage::from_raw(w, h, bytes).unwrap().save(path).unwrap();
}

/// Grow every object into the background by one pixel (8-neighbourhood),
/// `times` times: what a segmenter that bleeds gives.
fn dilate(mask: &[u16], w: usize, h: usize, times: usize) -> Vec<u16> {
    let mut m = mask.to_vec();
    for _ in 0..times {
        let prev = m.clone();
        for y in 0..h {
            for x in 0..w {
                if prev[y * w + x] != 0 {
                    continue;
                }
                let (x0, x1, y0, y1) = (
                    x.saturating_sub(1),
                    (x + 1).min(w - 1),
                    y.saturating_sub(1),
                    (y + 1).min(h - 1),
                );
                m[y * w + x] = (y0..=y1)
                    .flat_map(|ny| (x0..=x1).map(move |nx| (nx, ny)))
                    .map(|(nx, ny)| prev[ny * w + nx])
                    .filter(|&v| v != 0)
                    .min()
                    .unwrap_or(0);
            }
        }
    }
    m
}

/// Masks folder with the exact masks of `frames` (dilated `grow` px) and the objects' names.
fn given_masks(scan: &Path, dir: &Path, frames: &[&str], grow: usize) {
    std::fs::create_dir_all(dir).unwrap();
    for stem in frames {
        let path = scan.join("gt/masks").join(format!("{stem}.png"));
        let (w, h) = image::image_dimensions(&path).unwrap();
        let truth = read_gray16(&path).unwrap();
        write_mask(
            &dir.join(format!("{stem}.png")),
            &dilate(&truth, w as usize, h as usize, grow),
            w,
            h,
        );
    }
    std::fs::write(dir.join("labels.json"), r#"{"1": "box", "2": "ball", "3": "can"}"#).unwrap();
}

/// Scores of the frames of `out` not in `given` against the exact masks.
fn score_others(scan: &Path, out: &Path, given: &[&str]) -> MaskScores {
    let mut scores = MaskScores::default();
    for entry in std::fs::read_dir(scan.join("gt/masks")).unwrap() {
        let path = entry.unwrap().path();
        let stem = path.file_stem().unwrap().to_str().unwrap().to_string();
        if given.contains(&stem.as_str()) {
            continue;
        }
        let predicted = read_gray16(&out.join("masks").join(format!("{stem}.png"))).unwrap();
        let truth = read_gray16(&path).unwrap();
        scores.add(&predicted, &truth, image::image_dimensions(&path).unwrap().0 as usize);
    }
    scores
}

/// `label --masks` with the scan's fitted model into `out`.
fn label_from_masks(scan: &Path, masks: &Path, out: &Path) {
    let model = scan.join("nerflabel/model.nlf");
    let o = run(&[
        "label",
        s(scan),
        "--masks",
        s(masks),
        "--model",
        s(&model),
        "--out",
        s(out),
    ]);
    assert!(o.status.success(), "{}", stderr(&o));
}

#[test]
fn masks_of_every_sixth_frame_label_the_other_frames() {
    let dir = tempfile::tempdir().unwrap();
    let scan = small_scan_fitted(dir.path());
    let given = ["000000", "000006", "000012", "000018"];
    let label = |masks: &Path, out: &Path| label_from_masks(&scan, masks, out);

    let (clean, clean_out) = (dir.path().join("clean"), dir.path().join("clean-labels"));
    given_masks(&scan, &clean, &given, 0);
    label(&clean, &clean_out);
    let scores = score_others(&scan, &clean_out, &given);
    let can = scores.per_object_mean_frame()[&3];
    eprintln!(
        "clean: mIoU {:.4}, can {can:.4}, predicted/true {:.3}",
        scores.mean_frame_iou(),
        scores.total_counts().pixel_ratio()
    );
    // Measured 0.929 (can 0.905, no sensor depth: from the rendered depth;
    // the table plane takes a rim of its base, 0.935 with --exact-boxes).
    assert!(scores.mean_frame_iou() > 0.90, "mIoU {}", scores.mean_frame_iou());
    assert!(can > 0.88, "the can has no sensor depth: IoU {can}");
    let ratio = scores.total_counts().pixel_ratio();
    assert!((0.93..1.07).contains(&ratio), "predicted/true pixels {ratio}");
    // Given frames are written as given.
    for stem in given {
        let name = format!("{stem}.png");
        assert_eq!(
            read_gray16(&clean_out.join("masks").join(&name)).unwrap(),
            read_gray16(&clean.join(&name)).unwrap(),
            "{stem}"
        );
    }
    let coco: Value = serde_json::from_slice(&std::fs::read(clean_out.join("coco.json")).unwrap()).unwrap();
    let names: Vec<&str> = coco["categories"]
        .as_array()
        .unwrap()
        .iter()
        .map(|c| c["name"].as_str().unwrap())
        .collect();
    assert_eq!(names, ["box", "ball", "can"]);
    assert!(coco["info"]["masks"].as_str().unwrap().ends_with("clean"));
    assert_eq!(
        coco["annotations"].as_array().unwrap().len(),
        72,
        "3 objects in each of 24 frames"
    );

    // Masks that bleed 2 px onto the background (at 160x120 a large share of
    // these 20-40 px objects) score within 0.02 of clean masks: the bleed
    // onto the table is the table's plane, excluded from the objects
    // (measured 0.933 against 0.929; 0.890 before that rule).
    let (bled, bled_out) = (dir.path().join("bled"), dir.path().join("bled-labels"));
    given_masks(&scan, &bled, &given, 2);
    label(&bled, &bled_out);
    let bled_scores = score_others(&scan, &bled_out, &given);
    eprintln!("dilated 2 px: mIoU {:.4}", bled_scores.mean_frame_iou());
    assert!(
        bled_scores.mean_frame_iou() > scores.mean_frame_iou() - 0.02,
        "dilated masks: mIoU {} against {} with clean masks",
        bled_scores.mean_frame_iou(),
        scores.mean_frame_iou()
    );
}

/// Remove object `id` from the given mask of frame `stem` in `dir`.
fn erase_object(dir: &Path, stem: &str, id: u16) {
    let path = dir.join(format!("{stem}.png"));
    let (w, h) = image::image_dimensions(&path).unwrap();
    let mask: Vec<u16> = read_gray16(&path)
        .unwrap()
        .into_iter()
        .map(|v| if v == id { 0 } else { v })
        .collect();
    write_mask(&path, &mask, w, h);
}

/// A segmenter that lost the ball in one frame is outvoted by the frames
/// that have it, and objects drawn in one frame only are carried to the
/// frames beside it.
#[test]
fn a_frame_missing_an_object_and_objects_given_once_are_still_labelled() {
    let dir = tempfile::tempdir().unwrap();
    let scan = small_scan_fitted(dir.path());
    let label = |masks: &Path, out: &Path| label_from_masks(&scan, masks, out);

    let given = ["000000", "000006", "000012", "000018"];
    let (clean, clean_out) = (dir.path().join("clean"), dir.path().join("clean-labels"));
    given_masks(&scan, &clean, &given, 0);
    label(&clean, &clean_out);
    let ball_clean = score_others(&scan, &clean_out, &given).per_object_mean_frame()[&2];
    let (lost, lost_out) = (dir.path().join("lost"), dir.path().join("lost-labels"));
    given_masks(&scan, &lost, &given, 0);
    erase_object(&lost, "000006", 2);
    label(&lost, &lost_out);
    let ball = score_others(&scan, &lost_out, &given).per_object_mean_frame()[&2];

    let (once, once_out) = (dir.path().join("once"), dir.path().join("once-labels"));
    given_masks(&scan, &once, &["000000"], 0);
    label(&once, &once_out);
    let mut beside = MaskScores::default();
    for stem in ["000001", "000002", "000023"] {
        let truth_path = scan.join("gt/masks").join(format!("{stem}.png"));
        let predicted = read_gray16(&once_out.join("masks").join(format!("{stem}.png"))).unwrap();
        let width = image::image_dimensions(&truth_path).unwrap().0 as usize;
        beside.add(&predicted, &read_gray16(&truth_path).unwrap(), width);
    }
    eprintln!(
        "ball missing from one of four masks: IoU {ball:.4} ({ball_clean:.4} with all four); one frame given, the frames beside it: mIoU {:.4}",
        beside.mean_frame_iou()
    );
    // Measured 0.894 against 0.940 (what only the lost frame saw is lost);
    // 0.854 when that frame's background voted inside the ball.
    assert!(
        ball > ball_clean - 0.07,
        "the ball, lost in one given frame: IoU {ball} against {ball_clean}"
    );
    // Measured 0.797 (objects of 20-40 px at 160x120, each seen from one side).
    assert!(
        beside.mean_frame_iou() > 0.75,
        "objects given once: mIoU {}",
        beside.mean_frame_iou()
    );
}

#[test]
fn both_layouts_give_the_same_labels_and_boxes_take_the_ids_after_the_masks() {
    let dir = tempfile::tempdir().unwrap();
    let scan = small_scan(dir.path());
    let given = ["000000", "000006", "000012", "000018"];
    let per_frame = dir.path().join("per-frame");
    given_masks(&scan, &per_frame, &given, 0);
    // The same masks, one folder per object of binary masks.
    let per_object = dir.path().join("per-object");
    for stem in given {
        let path = scan.join("gt/masks").join(format!("{stem}.png"));
        let (w, h) = image::image_dimensions(&path).unwrap();
        let truth = read_gray16(&path).unwrap();
        for id in 1..=3u16 {
            let folder = per_object.join(id.to_string());
            std::fs::create_dir_all(&folder).unwrap();
            let binary: Vec<u16> = truth.iter().map(|&v| if v == id { 255 } else { 0 }).collect();
            write_mask(&folder.join(format!("{stem}.png")), &binary, w, h);
        }
    }
    let label = |masks: &Path, out: &Path, extra: &[&str]| {
        let mut args = vec![
            "label",
            s(&scan),
            "--masks",
            s(masks),
            "--source",
            "sensor",
            "--out",
            s(out),
        ];
        args.extend_from_slice(extra);
        let o = run(&args);
        assert!(o.status.success(), "{}", stderr(&o));
    };
    let (a, b) = (dir.path().join("a"), dir.path().join("b"));
    label(&per_frame, &a, &[]);
    label(&per_object, &b, &[]);
    for entry in std::fs::read_dir(a.join("masks")).unwrap() {
        let name = entry.unwrap().file_name();
        assert_eq!(
            read_gray16(&a.join("masks").join(&name)).unwrap(),
            read_gray16(&b.join("masks").join(&name)).unwrap(),
            "{name:?}"
        );
    }
    // Sensor depth misses the can and has holes, but the box and the ball
    // carry over (measured 0.835 and 0.778).
    let scores = score_others(&scan, &a, &given);
    let objects = scores.per_object_mean_frame();
    assert!(objects[&1] > 0.75 && objects[&2] > 0.7, "{objects:?}");

    // Boxes beside masks: box k takes id 3 + k, and labels only what the masks leave as background.
    let c = dir.path().join("c");
    label(&per_frame, &c, &["--boxes", s(&scan.join("boxes.json"))]);
    let coco: Value = serde_json::from_slice(&std::fs::read(c.join("coco.json")).unwrap()).unwrap();
    let ids: std::collections::BTreeSet<u64> = coco["annotations"]
        .as_array()
        .unwrap()
        .iter()
        .map(|a| a["instance_id"].as_u64().unwrap())
        .collect();
    assert!(ids.contains(&1) && ids.contains(&4), "mask ids and box ids: {ids:?}");
    let masks_only = read_gray16(&a.join("masks/000006.png")).unwrap();
    let with_boxes = read_gray16(&c.join("masks/000006.png")).unwrap();
    for (m, wb) in masks_only.iter().zip(&with_boxes) {
        if *m > 0 {
            assert_eq!(m, wb, "a mask label keeps its pixel");
        }
    }
}

#[test]
fn bad_masks_are_a_clear_error_and_leave_earlier_labels_untouched() {
    let dir = tempfile::tempdir().unwrap();
    let scan = small_scan(dir.path());
    let out = dir.path().join("labels");
    let good = dir.path().join("good");
    given_masks(&scan, &good, &["000003"], 0);
    let ok = run(&[
        "label",
        s(&scan),
        "--masks",
        s(&good),
        "--source",
        "sensor",
        "--out",
        s(&out),
    ]);
    assert!(ok.status.success(), "{}", stderr(&ok));
    let before = std::fs::read(out.join("coco.json")).unwrap();

    let bad = dir.path().join("bad");
    std::fs::create_dir_all(&bad).unwrap();
    std::fs::write(bad.join("000004.png"), b"truncated").unwrap();
    let o = run(&[
        "label",
        s(&scan),
        "--masks",
        s(&bad),
        "--source",
        "sensor",
        "--out",
        s(&out),
    ]);
    assert_eq!(o.status.code(), Some(1), "{}", stderr(&o));
    assert!(
        stderr(&o).contains("000004.png") && stderr(&o).contains("not a readable PNG"),
        "{}",
        stderr(&o)
    );
    assert_eq!(std::fs::read(out.join("coco.json")).unwrap(), before);

    // Neither boxes nor masks: a usage error.
    let o = run(&["label", s(&scan), "--source", "sensor"]);
    assert_eq!(o.status.code(), Some(2), "{}", stderr(&o));
    assert!(stderr(&o).contains("--boxes"), "{}", stderr(&o));
}
