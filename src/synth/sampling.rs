//! Viewpoint candidates as in NeRFing it (section III-D): a position drawn
//! uniformly in the bounding box of the scan's camera positions expressed in
//! a randomly chosen object's frame, kept only if it clears the scanned
//! point cloud, looking at that object's centre and then turned by a random
//! rotation: uniform in [-pi/4, pi/4] about the camera's x and y axes and in
//! [-pi, pi] about its optical axis.
//!
//! Candidate `i` of seed `s` depends only on `(s, i)` (its own RNG stream),
//! so candidates can be generated in parallel and the accepted sequence does
//! not depend on how the work is split.

use super::error::SynthError;
use crate::rng::Rng;
use kiddo::{ImmutableKdTree, SquaredEuclidean};
use nalgebra::{IsometryMatrix3, Point3, Rotation3, Translation3, Vector3};
use std::f64::consts::{FRAC_PI_4, PI};

/// Largest tilt of the optical axis about the camera's x and y axes.
pub const MAX_TILT: f64 = FRAC_PI_4;
/// Default clearance as a fraction of the scan's typical clearance: the
/// median distance from a scan camera to its nearest scanned point.
pub const CLEARANCE_FRACTION: f64 = 0.2;

/// Something to look at: a centre and the frame whose axes bound the positions.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Target {
    /// Look-at point, world metres.
    pub center: Point3<f64>,
    /// Target-to-world rotation (identity for the scene frame).
    pub rotation: Rotation3<f64>,
}

/// Where positions are drawn for one target: the camera box in its frame.
#[derive(Clone, Copy, Debug)]
struct Region {
    target: Target,
    min: Vector3<f64>,
    max: Vector3<f64>,
}

/// Outcome of one candidate.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Candidate {
    /// Closer than the clearance to the scanned points (or at the target itself).
    TooClose,
    /// A pose to probe.
    Pose {
        /// Camera-to-world, OpenCV axes.
        camera_to_world: IsometryMatrix3<f64>,
        /// Index of the target looked at.
        target: usize,
        /// Distance to the nearest scanned point (infinite without a cloud).
        nearest_scanned_m: f64,
    },
}

/// The scanned points in a k-d tree, for clearance queries.
pub struct Cloud {
    tree: Option<ImmutableKdTree<f32, 3>>,
}

impl Cloud {
    /// Index `points` (world metres); an empty slice gives an empty cloud.
    pub fn new(points: &[[f32; 3]]) -> Result<Cloud, SynthError> {
        if points.is_empty() {
            return Ok(Cloud { tree: None });
        }
        let tree = ImmutableKdTree::new_from_slice(points).map_err(|e| SynthError::KdTree(format!("{e:?}")))?;
        Ok(Cloud { tree: Some(tree) })
    }

    /// Whether the cloud has no points.
    pub fn is_empty(&self) -> bool {
        self.tree.is_none()
    }

    /// Distance from `p` to the nearest point; infinite for an empty cloud.
    pub fn distance(&self, p: &Point3<f64>) -> f64 {
        let Some(tree) = &self.tree else { return f64::INFINITY };
        let q: [f32; 3] = p.coords.cast::<f32>().into();
        let nearest = tree.query(&q).nearest_one::<SquaredEuclidean<f32>>().execute();
        f64::from(nearest.distance).sqrt()
    }

    /// The default clearance: [`CLEARANCE_FRACTION`] of the median distance
    /// from the scan's cameras to their nearest scanned point: scaled to how
    /// far the operator kept the camera (0.15 m on the tabletop fixture, whose
    /// cameras keep a median 0.76 m). `None` without points.
    pub fn default_clearance(&self, cameras: &[Point3<f64>]) -> Option<f64> {
        let mut d: Vec<f64> = cameras
            .iter()
            .map(|c| self.distance(c))
            .filter(|d| d.is_finite())
            .collect();
        if d.is_empty() {
            return None;
        }
        let mid = d.len() / 2;
        let (_, median, _) = d.select_nth_unstable_by(mid, f64::total_cmp);
        Some(CLEARANCE_FRACTION * *median)
    }
}

/// Draws viewpoint candidates around targets.
pub struct PoseSampler<'a> {
    regions: Vec<Region>,
    cloud: &'a Cloud,
    clearance: f64,
}

impl<'a> PoseSampler<'a> {
    /// Sampler over `targets` (at least one) with the bounding boxes of
    /// `cameras` in each target's frame; positions within `clearance` of `cloud` are refused.
    pub fn new(
        cameras: &[Point3<f64>],
        targets: &[Target],
        cloud: &'a Cloud,
        clearance: f64,
    ) -> Result<Self, SynthError> {
        if cameras.is_empty() {
            return Err(SynthError::NoFrames);
        }
        if targets.is_empty() {
            return Err(SynthError::Options("no target to look at".into()));
        }
        if !(clearance.is_finite() && clearance >= 0.0) {
            return Err(SynthError::Options(format!(
                "clearance {clearance} m must be a finite number >= 0"
            )));
        }
        let regions = targets
            .iter()
            .map(|&target| {
                let to_local = |p: &Point3<f64>| target.rotation.inverse() * (p - target.center);
                let (min, max) = cameras.iter().fold(
                    (Vector3::repeat(f64::INFINITY), Vector3::repeat(f64::NEG_INFINITY)),
                    |(lo, hi), c| (lo.inf(&to_local(c)), hi.sup(&to_local(c))),
                );
                Region { target, min, max }
            })
            .collect();
        Ok(PoseSampler {
            regions,
            cloud,
            clearance,
        })
    }

    /// Clearance in metres.
    pub fn clearance(&self) -> f64 {
        self.clearance
    }

    /// Candidate number `index` for `seed`.
    pub fn candidate(&self, seed: u64, index: u64) -> Candidate {
        let mut rng = Rng::new(seed, index);
        let which = rng.below(self.regions.len() as u64) as usize;
        let Some(region) = self.regions.get(which) else {
            return Candidate::TooClose;
        };
        let local = Vector3::new(
            rng.range(region.min.x, region.max.x),
            rng.range(region.min.y, region.max.y),
            rng.range(region.min.z, region.max.z),
        );
        let eye = region.target.center + region.target.rotation * local;
        let tilt_x = rng.range(-MAX_TILT, MAX_TILT);
        let tilt_y = rng.range(-MAX_TILT, MAX_TILT);
        let roll = rng.range(-PI, PI);
        let Some(look) = look_at(&eye, &region.target.center) else {
            return Candidate::TooClose;
        };
        let nearest_scanned_m = self.cloud.distance(&eye);
        if self.clearance > 0.0 && nearest_scanned_m < self.clearance {
            return Candidate::TooClose;
        }
        let rotation = look
            * Rotation3::from_axis_angle(&Vector3::x_axis(), tilt_x)
            * Rotation3::from_axis_angle(&Vector3::y_axis(), tilt_y)
            * Rotation3::from_axis_angle(&Vector3::z_axis(), roll);
        let camera_to_world = IsometryMatrix3::from_parts(Translation3::from(eye.coords), rotation);
        Candidate::Pose {
            camera_to_world,
            target: which,
            nearest_scanned_m,
        }
    }
}

/// Camera-to-world rotation (OpenCV axes) whose optical axis points from
/// `eye` to `target`; the roll is arbitrary but fixed. `None` if they coincide.
pub fn look_at(eye: &Point3<f64>, target: &Point3<f64>) -> Option<Rotation3<f64>> {
    let z = unit(&(target - eye))?;
    // Any helper axis not parallel to z: the world axis least aligned with it.
    let a = z.abs();
    let helper = if a.x <= a.y && a.x <= a.z {
        Vector3::x()
    } else if a.y <= a.z {
        Vector3::y()
    } else {
        Vector3::z()
    };
    let x = unit(&helper.cross(&z))?;
    let y = z.cross(&x);
    Some(Rotation3::from_matrix_unchecked(nalgebra::Matrix3::from_columns(&[
        x, y, z,
    ])))
}

/// `v` scaled to unit length by its reciprocal norm (the rounding the
/// sampler has always used, so sampled poses stay bit for bit); `None` for
/// a zero or non-finite vector.
fn unit(v: &Vector3<f64>) -> Option<Vector3<f64>> {
    let rcp = 1.0 / v.norm();
    (rcp.is_finite() && rcp > 0.0).then(|| v * rcp)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A floor grid at z = 0 plus a dense ball of radius 0.2 at (0.3, 0, 0.3).
    fn scene_points() -> Vec<[f32; 3]> {
        let mut pts = Vec::new();
        for i in -40..=40 {
            for j in -40..=40 {
                pts.push([i as f32 * 0.05, j as f32 * 0.05, 0.0]);
            }
        }
        let mut rng = Rng::new(5, 0);
        for _ in 0..3000 {
            let d = Vector3::new(rng.normal(), rng.normal(), rng.normal()).normalize() * 0.2;
            pts.push((Vector3::new(0.3, 0.0, 0.3) + d).cast::<f32>().into());
        }
        pts
    }

    /// Scan cameras on a ring of radius 1.2 at heights 0.4..0.8.
    fn cameras() -> Vec<Point3<f64>> {
        (0..24)
            .map(|i| {
                let a = i as f64 * std::f64::consts::TAU / 24.0;
                Point3::new(1.2 * a.cos(), 1.2 * a.sin(), 0.4 + 0.4 * (i % 2) as f64)
            })
            .collect()
    }

    fn targets() -> Vec<Target> {
        vec![
            Target {
                center: Point3::new(0.3, 0.0, 0.3),
                rotation: Rotation3::identity(),
            },
            Target {
                center: Point3::new(-0.4, 0.2, 0.05),
                rotation: Rotation3::from_axis_angle(&Vector3::z_axis(), 0.7),
            },
        ]
    }

    fn brute_distance(points: &[[f32; 3]], p: &Point3<f64>) -> f64 {
        points
            .iter()
            .map(|q| (Point3::new(q[0] as f64, q[1] as f64, q[2] as f64) - p).norm())
            .fold(f64::INFINITY, f64::min)
    }

    #[test]
    fn clearance_is_respected_exactly_over_many_seeds() {
        let points = scene_points();
        let cloud = Cloud::new(&points).unwrap();
        let clearance = 0.3;
        let sampler = PoseSampler::new(&cameras(), &targets(), &cloud, clearance).unwrap();
        let (mut kept, mut refused) = (0, 0);
        for seed in 0..20 {
            for i in 0..40 {
                match sampler.candidate(seed, i) {
                    Candidate::Pose {
                        camera_to_world,
                        nearest_scanned_m,
                        ..
                    } => {
                        let d = brute_distance(&points, &Point3::from(camera_to_world.translation.vector));
                        assert!(d >= clearance - 1e-5, "seed {seed} candidate {i}: {d} m from the cloud");
                        assert!((nearest_scanned_m - d).abs() < 1e-5, "{nearest_scanned_m} vs {d}");
                        kept += 1;
                    }
                    Candidate::TooClose => refused += 1,
                }
            }
        }
        // Both outcomes occur: the camera boxes reach down to the floor.
        assert!(kept > 200 && refused > 50, "kept {kept}, refused {refused}");
    }

    #[test]
    fn tilt_and_roll_stay_in_their_ranges_and_fill_them() {
        let cloud = Cloud::new(&[]).unwrap();
        let targets = targets();
        let sampler = PoseSampler::new(&cameras(), &targets, &cloud, 0.0).unwrap();
        let mut max_axis_angle = 0.0f64;
        let (mut tilt_range, mut roll_range) = ((0.0f64, 0.0f64), (0.0f64, 0.0f64));
        let mut roll_bins = [0usize; 8];
        let mut n = 0;
        for seed in 0..10 {
            for i in 0..200 {
                let Candidate::Pose {
                    camera_to_world,
                    target,
                    nearest_scanned_m,
                } = sampler.candidate(seed, i)
                else {
                    panic!("no clearance, no refusal")
                };
                assert_eq!(nearest_scanned_m, f64::INFINITY, "an empty cloud is infinitely far");
                n += 1;
                let eye = Point3::from(camera_to_world.translation.vector);
                let r = *camera_to_world.rotation.matrix();
                assert!(
                    (r.determinant() - 1.0).abs() < 1e-9
                        && (r.transpose() * r - nalgebra::Matrix3::identity()).amax() < 1e-9
                );
                let to_target = (targets[target].center - eye).normalize();
                let angle = r.column(2).dot(&to_target).clamp(-1.0, 1.0).acos();
                // The optical axis leaves the look direction by at most acos(cos^2(pi/4)) = pi/3.
                assert!(angle <= PI / 3.0 + 1e-9 && angle <= FRAC_PI_4 * 2f64.sqrt(), "{angle}");
                max_axis_angle = max_axis_angle.max(angle);
                // Recover the angles: Q = Rx(a) Ry(b) Rz(c) relative to the look-at frame.
                let q = look_at(&eye, &targets[target].center).unwrap().matrix().transpose() * r;
                let (a, b) = ((-q[(1, 2)]).atan2(q[(2, 2)]), q[(0, 2)].asin());
                let c = (-q[(0, 1)]).atan2(q[(0, 0)]);
                for t in [a, b] {
                    assert!(t.abs() <= MAX_TILT + 1e-9, "tilt {t}");
                    tilt_range = (tilt_range.0.min(t), tilt_range.1.max(t));
                }
                roll_range = (roll_range.0.min(c), roll_range.1.max(c));
                roll_bins[(((c + PI) / (2.0 * PI) * 8.0) as usize).min(7)] += 1;
            }
        }
        assert!(max_axis_angle > 0.95, "tilts never reach the corners: {max_axis_angle}");
        assert!(tilt_range.0 < -0.75 && tilt_range.1 > 0.75, "{tilt_range:?}");
        assert!(roll_range.0 < -3.0 && roll_range.1 > 3.0, "{roll_range:?}");
        for (k, &count) in roll_bins.iter().enumerate() {
            assert!(
                (count as f64 - n as f64 / 8.0).abs() < 0.25 * n as f64 / 8.0,
                "roll bin {k}: {count} of {n}"
            );
        }
    }

    #[test]
    fn positions_fill_the_camera_box_in_the_target_frame() {
        let cloud = Cloud::new(&[]).unwrap();
        let cams = cameras();
        let t = Target {
            center: Point3::new(-0.4, 0.2, 0.05),
            rotation: Rotation3::from_axis_angle(&Vector3::z_axis(), 0.7),
        };
        let sampler = PoseSampler::new(&cams, &[t], &cloud, 0.0).unwrap();
        let local = |p: &Point3<f64>| t.rotation.inverse() * (p - t.center);
        let infinite = (Vector3::repeat(f64::INFINITY), Vector3::repeat(f64::NEG_INFINITY));
        let (lo, hi) = cams
            .iter()
            .fold(infinite, |(a, b), c| (a.inf(&local(c)), b.sup(&local(c))));
        let (mut seen_lo, mut seen_hi) = infinite;
        for i in 0..2000 {
            let Candidate::Pose { camera_to_world, .. } = sampler.candidate(3, i) else {
                panic!()
            };
            let p = local(&Point3::from(camera_to_world.translation.vector));
            assert!(
                (0..3).all(|a| p[a] >= lo[a] - 1e-9 && p[a] <= hi[a] + 1e-9),
                "{p} outside {lo}..{hi}"
            );
            seen_lo = seen_lo.inf(&p);
            seen_hi = seen_hi.sup(&p);
        }
        let span = hi - lo;
        assert!((0..3).all(|a| seen_lo[a] - lo[a] <= span[a] * 0.02 && hi[a] - seen_hi[a] <= span[a] * 0.02));
    }

    #[test]
    fn candidates_depend_only_on_seed_and_index() {
        let points = scene_points();
        let cloud = Cloud::new(&points).unwrap();
        let a = PoseSampler::new(&cameras(), &targets(), &cloud, 0.2).unwrap();
        let b = PoseSampler::new(&cameras(), &targets(), &cloud, 0.2).unwrap();
        let run = |s: &PoseSampler, seed| (0..50).map(|i| s.candidate(seed, i)).collect::<Vec<_>>();
        assert_eq!(run(&a, 9), run(&b, 9));
        assert_ne!(run(&a, 9), run(&a, 10));
        assert_eq!(a.candidate(9, 17), b.candidate(9, 17));
    }

    #[test]
    fn default_clearance_is_a_fraction_of_the_median_camera_distance() {
        let points = scene_points();
        let cloud = Cloud::new(&points).unwrap();
        let cams = cameras();
        let mut d: Vec<f64> = cams.iter().map(|c| brute_distance(&points, c)).collect();
        d.sort_by(f64::total_cmp);
        let want = CLEARANCE_FRACTION * d[d.len() / 2];
        let got = cloud.default_clearance(&cams).unwrap();
        assert!((got - want).abs() < 1e-5, "{got} vs {want}");
        assert_eq!(Cloud::new(&[]).unwrap().default_clearance(&cams), None);
    }

    #[test]
    fn bad_inputs_are_errors() {
        let cloud = Cloud::new(&[]).unwrap();
        assert!(matches!(
            PoseSampler::new(&[], &targets(), &cloud, 0.1),
            Err(SynthError::NoFrames)
        ));
        assert!(PoseSampler::new(&cameras(), &[], &cloud, 0.1).is_err());
        for c in [-0.1, f64::NAN, f64::INFINITY] {
            assert!(PoseSampler::new(&cameras(), &targets(), &cloud, c).is_err(), "{c}");
        }
    }
}
