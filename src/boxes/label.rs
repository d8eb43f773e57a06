//! The per-frame labelling driver: find the pixels whose rays can meet a
//! box, get the surface depth behind each (rendered first crossing, sensor,
//! or both fused), classify the surface point into the boxes, and derive
//! tight 2D boxes and object poses from the resulting instance mask.
//!
//! NeRF rays march from the near end of the unit cube (so occluders in front
//! of a box are found) only to the far end of the ray's interval through the
//! boxes, and stop at termination.

use super::boundary::snap_to_colour;
use super::classify::{BoxClassifier, Overlap};
use super::cleanup::clean_mask;
use super::options::{DepthSource, LabelError, LabelOptions};
use super::parse::BoxSet;
use super::project::{project_box, PixelRect};
use super::reach::{self, Contested};
use super::support::{excluded_planes, ExcludedPlane};
use super::surface::{first_crossings, skip_shared_empty_space, CrossingOptions, SurfaceWorkspace};
use super::tsdf::BoxTsdf;
use crate::nerf::camera::LocalCamera;
use crate::nerf::model_file::Model;
use crate::nerf::render::march::ray_interval;
use crate::nerf::render::rays::{RenderOptions, RenderRay};
use crate::nerf::render::view::ViewRenderer;
use crate::poses::sample_depth_points;
use crate::scan::{vouched_free_distance, vouched_start, Frame, Scan};
use nalgebra::{IsometryMatrix3, Point3, Vector3};
use rayon::prelude::*;
use std::sync::atomic::{AtomicUsize, Ordering};

/// Rays rendered per call of the renderer.
const PACKET: usize = 4096;
/// Measured surface points sampled from the scan to find support planes.
const SUPPORT_POINTS: usize = 2_000_000;

/// One visible instance in one frame.
#[derive(Clone, Debug, PartialEq)]
pub struct InstanceLabel {
    pub instance_id: u32,
    /// Tight pixel bounds of the instance's mask pixels.
    pub bbox: PixelRect,
    /// Mask pixels.
    pub area: u64,
    /// Rigid box pose in the camera frame (OpenCV axes): world-to-camera x object-to-world.
    pub object_to_camera: IsometryMatrix3<f64>,
}

/// Labels of one frame.
#[derive(Clone, Debug)]
pub struct FrameLabel {
    pub frame_id: u64,
    pub name: String,
    pub width: u32,
    pub height: u32,
    /// Instance id per pixel, row-major, 0 = background.
    pub mask: Vec<u16>,
    /// Z-depth in metres per pixel (0 = no surface), with full depth only.
    pub depth_m: Option<Vec<f32>>,
    /// Visible instances in instance-id order.
    pub instances: Vec<InstanceLabel>,
    /// Instance ids whose box projects into the image (visible or occluded).
    pub in_view: Vec<u32>,
    /// Pixels whose ray meets a box.
    pub box_pixels: usize,
    /// Rays handed to the renderer.
    pub rendered_rays: usize,
}

/// A pixel whose depth is needed.
#[derive(Clone, Copy)]
struct Job {
    x: u32,
    y: u32,
    /// Far end of the ray's interval through the boxes, metres along the unit ray.
    box_far: Option<f64>,
}

/// The surface seen behind some pixels of one frame.
pub struct FrameSurface {
    jobs: Vec<Job>,
    /// Camera z of each job's surface in metres (0 = none).
    depths: Vec<f64>,
    /// Instance ids whose box projects into the image.
    pub in_view: Vec<u32>,
    /// Pixels whose ray meets a box.
    pub box_pixels: usize,
    /// Rays handed to the renderer.
    pub rendered_rays: usize,
}

impl FrameSurface {
    /// Pixels with a surface: (x, y, camera z in metres).
    pub fn points(&self) -> impl Iterator<Item = (u32, u32, f64)> + '_ {
        self.jobs
            .iter()
            .zip(&self.depths)
            .filter(|(_, &z)| z > 0.0)
            .map(|(j, &z)| (j.x, j.y, z))
    }

    /// Camera z of every pixel of the `w` x `h` frame (0 = no surface): what
    /// [`surface_normal`] reads.
    pub fn z_image(&self, w: u32, h: u32) -> Vec<f64> {
        z_image(&self.jobs, &self.depths, w, h)
    }
}

fn z_image(jobs: &[Job], depths: &[f64], w: u32, h: u32) -> Vec<f64> {
    let mut z_image = vec![0.0f64; w as usize * h as usize];
    for (j, &z) in jobs.iter().zip(depths) {
        z_image[j.y as usize * w as usize + j.x as usize] = z;
    }
    z_image
}

/// Labels frames of one scan with one box set and depth source.
pub struct Labeler<'a> {
    boxes: &'a BoxSet,
    classifier: BoxClassifier,
    options: LabelOptions,
    renderer: Option<ViewRenderer<'a>>,
    render: Option<RenderOptions>,
    /// Fused source: largest sensor/rendered disagreement that keeps the sensor depth, metres.
    fused_tolerance_m: f64,
    /// A surface point this far (metres) in front of a box the ray then
    /// enters belongs to that box (0 for the sensor source).
    box_tolerance_m: f64,
    /// Per box (instance id - 1): planes of the scene excluded from it
    /// (supports and walls a loosely drawn box reaches into).
    excluded: Vec<Vec<ExcludedPlane>>,
    /// Rendered surfaces lie within about this of the true ones (a finest
    /// grid cell; 0 for the sensor source).
    surface_error_m: f64,
    /// Fused source: the scan's sensor depth fused over all frames around the boxes.
    sensor_fusion: Option<BoxTsdf>,
}

impl<'a> Labeler<'a> {
    /// Prepare labelling; `model` is required by the nerf and fused sources.
    pub fn new(boxes: &'a BoxSet, model: Option<&'a Model>, options: LabelOptions) -> Result<Self, LabelError> {
        let (renderer, render, cell_m) = match (options.source.needs_model(), model) {
            (true, None) => return Err(LabelError::MissingModel(options.source)),
            (false, _) => (None, None, 0.0),
            (true, Some(m)) => {
                // Whole frames: a grid re-estimated from the field skips more
                // empty space, well worth its set-up over many frames.
                let r = if options.full_depth && !options.few_frames {
                    ViewRenderer::pruned(m)?
                } else {
                    ViewRenderer::new(m)?
                };
                let cell_local = 1.0 / m.header.field.grid.finest_resolution.max(1) as f64;
                let cell_m = r.transform.local_to_world_distance(cell_local);
                (Some(r), Some(m.render_options(false)), cell_m)
            }
        };
        let fused_tolerance_m = options.fused_tolerance_cells * cell_m;
        let box_tolerance_m = options.box_tolerance_cells * cell_m;
        Ok(Labeler {
            boxes,
            classifier: BoxClassifier::with_overlap(boxes, options.overlap),
            options,
            renderer,
            render,
            fused_tolerance_m,
            box_tolerance_m,
            excluded: vec![Vec::new(); boxes.boxes.len()],
            surface_error_m: cell_m,
            sensor_fusion: None,
        })
    }

    /// Fused source: fuse the scan's sensor depth over all frames around the
    /// boxes (voxels of half a finest grid cell, the rendered surface's own
    /// precision), and take the sensor depth from there instead of from each
    /// frame alone. Other sources: nothing.
    pub fn fuse_sensor_depth(&mut self, scan: &Scan) {
        if self.options.source == DepthSource::Fused && self.surface_error_m > 0.0 {
            self.sensor_fusion = Some(BoxTsdf::fuse(&scan.frames, self.boxes, 0.5 * self.surface_error_m));
        }
    }

    /// Find, from the scan's measured depth, the support and wall planes
    /// each box reaches into ([`super::support`]) and exclude them from the
    /// box; nothing with `exact_boxes`. Returns how many planes were found.
    pub fn exclude_supports(&mut self, scan: &Scan) -> Result<usize, LabelError> {
        if self.options.exact_boxes {
            return Ok(0);
        }
        let samples = sample_depth_points(scan, SUPPORT_POINTS)
            .map_err(|e| LabelError::Option(format!("cannot sample the scan's depth to find support planes: {e}")))?;
        let cameras: Vec<Point3<f64>> = scan.frames.iter().map(Frame::camera_center).collect();
        Ok(self.exclude_supports_among(&samples.points, &cameras))
    }

    /// [`Self::exclude_supports`] with the scan's surface points (world
    /// metres) sampled once by the caller (the annotation server labels
    /// one frame per edit), and the camera centres they were seen from.
    pub fn exclude_supports_among(&mut self, points: &[Point3<f64>], cameras: &[Point3<f64>]) -> usize {
        if self.options.exact_boxes {
            return 0;
        }
        self.excluded = excluded_planes(self.boxes, points, cameras, 0, self.box_tolerance_m);
        self.excluded.iter().map(Vec::len).sum()
    }

    /// How far above an excluded plane a surface point still counts as the
    /// plane: the plane's measured noise band for sensor depth; rendered
    /// surfaces are smooth, and the finest grid places them to within half a
    /// cell, its nearest vertex (the plane itself, fitted to thousands of
    /// points, is far more precise).
    fn plane_band(&self, plane: &ExcludedPlane) -> f64 {
        match self.options.source {
            DepthSource::Sensor => plane.band,
            DepthSource::Nerf | DepthSource::Fused => 0.5 * self.surface_error_m,
        }
    }

    /// The planes excluded from each box (indexed like the box set).
    pub fn excluded_planes(&self) -> &[Vec<ExcludedPlane>] {
        &self.excluded
    }

    /// Whether any box has a plane excluded from it.
    pub fn excludes_any_plane(&self) -> bool {
        self.excluded.iter().any(|planes| !planes.is_empty())
    }

    /// Whether the planes excluded from box `index` (of the box set) take
    /// the surface point `point`: on a plane's band it is the plane itself,
    /// unless the surface there is steep to it (`normal`: an object's side
    /// meeting its support; asked for the normal over neighbours at least
    /// the given metres apart); behind the band it is always the plane's side.
    pub fn excluded_at(&self, index: usize, point: &Point3<f64>, normal: impl Fn(f64) -> Option<Vector3<f64>>) -> bool {
        let Some(planes) = self.excluded.get(index) else {
            return false;
        };
        planes.iter().any(|plane| {
            let (distance, band) = (plane.distance(point), self.plane_band(plane));
            distance < 0.0
                || (distance <= band
                    && !normal(self.normal_span(band)).is_some_and(|n| n.dot(&plane.normal).abs() < STEEP_COSINE))
        })
    }

    /// How far apart the neighbours a surface normal is taken over must be:
    /// sensor depth is as noisy as the plane's band says (its normals over
    /// neighbouring pixels point anywhere), so across the band; rendered and
    /// fused surfaces are smooth (the field, or depth averaged over frames),
    /// so over neighbouring pixels, which keeps an object's foot and does not
    /// take a support's edge for a steep side.
    fn normal_span(&self, band: f64) -> f64 {
        match self.options.source {
            DepthSource::Sensor => band,
            DepthSource::Nerf | DepthSource::Fused => 0.0,
        }
    }

    /// Whether a point in several boxes goes to the object that reaches it
    /// ([`reach`]): with the smallest-box rule, unless the boxes are taken
    /// exactly as drawn.
    fn contest_overlaps(&self) -> bool {
        self.options.overlap == Overlap::Smallest && !self.options.exact_boxes && self.classifier.len() > 1
    }

    /// How far rendered surfaces may lie from the true ones, metres (a
    /// finest grid cell; 0 for the sensor source).
    pub fn surface_error_m(&self) -> f64 {
        self.surface_error_m
    }

    /// The options in use.
    pub fn options(&self) -> &LabelOptions {
        &self.options
    }

    /// Sensor/rendered agreement tolerance of the fused source, metres.
    pub fn fused_tolerance_m(&self) -> f64 {
        self.fused_tolerance_m
    }

    /// Label frames in parallel; `progress` hears the number of frames finished so far.
    pub fn label_frames(&self, frames: &[&Frame], progress: &(dyn Fn(usize) + Sync)) -> Vec<FrameLabel> {
        let done = AtomicUsize::new(0);
        frames
            .par_iter()
            .map(|frame| {
                let label = self.label_frame(frame);
                progress(done.fetch_add(1, Ordering::Relaxed) + 1);
                label
            })
            .collect()
    }

    /// The surface behind the pixels whose rays can meet a box (every
    /// pixel with full depth), from the configured depth source.
    pub fn surface(&self, frame: &Frame) -> FrameSurface {
        self.surface_where(frame, &|_, _| true)
    }

    /// [`Self::surface`] of the pixels (x, y) that `keep` accepts.
    pub fn surface_where(&self, frame: &Frame, keep: &dyn Fn(u32, u32) -> bool) -> FrameSurface {
        let (w, h) = frame.size();
        let c2w = &frame.camera_to_world;
        let k = frame.intrinsics;
        let origin = Point3::from(c2w.translation.vector);
        let rot = c2w.rotation;
        let full = self.options.full_depth;

        // Pixels whose ray can meet a box: inside a projected rectangle and
        // with a non-empty interval through the boxes.
        let mut in_view = Vec::new();
        let mut candidate = vec![false; if full { 0 } else { w as usize * h as usize }];
        for b in &self.boxes.boxes {
            if let Some(r) = project_box(b, c2w, &k, (w, h)) {
                in_view.push(b.instance_id);
                if !full {
                    for y in r.y0..r.y1 {
                        let row = y as usize * w as usize;
                        candidate[row + r.x0 as usize..row + r.x1 as usize].fill(true);
                    }
                }
            }
        }
        let mut jobs = Vec::new();
        let mut box_pixels = 0;
        for y in 0..h {
            for x in 0..w {
                if (!full && !candidate[y as usize * w as usize + x as usize]) || !keep(x, y) {
                    continue;
                }
                let ray = rot * k.unproject(x as f64, y as f64);
                // Times the reciprocal length, as before the move to nalgebra (same bits).
                let dir = ray * (1.0 / ray.norm());
                let box_far = self.classifier.ray_interval(&origin, &dir).map(|(_, t1)| t1);
                box_pixels += box_far.is_some() as usize;
                if full || box_far.is_some() {
                    jobs.push(Job { x, y, box_far });
                }
            }
        }

        let rendered = match self.options.source {
            DepthSource::Sensor => None,
            DepthSource::Nerf | DepthSource::Fused => Some(self.render_jobs(frame, &jobs)),
        };
        let sensor = |j: &Job| frame.depth.as_ref().map_or(0.0, |d| d.get(j.x, j.y) as f64);
        // The fused source takes the sensor's surface only within its
        // tolerance of the rendered one: only that stretch of the ray is
        // searched in the fused sensor depth.
        let fused = |j: &Job, rendered: f64| match &self.sensor_fusion {
            _ if rendered <= 0.0 => rendered,
            Some(tsdf) => {
                let ray = rot * k.unproject(j.x as f64, j.y as f64);
                let len = ray.norm();
                let tolerance = self.fused_tolerance_m;
                let z = tsdf.depth_between(
                    &origin,
                    &(ray / len),
                    1.0 / len,
                    rendered - tolerance,
                    rendered + tolerance,
                );
                self.fuse(z, rendered)
            }
            None => self.fuse(sensor(j), rendered),
        };
        let depths: Vec<f64> = jobs
            .iter()
            .enumerate()
            .map(|(i, j)| match (self.options.source, &rendered) {
                (DepthSource::Nerf, Some(r)) => r[i],
                (DepthSource::Fused, Some(r)) => fused(j, r[i]),
                _ => sensor(j),
            })
            .collect();
        FrameSurface {
            rendered_rays: if rendered.is_some() { jobs.len() } else { 0 },
            jobs,
            depths,
            in_view,
            box_pixels,
        }
    }

    /// Label one frame (its rays are rendered in parallel packets).
    pub fn label_frame(&self, frame: &Frame) -> FrameLabel {
        let (w, h) = frame.size();
        let c2w = &frame.camera_to_world;
        let k = frame.intrinsics;
        let origin = Point3::from(c2w.translation.vector);
        let rot = c2w.rotation;
        let FrameSurface {
            jobs,
            depths,
            in_view,
            box_pixels,
            rendered_rays,
        } = self.surface(frame);
        let mut mask = vec![0u16; w as usize * h as usize];
        let mut depth_m = self.options.full_depth.then(|| vec![0.0f32; w as usize * h as usize]);
        // Camera z of every job's surface (0 = none), for the surface normals
        // the excluded planes need and for contested overlaps; built only
        // when one of them reads it.
        let z_image_of_jobs = || z_image(&jobs, &depths, w, h);
        let mut z_image = Vec::new();
        if self.excludes_any_plane() {
            z_image = z_image_of_jobs();
        }
        let mut contested = Contested::default();
        let point_at = |x: u32, y: u32, z: f64| c2w * Point3::from(k.unproject(x as f64, y as f64) * z);
        for (j, &z) in jobs.iter().zip(&depths) {
            let index = j.y as usize * w as usize + j.x as usize;
            if let Some(d) = depth_m.as_mut() {
                d[index] = z as f32;
            }
            if z > 0.0 && j.box_far.is_some() {
                let ray = rot * k.unproject(j.x as f64, j.y as f64);
                let len = ray.norm();
                // Ids fit in 16 bits: parsing caps the box count at 65535.
                let dir = ray / len;
                let id = self
                    .classifier
                    .classify_on_ray(&origin, &dir, z * len, self.box_tolerance_m);
                let point = origin + dir * (z * len);
                let excluded_from = |id: u32| {
                    self.excluded_at(id as usize - 1, &point, |span| {
                        surface_normal(&z_image, w, h, j.x, j.y, span, &point_at)
                    })
                };
                let excluded = id > 0 && excluded_from(id);
                mask[index] = if excluded { 0 } else { id as u16 };
                if id > 0 && !excluded && self.contest_overlaps() {
                    let holders: Vec<u32> = self
                        .classifier
                        .containing(point)
                        .filter(|&other| other == id || !excluded_from(other))
                        .collect();
                    if holders.len() >= 2 && holders[0] == id {
                        contested.push(mask.len(), index, holders);
                    }
                }
            }
        }
        if !contested.is_empty() {
            if z_image.is_empty() {
                z_image = z_image_of_jobs();
            }
            let steps = reach::SurfaceSteps {
                camera: k,
                surface_error_m: self.surface_error_m,
            };
            reach::resolve(&mut mask, &z_image, w as usize, &contested, steps);
        }
        let mask = finish_mask(mask, frame, &self.options);
        let instances = instances_of(&mask, w, h, self.boxes, &c2w.inverse());
        FrameLabel {
            frame_id: frame.id,
            name: frame.name.clone(),
            width: w,
            height: h,
            mask,
            depth_m,
            instances,
            in_view,
            box_pixels,
            rendered_rays,
        }
    }

    /// Fused rule: the sensor depth where it exists and agrees with the
    /// rendered depth within the tolerance, else the rendered depth.
    fn fuse(&self, sensor: f64, rendered: f64) -> f64 {
        if sensor > 0.0 && rendered > 0.0 && (sensor - rendered).abs() <= self.fused_tolerance_m {
            sensor
        } else {
            rendered
        }
    }

    /// Rendered z-depth in metres (0 = no surface) for every job, packets in parallel.
    fn render_jobs(&self, frame: &Frame, jobs: &[Job]) -> Vec<f64> {
        let mut depth = vec![0.0; jobs.len()];
        let (Some(renderer), Some(opts)) = (&self.renderer, &self.render) else {
            return depth;
        };
        let (w, h) = frame.size();
        let camera: LocalCamera = renderer.local_camera(&frame.camera_to_world, &frame.intrinsics, w, h);
        let scale = renderer.transform.scale();
        // Where the frame measured depth it vouches that space nearer than
        // its nearest measurement is free, as it did for the fit: a floater
        // there (space no training view held, before a frame the fit kept
        // out) would hide everything behind it. Local distance along the
        // ray to that depth = metres * scale * norm.
        let free_z = frame
            .depth
            .as_ref()
            .map_or(0.0, |d| vouched_free_distance(&d.metres) as f64 * scale) as f32;
        let near_of = |j: &Job, norm: f32| {
            let measured = frame.depth.as_ref().map_or(0.0, |d| d.get(j.x, j.y));
            opts.rule.min_step.max(vouched_start(measured, free_z, norm))
        };
        let (field, grid) = (&renderer.model.field, renderer.grid());
        let crossing = CrossingOptions {
            rule: opts.rule,
            threshold: self.options.surface_opacity,
            max_samples: opts.max_samples_per_ray,
        };
        jobs.par_chunks(PACKET).zip(depth.par_chunks_mut(PACKET)).for_each_init(
            || (SurfaceWorkspace::default(), Vec::new(), Vec::new(), Vec::new()),
            |(ws, rays, index, out), (chunk, depth)| {
                rays.clear();
                index.clear();
                for (i, j) in chunk.iter().enumerate() {
                    let (ray, norm) = camera.ray(j.x as f32, j.y as f32);
                    let Some((t0, t1)) = ray_interval(&ray, near_of(j, norm)) else {
                        continue;
                    };
                    // World metres along the unit ray -> local units along the unit local ray.
                    let t_max = match (self.options.full_depth, j.box_far) {
                        (false, Some(far)) => t1.min((far * scale) as f32),
                        _ => t1,
                    };
                    if t_max > t0 {
                        rays.push(RenderRay { ray, t_min: t0, t_max });
                        index.push((i, norm));
                    }
                }
                skip_shared_empty_space(grid, rays);
                out.clear();
                out.resize(rays.len(), None);
                first_crossings(field, grid, rays, &crossing, ws, out);
                for (o, &(i, norm)) in out.iter().zip(index.iter()) {
                    if let Some(t) = *o {
                        // Distance along the unit local ray -> local z -> metres.
                        let z = t as f64 / norm as f64 / scale;
                        if z.is_finite() && z > 0.0 {
                            depth[i] = z;
                        }
                    }
                }
            },
        );
        depth
    }
}

/// A surface within an excluded plane's band whose normal is at more than
/// 45 degrees to the plane's belongs to what stands on the plane, not to it.
const STEEP_COSINE: f64 = std::f64::consts::FRAC_1_SQRT_2;
/// Farthest neighbour a surface normal is taken over, pixels.
const MAX_NORMAL_STEP_PX: f64 = 16.0;

/// Unit normal of the surface seen at pixel (x, y) from the camera-z image
/// `z` (0 = no surface): along each image axis, the difference to the
/// neighbour nearer in depth, so a depth edge does not tilt it. The
/// neighbours are the pixels at least `span_m` metres of surface away (one
/// pixel at least): sensor depth a millimetre noisy, one sub-millimetre
/// pixel apart, gives a table random normals. `None` without a neighbour on
/// either axis.
pub(crate) fn surface_normal(
    z: &[f64],
    w: u32,
    h: u32,
    x: u32,
    y: u32,
    span_m: f64,
    point_at: &dyn Fn(u32, u32, f64) -> Point3<f64>,
) -> Option<Vector3<f64>> {
    let at = |x: u32, y: u32| z[y as usize * w as usize + x as usize];
    let centre_z = at(x, y);
    let centre = point_at(x, y, centre_z);
    // Pixels between the neighbours: one, unless a span is asked for.
    let step = if span_m > 0.0 {
        let footprint = (point_at(x + 1, y, centre_z) - centre).norm();
        (span_m / footprint).ceil().clamp(1.0, MAX_NORMAL_STEP_PX) as u32
    } else {
        1
    };
    // The neighbour along one axis nearer in depth, as a vector from the centre.
    let tangent = |a: Option<(u32, u32)>, b: Option<(u32, u32)>| -> Option<Vector3<f64>> {
        let near = |p: Option<(u32, u32)>| p.map(|(px, py)| (px, py, at(px, py))).filter(|&(_, _, pz)| pz > 0.0);
        match (near(a), near(b)) {
            (Some(p), Some(q)) if (p.2 - centre_z).abs() <= (q.2 - centre_z).abs() => {
                Some(centre - point_at(p.0, p.1, p.2))
            }
            (_, Some(q)) => Some(point_at(q.0, q.1, q.2) - centre),
            (Some(p), None) => Some(centre - point_at(p.0, p.1, p.2)),
            (None, None) => None,
        }
    };
    let horizontal = tangent(
        x.checked_sub(step).map(|l| (l, y)),
        (x + step < w).then_some((x + step, y)),
    )?;
    let vertical = tangent(
        y.checked_sub(step).map(|u| (x, u)),
        (y + step < h).then_some((x, y + step)),
    )?;
    let n = horizontal.cross(&vertical);
    let length = n.norm();
    (length > 0.0 && length.is_finite()).then(|| n / length)
}

/// A frame's mask after the options' boundary steps: silhouettes snapped to
/// the colour edges, then small holes and specks cleaned up.
pub(crate) fn finish_mask(mut mask: Vec<u16>, frame: &Frame, options: &LabelOptions) -> Vec<u16> {
    if options.snap_to_colour {
        mask = snap_to_colour(&mask, &frame.rgb);
    }
    if options.cleanup_fraction > 0.0 {
        let (w, h) = frame.size();
        clean_mask(&mut mask, w, h, options.cleanup_fraction);
    }
    mask
}

/// Tight boxes, areas and camera-frame poses of the instances in a mask.
pub fn instances_of(
    mask: &[u16],
    width: u32,
    height: u32,
    boxes: &BoxSet,
    world_to_camera: &IsometryMatrix3<f64>,
) -> Vec<InstanceLabel> {
    let mut found: std::collections::BTreeMap<u16, (PixelRect, u64)> = std::collections::BTreeMap::new();
    for y in 0..height {
        let row = &mask[y as usize * width as usize..(y as usize + 1) * width as usize];
        for (x, &id) in row.iter().enumerate() {
            if id == 0 {
                continue;
            }
            let x = x as u32;
            let e = found.entry(id).or_insert((
                PixelRect {
                    x0: x,
                    y0: y,
                    x1: x + 1,
                    y1: y + 1,
                },
                0,
            ));
            e.0 = e.0.union(&PixelRect {
                x0: x,
                y0: y,
                x1: x + 1,
                y1: y + 1,
            });
            e.1 += 1;
        }
    }
    found
        .into_iter()
        .filter_map(|(id, (bbox, area))| {
            let b = boxes.by_instance(id as u32)?;
            Some(InstanceLabel {
                instance_id: id as u32,
                bbox,
                area,
                object_to_camera: world_to_camera * b.object_to_world(),
            })
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::boxes::classify::Overlap;
    use crate::boxes::parse::Box3;
    use crate::scan::{DepthMap, Intrinsics};
    use nalgebra::Rotation3;

    /// A camera of focal length `f` pixels looking through the middle of a w x h image.
    fn centred_camera(f: f64, w: u32, h: u32) -> Intrinsics {
        Intrinsics {
            fx: f,
            fy: f,
            cx: (w as f64 - 1.0) / 2.0,
            cy: (h as f64 - 1.0) / 2.0,
        }
    }

    /// Found on a real YCB-Video scan: sensor depth of a table 0.6 m away,
    /// 1 mm noisy on pixels 0.6 mm apart, gave one-pixel normals at random,
    /// so the table beside an object counted as the object's steep side.
    /// Over neighbours a noise band (3 sigma) apart the table is flat.
    #[test]
    fn a_noisy_table_is_flat_over_its_noise_band() {
        let (w, h) = (120u32, 90u32);
        let k = centred_camera(1000.0, w, h);
        // The camera looks straight down at the table: depth 0.6 m + noise.
        let mut rng = crate::rng::Rng::new(11, 0);
        let z: Vec<f64> = (0..w * h).map(|_| 0.6 + 0.001 * rng.normal()).collect();
        let point_at = |x: u32, y: u32, z: f64| Point3::from(k.unproject(x as f64, y as f64) * z);
        let up = Vector3::z();
        let steep_share = |span: f64| {
            let mut steep = 0;
            for y in 20..70 {
                for x in 20..100 {
                    let n = surface_normal(&z, w, h, x, y, span, &point_at).unwrap();
                    steep += (n.dot(&up).abs() < STEEP_COSINE) as usize;
                }
            }
            steep as f64 / (50.0 * 80.0)
        };
        let (one_pixel, over_band) = (steep_share(0.0), steep_share(0.003));
        assert!(
            one_pixel > 0.3,
            "one-pixel normals of this table are random: {one_pixel}"
        );
        assert!(over_band < 0.02, "steep share over the band: {over_band}");
    }

    /// Sensor source on a hand-made frame: a wall 2 m ahead, a 0.5 m cube
    /// centred on it and a second box out of view.
    #[test]
    fn sensor_labels_of_a_wall_through_a_box() {
        let (w, h) = (64u32, 48u32);
        let k = centred_camera(40.0, w, h);
        let depth = DepthMap {
            width: w,
            height: h,
            metres: vec![2.0; (w * h) as usize],
        };
        let frame = Frame::new(
            7,
            "000007",
            image::RgbImage::new(w, h),
            Some(depth),
            nalgebra::IsometryMatrix3::identity(),
            k,
        );
        let cube = Box3 {
            label: "cube".into(),
            instance_id: 1,
            center: Point3::new(0.0, 0.0, 2.0),
            size: Vector3::repeat(0.5),
            rotation: Rotation3::identity(),
        };
        let away = Box3 {
            label: "away".into(),
            instance_id: 2,
            center: Point3::new(0.0, 0.0, -3.0),
            ..cube.clone()
        };
        let boxes = BoxSet::from_boxes(vec![cube, away]);
        let opts = LabelOptions {
            source: DepthSource::Sensor,
            ..LabelOptions::default()
        };
        let label = Labeler::new(&boxes, None, opts).unwrap().label_frame(&frame);
        // Wall points (x, y, 2) fall in the cube when |x|, |y| <= 0.25: |u - cx| <= 40 * 0.25 / 2 = 5.
        let inside = |u: u32, v: u32| (u as f64 - k.cx).abs() <= 5.0 && (v as f64 - k.cy).abs() <= 5.0;
        for v in 0..h {
            for u in 0..w {
                assert_eq!(
                    label.mask[(v * w + u) as usize],
                    inside(u, v) as u16,
                    "pixel ({u}, {v})"
                );
            }
        }
        assert_eq!(label.in_view, vec![1]);
        assert_eq!(label.instances.len(), 1);
        let inst = &label.instances[0];
        assert_eq!((inst.instance_id, inst.area), (1, 100));
        assert_eq!(
            inst.bbox,
            PixelRect {
                x0: 27,
                y0: 19,
                x1: 37,
                y1: 29
            }
        );
        assert_eq!(inst.object_to_camera.translation.vector, Vector3::new(0.0, 0.0, 2.0));
        // Rays through the cube: its front face spans |u - cx| <= 40 * 0.25 / 1.75.
        assert!(
            label.box_pixels > 100 && label.box_pixels < 14 * 14,
            "{}",
            label.box_pixels
        );
        assert_eq!(label.rendered_rays, 0);
        assert!(label.depth_m.is_none());
    }

    /// A face standing on a floor, its box dipping 1 cm into the floor, the
    /// floor excluded with a 1 cm band: the floor inside the box is not
    /// labelled, the face's foot within the band is (it is steep to the floor).
    #[test]
    fn an_objects_foot_in_the_support_band_is_kept_and_the_support_is_not() {
        let (w, h) = (200u32, 200u32);
        let k = centred_camera(400.0, w, h);
        // Camera at the origin looking along +z, y down: a face at z = 2 for
        // |x| <= 0.25 down to the floor at y = 0.3.
        let surface = |u: u32, v: u32| -> (f64, bool) {
            let (dx, dy) = ((u as f64 - k.cx) / k.fx, (v as f64 - k.cy) / k.fy);
            let on_face = (2.0 * dx).abs() <= 0.25 && 2.0 * dy < 0.3;
            if on_face || dy <= 0.0 {
                (if on_face { 2.0 } else { 0.0 }, on_face)
            } else {
                (0.3 / dy, false)
            }
        };
        let metres = (0..h)
            .flat_map(|v| (0..w).map(move |u| (u, v)))
            .map(|(u, v)| surface(u, v).0 as f32)
            .collect();
        let depth = DepthMap {
            width: w,
            height: h,
            metres,
        };
        let frame = Frame::new(
            0,
            "000000",
            image::RgbImage::new(w, h),
            Some(depth),
            nalgebra::IsometryMatrix3::identity(),
            k,
        );
        let b = Box3 {
            label: "face".into(),
            instance_id: 1,
            center: Point3::new(0.0, 0.055, 2.0),
            size: Vector3::new(0.52, 0.51, 0.2),
            rotation: Rotation3::identity(),
        };
        let boxes = BoxSet::from_boxes(vec![b.clone()]);
        let opts = LabelOptions {
            source: DepthSource::Sensor,
            ..LabelOptions::default()
        };
        let mut labeler = Labeler::new(&boxes, None, opts).unwrap();
        labeler.excluded = vec![vec![ExcludedPlane {
            normal: Vector3::new(0.0, -1.0, 0.0),
            offset: 0.3,
            band: 0.01,
        }]];
        let label = labeler.label_frame(&frame);
        let (mut foot, mut floor_in_box) = (0, 0);
        for v in 0..h {
            for u in 0..w {
                let (z, on_face) = surface(u, v);
                let p = Point3::new((u as f64 - k.cx) / k.fx * z, (v as f64 - k.cy) / k.fy * z, z);
                let labelled = label.mask[(v * w + u) as usize] == 1;
                if on_face && p.y > 0.29 && u > 2 && u < w - 3 {
                    foot += 1;
                    assert!(
                        labelled,
                        "the face's foot at ({u}, {v}), {:.3} m above the floor, is kept",
                        0.3 - p.y
                    );
                }
                if !on_face && z > 0.0 && b.contains(&p) {
                    floor_in_box += 1;
                    assert!(!labelled, "floor point ({u}, {v}) inside the box is excluded");
                }
            }
        }
        assert!(
            foot >= 100 && floor_in_box >= 100,
            "{foot} foot and {floor_in_box} floor pixels tested"
        );
    }

    /// A 64 x 48 frame at the identity pose whose depth in pixel column u is
    /// `metres(u)`, and two boxes spanning depths `z0..z1`: box 1 with x in
    /// [-0.5, 0.05], box 2 (larger) with x in [-0.05, 0.55].
    fn two_boxes_side_by_side(metres: impl Fn(u32) -> f32, (z0, z1): (f64, f64)) -> (Frame, BoxSet) {
        let (w, h) = (64u32, 48u32);
        let k = centred_camera(40.0, w, h);
        let depth = DepthMap {
            width: w,
            height: h,
            metres: (0..w * h).map(|i| metres(i % w)).collect(),
        };
        let frame = Frame::new(
            0,
            "000000",
            image::RgbImage::new(w, h),
            Some(depth),
            nalgebra::IsometryMatrix3::identity(),
            k,
        );
        let left = Box3 {
            label: "a".into(),
            instance_id: 1,
            center: Point3::new(-0.225, 0.0, 0.5 * (z0 + z1)),
            size: Vector3::new(0.55, 0.5, z1 - z0),
            rotation: Rotation3::identity(),
        };
        let right = Box3 {
            label: "b".into(),
            instance_id: 2,
            center: Point3::new(0.25, 0.0, 0.5 * (z0 + z1)),
            size: Vector3::new(0.6, 0.5, z1 - z0),
            ..left.clone()
        };
        (frame, BoxSet::from_boxes(vec![left, right]))
    }

    #[test]
    fn a_neighbours_face_in_a_boxs_margin_goes_to_the_neighbour_behind_a_depth_step() {
        // Object a (left half of the image) at 1.9 m, object b behind it at
        // 2.4 m; both boxes hold both depths.
        let (frame, boxes) = two_boxes_side_by_side(|u| if (u as f64) < 31.5 { 1.9 } else { 2.4 }, (1.7, 2.6));
        let ids = |exact_boxes: bool| {
            let opts = LabelOptions {
                source: DepthSource::Sensor,
                exact_boxes,
                ..LabelOptions::default()
            };
            let label = Labeler::new(&boxes, None, opts).unwrap().label_frame(&frame);
            let row = 24 * 64;
            // Columns 31 (a's face, x = -0.02) and 32 (b's face, x = 0.03):
            // both points lie in both boxes.
            [label.mask[row + 31], label.mask[row + 32]]
        };
        // b's face lies in a's margin, behind the step where a ends: b's.
        assert_eq!(ids(false), [1, 2]);
        // Boxes taken exactly as drawn: the smallest box takes both.
        assert_eq!(ids(true), [1, 1]);
    }

    /// Two boxes side by side on the wall, overlapping by 10 cm: the
    /// smallest rule taken exactly gives the overlap to the smaller box; by
    /// default each box's surface reaches the overlap without a depth step,
    /// so it splits where the two are equally far, as the deepest rule
    /// splits it where the boxes' faces are.
    #[test]
    fn overlapping_boxes_follow_the_overlap_rule() {
        let (frame, boxes) = two_boxes_side_by_side(|_| 2.0, (1.75, 2.25));
        let (w, h, k) = (64usize, 48usize, frame.intrinsics);
        let id_at = |overlap: Overlap, exact_boxes: bool, x: f64| {
            let opts = LabelOptions {
                source: DepthSource::Sensor,
                overlap,
                exact_boxes,
                ..LabelOptions::default()
            };
            let label = Labeler::new(&boxes, None, opts).unwrap().label_frame(&frame);
            // Wall point x at 2 m: u = cx + fx * x / 2.
            let u = (k.cx + k.fx * x / 2.0).round() as usize;
            label.mask[(h / 2) * w + u]
        };
        // The overlap's right part (x = 0.04): the smaller box 1 taken
        // exactly, else box 2, whose own surface and faces are nearer.
        assert_eq!(id_at(Overlap::Smallest, true, 0.04), 1);
        assert_eq!(id_at(Overlap::Smallest, false, 0.04), 2);
        assert_eq!(id_at(Overlap::Deepest, false, 0.04), 2);
        // Its left part (x = -0.04): box 1 by every rule, as outside the overlap.
        for (overlap, exact) in [
            (Overlap::Smallest, true),
            (Overlap::Smallest, false),
            (Overlap::Deepest, false),
        ] {
            assert_eq!(id_at(overlap, exact, -0.04), 1);
        }
        assert_eq!(
            (
                id_at(Overlap::Smallest, false, -0.3),
                id_at(Overlap::Deepest, false, 0.3)
            ),
            (1, 2)
        );
    }
}
