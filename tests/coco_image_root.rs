//! `label` records where the COCO images are: `info.scan` and
//! `info.image_root` are absolute, every `image_root/file_name` is the
//! frame's colour file, `--image-root` moves the root, and a partial
//! relabel under another root is refused rather than mixing roots.

mod common;

use common::{label_sensor, s, small_scan, stderr};
use serde_json::Value;
use std::path::{Path, PathBuf};

fn coco(out: &Path) -> Value {
    serde_json::from_slice(&std::fs::read(out.join("coco.json")).unwrap()).unwrap()
}

/// The images' (frame id, file_name), after checking that each
/// `image_root/file_name` is a file; and the image root.
fn images(coco: &Value) -> (PathBuf, Vec<(u64, String)>) {
    let root = PathBuf::from(coco["info"]["image_root"].as_str().unwrap());
    assert!(root.is_absolute(), "info.image_root {} is not absolute", root.display());
    let names: Vec<(u64, String)> = coco["images"]
        .as_array()
        .unwrap()
        .iter()
        .map(|i| {
            (
                i["frame_id"].as_u64().unwrap(),
                i["file_name"].as_str().unwrap().to_string(),
            )
        })
        .collect();
    for (_, name) in &names {
        assert!(
            root.join(name).is_file(),
            "{} does not exist",
            root.join(name).display()
        );
    }
    (root, names)
}

#[test]
fn coco_file_names_resolve_against_the_recorded_image_root() {
    let dir = tempfile::tempdir().unwrap();
    let scan = small_scan(dir.path());
    let scan_abs = std::fs::canonicalize(&scan).unwrap();
    let parent = scan_abs.parent().unwrap().to_path_buf();
    let out = dir.path().join("labels");

    // Default: relative to the scan folder, which info.scan names absolutely.
    let o = label_sensor(&scan, &out, &[]);
    assert!(o.status.success(), "{}", stderr(&o));
    let c = coco(&out);
    assert_eq!(c["info"]["scan"].as_str().unwrap(), scan_abs.to_str().unwrap());
    let (root, names) = images(&c);
    assert_eq!(root, scan_abs);
    assert_eq!(names.len(), 24);
    assert!(names.iter().all(|(_, n)| n.starts_with("rgb/")), "{names:?}");

    // A partial relabel under another root would mix roots: refused, outputs kept.
    let o = label_sensor(&scan, &out, &["--frames", "2..5", "--image-root", s(&parent)]);
    assert!(!o.status.success());
    let err = stderr(&o);
    assert!(err.contains("relative to") && err.contains("--image-root"), "{err}");
    assert_eq!(coco(&out), c);

    // Every frame under the scan's parent: file_names start with `scan/`.
    let o = label_sensor(&scan, &out, &["--image-root", s(&parent)]);
    assert!(o.status.success(), "{}", stderr(&o));
    let (root, names) = images(&coco(&out));
    assert_eq!(root, parent);
    assert_eq!(names.len(), 24);
    assert!(names.iter().all(|(_, n)| n.starts_with("scan/rgb/")), "{names:?}");

    // A partial relabel under the same root merges consistently.
    let o = label_sensor(&scan, &out, &["--frames", "2..5", "--image-root", s(&parent)]);
    assert!(o.status.success(), "{}", stderr(&o));
    let (_, merged) = images(&coco(&out));
    assert_eq!(merged, names);

    // A root the images are not under: `..` components lead to them.
    let out2 = dir.path().join("labels2");
    let o = label_sensor(&scan, &out2, &["--image-root", s(&scan.join("depth"))]);
    assert!(o.status.success(), "{}", stderr(&o));
    let (root, names) = images(&coco(&out2));
    assert_eq!(root, scan_abs.join("depth"));
    assert!(names.iter().all(|(_, n)| n.starts_with("../rgb/")), "{names:?}");

    // A missing root is named in the error.
    let o = label_sensor(&scan, &out2, &["--image-root", s(&dir.path().join("nowhere"))]);
    assert!(!o.status.success());
    assert!(stderr(&o).contains("nowhere"), "{}", stderr(&o));
}
