//! Carry given masks to every frame: lift each labelled pixel to its surface
//! point (the depth source's depth), vote in a [`VoteVolume`], then label
//! each frame's surface points by the votes around them.
//!
//! - Pixels near a label change in a given mask vote with less weight (a
//!   drawn or predicted mask is least certain at its boundary; masks that
//!   bleed 2-3 px onto the background are outvoted there by other frames).
//! - Background pixels vote too, so a surface some frames saw as background
//!   stays background.
//! - Each object gets a box from its lifted points (principal axes, robust
//!   extents): its pose in COCO, and, grown by a margin, the region whose
//!   rays a frame renders.

use super::read::GivenMasks;
use super::votes::VoteVolume;
use crate::boxes::label::{finish_mask, instances_of, surface_normal};
use crate::boxes::output::FrameLabelling;
use crate::boxes::{Box3, BoxClassifier, BoxSet, FrameLabel, LabelError, LabelOptions, Labeler, PixelRect};
use crate::poses::symmetric_eigen;
use crate::scan::{Frame, Scan};
use nalgebra::{Matrix3, Point3, Rotation3, Vector3};
use std::collections::{BTreeMap, BTreeSet, HashMap};

/// Distance (pixels) to a label change from which a given pixel votes with
/// full weight; nearer pixels vote with (d + 1) / (this + 1).
const CERTAIN_FROM_PX: usize = 3;
/// A background pixel's vote weighs this much of an object pixel's: a mask
/// that misses an object in one frame (a segmenter lost it) is outvoted
/// by one other frame that has it, while a mask's bleed, which votes
/// with boundary weight, stays outvoted by the background of others.
const BACKGROUND_WEIGHT: f32 = 0.75;
/// Extents of an object's box: these quantiles of its lifted points along
/// each principal axis (a few stray points do not stretch it).
const EXTENT_QUANTILE: f64 = 0.005;
/// Cells (in finest voxels) of the clusters an object's box is fitted to:
/// gaps of up to about this many voxels join a cluster.
const CLUSTER_VOXELS: f64 = 2.0;
/// Lifted points kept per object to fit its box (evenly strided).
const BOX_POINTS: usize = 200_000;
/// The rendered region around an object's box grows by this share of the
/// box's longest side on every side (surfaces the given frames did not see
/// from the front, which the coarse votes may still claim).
const REGION_MARGIN_SHARE: f64 = 0.1;
/// Pixels of background lifted around a given mask's objects beyond the
/// region margin (silhouettes move by a few pixels between views).
const SURROUNDING_PX: usize = 16;

/// What lifting the given masks produced.
pub struct Lifted {
    pub votes: VoteVolume,
    /// One box per object (instance id = object id, label = its name).
    pub objects: BoxSet,
    /// The objects' boxes grown by a margin: where frames are rendered.
    pub regions: BoxSet,
    /// Surface points lifted (pixels with depth in the given frames).
    pub lifted_points: usize,
    /// Objects that cannot be carried (no given pixel of theirs has depth).
    pub warnings: Vec<String>,
}

impl Lifted {
    /// Object id -> index of its region in `regions` (`lift` builds the
    /// regions in the order of the objects).
    pub fn region_of(&self) -> HashMap<u16, usize> {
        self.objects
            .boxes
            .iter()
            .enumerate()
            .map(|(i, b)| (b.instance_id as u16, i))
            .collect()
    }
}

/// A given frame's lifted pixels (world point, given id, vote weight) and
/// the objects its mask has.
struct LiftedFrame {
    points: Vec<(Point3<f64>, u16, f32)>,
    objects: BTreeSet<u16>,
}

/// Lift the given masks: `labeler` must give every pixel's surface
/// (full depth, no boxes).
pub fn lift(
    scan: &Scan,
    given: &GivenMasks,
    labeler: &Labeler,
    progress: &(dyn Fn(usize) + Sync),
) -> Result<Lifted, LabelError> {
    // Lift every given frame first: a frame that lacks an object needs the
    // object's rough extent from the others before its background votes.
    let mut voxel: Option<f64> = None;
    let mut lifted_frames: Vec<LiftedFrame> = Vec::new();
    let mut object_points: BTreeMap<u16, Vec<Point3<f64>>> = given.objects.keys().map(|&id| (id, Vec::new())).collect();
    let mut lifted_points = 0;
    for (done, (&index, mask)) in given.frames.iter().enumerate() {
        let frame = &scan.frames[index];
        let (w, h) = frame.size();
        let near_objects = object_surroundings(mask, w as usize, h as usize);
        let surface = labeler.surface_where(frame, &|x, y| near_objects.contains(x, y));
        let points: Vec<(u32, u32, f64)> = surface.points().collect();
        voxel.get_or_insert_with(|| voxel_size(&points, frame, labeler));
        let mut weights = boundary_weights(mask, w as usize, h as usize);
        let k = frame.intrinsics;
        let footprint = 1.0 / (0.5 * (k.fx + k.fy)).max(1e-9);
        drop_bleeding(mask, &mut weights, &points, w as usize, h as usize, |z, pixels| {
            labeler.surface_error_m() + STEP_PIXELS * pixels as f64 * z * footprint
        });
        let mut lifted = Vec::with_capacity(points.len());
        for &(x, y, z) in &points {
            let i = y as usize * w as usize + x as usize;
            let p = world_point(frame, x, y, z);
            lifted.push((p, mask[i], weights[i]));
            if mask[i] > 0 && weights[i] >= 1.0 {
                if let Some(list) = object_points.get_mut(&mask[i]) {
                    list.push(p);
                }
            }
        }
        let present: BTreeSet<u16> = mask.iter().copied().filter(|&id| id > 0).collect();
        lifted_frames.push(LiftedFrame {
            points: lifted,
            objects: present,
        });
        lifted_points += points.len();
        progress(done + 1);
    }
    let voxel = voxel.ok_or_else(|| LabelError::Option("no given mask names a frame of the scan".into()))?;
    // A mask that lacks an object (a segmenter lost it) says background
    // where the object is: its background points inside the object's rough
    // box do not vote, so frames that have the object decide there.
    let rough: BTreeMap<u16, Box3> = object_points
        .iter()
        .filter_map(|(&id, points)| {
            Some((
                id,
                principal_box(&largest_cluster(points, CLUSTER_VOXELS * voxel), voxel)?,
            ))
        })
        .collect();
    let mut votes = VoteVolume::new(voxel);
    for frame in &lifted_frames {
        let lost: Vec<&Box3> = rough
            .iter()
            .filter(|(id, _)| !frame.objects.contains(id))
            .map(|(_, b)| b)
            .collect();
        for (p, id, weight) in &frame.points {
            if *id == 0 {
                if !lost.iter().any(|b| b.contains(p)) {
                    votes.add(p, 0, BACKGROUND_WEIGHT * weight);
                }
            } else {
                votes.add(p, *id, *weight);
            }
        }
    }
    let mut objects = Vec::new();
    let mut regions = Vec::new();
    let mut warnings = Vec::new();
    for (&id, points) in &object_points {
        let name = given.objects.get(&id).cloned().unwrap_or_default();
        // A pixel of the object whose depth missed it (a thin or far object,
        // depth through to the wall behind) lifts far away: keep the points
        // the votes confirm, then the largest connected cluster of them.
        let confirmed: Vec<Point3<f64>> = points.iter().copied().filter(|p| votes.classify(p).0 == id).collect();
        let cluster = largest_cluster(&confirmed, CLUSTER_VOXELS * voxel);
        let Some(mut b) = principal_box(&cluster, voxel) else {
            warnings.push(format!(
                "object {id} (`{name}`): no pixel of it in the given masks has a surface depth, so no other frame gets it (the sensor measured none there: fit a model and use the nerf or fused source)"
            ));
            continue;
        };
        b.label = name;
        b.instance_id = id as u32;
        let margin = REGION_MARGIN_SHARE * b.size.max();
        regions.push(Box3 {
            size: b.size + Vector3::repeat(2.0 * margin),
            instance_id: regions.len() as u32 + 1,
            ..b.clone()
        });
        objects.push(b);
    }
    Ok(Lifted {
        votes,
        objects: BoxSet::from_boxes(objects),
        regions: BoxSet::from_boxes(regions),
        lifted_points,
        warnings,
    })
}

/// A mask that bleeds past an object's silhouette labels what lies behind
/// it: a pixel near the background (within [`CERTAIN_FROM_PX`]) whose surface lies
/// behind a pixel of the same label within [`CERTAIN_FROM_PX`] by more than
/// `max_step(z, pixels apart)` (one surface seen obliquely steps by less)
/// votes not at all (weight 0).
fn drop_bleeding(
    mask: &[u16],
    weights: &mut [f32],
    points: &[(u32, u32, f64)],
    w: usize,
    h: usize,
    max_step: impl Fn(f64, usize) -> f64,
) {
    let mut z = vec![0.0f64; mask.len()];
    for &(x, y, d) in points {
        z[y as usize * w + x as usize] = d;
    }
    let r = CERTAIN_FROM_PX;
    for y in 0..h {
        for x in 0..w {
            let i = y * w + x;
            let (id, depth) = (mask[i], z[i]);
            if id == 0 || depth <= 0.0 || weights[i] >= 1.0 {
                continue;
            }
            let mut window = (y.saturating_sub(r)..(y + r + 1).min(h))
                .flat_map(|ny| (x.saturating_sub(r)..(x + r + 1).min(w)).map(move |nx| (nx, ny)));
            // Bleeding runs onto the background; a pixel beside a
            // neighbouring object only (a label change between objects) keeps its vote.
            if !window.clone().any(|(nx, ny)| mask[ny * w + nx] == 0) {
                continue;
            }
            let behind = window.any(|(nx, ny)| {
                let j = ny * w + nx;
                let apart = nx.abs_diff(x).max(ny.abs_diff(y));
                mask[j] == id && z[j] > 0.0 && depth - z[j] > max_step(depth, apart)
            });
            if behind {
                weights[i] = 0.0;
            }
        }
    }
}

/// Largest depth step, in pixel footprints per pixel apart, between pixels
/// of one surface (a surface seen at up to 76 degrees: tan 76 = 4).
const STEP_PIXELS: f64 = 4.0;

/// Points of `points` in the largest 26-connected cluster of occupied
/// cells of side `cell` (by point count).
fn largest_cluster(points: &[Point3<f64>], cell: f64) -> Vec<Point3<f64>> {
    let key = |p: Point3<f64>| {
        let q = (p.coords / cell).map(f64::floor);
        [q.x as i64, q.y as i64, q.z as i64]
    };
    let mut counts: BTreeMap<[i64; 3], usize> = BTreeMap::new();
    for &p in points {
        *counts.entry(key(p)).or_default() += 1;
    }
    let mut component: BTreeMap<[i64; 3], usize> = BTreeMap::new();
    let mut sizes: Vec<usize> = Vec::new();
    for &start in counts.keys() {
        if component.contains_key(&start) {
            continue;
        }
        let id = sizes.len();
        let mut size = 0;
        let mut stack = vec![start];
        component.insert(start, id);
        while let Some(c) = stack.pop() {
            size += counts[&c];
            for dx in -1..=1 {
                for dy in -1..=1 {
                    for dz in -1..=1 {
                        let n = [c[0] + dx, c[1] + dy, c[2] + dz];
                        if counts.contains_key(&n) && !component.contains_key(&n) {
                            component.insert(n, id);
                            stack.push(n);
                        }
                    }
                }
            }
        }
        sizes.push(size);
    }
    let Some(best) = (0..sizes.len()).max_by_key(|&i| (sizes[i], std::cmp::Reverse(i))) else {
        return Vec::new();
    };
    points.iter().copied().filter(|&p| component[&key(p)] == best).collect()
}

/// Pixels around a given mask's objects whose votes can matter: the
/// rectangle of its object pixels grown by [`REGION_MARGIN_SHARE`] of its
/// larger side and [`SURROUNDING_PX`] pixels (background farther away lifts
/// to points outside every object's region).
fn object_surroundings(mask: &[u16], w: usize, h: usize) -> PixelRect {
    let (mut x0, mut y0, mut x1, mut y1) = (w, h, 0, 0);
    for (i, _) in mask.iter().enumerate().filter(|(_, &id)| id > 0) {
        let (x, y) = (i % w, i / w);
        (x0, y0, x1, y1) = (x0.min(x), y0.min(y), x1.max(x + 1), y1.max(y + 1));
    }
    if x1 <= x0 {
        // No object: this frame says where objects are not, anywhere.
        return PixelRect {
            x0: 0,
            y0: 0,
            x1: w as u32,
            y1: h as u32,
        };
    }
    let grow = (REGION_MARGIN_SHARE * (x1 - x0).max(y1 - y0) as f64).ceil() as usize + SURROUNDING_PX;
    PixelRect {
        x0: x0.saturating_sub(grow) as u32,
        y0: y0.saturating_sub(grow) as u32,
        x1: (x1 + grow).min(w) as u32,
        y1: (y1 + grow).min(h) as u32,
    }
}

/// Every object of the masks and, after them, the boxes (box k takes id
/// `first + k - 1` with `first` one above the largest mask id): the set the
/// outputs describe, and `first`.
pub fn objects_and_boxes(lifted: &Lifted, boxes: Option<&BoxSet>) -> Result<(BoxSet, u16), LabelError> {
    let first = lifted.objects.max_instance_id() + 1;
    let mut all: Vec<Box3> = lifted.objects.boxes.clone();
    if let Some(boxes) = boxes {
        let last = first as usize + boxes.boxes.len() - 1;
        if last > u16::MAX as usize {
            return Err(LabelError::Option(format!(
                "{} boxes after mask ids up to {} exceed the 65535 instance ids a mask can hold",
                boxes.boxes.len(),
                first - 1
            )));
        }
        all.extend(boxes.boxes.iter().map(|b| Box3 {
            instance_id: first + b.instance_id - 1,
            ..b.clone()
        }));
    }
    Ok((BoxSet::from_boxes(all), first.min(u16::MAX as u32) as u16))
}

/// The object id of a world point from the votes, inside the objects'
/// regions only (0 elsewhere): what `synth` labels its views with.
pub struct PointLabels<'a> {
    lifted: &'a Lifted,
    regions: BoxClassifier,
}

impl<'a> PointLabels<'a> {
    pub fn new(lifted: &'a Lifted) -> PointLabels<'a> {
        PointLabels {
            regions: BoxClassifier::new(&lifted.regions),
            lifted,
        }
    }

    pub fn classify(&self, point: &Point3<f64>) -> u16 {
        if self.regions.classify(point) == 0 {
            return 0;
        }
        self.lifted.votes.classify(point).0
    }
}

/// Finest voxel: a finest grid cell of the model (how precisely rendered
/// surfaces are placed), at least one pixel footprint at the median depth
/// of the first labelled frame (how densely pixels sample the surface).
fn voxel_size(points: &[(u32, u32, f64)], frame: &Frame, labeler: &Labeler) -> f64 {
    let mut z: Vec<f64> = points.iter().map(|p| p.2).collect();
    let median = if z.is_empty() {
        1.0
    } else {
        let mid = z.len() / 2;
        *z.select_nth_unstable_by(mid, f64::total_cmp).1
    };
    let k = frame.intrinsics;
    let footprint = median / (0.5 * (k.fx + k.fy)).max(1e-9);
    let voxel = footprint.max(labeler.surface_error_m());
    if voxel.is_finite() && voxel > 0.0 {
        voxel
    } else {
        1e-3
    }
}

fn world_point(frame: &Frame, x: u32, y: u32, z: f64) -> Point3<f64> {
    frame.camera_to_world * Point3::from(frame.intrinsics.unproject(x as f64, y as f64) * z)
}

/// Vote weight of each pixel from its distance (4-neighbour steps) to the
/// nearest pixel of another label.
fn boundary_weights(mask: &[u16], w: usize, h: usize) -> Vec<f32> {
    let far = CERTAIN_FROM_PX;
    let mut distance = vec![far; mask.len()];
    let mut frontier = Vec::new();
    for y in 0..h {
        for x in 0..w {
            let i = y * w + x;
            let differs = |j: usize| mask[j] != mask[i];
            let edge = (x > 0 && differs(i - 1))
                || (x + 1 < w && differs(i + 1))
                || (y > 0 && differs(i - w))
                || (y + 1 < h && differs(i + w));
            if edge {
                distance[i] = 0;
                frontier.push(i);
            }
        }
    }
    let mut step = 0;
    while !frontier.is_empty() && step + 1 < far {
        step += 1;
        let mut next = Vec::new();
        for &i in &frontier {
            let (x, y) = (i % w, i / w);
            let neighbours = [
                (x > 0).then(|| i - 1),
                (x + 1 < w).then(|| i + 1),
                (y > 0).then(|| i - w),
                (y + 1 < h).then(|| i + w),
            ];
            for j in neighbours.into_iter().flatten() {
                if distance[j] > step {
                    distance[j] = step;
                    next.push(j);
                }
            }
        }
        frontier = next;
    }
    distance
        .into_iter()
        .map(|d| (d + 1) as f32 / (far + 1) as f32)
        .map(|v| v.min(1.0))
        .collect()
}

/// A box on the points' principal axes spanning their robust extents,
/// grown by `pad` metres; `None` for fewer than 4 points.
fn principal_box(points: &[Point3<f64>], pad: f64) -> Option<Box3> {
    if points.len() < 4 {
        return None;
    }
    let stride = points.len().div_ceil(BOX_POINTS);
    let sample: Vec<Vector3<f64>> = points.iter().step_by(stride).map(|p| p.coords).collect();
    let n = sample.len() as f64;
    let mean = sample.iter().sum::<Vector3<f64>>() / n;
    let mut cov = Matrix3::zeros();
    for p in &sample {
        let d = p - mean;
        cov += d * d.transpose();
    }
    let (_, mut axes) = symmetric_eigen(cov * (1.0 / n));
    if axes.determinant() < 0.0 {
        axes.set_column(2, &-axes.column(2));
    }
    let mut lo = Vector3::zeros();
    let mut hi = Vector3::zeros();
    for a in 0..3 {
        let axis = axes.column(a);
        let mut along: Vec<f64> = sample.iter().map(|p| (p - mean).dot(&axis)).collect();
        along.sort_by(f64::total_cmp);
        let at = |q: f64| along[((q * (along.len() - 1) as f64).round() as usize).min(along.len() - 1)];
        lo[a] = at(EXTENT_QUANTILE);
        hi[a] = at(1.0 - EXTENT_QUANTILE);
    }
    let centre_local = (lo + hi) * 0.5;
    Some(Box3 {
        label: String::new(),
        instance_id: 0,
        center: Point3::from(mean + axes * centre_local),
        size: (hi - lo) + Vector3::repeat(2.0 * pad),
        rotation: Rotation3::from_matrix_unchecked(axes),
    })
}

/// Labels every frame from the votes of the given masks (and optionally
/// boxes, which label what the masks leave as background).
pub struct MaskLabeler<'a> {
    /// Frame id -> its given mask.
    given_by_frame: HashMap<u64, &'a Vec<u16>>,
    votes: &'a VoteVolume,
    /// Renders the surface inside the objects' regions, and holds the
    /// support planes excluded from each region.
    surface: &'a Labeler<'a>,
    /// Object id -> index of its region in the surface labeler's box set.
    region_of: HashMap<u16, usize>,
    /// Boxes' labeler and the id its box 1 takes in the output.
    boxes: Option<(&'a Labeler<'a>, u16)>,
    /// Every object and box, by output instance id.
    all: &'a BoxSet,
    options: LabelOptions,
}

impl<'a> MaskLabeler<'a> {
    pub fn new(
        scan: &'a Scan,
        given: &'a GivenMasks,
        lifted: &'a Lifted,
        surface: &'a Labeler<'a>,
        boxes: Option<(&'a Labeler<'a>, u16)>,
        all: &'a BoxSet,
        options: LabelOptions,
    ) -> MaskLabeler<'a> {
        let given_by_frame = given.frames.iter().map(|(&i, m)| (scan.frames[i].id, m)).collect();
        let region_of = lifted.region_of();
        MaskLabeler {
            given_by_frame,
            votes: &lifted.votes,
            surface,
            region_of,
            boxes,
            all,
            options,
        }
    }
}

impl FrameLabelling for MaskLabeler<'_> {
    fn label_frame(&self, frame: &Frame) -> FrameLabel {
        let (w, h) = frame.size();
        let given = self.given_by_frame.get(&frame.id);
        // A given frame's mask is kept: its surface is needed only for --depth.
        let surface = if given.is_none() || self.options.full_depth {
            self.surface.surface(frame)
        } else {
            self.surface.surface_where(frame, &|_, _| false)
        };
        let mut mask = match given {
            Some(m) => (*m).clone(),
            None => {
                let mut mask = vec![0u16; w as usize * h as usize];
                // For the normals the excluded planes need, when there are any.
                let z_image = if self.surface.excludes_any_plane() {
                    surface.z_image(w, h)
                } else {
                    Vec::new()
                };
                let point_at = |x: u32, y: u32, z: f64| world_point(frame, x, y, z);
                for (x, y, z) in surface.points() {
                    let p = world_point(frame, x, y, z);
                    let (id, _) = self.votes.classify(&p);
                    // A mask that bleeds onto the support an object stands on
                    // lifts to the support plane: the plane is not the object.
                    let on_support = self.region_of.get(&id).is_some_and(|&region| {
                        self.surface
                            .excluded_at(region, &p, |span| surface_normal(&z_image, w, h, x, y, span, &point_at))
                    });
                    mask[y as usize * w as usize + x as usize] = if on_support { 0 } else { id };
                }
                mask
            }
        };
        let depth_m = self.options.full_depth.then(|| {
            let mut d = vec![0.0f32; w as usize * h as usize];
            for (x, y, z) in surface.points() {
                d[y as usize * w as usize + x as usize] = z as f32;
            }
            d
        });
        if let Some((labeler, first_id)) = self.boxes {
            let boxed = labeler.label_frame(frame);
            for (m, &b) in mask.iter_mut().zip(&boxed.mask) {
                if *m == 0 && b > 0 {
                    *m = first_id + (b - 1);
                }
            }
        }
        if given.is_none() {
            mask = finish_mask(mask, frame, &self.options);
        }
        let instances = instances_of(&mask, w, h, self.all, &frame.camera_to_world.inverse());
        let in_view = self
            .all
            .boxes
            .iter()
            .filter(|b| crate::boxes::project_box(b, &frame.camera_to_world, &frame.intrinsics, (w, h)).is_some())
            .map(|b| b.instance_id)
            .collect();
        FrameLabel {
            frame_id: frame.id,
            name: frame.name.clone(),
            width: w,
            height: h,
            mask,
            depth_m,
            instances,
            in_view,
            box_pixels: surface.box_pixels,
            rendered_rays: surface.rendered_rays,
        }
    }

    fn options(&self) -> &LabelOptions {
        &self.options
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn pixels_near_a_label_change_vote_with_less_weight() {
        let (w, h) = (10, 1);
        let mask: Vec<u16> = (0..w).map(|x| if x < 5 { 0 } else { 2 }).collect();
        let weights = boundary_weights(&mask, w, h);
        assert_eq!(weights[4], 0.25);
        assert_eq!(weights[5], 0.25);
        assert_eq!(weights[3], 0.5);
        assert_eq!(weights[6], 0.5);
        assert_eq!(weights[2], 0.75);
        assert_eq!(weights[0], 1.0);
        assert_eq!(weights[9], 1.0);
    }

    #[test]
    fn mask_pixels_behind_their_object_vote_not_at_all() {
        // Object 1 at 1 m in x < 6, its mask bleeding two pixels onto a wall at 2 m.
        let (w, h) = (10, 1);
        let mask: Vec<u16> = (0..w).map(|x| if x < 8 { 1 } else { 0 }).collect();
        let points: Vec<(u32, u32, f64)> = (0..w as u32).map(|x| (x, 0, if x < 6 { 1.0 } else { 2.0 })).collect();
        let mut weights = boundary_weights(&mask, w, h);
        drop_bleeding(&mask, &mut weights, &points, w, h, |z, apart| {
            0.01 + 4.0 * apart as f64 * z / 500.0
        });
        assert_eq!(&weights[6..8], &[0.0, 0.0], "the bleed onto the wall");
        assert!(
            weights[5] > 0.0 && weights[8] > 0.0,
            "the object's edge and the wall's own label vote"
        );
    }

    #[test]
    fn the_largest_cluster_drops_points_lifted_far_behind_the_object() {
        let mut points: Vec<Point3<f64>> = (0..200)
            .map(|i| Point3::new(0.001 * (i % 20) as f64, 0.001 * (i / 20) as f64, 1.0))
            .collect();
        // A few pixels whose depth went through to a wall 2 m behind.
        points.extend((0..30).map(|i| Point3::new(0.001 * i as f64, 0.0, 3.0)));
        let kept = largest_cluster(&points, 0.01);
        assert_eq!(kept.len(), 200);
        assert!(kept.iter().all(|p| p.z == 1.0));
    }

    #[test]
    fn a_principal_box_spans_a_rotated_slab_of_points() {
        // Points of a 0.4 x 0.2 x 0.1 slab rotated 30 degrees about z.
        let rot = Rotation3::from_axis_angle(&Vector3::z_axis(), 30f64.to_radians());
        let mut points = Vec::new();
        for i in 0..=40 {
            for j in 0..=20 {
                for k in 0..=10 {
                    let local = Vector3::new(i as f64 * 0.01 - 0.2, j as f64 * 0.01 - 0.1, k as f64 * 0.01 - 0.05);
                    points.push(Point3::new(1.0, 2.0, 3.0) + rot * local);
                }
            }
        }
        let b = principal_box(&points, 0.0).unwrap();
        assert!((b.center - Point3::new(1.0, 2.0, 3.0)).norm() < 1e-9);
        let mut size: [f64; 3] = b.size.into();
        size.sort_by(f64::total_cmp);
        assert!(
            (size[0] - 0.1).abs() < 0.002 && (size[1] - 0.2).abs() < 0.003 && (size[2] - 0.4).abs() < 0.005,
            "{size:?}"
        );
        assert!(b.rotation.matrix().determinant() > 0.999);
        // The longest axis is the rotated x axis (up to sign).
        assert!(b.rotation.matrix().column(0).dot(&rot.matrix().column(0)).abs() > 0.999);
    }
}
