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
use glam::{DMat3, DMat4, DVec3};
use kiddo::{ImmutableKdTree, SquaredEuclidean};
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
    pub center: DVec3,
    /// Target-to-world rotation (identity for the scene frame).
    pub rotation: DMat3,
}

/// Where positions are drawn for one target: the camera box in its frame.
#[derive(Clone, Copy, Debug)]
struct Region {
    target: Target,
    min: DVec3,
    max: DVec3,
}

/// Outcome of one candidate.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Candidate {
    /// Closer than the clearance to the scanned points (or at the target itself).
    TooClose,
    /// A pose to probe.
    Pose {
        /// Camera-to-world, OpenCV axes.
        camera_to_world: DMat4,
        /// Index of the target looked at.
        target: usize,
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
    pub fn distance(&self, p: DVec3) -> f64 {
        let Some(tree) = &self.tree else { return f64::INFINITY };
        let q = p.as_vec3().to_array();
        let nearest = tree.query(&q).nearest_one::<SquaredEuclidean<f32>>().execute();
        f64::from(nearest.distance).sqrt()
    }

    /// The default clearance: [`CLEARANCE_FRACTION`] of the median distance
    /// from the scan's cameras to their nearest scanned point: scaled to how
    /// far the operator kept the camera (0.15 m on the tabletop fixture, whose
    /// cameras keep a median 0.76 m). `None` without points.
    pub fn default_clearance(&self, cameras: &[DVec3]) -> Option<f64> {
        let mut d: Vec<f64> = cameras
            .iter()
            .map(|&c| self.distance(c))
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
    pub fn new(cameras: &[DVec3], targets: &[Target], cloud: &'a Cloud, clearance: f64) -> Result<Self, SynthError> {
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
                let to_local = |p: DVec3| target.rotation.transpose() * (p - target.center);
                let (min, max) = cameras
                    .iter()
                    .fold((DVec3::INFINITY, DVec3::NEG_INFINITY), |(lo, hi), &c| {
                        (lo.min(to_local(c)), hi.max(to_local(c)))
                    });
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
        let local = DVec3::new(
            rng.range(region.min.x, region.max.x),
            rng.range(region.min.y, region.max.y),
            rng.range(region.min.z, region.max.z),
        );
        let eye = region.target.center + region.target.rotation * local;
        let tilt_x = rng.range(-MAX_TILT, MAX_TILT);
        let tilt_y = rng.range(-MAX_TILT, MAX_TILT);
        let roll = rng.range(-PI, PI);
        let Some(look) = look_at(eye, region.target.center) else {
            return Candidate::TooClose;
        };
        if self.clearance > 0.0 && self.cloud.distance(eye) < self.clearance {
            return Candidate::TooClose;
        }
        let rotation =
            look * DMat3::from_rotation_x(tilt_x) * DMat3::from_rotation_y(tilt_y) * DMat3::from_rotation_z(roll);
        let camera_to_world = DMat4::from_cols(
            rotation.x_axis.extend(0.0),
            rotation.y_axis.extend(0.0),
            rotation.z_axis.extend(0.0),
            eye.extend(1.0),
        );
        Candidate::Pose {
            camera_to_world,
            target: which,
        }
    }
}

/// Camera-to-world rotation (OpenCV axes) whose optical axis points from
/// `eye` to `target`; the roll is arbitrary but fixed. `None` if they coincide.
pub fn look_at(eye: DVec3, target: DVec3) -> Option<DMat3> {
    let z = (target - eye).try_normalize()?;
    // Any helper axis not parallel to z: the world axis least aligned with it.
    let a = z.abs();
    let helper = if a.x <= a.y && a.x <= a.z {
        DVec3::X
    } else if a.y <= a.z {
        DVec3::Y
    } else {
        DVec3::Z
    };
    let x = helper.cross(z).normalize();
    let y = z.cross(x);
    Some(DMat3::from_cols(x, y, z))
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
            let d = DVec3::new(rng.normal(), rng.normal(), rng.normal()).normalize() * 0.2;
            pts.push((DVec3::new(0.3, 0.0, 0.3) + d).as_vec3().to_array());
        }
        pts
    }

    /// Scan cameras on a ring of radius 1.2 at heights 0.4..0.8.
    fn cameras() -> Vec<DVec3> {
        (0..24)
            .map(|i| {
                let a = i as f64 * std::f64::consts::TAU / 24.0;
                DVec3::new(1.2 * a.cos(), 1.2 * a.sin(), 0.4 + 0.4 * (i % 2) as f64)
            })
            .collect()
    }

    fn targets() -> Vec<Target> {
        vec![
            Target {
                center: DVec3::new(0.3, 0.0, 0.3),
                rotation: DMat3::IDENTITY,
            },
            Target {
                center: DVec3::new(-0.4, 0.2, 0.05),
                rotation: DMat3::from_rotation_z(0.7),
            },
        ]
    }

    fn brute_distance(points: &[[f32; 3]], p: DVec3) -> f64 {
        points
            .iter()
            .map(|q| (DVec3::new(q[0] as f64, q[1] as f64, q[2] as f64) - p).length())
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
                    Candidate::Pose { camera_to_world, .. } => {
                        let d = brute_distance(&points, camera_to_world.w_axis.truncate());
                        assert!(d >= clearance - 1e-5, "seed {seed} candidate {i}: {d} m from the cloud");
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
                } = sampler.candidate(seed, i)
                else {
                    panic!("no clearance, no refusal")
                };
                n += 1;
                let eye = camera_to_world.w_axis.truncate();
                let r = DMat3::from_mat4(camera_to_world);
                assert!((r.determinant() - 1.0).abs() < 1e-9 && (r.transpose() * r).abs_diff_eq(DMat3::IDENTITY, 1e-9));
                let to_target = (targets[target].center - eye).normalize();
                let angle = r.z_axis.dot(to_target).clamp(-1.0, 1.0).acos();
                // The optical axis leaves the look direction by at most acos(cos^2(pi/4)) = pi/3.
                assert!(angle <= PI / 3.0 + 1e-9 && angle <= FRAC_PI_4 * 2f64.sqrt(), "{angle}");
                max_axis_angle = max_axis_angle.max(angle);
                // Recover the angles: Q = Rx(a) Ry(b) Rz(c) relative to the look-at frame.
                let q = look_at(eye, targets[target].center).unwrap().transpose() * r;
                let (a, b) = ((-q.z_axis.y).atan2(q.z_axis.z), q.z_axis.x.asin());
                let c = (-q.y_axis.x).atan2(q.x_axis.x);
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
            center: DVec3::new(-0.4, 0.2, 0.05),
            rotation: DMat3::from_rotation_z(0.7),
        };
        let sampler = PoseSampler::new(&cams, &[t], &cloud, 0.0).unwrap();
        let local = |p: DVec3| t.rotation.transpose() * (p - t.center);
        let (lo, hi) = cams.iter().fold((DVec3::INFINITY, DVec3::NEG_INFINITY), |(a, b), &c| {
            (a.min(local(c)), b.max(local(c)))
        });
        let (mut seen_lo, mut seen_hi) = (DVec3::INFINITY, DVec3::NEG_INFINITY);
        for i in 0..2000 {
            let Candidate::Pose { camera_to_world, .. } = sampler.candidate(3, i) else {
                panic!()
            };
            let p = local(camera_to_world.w_axis.truncate());
            assert!(
                p.cmpge(lo - 1e-9).all() && p.cmple(hi + 1e-9).all(),
                "{p} outside {lo}..{hi}"
            );
            seen_lo = seen_lo.min(p);
            seen_hi = seen_hi.max(p);
        }
        let span = hi - lo;
        assert!((seen_lo - lo).cmple(span * 0.02).all() && (hi - seen_hi).cmple(span * 0.02).all());
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
        let mut d: Vec<f64> = cams.iter().map(|&c| brute_distance(&points, c)).collect();
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
