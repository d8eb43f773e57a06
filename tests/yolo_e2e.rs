//! `label --yolo` on the committed fixture, read back the way ultralytics
//! reads a dataset: `data.yaml` keys, the train/val lists (`./` lines
//! relative to the list), each image's label file found by replacing the
//! last `/images/` with `/labels/` and the extension with `.txt`. With
//! PyYAML the same walk runs in Python on `yaml.safe_load`; with
//! ultralytics installed, its own `check_det_dataset` reads the dataset.

mod common;

use common::{label_sensor, run, small_scan, stderr};
use serde_json::Value;
use std::collections::{BTreeMap, BTreeSet};
use std::path::{Path, PathBuf};

/// What `data.yaml` holds, read as ultralytics does (path, train, val, names).
struct DataYaml {
    path: PathBuf,
    train: String,
    val: String,
    names: Vec<String>,
}

/// A YAML scalar as written: double-quoted (JSON string syntax) or plain.
fn scalar(text: &str) -> String {
    let text = text.trim();
    if text.starts_with('"') {
        serde_json::from_str(text).unwrap()
    } else {
        text.to_string()
    }
}

/// The block-mapping subset `data.yaml` uses: top-level `key: value` and
/// `names:` followed by indented `index: name` lines; `#` starts a comment.
fn read_data_yaml(file: &Path) -> DataYaml {
    let text = std::fs::read_to_string(file).unwrap();
    let mut top: BTreeMap<String, String> = BTreeMap::new();
    let mut names: BTreeMap<usize, String> = BTreeMap::new();
    let mut in_names = false;
    for line in text.lines() {
        if line.trim_start().starts_with('#') || line.trim().is_empty() {
            continue;
        }
        let indented = line.starts_with(' ');
        let (key, value) = line
            .trim()
            .split_once(':')
            .unwrap_or_else(|| panic!("not a mapping line: {line}"));
        if indented {
            assert!(in_names, "indented line outside `names`: {line}");
            names.insert(key.trim().parse().unwrap(), scalar(value));
        } else {
            in_names = key == "names" && value.trim().is_empty();
            if !in_names {
                top.insert(key.to_string(), scalar(value));
            }
        }
    }
    assert_eq!(
        names.keys().copied().collect::<Vec<_>>(),
        (0..names.len()).collect::<Vec<_>>(),
        "names indexed from 0 without gaps"
    );
    if let Some(nc) = top.get("nc") {
        assert_eq!(nc.parse::<usize>().unwrap(), names.len());
    }
    DataYaml {
        path: PathBuf::from(&top["path"]),
        train: top["train"].clone(),
        val: top["val"].clone(),
        names: names.into_values().collect(),
    }
}

/// Image paths of a list file; `./x` is relative to the list's folder.
fn read_list(list: &Path) -> Vec<String> {
    let parent = format!("{}/", list.parent().unwrap().display());
    std::fs::read_to_string(list)
        .unwrap()
        .lines()
        .map(|x| match x.strip_prefix("./") {
            Some(rest) => format!("{parent}{rest}"),
            None => x.to_string(),
        })
        .collect()
}

/// ultralytics' `img2label_paths`: the last `/images/` becomes `/labels/`,
/// the extension `.txt`.
fn label_path(image: &str) -> PathBuf {
    let (head, tail) = image.rsplit_once("/images/").expect("an image under images/");
    let replaced = format!("{head}/labels/{tail}");
    let stem = replaced.rsplit_once('.').map_or(replaced.as_str(), |(a, _)| a);
    PathBuf::from(format!("{stem}.txt"))
}

/// One label line: class index and its normalised numbers.
fn parse_line(line: &str) -> (usize, Vec<f64>) {
    let mut fields = line.split_whitespace();
    let class = fields.next().unwrap().parse().unwrap();
    (class, fields.map(|v| v.parse().unwrap()).collect())
}

/// Pixels whose centre is inside the polygon (even-odd), as a fill rasterises it.
fn rasterise(points: &[(f64, f64)], w: usize, h: usize) -> Vec<bool> {
    let mut out = vec![false; w * h];
    for y in 0..h {
        let py = y as f64 + 0.5;
        for x in 0..w {
            let px = x as f64 + 0.5;
            let mut inside = false;
            for k in 0..points.len() {
                let (a, b) = (points[k], points[(k + 1) % points.len()]);
                if (a.1 > py) != (b.1 > py) && px < a.0 + (py - a.1) / (b.1 - a.1) * (b.0 - a.0) {
                    inside = !inside;
                }
            }
            out[y * w + x] = inside;
        }
    }
    out
}

/// An instance-id PNG as u16 values (8-bit files are widened, not rescaled).
fn mask_ids(path: &Path) -> (usize, usize, Vec<u16>) {
    match image::open(path).unwrap() {
        image::DynamicImage::ImageLuma8(m) => (
            m.width() as usize,
            m.height() as usize,
            m.into_raw().into_iter().map(u16::from).collect(),
        ),
        image::DynamicImage::ImageLuma16(m) => (m.width() as usize, m.height() as usize, m.into_raw()),
        other => panic!("{}: colour type {:?}", path.display(), other.color()),
    }
}

/// Everything ultralytics needs, checked; returns the image path and split of every listed frame.
fn check_like_ultralytics(out: &Path, segments: bool) -> BTreeMap<String, &'static str> {
    let yaml = out.join("yolo/data.yaml");
    let data = read_data_yaml(&yaml);
    assert!(data.path.is_absolute(), "{}", data.path.display());
    assert_eq!(data.path, std::fs::canonicalize(out.join("yolo")).unwrap());
    let coco: Value = serde_json::from_slice(&std::fs::read(out.join("coco.json")).unwrap()).unwrap();
    let categories: Vec<&str> = coco["categories"]
        .as_array()
        .unwrap()
        .iter()
        .map(|c| c["name"].as_str().unwrap())
        .collect();
    assert_eq!(data.names, categories, "class index = COCO category id - 1");
    let mut split = BTreeMap::new();
    let (mut lines_checked, mut ious) = (0, Vec::new());
    for (key, list) in [("train", &data.train), ("val", &data.val)] {
        for image in read_list(&data.path.join(list)) {
            assert!(Path::new(&image).is_file(), "{image}");
            let label = label_path(&image);
            let text = std::fs::read_to_string(&label).unwrap_or_else(|e| panic!("{}: {e}", label.display()));
            assert!(split.insert(image.clone(), key).is_none(), "{image} listed twice");
            let stem = label.file_stem().unwrap().to_str().unwrap().to_string();
            let (w, h, mask) = mask_ids(&out.join("masks").join(format!("{stem}.png")));
            let picture = image::open(&image).unwrap();
            assert_eq!((picture.width() as usize, picture.height() as usize), (w, h));
            let record = coco["images"]
                .as_array()
                .unwrap()
                .iter()
                .find(|i| i["mask_file"] == format!("masks/{stem}.png"))
                .unwrap();
            let annotations: Vec<&Value> = coco["annotations"]
                .as_array()
                .unwrap()
                .iter()
                .filter(|a| a["image_id"] == record["id"])
                .collect();
            assert_eq!(
                text.lines().count(),
                annotations.len(),
                "{stem}: one line per visible object"
            );
            for (line, annotation) in text.lines().zip(annotations) {
                let (class, values) = parse_line(line);
                assert!(class < data.names.len(), "{stem}: class {class}");
                assert_eq!(class as u64 + 1, annotation["category_id"].as_u64().unwrap());
                assert!(values.iter().all(|v| (0.0..=1.0).contains(v)), "{stem}: {line}");
                if segments {
                    assert!(values.len() >= 6 && values.len() % 2 == 0, "{stem}: {line}");
                    let points: Vec<(f64, f64)> =
                        values.chunks(2).map(|p| (p[0] * w as f64, p[1] * h as f64)).collect();
                    let id = annotation["instance_id"].as_u64().unwrap() as u16;
                    let want: Vec<bool> = mask.iter().map(|&m| m == id).collect();
                    let got = rasterise(&points, w, h);
                    let inter = want.iter().zip(&got).filter(|(a, b)| **a && **b).count();
                    let union = want.iter().zip(&got).filter(|(a, b)| **a || **b).count();
                    // Every mask pixel is inside its outline (holes are filled, so IoU may be lower).
                    let covered = inter as f64 / want.iter().filter(|&&b| b).count() as f64;
                    assert!(
                        covered > 0.99,
                        "{stem}: instance {id}: {covered} of its pixels in the polygon"
                    );
                    if annotation["area"].as_f64().unwrap() >= 50.0 {
                        ious.push(inter as f64 / union as f64);
                    }
                } else {
                    assert_eq!(values.len(), 4, "{stem}: {line}");
                    let bbox: Vec<f64> = annotation["bbox"]
                        .as_array()
                        .unwrap()
                        .iter()
                        .map(|v| v.as_f64().unwrap())
                        .collect();
                    let want = [
                        (bbox[0] + bbox[2] / 2.0) / w as f64,
                        (bbox[1] + bbox[3] / 2.0) / h as f64,
                        bbox[2] / w as f64,
                        bbox[3] / h as f64,
                    ];
                    for (v, t) in values.iter().zip(want) {
                        assert!((v - t).abs() < 1e-6, "{stem}: {line} against COCO {bbox:?}");
                    }
                }
                lines_checked += 1;
            }
        }
    }
    assert!(
        lines_checked >= 40,
        "the fixture's objects are mostly visible: {lines_checked} lines"
    );
    if segments {
        let mean = ious.iter().sum::<f64>() / ious.len() as f64;
        let worst = ious.iter().copied().fold(1.0, f64::min);
        eprintln!(
            "polygons against masks: mean IoU {mean:.4}, worst {worst:.4} over {} objects",
            ious.len()
        );
        assert!(mean > 0.97 && worst > 0.85, "mean {mean}, worst {worst}");
    }
    split
}

/// The same walk in Python on `yaml.safe_load`, when PyYAML is there;
/// ultralytics' own dataset check when it is installed.
fn check_in_python(out: &Path, segments: bool, frames: usize) {
    let has = |module: &str| {
        std::process::Command::new("python3")
            .args(["-c", &format!("import {module}")])
            .output()
            .is_ok_and(|o| o.status.success())
    };
    if !has("yaml") {
        eprintln!("python3 with PyYAML is not available: skipping the Python reading of data.yaml");
        return;
    }
    let script = r#"
import os, sys, yaml
from pathlib import Path
data = yaml.safe_load(open(sys.argv[1]))
seg = sys.argv[2] == "seg"
path = Path(data["path"])
assert path.is_absolute() and path.is_dir(), path
names = data["names"]
assert isinstance(names, dict) and sorted(names) == list(range(len(names))), names
seen = set()
for split in ("train", "val"):
    lst = (path / data[split]).resolve()
    parent = str(lst.parent) + os.sep
    files = [x.replace("./", parent) if x.startswith("./") else x for x in lst.read_text().strip().splitlines()]
    sa, sb = f"{os.sep}images{os.sep}", f"{os.sep}labels{os.sep}"
    for img in files:
        lb = sb.join(img.rsplit(sa, 1)).rsplit(".", 1)[0] + ".txt"
        assert os.path.isfile(img) and os.path.isfile(lb), (img, lb)
        for row in open(lb).read().strip().splitlines():
            v = row.split()
            assert 0 <= int(v[0]) < len(names), row
            xs = [float(t) for t in v[1:]]
            assert all(0 <= t <= 1 for t in xs), row
            assert (len(xs) >= 6 and len(xs) % 2 == 0) if seg else len(xs) == 4, row
        assert img not in seen, img
        seen.add(img)
print(len(seen))
"#;
    let yaml = out.join("yolo/data.yaml");
    let o = std::process::Command::new("python3")
        .args(["-c", script])
        .arg(&yaml)
        .arg(if segments { "seg" } else { "box" })
        .output()
        .unwrap();
    assert!(
        o.status.success(),
        "Python rejected the dataset: {}",
        String::from_utf8_lossy(&o.stderr)
    );
    assert_eq!(String::from_utf8_lossy(&o.stdout).trim(), frames.to_string());
    if !has("ultralytics") {
        eprintln!("ultralytics is not installed: skipping its own check_det_dataset (the walk above mirrors it)");
        return;
    }
    let script = r#"
import sys
from ultralytics.data.utils import check_det_dataset, img2label_paths
d = check_det_dataset(sys.argv[1])
n = 0
for split in ("train", "val"):
    lines = open(d[split]).read().strip().splitlines()
    for label in img2label_paths([l.replace("./", str(__import__("pathlib").Path(d[split]).parent) + "/", 1) for l in lines]):
        open(label).close()
        n += 1
assert d["nc"] == len(d["names"])
print(n)
"#;
    let o = std::process::Command::new("python3")
        .args(["-c", script])
        .arg(&yaml)
        .output()
        .unwrap();
    assert!(
        o.status.success(),
        "ultralytics rejected the dataset: {}",
        String::from_utf8_lossy(&o.stderr)
    );
    assert_eq!(
        String::from_utf8_lossy(&o.stdout).lines().last().unwrap_or("").trim(),
        frames.to_string()
    );
}

fn frame_of(image: &str) -> u64 {
    Path::new(image).file_stem().unwrap().to_str().unwrap().parse().unwrap()
}

#[test]
fn yolo_boxes_dataset_reads_like_ultralytics_with_a_block_split_over_every_frame() {
    let dir = tempfile::tempdir().unwrap();
    let scan = small_scan(dir.path());
    let out = dir.path().join("labels");
    let o = label_sensor(&scan, &out, &["--yolo"]);
    assert!(o.status.success(), "{}", stderr(&o));
    let stdout = String::from_utf8_lossy(&o.stdout);
    assert!(
        stdout.contains("YOLO dataset for ultralytics") && stdout.contains("data.yaml"),
        "{stdout}"
    );
    let split = check_like_ultralytics(&out, false);
    check_in_python(&out, false, 24);
    // Every labelled frame once, train and val disjoint (a map) and both used.
    let frames: BTreeSet<u64> = split.keys().map(|i| frame_of(i)).collect();
    assert_eq!(frames, (0..24).collect());
    let val: Vec<u64> = split
        .iter()
        .filter(|(_, k)| **k == "val")
        .map(|(i, _)| frame_of(i))
        .collect();
    assert!((4..=6).contains(&val.len()), "0.2 of 24 frames in 10 blocks: {val:?}");
    // Contiguous blocks: two drawn blocks make at most two runs of frames.
    let runs = val.iter().filter(|&&f| f == 0 || !val.contains(&(f - 1))).count();
    assert!(runs <= 2, "{val:?}");
    // Hard links to the scan's own colour files by default.
    #[cfg(unix)]
    {
        use std::os::unix::fs::MetadataExt;
        let image = out.join("yolo/images/000005.png");
        let source = scan.join("rgb/000005.png");
        assert_eq!(
            std::fs::metadata(&image).unwrap().ino(),
            std::fs::metadata(&source).unwrap().ino()
        );
    }
}

#[test]
fn yolo_seg_polygons_cover_the_masks_and_copies_split_by_the_seed() {
    let dir = tempfile::tempdir().unwrap();
    let scan = small_scan(dir.path());
    let out = dir.path().join("labels");
    // An earlier version's YOLO files in a folder of ours are removed by the run.
    std::fs::create_dir_all(out.join("labels")).unwrap();
    std::fs::write(out.join("labels/000000.txt"), "0 0.5 0.5 0.1 0.1\n").unwrap();
    std::fs::write(out.join("classes.txt"), "box\n").unwrap();
    std::fs::write(out.join(".nerflabel-labels"), "").unwrap();
    let args = [
        "--yolo-seg",
        "--yolo-images",
        "copy",
        "--yolo-val",
        "0.3",
        "--seed",
        "3",
    ];
    let o = label_sensor(&scan, &out, &args);
    assert!(o.status.success(), "{}", stderr(&o));
    assert!(
        !out.join("labels").exists() && !out.join("classes.txt").exists(),
        "stale YOLO files left"
    );
    let split = check_like_ultralytics(&out, true);
    check_in_python(&out, true, 24);
    let val: BTreeSet<u64> = split
        .iter()
        .filter(|(_, k)| **k == "val")
        .map(|(i, _)| frame_of(i))
        .collect();
    assert!((6..=9).contains(&val.len()), "3 of 10 blocks of 24 frames: {val:?}");
    let image = out.join("yolo/images/000005.png");
    assert_eq!(
        std::fs::read(&image).unwrap(),
        std::fs::read(scan.join("rgb/000005.png")).unwrap()
    );
    #[cfg(unix)]
    {
        use std::os::unix::fs::MetadataExt;
        assert_ne!(
            std::fs::metadata(&image).unwrap().ino(),
            std::fs::metadata(scan.join("rgb/000005.png")).unwrap().ino(),
            "a copy, not a link"
        );
    }
    // The same seed gives the same split; relabelling a few frames keeps it.
    let lists =
        |out: &Path| ["train.txt", "val.txt"].map(|l| std::fs::read_to_string(out.join("yolo").join(l)).unwrap());
    let before = lists(&out);
    let o = label_sensor(&scan, &out, &[&args[..], &["--frames", "3..6"]].concat());
    assert!(o.status.success(), "{}", stderr(&o));
    assert_eq!(lists(&out), before);
    check_like_ultralytics(&out, true);
    // Boxes into a folder of polygons, for some frames only: refused, nothing changed.
    let o = label_sensor(&scan, &out, &["--yolo", "--frames", "3..6"]);
    assert!(!o.status.success());
    assert!(stderr(&o).contains("outline polygons"), "{}", stderr(&o));
    assert_eq!(lists(&out), before);
}

#[test]
fn yolo_options_are_checked_before_any_work() {
    let dir = tempfile::tempdir().unwrap();
    let scan = small_scan(dir.path());
    let out = dir.path().join("labels");
    for (args, words) in [
        (vec!["--yolo", "--yolo-val", "1"], "below 1"),
        (vec!["--yolo", "--yolo-val=-0.1"], "at least 0"),
        (vec!["--yolo", "--yolo-val", "half"], "not a number"),
        (vec!["--yolo-images", "copy"], "add --yolo"),
        (vec!["--yolo", "--yolo-images", "symlink"], "symlink"),
    ] {
        let o = label_sensor(&scan, &out, &args);
        assert!(!o.status.success(), "{args:?}");
        assert!(stderr(&o).contains(words), "{args:?}: {}", stderr(&o));
        assert!(!out.exists(), "{args:?} wrote something");
    }
}

#[test]
fn label_help_documents_the_yolo_options() {
    let o = run(&["label", "--help"]);
    assert!(o.status.success());
    let text = String::from_utf8_lossy(&o.stdout).into_owned();
    for option in ["--yolo", "--yolo-seg", "--yolo-images", "--yolo-val", "--seed"] {
        assert!(
            text.contains(&format!("      {option} ")) || text.contains(&format!("      {option}\n")),
            "{option} missing from label --help"
        );
    }
    // Only the YOLO options: the rest of `label --help` changes with other
    // work, and clap places the global options at varying points among them.
    let top = String::from_utf8_lossy(&run(&["--help"]).stdout).into_owned();
    let global: Vec<String> = top
        .lines()
        .filter_map(|l| l.trim_start().strip_prefix("--"))
        .map(|o| o.split([' ', ',']).next().unwrap_or("").to_string())
        .filter(|o| o != "help" && o != "version")
        .collect();
    let mut own = String::new();
    let mut skipping = false;
    for line in text.lines() {
        if line.starts_with("  ") && line.trim_start().starts_with('-') {
            skipping = global.iter().any(|g| line.trim_start().starts_with(&format!("--{g}")));
        }
        if !skipping {
            own.push_str(line);
            own.push('\n');
        }
    }
    let start = own.find("      --yolo\n").unwrap();
    let end = start + own[start..].find("      --seed").unwrap();
    let end = end + own[end..].find("\n\n").unwrap_or(own.len() - end);
    insta::assert_snapshot!("label_help_yolo", &own[start..end]);
}
