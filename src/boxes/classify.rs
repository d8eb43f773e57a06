//! Point-in-box classification and ray/box intervals with the world-to-box
//! transforms precomputed. A point inside several boxes belongs to the
//! smallest (FORMATS.md section 2; ties: the lower instance id), or, with
//! [`Overlap::Deepest`], to the box it lies deepest inside.

use super::parse::BoxSet;
use crate::poses::DAabb;
use nalgebra::{Point3, Rotation3, Vector3};

/// One box prepared for fast tests.
#[derive(Clone, Copy, Debug)]
struct Prepared {
    /// World-to-box rotation (transpose of box-to-world).
    world_to_box: Rotation3<f64>,
    center: Point3<f64>,
    half: Vector3<f64>,
    /// World-axis bounds of the box, for a cheap first rejection.
    lo: Point3<f64>,
    hi: Point3<f64>,
    instance_id: u32,
}

impl Prepared {
    #[inline]
    fn contains(&self, p: &Point3<f64>) -> bool {
        self.depth_of(p).is_some()
    }

    /// Distance from `p` to the nearest face when `p` is inside (0 on a face).
    #[inline]
    fn depth_of(&self, p: &Point3<f64>) -> Option<f64> {
        if (0..3).any(|a| p[a] < self.lo[a] || p[a] > self.hi[a]) {
            return None;
        }
        let room = self.half - (self.world_to_box * (p - self.center)).abs();
        let depth = room.min();
        (depth >= 0.0).then_some(depth)
    }

    /// Parameter interval [t0, t1] of `origin + t * dir` inside the box (t unbounded).
    #[inline]
    fn ray(&self, origin: &Point3<f64>, dir: &Vector3<f64>) -> Option<(f64, f64)> {
        let o = Point3::from(self.world_to_box * (origin - self.center));
        let d = self.world_to_box * dir;
        DAabb::new(Point3::from(-self.half), Point3::from(self.half))
            .line_crossing(&o, &d)
            .map(|c| (c.t_near, c.t_far))
    }
}

/// Which box a point inside several boxes belongs to.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, clap::ValueEnum)]
pub enum Overlap {
    /// The smallest box (FORMATS.md section 2): a small box drawn inside a
    /// large one (a lid on a crate) keeps its part.
    #[default]
    Smallest,
    /// The box whose faces are farthest from the point: where boxes of
    /// neighbouring objects overlap by their margins, each object's faces
    /// stay with its own box.
    Deepest,
}

impl Overlap {
    /// The command-line spelling.
    pub fn name(self) -> &'static str {
        match self {
            Overlap::Smallest => "smallest",
            Overlap::Deepest => "deepest",
        }
    }
}

/// Classifies world points into the boxes of a [`BoxSet`].
#[derive(Clone, Debug)]
pub struct BoxClassifier {
    /// Sorted by volume, then instance id: with [`Overlap::Smallest`] the
    /// first hit is the answer, and it breaks [`Overlap::Deepest`]'s ties.
    boxes: Vec<Prepared>,
    overlap: Overlap,
}

impl BoxClassifier {
    /// Prepare every box of `set`; a point in several boxes goes to the smallest.
    pub fn new(set: &BoxSet) -> Self {
        Self::with_overlap(set, Overlap::Smallest)
    }

    /// Prepare every box of `set` with the given overlap rule.
    pub fn with_overlap(set: &BoxSet, overlap: Overlap) -> Self {
        let mut order: Vec<&super::parse::Box3> = set.boxes.iter().collect();
        order.sort_by(|a, b| {
            a.volume()
                .total_cmp(&b.volume())
                .then(a.instance_id.cmp(&b.instance_id))
        });
        let boxes = order
            .into_iter()
            .map(|b| {
                let half = b.size * 0.5;
                let r = b.rotation;
                let extent = b.world_half_extent();
                // A hair of slack so the coarse test never rejects a face point.
                let slack = Vector3::repeat(1e-12 * (1.0 + b.center.coords.abs().max() + extent.max()));
                Prepared {
                    world_to_box: r.transpose(),
                    center: b.center,
                    half,
                    lo: b.center - extent - slack,
                    hi: b.center + extent + slack,
                    instance_id: b.instance_id,
                }
            })
            .collect();
        BoxClassifier { boxes, overlap }
    }

    /// Number of boxes.
    pub fn len(&self) -> usize {
        self.boxes.len()
    }

    /// Whether there are no boxes.
    pub fn is_empty(&self) -> bool {
        self.boxes.is_empty()
    }

    /// Instance id of the box holding `p` (by the overlap rule), 0 = none.
    #[inline]
    pub fn classify(&self, p: &Point3<f64>) -> u32 {
        match self.overlap {
            Overlap::Smallest => self.boxes.iter().find(|b| b.contains(p)).map_or(0, |b| b.instance_id),
            Overlap::Deepest => {
                let mut best: Option<(f64, u32)> = None;
                for b in &self.boxes {
                    if let Some(depth) = b.depth_of(p) {
                        if best.is_none_or(|(d, _)| depth > d) {
                            best = Some((depth, b.instance_id));
                        }
                    }
                }
                best.map_or(0, |(_, id)| id)
            }
        }
    }

    /// Instance ids of every box holding `p`, smallest box first.
    pub fn containing(&self, p: Point3<f64>) -> impl Iterator<Item = u32> + '_ {
        self.boxes.iter().filter(move |b| b.contains(&p)).map(|b| b.instance_id)
    }

    /// Instance id for the surface point at `t` along the unit ray: the
    /// box holding it, else the smallest box the ray enters within
    /// `tolerance` behind it (a surface resolved only to about that much,
    /// met just in front of a box, belongs to what is in the box); 0 = none.
    pub fn classify_on_ray(&self, origin: &Point3<f64>, dir: &Vector3<f64>, t: f64, tolerance: f64) -> u32 {
        let id = self.classify(&(origin + dir * t));
        if id != 0 || tolerance.is_nan() || tolerance <= 0.0 {
            return id;
        }
        self.boxes
            .iter()
            .find(|b| b.ray(origin, dir).is_some_and(|(t0, _)| t0 > t && t0 <= t + tolerance))
            .map_or(0, |b| b.instance_id)
    }

    /// Hull [t0, t1] (t0 >= 0) of the intervals of `origin + t * dir` through
    /// all boxes; `None` when the ray meets no box in front of the origin.
    pub fn ray_interval(&self, origin: &Point3<f64>, dir: &Vector3<f64>) -> Option<(f64, f64)> {
        let mut hull: Option<(f64, f64)> = None;
        for b in &self.boxes {
            if let Some((t0, t1)) = b.ray(origin, dir) {
                if t1 < 0.0 {
                    continue;
                }
                let t0 = t0.max(0.0);
                hull = Some(match hull {
                    None => (t0, t1),
                    Some((a, c)) => (a.min(t0), c.max(t1)),
                });
            }
        }
        hull
    }
}

#[cfg(test)]
mod tests {
    use super::super::parse::Box3;
    use super::*;
    use crate::rng::Rng;
    use nalgebra::{Quaternion, UnitQuaternion};

    fn random_rotation(rng: &mut Rng) -> Rotation3<f64> {
        let (x, y, z, w) = (rng.normal(), rng.normal(), rng.normal(), rng.normal());
        UnitQuaternion::from_quaternion(Quaternion::new(w, x, y, z)).to_rotation_matrix()
    }

    /// Random oriented boxes with nested and overlapping pairs.
    pub(crate) fn random_set(rng: &mut Rng, n: usize) -> BoxSet {
        let mut boxes: Vec<Box3> = Vec::new();
        for i in 0..n {
            let id = i as u32 + 1;
            let b = if i % 3 == 2 {
                // Nested in (or overlapping) the previous box: same centre region, smaller.
                let prev = &boxes[i - 1];
                Box3 {
                    label: format!("n{i}"),
                    instance_id: id,
                    center: prev.center
                        + Vector3::new(rng.range(-0.1, 0.1), rng.range(-0.1, 0.1), rng.range(-0.1, 0.1)),
                    size: prev.size * rng.range(0.3, 0.9),
                    rotation: random_rotation(rng),
                }
            } else {
                Box3 {
                    label: format!("b{}", i % 4),
                    instance_id: id,
                    center: Point3::new(rng.range(-1.0, 1.0), rng.range(-1.0, 1.0), rng.range(-1.0, 1.0)),
                    size: Vector3::new(rng.range(0.1, 1.0), rng.range(0.1, 1.0), rng.range(0.1, 1.0)),
                    rotation: random_rotation(rng),
                }
            };
            boxes.push(b);
        }
        // An exact duplicate of box 1: equal volume, the lower id must win.
        let mut dup = boxes[0].clone();
        dup.instance_id = n as u32 + 1;
        boxes.push(dup);
        BoxSet::from_boxes(boxes)
    }

    /// The definition: among boxes containing p, the smallest, then lowest id.
    fn brute_force(set: &BoxSet, p: &Point3<f64>) -> u32 {
        set.boxes
            .iter()
            .filter(|b| b.contains(p))
            .min_by(|a, b| {
                a.volume()
                    .total_cmp(&b.volume())
                    .then(a.instance_id.cmp(&b.instance_id))
            })
            .map_or(0, |b| b.instance_id)
    }

    #[test]
    fn classification_matches_brute_force_on_random_boxes() {
        let mut rng = Rng::new(11, 0);
        let mut inside_several = 0;
        let mut hits = 0;
        for round in 0..20 {
            let set = random_set(&mut rng, 9 + round % 4);
            let classifier = BoxClassifier::new(&set);
            assert_eq!(classifier.len(), set.boxes.len());
            for _ in 0..5000 {
                let p = &Point3::new(rng.range(-1.3, 1.3), rng.range(-1.3, 1.3), rng.range(-1.3, 1.3));
                let want = brute_force(&set, p);
                assert_eq!(classifier.classify(p), want, "round {round} point {p}");
                hits += (want != 0) as usize;
                inside_several += (set.boxes.iter().filter(|b| b.contains(p)).count() > 1) as usize;
            }
            // Points near every box's centre exercise the nested cases densely.
            for b in &set.boxes {
                for _ in 0..200 {
                    let at = Vector3::new(rng.range(-0.6, 0.6), rng.range(-0.6, 0.6), rng.range(-0.6, 0.6));
                    let p = b.center + b.rotation * b.size.component_mul(&at);
                    assert_eq!(classifier.classify(&p), brute_force(&set, &p));
                }
            }
        }
        assert!(hits > 5_000, "test points must hit boxes often: {hits}");
        assert!(inside_several > 500, "overlaps must be exercised: {inside_several}");
    }

    /// The deepest rule: among boxes containing p, the one whose nearest face
    /// is farthest, then the smallest, then the lowest id.
    fn brute_force_deepest(set: &BoxSet, p: &Point3<f64>) -> u32 {
        let depth = |b: &Box3| (b.size * 0.5 - b.to_local(p).abs()).min();
        set.boxes
            .iter()
            .filter(|b| b.contains(p))
            .min_by(|a, b| {
                depth(b)
                    .total_cmp(&depth(a))
                    .then(a.volume().total_cmp(&b.volume()))
                    .then(a.instance_id.cmp(&b.instance_id))
            })
            .map_or(0, |b| b.instance_id)
    }

    #[test]
    fn deepest_rule_matches_brute_force_on_random_boxes() {
        let mut rng = Rng::new(12, 0);
        let mut differs = 0;
        for round in 0..10 {
            let set = random_set(&mut rng, 9 + round % 4);
            let deepest = BoxClassifier::with_overlap(&set, Overlap::Deepest);
            for _ in 0..5000 {
                let p = &Point3::new(rng.range(-1.3, 1.3), rng.range(-1.3, 1.3), rng.range(-1.3, 1.3));
                let want = brute_force_deepest(&set, p);
                assert_eq!(deepest.classify(p), want, "round {round} point {p}");
                differs += (want != brute_force(&set, p)) as usize;
            }
        }
        assert!(differs > 100, "the two rules must disagree somewhere: {differs}");
    }

    /// Two objects 2 mm apart, boxes drawn 1 cm beyond each: the boxes
    /// overlap by 1.8 cm. The smallest rule gives the big object's near face
    /// to the small box; the deepest rule keeps each face with its own box.
    #[test]
    fn neighbouring_boxes_keep_their_own_faces_with_the_deepest_rule() {
        let box_around = |id: u32, lo: f64, hi: f64| Box3 {
            label: format!("o{id}"),
            instance_id: id,
            center: Point3::new(0.5 * (lo + hi), 0.0, 0.0),
            size: Vector3::new(hi - lo + 0.02, 0.2, 0.2),
            rotation: Rotation3::identity(),
        };
        // Small object x in [0, 0.1], big one x in [0.102, 0.302].
        let set = BoxSet::from_boxes(vec![box_around(1, 0.0, 0.1), box_around(2, 0.102, 0.302)]);
        let small_face = &Point3::new(0.1, 0.0, 0.0);
        let big_face = &Point3::new(0.102, 0.0, 0.0);
        let smallest = BoxClassifier::new(&set);
        assert_eq!((smallest.classify(small_face), smallest.classify(big_face)), (1, 1));
        let deepest = BoxClassifier::with_overlap(&set, Overlap::Deepest);
        assert_eq!((deepest.classify(small_face), deepest.classify(big_face)), (1, 2));
        // Outside both, and deep inside each: the rules agree.
        for (p, id) in [
            (Point3::new(-0.02, 0.0, 0.0), 0),
            (Point3::new(0.05, 0.0, 0.0), 1),
            (Point3::new(0.2, 0.0, 0.0), 2),
        ] {
            assert_eq!((smallest.classify(&p), deepest.classify(&p)), (id, id), "{p}");
        }
        use clap::ValueEnum;
        assert_eq!(Overlap::from_str("deepest", false), Ok(Overlap::Deepest));
        assert_eq!(
            Overlap::from_str(Overlap::Smallest.name(), false),
            Ok(Overlap::Smallest)
        );
        assert!(Overlap::from_str("largest", false).is_err());
    }

    #[test]
    fn surface_points_just_in_front_of_a_box_go_to_the_box_the_ray_enters() {
        let mut rng = Rng::new(17, 0);
        let (mut inside, mut in_front, mut outside) = (0, 0, 0);
        for _ in 0..20 {
            let set = random_set(&mut rng, 6);
            let c = BoxClassifier::new(&set);
            for _ in 0..300 {
                let origin = Point3::new(rng.range(-3.0, 3.0), rng.range(-3.0, 3.0), rng.range(-3.0, 3.0));
                let dir = (Point3::new(rng.range(-1.0, 1.0), rng.range(-1.0, 1.0), rng.range(-1.0, 1.0)) - origin)
                    .normalize();
                let (t, tolerance) = (rng.range(0.0, 5.0), rng.range(0.0, 0.5));
                // Reference by sampling: the point's own box, else the smallest
                // box holding a sample within the tolerance behind it.
                let step = 1e-4;
                let entries: Vec<f64> = set
                    .boxes
                    .iter()
                    .filter_map(|b| {
                        c.boxes
                            .iter()
                            .find(|p| p.instance_id == b.instance_id)?
                            .ray(&origin, &dir)
                    })
                    .map(|(t0, _)| t0)
                    .collect();
                if entries
                    .iter()
                    .any(|&t0| (t0 - t).abs() < 2.0 * step || (t0 - t - tolerance).abs() < 2.0 * step)
                {
                    continue;
                }
                let own = brute_force(&set, &(origin + dir * t));
                let want = if own != 0 {
                    inside += 1;
                    own
                } else {
                    let ahead: Vec<&Box3> = set
                        .boxes
                        .iter()
                        .filter(|b| {
                            (1..=(tolerance / step) as usize)
                                .any(|k| b.contains(&(origin + dir * (t + k as f64 * step))))
                        })
                        .collect();
                    let best = ahead.iter().min_by(|a, b| {
                        a.volume()
                            .total_cmp(&b.volume())
                            .then(a.instance_id.cmp(&b.instance_id))
                    });
                    best.map_or_else(
                        || {
                            outside += 1;
                            0
                        },
                        |b| {
                            in_front += 1;
                            b.instance_id
                        },
                    )
                };
                assert_eq!(
                    c.classify_on_ray(&origin, &dir, t, tolerance),
                    want,
                    "t {t} tolerance {tolerance}"
                );
                assert_eq!(c.classify_on_ray(&origin, &dir, t, 0.0), own);
            }
        }
        assert!(
            inside > 100 && in_front > 100 && outside > 100,
            "{inside} inside, {in_front} in front, {outside} outside"
        );
    }

    #[test]
    fn duplicate_box_goes_to_the_lower_instance_id() {
        let mut rng = Rng::new(3, 0);
        let set = random_set(&mut rng, 4);
        let dup = set.boxes.last().unwrap();
        let c = BoxClassifier::new(&set);
        // The duplicate's centre lies in box 1 and the duplicate (and maybe smaller ones).
        let id = c.classify(&dup.center);
        assert_ne!(id, dup.instance_id);
        assert_eq!(id, brute_force(&set, &dup.center));
    }

    #[test]
    fn ray_interval_is_the_hull_of_the_contained_samples() {
        let mut rng = Rng::new(5, 0);
        let mut met = 0;
        for _ in 0..20 {
            let set = random_set(&mut rng, 6);
            let c = BoxClassifier::new(&set);
            for _ in 0..200 {
                let origin = Point3::new(rng.range(-3.0, 3.0), rng.range(-3.0, 3.0), rng.range(-3.0, 3.0));
                let target = Point3::new(rng.range(-1.0, 1.0), rng.range(-1.0, 1.0), rng.range(-1.0, 1.0));
                // Unnormalised direction: t is in units of dir.
                let dir = (target - origin) * rng.range(0.5, 2.0);
                let step = 1e-3;
                let inside: Vec<f64> = (0..6000)
                    .map(|k| k as f64 * step)
                    .filter(|&t| set.boxes.iter().any(|b| b.contains(&(origin + dir * t))))
                    .collect();
                match c.ray_interval(&origin, &dir) {
                    None => assert!(inside.is_empty(), "missed samples at {:?}", inside.first()),
                    // A grazing hit shorter than the sampling step may have no sample inside.
                    Some((t0, t1)) if inside.is_empty() => assert!(t1 - t0 <= step, "[{t0}, {t1}] without samples"),
                    Some((t0, t1)) => {
                        met += 1;
                        assert!(t0 >= 0.0 && t0 <= t1);
                        let (first, last) = (inside[0], inside[inside.len() - 1]);
                        assert!(t0 <= first + 1e-9 && first - t0 <= step + 1e-9, "t0 {t0} first {first}");
                        assert!(t1 >= last - 1e-9 && t1 - last <= step + 1e-9, "t1 {t1} last {last}");
                    }
                }
            }
        }
        assert!(met > 1000, "most rays aim at boxes: {met}");
        // A ray starting inside a box starts its interval at 0; one pointing away misses.
        let set = BoxSet::from_boxes(vec![Box3 {
            label: "a".into(),
            instance_id: 1,
            center: Point3::origin(),
            size: Vector3::repeat(1.0),
            rotation: Rotation3::identity(),
        }]);
        let c = BoxClassifier::new(&set);
        assert_eq!(c.ray_interval(&Point3::origin(), &Vector3::x()), Some((0.0, 0.5)));
        assert_eq!(c.ray_interval(&Point3::new(2.0, 0.0, 0.0), &Vector3::x()), None);
        assert_eq!(c.ray_interval(&Point3::new(2.0, 0.7, 0.0), &-Vector3::x()), None);
        assert_eq!(
            c.ray_interval(&Point3::new(2.0, 0.0, 0.0), &(-Vector3::x() * 2.0)),
            Some((0.75, 1.25))
        );
    }
}
