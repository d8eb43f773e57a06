//! The `synth` driver: pick the views (sampled or from a poses file), render
//! them in parallel batches and stream them in order into the Parquet file,
//! so the same seed gives the same bytes and memory does not grow with `n`.

use super::error::{Rejections, SynthError};
use super::parquet::SynthWriter;
use super::poses_file::{ViewSpec, MAX_VIEWS};
use super::sampling::{Cloud, PoseSampler, Target};
use super::triplet::{render_view, Instances, PointClassifier, SynthView};
use super::viewpoints::{ViewStream, MIN_OBSERVED};
use crate::boxes::{BoxClassifier, BoxSet, DepthSource, LabelOptions, Labeler};
use crate::nerf::model_file::Model;
use crate::nerf::render::view::ViewRenderer;
use crate::poses::{fuse_cloud, CloudOptions};
use crate::scan::{Scan, MAX_IMAGE_SIDE};
use nalgebra::{Point3, Rotation3, Vector3};
use rayon::prelude::*;
use std::path::Path;
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::Instant;

/// Most views per row group (and per parallel rendering batch).
pub const MAX_GROUP_VIEWS: usize = 16;
/// Memory budget of one rendering batch; large views make smaller row groups.
const BATCH_BUDGET_BYTES: u64 = 256 << 20;
/// Working memory per rendered pixel (ray outputs, pixel list, images, PNGs).
const BYTES_PER_PIXEL: u64 = 64;

/// What to synthesise.
#[derive(Clone, Debug)]
pub struct SynthOptions {
    /// Views to sample (ignored with `poses`).
    pub n: usize,
    /// Image width; `None` = the scan's (or from `height` at the scan's aspect).
    pub width: Option<u32>,
    /// Image height; `None` = the scan's (or from `width` at the scan's aspect).
    pub height: Option<u32>,
    pub seed: u64,
    /// Minimum distance from a sampled camera to the scanned points, metres;
    /// `None` = a fifth of the median distance from the scan's cameras to their nearest point.
    pub clearance: Option<f64>,
    /// Render these views instead of sampling.
    pub poses: Option<Vec<ViewSpec>>,
    /// Fraction of probe pixels that must have opacity > 0.5.
    pub min_observed: f64,
    /// CRC-32 of the model file's bytes, recorded in the file's metadata.
    pub model_checksum: u32,
    /// Render colour with the appearance (exposure, white balance) of this
    /// scan frame; `None`: the model's neutral appearance.
    pub appearance: Option<usize>,
    /// Label exactly what each box encloses; by default the support and
    /// wall planes `label` excludes from a box are excluded here too.
    pub exact_boxes: bool,
}

impl Default for SynthOptions {
    fn default() -> Self {
        SynthOptions {
            n: 500,
            width: None,
            height: None,
            seed: 0,
            clearance: None,
            poses: None,
            min_observed: MIN_OBSERVED,
            model_checksum: 0,
            appearance: None,
            exact_boxes: false,
        }
    }
}

/// Progress reports.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum SynthProgress {
    /// Set-up done: views to write, the clearance used and the cloud's size.
    Prepared {
        views: usize,
        clearance_m: Option<f64>,
        cloud_points: usize,
    },
    /// `done` of `total` views written after `seconds`.
    Views { done: usize, total: usize, seconds: f64 },
}

/// What a run produced.
#[derive(Clone, Debug, PartialEq, serde::Serialize)]
pub struct SynthSummary {
    pub views: usize,
    /// Sampled candidates consumed (accepted + rejected); 0 with a poses file.
    pub attempts: u64,
    pub rejections: Rejections,
    /// Clearance used, metres (`None` with a poses file).
    pub clearance_m: Option<f64>,
    pub seconds: f64,
    pub views_per_s: f64,
    /// Size of the written file.
    pub bytes: u64,
}

/// The labelled objects: where sampled views look and how pixels are labelled.
pub struct Objects<'a> {
    /// Object centres and frames (empty: look at the scene centre).
    pub targets: Vec<Target>,
    pub instances: Instances<'a>,
}

impl<'a> Objects<'a> {
    /// The objects of a box set (boxes, or given masks' objects): views
    /// aimed at each box, labels by instance id, points labelled by `classify`.
    pub fn of(set: &BoxSet, classify: &'a PointClassifier<'a>) -> Objects<'a> {
        let mut labels = vec![String::new(); set.max_instance_id() as usize];
        for b in &set.boxes {
            if let Some(slot) = (b.instance_id as usize).checked_sub(1).and_then(|i| labels.get_mut(i)) {
                slot.clone_from(&b.label);
            }
        }
        Objects {
            targets: set
                .boxes
                .iter()
                .map(|b| Target {
                    center: b.center,
                    rotation: b.rotation,
                })
                .collect(),
            instances: Instances { classify, labels },
        }
    }
}

/// What sampling needs from the scan.
struct Sampling {
    cloud: Cloud,
    cameras: Vec<Point3<f64>>,
    clearance: f64,
    targets: Vec<Target>,
    /// Points in the cloud.
    points: usize,
}

impl Sampling {
    /// Fuse the scan's depth into the clearance cloud and pick the targets.
    fn prepare(scan: &Scan, objects: &Objects, clearance: Option<f64>) -> Result<Sampling, SynthError> {
        let fused = fuse_cloud(scan, &CloudOptions::default())?;
        let cloud = Cloud::new(&fused.positions)?;
        let cameras: Vec<Point3<f64>> = scan.frames.iter().map(|f| f.camera_center()).collect();
        let clearance = match clearance {
            Some(c) if c > 0.0 && cloud.is_empty() => return Err(SynthError::NoCloud { clearance: c }),
            Some(c) => c,
            None => cloud.default_clearance(&cameras).unwrap_or(0.0),
        };
        let targets = if objects.targets.is_empty() {
            vec![Target {
                center: fused.bounds.center(),
                rotation: Rotation3::identity(),
            }]
        } else {
            objects.targets.clone()
        };
        Ok(Sampling {
            cloud,
            cameras,
            clearance,
            targets,
            points: fused.len(),
        })
    }
}

/// Where the views come from.
enum Source<'a> {
    Given(&'a [ViewSpec]),
    Sampled(Box<ViewStream<'a>>),
}

/// Render views of `model` for `scan` into the Parquet file `out`: sampled
/// around the `boxes` (around the scene centre without them) or as listed in
/// `options.poses`, masks labelled by the boxes. `stop` interrupts between
/// views, leaving nothing at `out`.
pub fn synthesize(
    scan: &Scan,
    model: &Model,
    boxes: Option<&BoxSet>,
    options: &SynthOptions,
    out: &Path,
    progress: &(dyn Fn(SynthProgress) + Sync),
    stop: &AtomicBool,
) -> Result<SynthSummary, SynthError> {
    let Some(set) = boxes.filter(|b| !b.boxes.is_empty()) else {
        let objects = Objects {
            targets: Vec::new(),
            instances: Instances::none(),
        };
        return synthesize_objects(scan, model, &objects, options, out, progress, stop);
    };
    let classifier = BoxClassifier::new(set);
    let supports = support_planes(set, model, scan, options.exact_boxes)?;
    let classify = |p: Point3<f64>, normal: &dyn Fn(f64) -> Option<Vector3<f64>>| match classifier.classify(&p) {
        0 => 0,
        id if supports.excluded_at(id as usize - 1, &p, normal) => 0,
        id => id,
    };
    synthesize_objects(scan, model, &Objects::of(set, &classify), options, out, progress, stop)
}

/// The support and wall planes `label` excludes from each box of `set`
/// (none with `exact_boxes`), held by a labeler of the rendered depth.
pub fn support_planes<'a>(
    set: &'a BoxSet,
    model: &'a Model,
    scan: &Scan,
    exact_boxes: bool,
) -> Result<Labeler<'a>, SynthError> {
    let options = LabelOptions {
        source: DepthSource::Nerf,
        exact_boxes,
        ..LabelOptions::default()
    };
    let mut labeler = Labeler::new(set, Some(model), options).map_err(|e| SynthError::Options(e.to_string()))?;
    labeler
        .exclude_supports(scan)
        .map_err(|e| SynthError::Options(e.to_string()))?;
    Ok(labeler)
}

/// [`synthesize`] with the objects given directly (targets and a point classifier).
pub fn synthesize_objects(
    scan: &Scan,
    model: &Model,
    objects: &Objects,
    options: &SynthOptions,
    out: &Path,
    progress: &(dyn Fn(SynthProgress) + Sync),
    stop: &AtomicBool,
) -> Result<SynthSummary, SynthError> {
    let start = Instant::now();
    // Many views of one model: skip the cells the model left empty.
    let mut renderer = ViewRenderer::pruned(model)?;
    if let Some(frame) = options.appearance {
        let name = || {
            scan.frames
                .get(frame)
                .map_or_else(|| frame.to_string(), |f| f.name.clone())
        };
        let map = model
            .frame_appearance(frame)
            .ok_or_else(|| SynthError::NoAppearance { frame: name() })?;
        // As the frame was captured: its exposure and the lens's falloff.
        renderer = renderer.with_appearance(map);
        if let Some(lens) = model.vignetting() {
            renderer = renderer.with_lens(lens);
        }
    }
    let first = scan.frames.first().ok_or(SynthError::NoFrames)?;
    let (total, group) = match &options.poses {
        Some(p) => (
            p.len(),
            group_views(p.iter().map(|v| pixels(v.width, v.height)).max().unwrap_or(1)),
        ),
        None => {
            let (w, h) = view_size(scan.size(), options.width, options.height)?;
            (options.n, group_views(pixels(w, h)))
        }
    };
    if total == 0 || total > MAX_VIEWS {
        return Err(SynthError::Options(format!(
            "asked for {total} views; give 1 to {MAX_VIEWS}"
        )));
    }
    if !(0.0..=1.0).contains(&options.min_observed) {
        return Err(SynthError::Options(format!(
            "min_observed {} must be in [0, 1]",
            options.min_observed
        )));
    }

    // Sampling needs the scanned cloud (clearance, scene centre); a poses file does not.
    let sampling = match &options.poses {
        Some(_) => None,
        None => Some(Sampling::prepare(scan, objects, options.clearance)?),
    };
    let mut source = match (&options.poses, &sampling) {
        (Some(p), _) => Source::Given(p),
        (None, Some(s)) => {
            let size = view_size(scan.size(), options.width, options.height)?;
            let k = first.intrinsics.scaled(scan.size(), size);
            let sampler = PoseSampler::new(&s.cameras, &s.targets, &s.cloud, s.clearance)?;
            let stream = ViewStream::new(
                sampler,
                &renderer,
                &objects.instances,
                k,
                size,
                options.seed,
                options.min_observed,
                total,
            );
            Source::Sampled(Box::new(stream))
        }
        (None, None) => return Err(SynthError::Options("internal: sampling without a cloud".into())),
    };
    let clearance_m = sampling.as_ref().map(|s| s.clearance);
    progress(SynthProgress::Prepared {
        views: total,
        clearance_m,
        cloud_points: sampling.as_ref().map_or(0, |s| s.points),
    });

    let metadata = [
        ("nerflabel_version", env!("CARGO_PKG_VERSION").to_string()),
        ("seed", options.seed.to_string()),
        ("scan", scan.root.display().to_string()),
        ("model_crc32", format!("{:08x}", options.model_checksum)),
        (
            "source",
            if options.poses.is_some() {
                "poses file"
            } else {
                "sampled"
            }
            .to_string(),
        ),
        (
            "clearance_m",
            clearance_m.map_or_else(|| "none".into(), |c| format!("{c:.6}")),
        ),
        (
            "appearance",
            options
                .appearance
                .and_then(|f| scan.frames.get(f))
                .map_or_else(|| "neutral".into(), |f| format!("frame {}", f.name)),
        ),
    ];
    let mut writer = SynthWriter::create(out, &metadata)?;
    let interrupted = |views| SynthError::Interrupted {
        path: out.to_path_buf(),
        views,
    };
    while writer.rows() < total {
        if stop.load(Ordering::Relaxed) {
            return Err(interrupted(writer.rows()));
        }
        let done = writer.rows();
        let specs: Vec<ViewSpec> = match &mut source {
            Source::Given(p) => p.iter().skip(done).take(group).copied().collect(),
            Source::Sampled(stream) => match stream.next_views(group, stop)? {
                Some(specs) => specs,
                None => return Err(interrupted(done)),
            },
        };
        if specs.is_empty() {
            return Err(SynthError::Options(format!(
                "internal: no view left after {done} of {total}"
            )));
        }
        let views = specs
            .par_iter()
            .enumerate()
            .map(|(j, spec)| {
                if stop.load(Ordering::Relaxed) {
                    return Err(interrupted(done));
                }
                render_view(&renderer, spec, &objects.instances, done + j)
            })
            .collect::<Result<Vec<SynthView>, SynthError>>()?;
        writer.write_group(&views)?;
        progress(SynthProgress::Views {
            done: writer.rows(),
            total,
            seconds: start.elapsed().as_secs_f64(),
        });
    }

    let (attempts, rejections) = match &source {
        Source::Given(_) => (0, Rejections::default()),
        Source::Sampled(s) => (s.attempts(), s.rejections()),
    };
    writer.append_metadata("views", total.to_string());
    writer.append_metadata("attempts", attempts.to_string());
    writer.append_metadata("rejected_too_close", rejections.too_close.to_string());
    writer.append_metadata("rejected_no_object", rejections.no_object.to_string());
    writer.append_metadata("rejected_unobserved", rejections.unobserved.to_string());
    writer.append_metadata("rejected_near_surface", rejections.near_surface.to_string());
    let bytes = writer.finish()?;
    let seconds = start.elapsed().as_secs_f64();
    Ok(SynthSummary {
        views: total,
        attempts,
        rejections,
        clearance_m,
        seconds,
        views_per_s: total as f64 / seconds.max(1e-9),
        bytes,
    })
}

/// Pixels of a view.
fn pixels(width: u32, height: u32) -> u64 {
    u64::from(width) * u64::from(height)
}

/// Views per batch and row group for views of `pixels` pixels.
fn group_views(pixels: u64) -> usize {
    (BATCH_BUDGET_BYTES / (BYTES_PER_PIXEL * pixels.max(1))).clamp(1, MAX_GROUP_VIEWS as u64) as usize
}

/// Output size from the options, defaulting to the scan's size and aspect.
pub fn view_size(scan: (u32, u32), width: Option<u32>, height: Option<u32>) -> Result<(u32, u32), SynthError> {
    let (sw, sh) = (f64::from(scan.0.max(1)), f64::from(scan.1.max(1)));
    let (w, h) = match (width, height) {
        (Some(w), Some(h)) => (w, h),
        (Some(w), None) => (w, (f64::from(w) * sh / sw).round() as u32),
        (None, Some(h)) => ((f64::from(h) * sw / sh).round() as u32, h),
        (None, None) => scan,
    };
    let ok = |s: u32| (1..=MAX_IMAGE_SIDE).contains(&s);
    if !(ok(w) && ok(h)) || pixels(w, h) > super::poses_file::MAX_VIEW_PIXELS {
        return Err(SynthError::Options(format!(
            "view size {w}x{h}: each side must be 1 to {MAX_IMAGE_SIDE} pixels, at most {} pixels in all",
            super::poses_file::MAX_VIEW_PIXELS
        )));
    }
    Ok((w, h))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn view_size_keeps_the_scan_aspect_and_refuses_absurd_sizes() {
        assert_eq!(view_size((640, 480), None, None).unwrap(), (640, 480));
        assert_eq!(view_size((640, 480), Some(320), None).unwrap(), (320, 240));
        assert_eq!(view_size((640, 480), None, Some(120)).unwrap(), (160, 120));
        assert_eq!(view_size((640, 480), Some(100), Some(100)).unwrap(), (100, 100));
        assert!(view_size((640, 480), Some(0), None).is_err());
        assert!(view_size((640, 480), Some(20_000), None).is_err());
        assert!(view_size((640, 480), Some(16_000), Some(16_000)).is_err());
    }

    #[test]
    fn row_groups_shrink_for_large_views_but_hold_at_least_one() {
        assert_eq!(group_views(320 * 240), MAX_GROUP_VIEWS);
        assert!(group_views(1920 * 1440) < MAX_GROUP_VIEWS);
        assert_eq!(group_views(8192 * 8192), 1);
    }
}
