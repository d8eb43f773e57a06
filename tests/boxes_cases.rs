//! Issue 6, boxes: a zero-volume box, one enclosing the whole scene (and
//! every camera), nested boxes, overlapping boxes and a box behind every
//! camera, labelled on the committed fixture. Each has a defined outcome:
//! a zero-volume box is accepted with a warning naming it and stays empty; a
//! point in several boxes goes to the smallest; a box no camera sees is
//! warned about and gets no pixel; the other boxes' masks never change.
//!
//! Masks come from the sensor depth with clean-up off, so every pixel's
//! label is exactly the classification of its surface point; one case also
//! runs the rendered (nerf) path.

use nalgebra::{Point3, Rotation3, Vector3};
use nerflabel::boxes::{
    read_boxes, write_labels, Box3, BoxSet, DepthSource, LabelOptions, LabelSummary, Labeler, OutputOptions,
};
use nerflabel::nerf::model_file::Model;
use nerflabel::nerf::occupancy::OccupancyGrid;
use nerflabel::nerf::train::fit::{fit, FitOptions};
use nerflabel::nerf::train::settings::FitSettings;
use nerflabel::nerf::train::settings::Preset;
use nerflabel::scan::{load, vouched_free_distance, LoadOptions, Scan};
use std::path::{Path, PathBuf};
use std::sync::atomic::AtomicBool;
use std::sync::OnceLock;

fn fixture() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("fixtures/small")
}

fn scan() -> &'static Scan {
    static SCAN: OnceLock<Scan> = OnceLock::new();
    SCAN.get_or_init(|| load(&fixture(), &LoadOptions::default()).unwrap())
}

fn fixture_boxes() -> Vec<Box3> {
    read_boxes(&fixture().join("boxes.json")).unwrap().boxes
}

/// Renumber boxes 1.. in list order.
fn set(mut boxes: Vec<Box3>) -> BoxSet {
    for (i, b) in boxes.iter_mut().enumerate() {
        b.instance_id = i as u32 + 1;
    }
    BoxSet::from_boxes(boxes)
}

/// These cases pin what the boxes' geometry gives each pixel, so neither
/// clean-up nor colour snapping may move a silhouette afterwards.
fn sensor() -> LabelOptions {
    LabelOptions {
        source: DepthSource::Sensor,
        cleanup_fraction: 0.0,
        snap_to_colour: false,
        ..LabelOptions::default()
    }
}

/// Masks of every frame (frame order).
fn masks(boxes: &BoxSet, options: LabelOptions, model: Option<&nerflabel::nerf::model_file::Model>) -> Vec<Vec<u16>> {
    let labeler = Labeler::new(boxes, model, options).unwrap();
    scan().frames.iter().map(|f| labeler.label_frame(f).mask).collect()
}

/// The fixture's own three boxes, labelled (the reference for every case).
fn baseline() -> &'static Vec<Vec<u16>> {
    static BASE: OnceLock<Vec<Vec<u16>>> = OnceLock::new();
    BASE.get_or_init(|| masks(&set(fixture_boxes()), sensor(), None))
}

/// Pixels (over all frames) labelled `id`.
fn count(masks: &[Vec<u16>], id: u16) -> usize {
    masks.iter().flatten().filter(|&&v| v == id).count()
}

/// Pixels where both sets of masks hold the given ids.
fn count_pairs(a: &[Vec<u16>], b: &[Vec<u16>], f: impl Fn(u16, u16) -> bool) -> usize {
    a.iter()
        .zip(b)
        .flat_map(|(x, y)| x.iter().zip(y))
        .filter(|(&p, &q)| f(p, q))
        .count()
}

/// Write labels to a temp folder and return the summary.
fn summary(boxes: &BoxSet, options: LabelOptions) -> LabelSummary {
    let dir = tempfile::tempdir().unwrap();
    let labeler = Labeler::new(boxes, None, options).unwrap();
    write_labels(dir.path(), scan(), boxes, &labeler, &OutputOptions::default(), &|_| {}).unwrap()
}

#[test]
fn baseline_labels_every_fixture_box() {
    let base = baseline();
    let pixels = base.len() * base[0].len();
    let n: Vec<usize> = (1..=3u16).map(|id| count(base, id)).collect();
    eprintln!("pixels of box, ball, can: {n:?} of {pixels}");
    assert!(n[0] > pixels / 100 && n[1] > pixels / 100, "{n:?}");
    // The can has no sensor depth (glass-like): only stray table points near its base fall in its box.
    assert!(n[2] < n[0] / 10, "{n:?}");
}

#[test]
fn zero_volume_box_is_accepted_with_a_warning_and_stays_empty() {
    let path = tempfile::NamedTempFile::new().unwrap();
    // A sheet lying on the table under the "box" object, and a line through the ball.
    let text = std::fs::read_to_string(fixture().join("boxes.json")).unwrap();
    let mut json: serde_json::Value = serde_json::from_str(&text).unwrap();
    let list = json["boxes"].as_array_mut().unwrap();
    list.push(serde_json::json!({"label": "sheet", "center": [-0.2, 0.15, 0.0], "size": [0.5, 0.5, 0.0]}));
    list.push(serde_json::json!({"label": "line", "center": [0.25, 0.1, 0.1227], "size": [0.0, 0.0, 0.4]}));
    std::fs::write(path.path(), json.to_string()).unwrap();
    let boxes = read_boxes(path.path()).unwrap();
    let warnings = boxes.warnings();
    assert_eq!(warnings.len(), 2, "{warnings:?}");
    assert!(
        warnings[0].contains("box 4 (`sheet`) has zero volume")
            && warnings[1].contains("box 5 (`line`) has zero volume"),
        "{warnings:?}"
    );
    let m = masks(&boxes, sensor(), None);
    assert_eq!(
        (count(&m, 4), count(&m, 5)),
        (0, 0),
        "a zero-volume box holds no surface point"
    );
    assert!(m == *baseline(), "the other boxes' masks changed");
    let s = summary(&boxes, sensor());
    assert_eq!(s.frames_visible[3..], [0, 0]);
    assert!(
        s.warnings.iter().any(|w| w.contains("box 4 (`sheet`) has zero volume")),
        "{:?}",
        s.warnings
    );
    assert!(
        s.warnings
            .iter()
            .any(|w| w.contains("box 4 (`sheet`) is in view") && w.contains("no surface point")),
        "{:?}",
        s.warnings
    );
    // A line meets (almost) no pixel-centre ray: warned as unseen or empty.
    assert!(
        s.warnings.iter().filter(|w| w.contains("box 5 (`line`)")).count() == 2,
        "{:?}",
        s.warnings
    );
}

/// A box around the whole scene and every camera.
fn enclosing() -> Box3 {
    let s = scan();
    let mut lo = Vector3::repeat(f64::INFINITY);
    let mut hi = Vector3::repeat(f64::NEG_INFINITY);
    for f in &s.frames {
        let c = f.camera_to_world.translation.vector;
        (lo, hi) = (lo.inf(&c), hi.sup(&c));
    }
    let centre = Point3::from((lo + hi) * 0.5);
    let size = (hi - lo) + Vector3::repeat(10.0);
    Box3 {
        label: "room".into(),
        instance_id: 0,
        center: centre,
        size,
        rotation: Rotation3::identity(),
    }
}

#[test]
fn box_enclosing_the_whole_scene_and_the_cameras_takes_only_what_no_smaller_box_holds() {
    let mut list = fixture_boxes();
    list.insert(0, enclosing());
    let boxes = set(list); // room = 1, fixture boxes 2..=4
    let m = masks(&boxes, sensor(), None);
    let base = baseline();
    // Every object pixel keeps its object; every other surface pixel is the room.
    let moved = count_pairs(base, &m, |b, n| b != 0 && n != b + 1);
    assert_eq!(moved, 0, "object pixels must stay with the smaller object boxes");
    let mut with_depth = 0;
    for (frame, mask) in scan().frames.iter().zip(&m) {
        let depth = frame.depth.as_ref().unwrap();
        for (i, &id) in mask.iter().enumerate() {
            let z = depth.metres[i];
            if z > 0.0 {
                with_depth += 1;
                assert_ne!(
                    id, 0,
                    "{}: a surface pixel fell outside a box enclosing everything",
                    frame.name
                );
            } else {
                assert_eq!(id, 0, "{}: a pixel without depth was labelled", frame.name);
            }
        }
    }
    assert_eq!(
        count(&m, 1) + count(base, 1) + count(base, 2) + count(base, 3),
        with_depth
    );
    assert!(count(&m, 1) > with_depth / 2, "the room holds most of the surface");
}

#[test]
fn nested_box_takes_its_part_and_the_outer_box_keeps_the_rest() {
    let outer = fixture_boxes()[0].clone();
    // The upper half of the "box" object, inside its box.
    let inner = Box3 {
        label: "lid".into(),
        center: outer.center + outer.rotation * Vector3::new(0.0, 0.0, outer.size.z * 0.25),
        size: outer.size.component_mul(&Vector3::new(1.0, 1.0, 0.5)),
        ..outer.clone()
    };
    let others = fixture_boxes()[1..].to_vec();
    let base = baseline();
    for (order, list) in [
        (
            "outer first",
            [vec![outer.clone(), inner.clone()], others.clone()].concat(),
        ),
        (
            "inner first",
            [vec![inner.clone(), outer.clone()], others.clone()].concat(),
        ),
    ] {
        let boxes = set(list);
        let (o, i) = if order == "outer first" { (1u16, 2u16) } else { (2, 1) };
        let m = masks(&boxes, sensor(), None);
        let (n_outer, n_inner) = (count(&m, o), count(&m, i));
        eprintln!("{order}: outer {n_outer}, inner {n_inner}");
        assert!(
            n_inner > 50 && n_outer > 50,
            "{order}: both parts are seen: outer {n_outer}, inner {n_inner}"
        );
        // Together exactly the pixels of the outer box alone.
        assert_eq!(
            count_pairs(base, &m, |b, n| (b == 1) != (n == o || n == i)),
            0,
            "{order}: outer + inner differ from the outer box alone"
        );
        // The other boxes are untouched.
        assert_eq!(count_pairs(base, &m, |b, n| b > 1 && n != b + 1), 0, "{order}");
    }
}

#[test]
fn overlapping_boxes_give_the_overlap_to_the_smaller_whatever_their_order() {
    let a = fixture_boxes()[0].clone();
    // 0.8 of a's width, shifted half a's width along a's x axis: overlaps the
    // part of a with local x in [0.1, 0.5] of its width, and is the smaller.
    let b = Box3 {
        label: "shifted".into(),
        center: a.center + a.rotation * Vector3::new(0.5 * a.size.x, 0.0, 0.0),
        size: a.size.component_mul(&Vector3::new(0.8, 1.0, 1.0)),
        ..a.clone()
    };
    let others = fixture_boxes()[1..].to_vec();
    let first = masks(
        &set([vec![a.clone(), b.clone()], others.clone()].concat()),
        sensor(),
        None,
    );
    let second = masks(&set([vec![b.clone(), a.clone()], others].concat()), sensor(), None);
    // Same masks with ids 1 and 2 swapped: the order in the file does not matter.
    let swap = |v: u16| match v {
        1 => 2,
        2 => 1,
        x => x,
    };
    assert_eq!(
        count_pairs(&first, &second, |p, q| swap(p) != q),
        0,
        "order changed the labels"
    );
    // Every pixel of a alone is still a or b (nothing lost) and the overlap went to b.
    let base = baseline();
    assert_eq!(count_pairs(base, &first, |p, q| p == 1 && q != 1 && q != 2), 0);
    let taken = count_pairs(base, &first, |p, q| p == 1 && q == 2);
    let kept = count_pairs(base, &first, |p, q| p == 1 && q == 1);
    eprintln!("of a's pixels: {kept} kept by a, {taken} taken by the smaller overlapping b");
    assert!(taken > 50 && kept > 50, "kept {kept}, taken {taken}");
}

/// A box well above every camera: all corners have negative camera-frame z.
fn behind_every_camera() -> Box3 {
    let s = scan();
    let top = s
        .frames
        .iter()
        .map(|f| f.camera_to_world.translation.vector.z)
        .fold(f64::NEG_INFINITY, f64::max);
    let b = Box3 {
        label: "sky".into(),
        instance_id: 0,
        center: Point3::new(0.0, 0.0, top + 20.0),
        size: Vector3::repeat(0.5),
        rotation: Rotation3::identity(),
    };
    for f in &s.frames {
        let w2c = f.camera_to_world.inverse();
        for c in b.corners() {
            assert!(
                (w2c * c).z < 0.0,
                "{}: test set-up: the box must be behind the camera",
                f.name
            );
        }
    }
    b
}

#[test]
fn box_behind_every_camera_is_warned_about_and_gets_no_pixel() {
    let boxes = set([fixture_boxes(), vec![behind_every_camera()]].concat());
    let m = masks(&boxes, sensor(), None);
    assert_eq!(count(&m, 4), 0);
    assert!(m == *baseline(), "the other boxes' masks changed");
    let labeler = Labeler::new(&boxes, None, sensor()).unwrap();
    for f in &scan().frames {
        assert!(
            !labeler.label_frame(f).in_view.contains(&4),
            "{}: a box behind the camera counted as in view",
            f.name
        );
    }
    let s = summary(&boxes, sensor());
    assert_eq!(s.frames_visible[3], 0);
    assert!(
        s.warnings
            .iter()
            .any(|w| w.contains("box 4 (`sky`) is outside the view of every labelled frame")),
        "{:?}",
        s.warnings
    );
}

/// A model of a few training steps: enough for the rendering path, not for accuracy.
fn briefly_fitted() -> &'static Model {
    static MODEL: OnceLock<Model> = OnceLock::new();
    MODEL.get_or_init(|| {
        let opts = FitOptions {
            settings: FitSettings {
                preset: Preset::Fast,
                holdout_every: 0,
                refine_poses: false,
                ..FitSettings::default()
            },
            steps: Some(5),
            ..FitOptions::default()
        };
        fit(&mut scan().clone(), &opts, &AtomicBool::new(false), &mut |_| {})
            .unwrap()
            .model
    })
}

/// Rendered depth of every pixel, with no colour snapping.
fn rendered_depth() -> LabelOptions {
    LabelOptions {
        source: DepthSource::Nerf,
        full_depth: true,
        snap_to_colour: false,
        ..LabelOptions::default()
    }
}

#[test]
fn rendered_depth_handles_a_box_around_the_cameras_and_one_behind_them() {
    let boxes = set(vec![enclosing(), behind_every_camera()]);
    let labeler = Labeler::new(&boxes, Some(briefly_fitted()), rendered_depth()).unwrap();
    let mut room = 0;
    for f in scan().frames.iter().step_by(6) {
        let l = labeler.label_frame(f);
        assert!(
            l.mask.iter().all(|&v| v != 2),
            "{}: the box behind the cameras got pixels",
            f.name
        );
        let depth = l.depth_m.as_ref().unwrap();
        assert!(
            depth.iter().all(|d| d.is_finite() && *d >= 0.0),
            "{}: non-finite rendered depth",
            f.name
        );
        // With the camera inside the room box every pixel's ray meets it.
        assert_eq!(l.box_pixels, (f.size().0 * f.size().1) as usize, "{}", f.name);
        room += l.mask.iter().filter(|&&v| v == 1).count();
        // Where a surface was rendered inside the room, it is labelled the room.
        let surfaced = depth.iter().zip(&l.mask).filter(|(d, m)| **d > 0.0 && **m == 0).count();
        assert!(
            surfaced < depth.len() / 100,
            "{}: {surfaced} rendered surface pixels left unlabelled",
            f.name
        );
    }
    assert!(room > 0, "the room box must receive the rendered surface");
}

/// Regression: in front of a frame the fit held out, space no training view
/// constrained held a floater that hid half of that frame's objects. Where
/// a frame measured depth it vouches that space nearer than half its
/// nearest measurement is free, as it did for the fit. Here density fills
/// all space, so only that rule keeps the rendered surface off the lens.
#[test]
fn space_a_frame_measured_free_renders_no_floater() {
    let mut model = briefly_fitted().clone();
    let density = &mut model.field.density;
    let outputs = density.config.output;
    let params = density.params.len();
    density.params.fill(0.0);
    density.params[params - outputs..].fill(8.0);
    model.occupancy = OccupancyGrid::full(model.occupancy.resolution());
    let boxes = set(vec![enclosing()]);
    let labeler = Labeler::new(&boxes, Some(&model), rendered_depth()).unwrap();
    let (mut measured, mut unmeasured_near) = (0, 0);
    for f in scan().frames.iter().step_by(5) {
        let sensor = &f.depth.as_ref().unwrap().metres;
        let free = vouched_free_distance(sensor);
        assert!(free > 0.1, "{}: test set-up: the frame measures depth", f.name);
        let rendered = labeler.label_frame(f).depth_m.unwrap();
        for (&r, &s) in rendered.iter().zip(sensor) {
            if s > 0.0 {
                measured += 1;
                assert!(
                    r >= free * 0.999,
                    "{}: rendered {r} m in space the frame measured free (< {free} m)",
                    f.name
                );
            } else if r < free {
                unmeasured_near += 1;
            }
        }
    }
    assert!(measured > 10_000, "{measured} measured pixels checked");
    // Where the frame measured nothing it vouches for nothing: the density is rendered.
    let unmeasured = scan()
        .frames
        .iter()
        .step_by(5)
        .map(|f| f.depth.as_ref().unwrap().metres.iter().filter(|&&s| s <= 0.0).count())
        .sum::<usize>();
    assert_eq!(
        unmeasured_near, unmeasured,
        "pixels without depth render the density in front of them"
    );
}
