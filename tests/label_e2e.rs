//! End to end: generate fixtures with exact ground truth, fit a small model,
//! label with the nerf and sensor sources and compare the masks with the
//! fixture's exact instance masks; check the written files against
//! FORMATS.md section 3 (and with pycocotools when Python has it).

use nerflabel::boxes::metrics::MaskScores;
use nerflabel::boxes::{
    read_boxes, write_labels, BoxSet, DepthSource, FrameRange, LabelOptions, Labeler, OutputOptions, YoloOptions,
};
use nerflabel::fixture::{generate, FixtureOptions, SceneKind};
use nerflabel::nerf::model_file::Model;
use nerflabel::nerf::train::fit::{fit, FitOptions};
use nerflabel::nerf::train::settings::FitSettings;
use nerflabel::nerf::train::settings::Preset;
use nerflabel::scan::{load, LoadOptions, Scan};
use serde_json::Value;
use std::path::Path;
use std::sync::atomic::AtomicBool;

fn fixture(dir: &Path, scene: SceneKind, w: u32, h: u32, frames: usize) -> Scan {
    let mut o = FixtureOptions::new(scene);
    (o.width, o.height, o.frames, o.holdout) = (w, h, Some(frames), Some(0));
    generate(dir, &o).unwrap();
    load(dir, &LoadOptions::default()).unwrap()
}

fn fit_steps(scan: &mut Scan, steps: u64) -> Model {
    let opts = FitOptions {
        settings: FitSettings {
            holdout_every: 0,
            preset: Preset::Fast,
            ..FitSettings::default()
        },
        steps: Some(steps),
        time: None,
        ..FitOptions::default()
    };
    fit(scan, &opts, &AtomicBool::new(false), &mut |_| {}).unwrap().model
}

/// An instance-id PNG as u16 values (8-bit files are widened, not rescaled).
fn read_ids(path: &Path) -> (u32, u32, Vec<u16>, bool) {
    match image::open(path).unwrap() {
        image::DynamicImage::ImageLuma8(m) => (
            m.width(),
            m.height(),
            m.into_raw().into_iter().map(u16::from).collect(),
            false,
        ),
        image::DynamicImage::ImageLuma16(m) => (m.width(), m.height(), m.into_raw(), true),
        other => panic!("{}: colour type {:?}", path.display(), other.color()),
    }
}

fn scores(dir: &Path, scan: &Scan, boxes: &BoxSet, model: Option<&Model>, source: DepthSource) -> MaskScores {
    let labeler = Labeler::new(
        boxes,
        model,
        LabelOptions {
            source,
            ..LabelOptions::default()
        },
    )
    .unwrap();
    let frames: Vec<_> = scan.frames.iter().collect();
    let done = std::sync::atomic::AtomicUsize::new(0);
    let labels = labeler.label_frames(&frames, &|n| {
        done.fetch_max(n, std::sync::atomic::Ordering::Relaxed);
    });
    assert_eq!(done.into_inner(), frames.len(), "progress reaches the frame count");
    let mut s = MaskScores::default();
    for l in &labels {
        s.add(
            &l.mask,
            &read_ids(&dir.join("gt/masks").join(format!("{}.png", l.name))).2,
            l.width as usize,
        );
    }
    s
}

#[test]
fn nerf_labels_match_ground_truth_and_beat_sensor_on_the_object_without_depth() {
    let dir = tempfile::tempdir().unwrap();
    let mut scan = fixture(dir.path(), SceneKind::Small, 160, 120, 24);
    let model = fit_steps(&mut scan, 400);
    let boxes = read_boxes(&dir.path().join("boxes.json")).unwrap();
    let can = boxes.boxes.iter().find(|b| b.label == "can").unwrap().instance_id as u16;
    let nerf = scores(dir.path(), &scan, &boxes, Some(&model), DepthSource::Nerf);
    let sensor = scores(dir.path(), &scan, &boxes, None, DepthSource::Sensor);
    let fused = scores(dir.path(), &scan, &boxes, Some(&model), DepthSource::Fused);
    for (name, s) in [("nerf", &nerf), ("sensor", &sensor), ("fused", &fused)] {
        eprintln!(
            "{name}: objects {:?} frame mIoU {:.3} box {:.3}",
            s.per_object(),
            s.mean_frame_iou(),
            s.mean_box_iou()
        );
    }
    assert!(nerf.mean_frame_iou() > 0.6, "nerf mIoU {}", nerf.mean_frame_iou());
    assert!(sensor.per_object()[&can] < 0.1, "the can has no sensor depth");
    assert!(
        nerf.per_object()[&can] > 0.5,
        "nerf must recover the can: {}",
        nerf.per_object()[&can]
    );
    assert!(
        fused.per_object()[&can] > 0.5,
        "fused falls back to the rendering on the can"
    );

    // Full depth: every pixel rendered; compare with the exact depth.
    let unit = nerflabel::fixture::read_meta(dir.path()).unwrap().gt_depth_unit;
    let labeler = Labeler::new(
        &boxes,
        Some(&model),
        LabelOptions {
            source: DepthSource::Nerf,
            full_depth: true,
            ..LabelOptions::default()
        },
    )
    .unwrap();
    let (mut errors, mut surface, mut found) = (Vec::new(), 0, 0);
    for frame in scan.frames.iter().step_by(6) {
        let label = labeler.label_frame(frame);
        let depth = label.depth_m.as_ref().unwrap();
        assert_eq!(depth.len(), 160 * 120);
        let exact = read_ids(&dir.path().join("gt/depth").join(format!("{}.png", frame.name))).2;
        for (&d, &e) in depth.iter().zip(&exact) {
            if e > 0 {
                surface += 1;
                if d > 0.0 {
                    found += 1;
                    errors.push((d as f64 - e as f64 * unit).abs());
                }
            }
        }
    }
    errors.sort_by(f64::total_cmp);
    let median = errors[errors.len() / 2];
    eprintln!(
        "full depth: {found}/{surface} pixels with a surface, median error {:.1} mm",
        median * 1000.0
    );
    assert!(
        found as f64 > 0.95 * surface as f64,
        "completed depth covers the scene: {found}/{surface}"
    );
    assert!(median < 0.03, "median depth error {median} m");
}

/// Reference COCO RLE string decoder (spec: 5-bit groups, 0x20 = more, 0x10 = sign,
/// counts after the third are deltas to the count two back), expanded to a row-major mask.
fn decode_rle(counts: &str, h: usize, w: usize) -> Vec<bool> {
    let b = counts.as_bytes();
    let (mut runs, mut p): (Vec<i64>, usize) = (Vec::new(), 0);
    while p < b.len() {
        let (mut x, mut k) = (0i64, 0);
        loop {
            let c = b[p] as i64 - 48;
            x |= (c & 0x1f) << (5 * k);
            p += 1;
            k += 1;
            if c & 0x20 == 0 {
                if c & 0x10 != 0 {
                    x |= -1i64 << (5 * k);
                }
                break;
            }
        }
        if runs.len() > 2 {
            x += runs[runs.len() - 2];
        }
        runs.push(x);
    }
    let mut column_major = Vec::with_capacity(h * w);
    for (i, &r) in runs.iter().enumerate() {
        column_major.extend(std::iter::repeat_n(i % 2 == 1, r as usize));
    }
    assert_eq!(column_major.len(), h * w);
    (0..h * w).map(|i| column_major[(i % w) * h + i / w]).collect()
}

#[test]
fn outputs_follow_formats_and_a_rerun_replaces_them() {
    let dir = tempfile::tempdir().unwrap();
    let scan = fixture(dir.path(), SceneKind::Tabletop, 160, 120, 8);
    let boxes = read_boxes(&dir.path().join("boxes.json")).unwrap();
    let out = dir.path().join("labels");
    let opts = LabelOptions {
        source: DepthSource::Sensor,
        full_depth: true,
        ..LabelOptions::default()
    };
    let labeler = Labeler::new(&boxes, None, opts).unwrap();
    let output = OutputOptions {
        frames: Some("1..7".parse().unwrap()),
        yolo: Some(YoloOptions::default()),
        ..OutputOptions::default()
    };
    let summary = write_labels(&out, &scan, &boxes, &labeler, &output, &|_| {}).unwrap();
    assert_eq!(summary.frames, 6);
    assert!(
        summary.annotations >= 12,
        "tabletop objects are mostly visible: {}",
        summary.annotations
    );
    assert!(
        summary.box_pixel_fraction > 0.01 && summary.box_pixel_fraction < 0.5,
        "{}",
        summary.box_pixel_fraction
    );

    let coco: Value = serde_json::from_slice(&std::fs::read(out.join("coco.json")).unwrap()).unwrap();
    assert_eq!(coco["info"]["source"], "sensor");
    assert_eq!(coco["info"]["overlap"], "smallest");
    assert_eq!(coco["info"]["colour_snap"], true);
    let images = coco["images"].as_array().unwrap();
    assert_eq!(images.len(), 6);
    assert_eq!(coco["categories"].as_array().unwrap().len(), boxes.categories.len());
    let mut checked = 0;
    for img in images {
        let name = format!("{:06}", img["frame_id"].as_u64().unwrap());
        assert_eq!(img["file_name"], format!("rgb/{name}.png"));
        let (w, h, mask, sixteen) = read_ids(&out.join("masks").join(format!("{name}.png")));
        assert_eq!((w, h, sixteen), (160, 120, false), "8-bit mask at the rgb size");
        let (dw, dh, _, depth16) = read_ids(&out.join("depth").join(format!("{name}.png")));
        assert_eq!((dw, dh, depth16), (160, 120, true));
        let yolo = std::fs::read_to_string(out.join("yolo/labels").join(format!("{name}.txt"))).unwrap();
        let anns: Vec<&Value> = coco["annotations"]
            .as_array()
            .unwrap()
            .iter()
            .filter(|a| a["image_id"] == img["id"])
            .collect();
        assert_eq!(yolo.lines().count(), anns.len());
        for a in anns {
            let id = a["instance_id"].as_u64().unwrap() as u16;
            let seg = &a["segmentation"];
            assert_eq!(seg["size"], serde_json::json!([120, 160]));
            let decoded = decode_rle(seg["counts"].as_str().unwrap(), 120, 160);
            let want: Vec<bool> = mask.iter().map(|&m| m == id).collect();
            assert_eq!(decoded, want, "RLE of instance {id} in {name} equals the mask file");
            let area = want.iter().filter(|&&b| b).count() as f64;
            assert_eq!(a["area"].as_f64().unwrap(), area);
            let (xs, ys): (Vec<usize>, Vec<usize>) =
                (0..want.len()).filter(|&i| want[i]).map(|i| (i % 160, i / 160)).unzip();
            let bbox: Vec<f64> = a["bbox"]
                .as_array()
                .unwrap()
                .iter()
                .map(|v| v.as_f64().unwrap())
                .collect();
            let (x0, x1) = (*xs.iter().min().unwrap() as f64, *xs.iter().max().unwrap() as f64 + 1.0);
            let (y0, y1) = (*ys.iter().min().unwrap() as f64, *ys.iter().max().unwrap() as f64 + 1.0);
            assert_eq!(bbox, vec![x0, y0, x1 - x0, y1 - y0]);
            assert_eq!(a["iscrowd"], 0);
            let m = a["object_to_camera"].as_array().unwrap();
            assert_eq!(m.len(), 4);
            assert_eq!(m[3], serde_json::json!([0.0, 0.0, 0.0, 1.0]));
            let z = m[2][3].as_f64().unwrap();
            assert!(z > 0.1 && z < 5.0, "a visible box lies in front of the camera: {z}");
            checked += 1;
        }
    }
    assert_eq!(checked, summary.annotations);
    let yaml = std::fs::read_to_string(out.join("yolo/data.yaml")).unwrap();
    assert_eq!(
        yaml.lines().filter(|l| l.starts_with("  ")).count(),
        boxes.categories.len(),
        "{yaml}"
    );
    pycocotools_check(&out.join("coco.json"));

    let listing = |dir: &Path| -> Vec<String> {
        let mut names: Vec<String> = std::fs::read_dir(dir)
            .unwrap()
            .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
            .collect();
        names.sort();
        names
    };
    let frames = 6; // labelled above: 1..7
                    // Re-run on frames 2 and 3 without depth or YOLO: the other frames keep
                    // every file; these two lose the depth and YOLO files this run did not rewrite.
    let labeler = Labeler::new(
        &boxes,
        None,
        LabelOptions {
            source: DepthSource::Sensor,
            ..LabelOptions::default()
        },
    )
    .unwrap();
    let output = OutputOptions {
        frames: Some(FrameRange {
            start: Some(2),
            end: Some(4),
        }),
        ..OutputOptions::default()
    };
    let partial = write_labels(&out, &scan, &boxes, &labeler, &output, &|_| {}).unwrap();
    assert!(
        partial
            .warnings
            .iter()
            .any(|w| w.contains("depth and YOLO files were removed")),
        "{:?}",
        partial.warnings
    );
    assert_eq!(
        listing(&out),
        vec![".nerflabel-labels", "coco.json", "depth", "masks", "yolo"]
    );
    assert_eq!(listing(&out.join("masks")).len(), frames);
    let depth = listing(&out.join("depth"));
    assert_eq!(depth.len(), frames - 2);
    assert!(!depth.contains(&"000002.png".to_string()) && !depth.contains(&"000003.png".to_string()));
    let coco: Value = serde_json::from_slice(&std::fs::read(out.join("coco.json")).unwrap()).unwrap();
    assert_eq!(coco["images"].as_array().unwrap().len(), frames);
    // The YOLO dataset keeps the other frames: their images and labels, listed once each.
    assert_eq!(listing(&out.join("yolo/images")).len(), frames - 2);
    assert_eq!(listing(&out.join("yolo/labels")).len(), frames - 2);
    let listed: usize = ["train.txt", "val.txt"]
        .iter()
        .map(|l| {
            std::fs::read_to_string(out.join("yolo").join(l))
                .unwrap()
                .lines()
                .count()
        })
        .sum();
    assert_eq!(listed, frames - 2);

    // A full re-run without depth or YOLO: nothing stale survives.
    let output = OutputOptions::default();
    write_labels(&out, &scan, &boxes, &labeler, &output, &|_| {}).unwrap();
    assert_eq!(listing(&out), vec![".nerflabel-labels", "coco.json", "masks"]);
    assert_eq!(listing(&out.join("masks")).len(), scan.frames.len());

    // A range with no frame is an error that leaves the outputs alone.
    let output = OutputOptions {
        frames: Some("100..200".parse().unwrap()),
        ..OutputOptions::default()
    };
    let err = write_labels(&out, &scan, &boxes, &labeler, &output, &|_| {})
        .unwrap_err()
        .to_string();
    assert!(err.contains("100..200"), "{err}");
    assert!(out.join("masks/000002.png").is_file());
}

/// Load coco.json with pycocotools and compare its areas and boxes with ours.
fn pycocotools_check(coco: &Path) {
    let probe = std::process::Command::new("python3")
        .args(["-c", "import pycocotools"])
        .output();
    if !probe.is_ok_and(|o| o.status.success()) {
        eprintln!("pycocotools is not installed: skipping the pycocotools check of coco.json");
        return;
    }
    let script = r#"
import json, sys
from pycocotools.coco import COCO
from pycocotools import mask as M
c = COCO(sys.argv[1])
n = 0
for a in c.dataset['annotations']:
    rle = c.annToRLE(a)
    assert int(M.area(rle)) == a['area'], (a['id'], M.area(rle), a['area'])
    assert [float(v) for v in M.toBbox(rle)] == a['bbox'], (a['id'], M.toBbox(rle), a['bbox'])
    assert c.annToMask(a).sum() == a['area']
    n += 1
print(n)
"#;
    let out = std::process::Command::new("python3")
        .args(["-c", script])
        .arg(coco)
        .output()
        .unwrap();
    assert!(
        out.status.success(),
        "pycocotools rejected coco.json: {}",
        String::from_utf8_lossy(&out.stderr)
    );
    let stdout = String::from_utf8_lossy(&out.stdout);
    let n: usize = stdout.lines().last().unwrap_or_default().trim().parse().unwrap();
    assert!(n > 0);
    eprintln!("pycocotools agrees on the area and bbox of {n} annotations");
}

#[test]
fn nerf_source_without_a_model_is_a_clear_error() {
    let boxes = nerflabel::boxes::parse_boxes(
        r#"{"boxes": [{"label": "a", "center": [0, 0, 0], "size": [1, 1, 1]}]}"#,
        Path::new("b.json"),
    )
    .unwrap();
    for source in [DepthSource::Nerf, DepthSource::Fused] {
        let err = Labeler::new(
            &boxes,
            None,
            LabelOptions {
                source,
                ..LabelOptions::default()
            },
        )
        .err()
        .unwrap()
        .to_string();
        assert!(err.contains(source.name()) && err.contains("--source sensor"), "{err}");
    }
}
