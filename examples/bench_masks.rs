//! Given masks carried to every frame (`label --masks`), scored against a
//! generated scene's exact masks on the frames that were not given.
//!
//! For each scene folder (made by `nerflabel fixture --realistic`, fitted to
//! MODEL): the true masks of every Nth frame (`--every N`) or of K frames
//! spread over the scan (`--given K`), optionally dilated by D pixels
//! (`--dilate D`, what a bleeding segmenter gives), are written to a masks
//! folder; the release binary labels the scan from them; the other frames
//! are scored: mean per-frame mIoU, predicted/true pixels, boundary F (2 px)
//! and each object's IoU, with the wall time of the label run. `--drop ID`
//! erases object ID from the first given mask (a mask missing an object).
//!
//! Run after `cargo build --release`:
//! `cargo run --release --example bench_masks -- [--every 20 | --given 3] [--dilate 2] [--drop ID] [--model NAME] [--source S] [--exact-boxes] SCENE...`
//! (`--exact-boxes`: no support plane excluded from the objects' regions.)
//! (MODEL defaults to SCENE/model-120s.nlf.)

use nerflabel::boxes::metrics::MaskScores;
use nerflabel::evaluate::read_gray16;
use std::path::{Path, PathBuf};
use std::process::Command;
use std::time::Instant;

type Error = Box<dyn std::error::Error>;

struct Args {
    every: Option<usize>,
    given: Option<usize>,
    dilate: usize,
    model: String,
    source: Option<String>,
    /// Object id erased from the first given mask (a mask missing an object).
    drop: Option<u16>,
    exact_boxes: bool,
    scenes: Vec<PathBuf>,
}

fn parse() -> Result<Args, Error> {
    let mut a = Args {
        every: None,
        given: None,
        dilate: 0,
        model: "model-120s.nlf".into(),
        source: None,
        drop: None,
        exact_boxes: false,
        scenes: Vec::new(),
    };
    let mut it = std::env::args().skip(1);
    while let Some(arg) = it.next() {
        let mut value = || it.next().ok_or(format!("{arg} needs a value"));
        match arg.as_str() {
            "--every" => a.every = Some(value()?.parse()?),
            "--given" => a.given = Some(value()?.parse()?),
            "--dilate" => a.dilate = value()?.parse()?,
            "--model" => a.model = value()?,
            "--source" => a.source = Some(value()?),
            "--drop" => a.drop = Some(value()?.parse()?),
            "--exact-boxes" => a.exact_boxes = true,
            _ => a.scenes.push(PathBuf::from(arg)),
        }
    }
    if a.scenes.is_empty() {
        return Err(
            "usage: bench_masks [--every N | --given K] [--dilate D] [--model NAME] [--source S] SCENE...".into(),
        );
    }
    Ok(a)
}

/// Grow every object into the background by `d` pixels (8-neighbourhood);
/// where two objects grow into one pixel, the lower id takes it.
fn dilate(mask: &[u16], w: usize, h: usize, d: usize) -> Vec<u16> {
    let mut m = mask.to_vec();
    for _ in 0..d {
        let prev = m.clone();
        for y in 0..h {
            for x in 0..w {
                if prev[y * w + x] != 0 {
                    continue;
                }
                let mut best = 0u16;
                for dy in -1i64..=1 {
                    for dx in -1i64..=1 {
                        let (nx, ny) = (x as i64 + dx, y as i64 + dy);
                        if nx < 0 || ny < 0 || nx >= w as i64 || ny >= h as i64 {
                            continue;
                        }
                        let v = prev[ny as usize * w + nx as usize];
                        if v != 0 && (best == 0 || v < best) {
                            best = v;
                        }
                    }
                }
                m[y * w + x] = best;
            }
        }
    }
    m
}

fn run_scene(args: &Args, scene: &Path, exe: &Path) -> Result<(), Error> {
    let truth_dir = scene.join("gt/masks");
    let mut stems: Vec<String> = std::fs::read_dir(&truth_dir)?
        .filter_map(|e| e.ok())
        .filter_map(|e| e.path().file_stem().map(|s| s.to_string_lossy().into_owned()))
        .collect();
    stems.sort();
    let chosen: Vec<usize> = match (args.every, args.given) {
        (_, Some(k)) => (0..k).map(|i| (i * (stems.len() - 1)) / (k - 1).max(1)).collect(),
        (Some(n), None) => (0..stems.len()).step_by(n.max(1)).collect(),
        (None, None) => (0..stems.len()).step_by(20).collect(),
    };
    let work = tempfile::tempdir()?;
    let masks = work.path().join("masks");
    std::fs::create_dir_all(&masks)?;
    for &i in &chosen {
        let path = truth_dir.join(format!("{}.png", stems[i]));
        let truth = read_gray16(&path)?;
        let (w, h) = image::image_dimensions(&path)?;
        let mut given = dilate(&truth, w as usize, h as usize, args.dilate);
        if let (Some(id), true) = (args.drop, i == chosen[0]) {
            given.iter_mut().filter(|v| **v == id).for_each(|v| *v = 0);
        }
        let bytes: Vec<u8> = given.iter().map(|&v| v.min(255) as u8).collect();
        image::GrayImage::from_raw(w, h, bytes)
            .ok_or("mask size")?
            .save(masks.join(format!("{}.png", stems[i])))?;
    }
    let out = work.path().join("labels");
    let mut cmd = Command::new(exe);
    cmd.arg("label")
        .arg(scene)
        .arg("--masks")
        .arg(&masks)
        .arg("--model")
        .arg(scene.join(&args.model))
        .arg("--out")
        .arg(&out);
    if let Some(s) = &args.source {
        cmd.arg("--source").arg(s);
    }
    if args.exact_boxes {
        cmd.arg("--exact-boxes");
    }
    let start = Instant::now();
    let status = cmd.status()?;
    let seconds = start.elapsed().as_secs_f64();
    if !status.success() {
        return Err(format!("{}: label failed ({status})", scene.display()).into());
    }
    let mut scores = MaskScores::default();
    let given: std::collections::BTreeSet<&str> = chosen.iter().map(|&i| stems[i].as_str()).collect();
    for stem in &stems {
        if given.contains(stem.as_str()) {
            continue;
        }
        let truth_path = truth_dir.join(format!("{stem}.png"));
        let predicted = read_gray16(&out.join("masks").join(format!("{stem}.png")))?;
        let truth = read_gray16(&truth_path)?;
        let width = image::image_dimensions(&truth_path)?.0 as usize;
        scores.add(&predicted, &truth, width);
    }
    let total = scores.total_counts();
    println!(
        "{}: {} given, {} scored: mIoU {:.4}, predicted/true px {:.3}, boundary F {:.3}, label {:.1} s",
        scene.display(),
        chosen.len(),
        stems.len() - chosen.len(),
        scores.mean_frame_iou(),
        total.pixel_ratio(),
        total.boundary_f(),
        seconds
    );
    for (id, iou) in scores.per_object_mean_frame() {
        println!("  object {id}: IoU {iou:.4}");
    }
    Ok(())
}

fn main() -> Result<(), Error> {
    let args = parse()?;
    let exe = std::env::current_exe()?
        .parent()
        .and_then(Path::parent)
        .map(|d| d.join("nerflabel"))
        .ok_or("cannot find the release binary beside the examples")?;
    for scene in &args.scenes {
        run_scene(&args, scene, &exe)?;
    }
    Ok(())
}
