//! Metric scale of the poses from the depth: structure-from-motion poses
//! (COLMAP, hloc) are right only up to a scale, while depth is metric. With
//! the camera positions scaled by the right factor, every frame's depth
//! lands on the surfaces the other frames measured; with a wrong one the
//! frames' surfaces slide apart. The scale is the one at which the median
//! distance from a frame's depth points to the nearest point of another
//! frame is least: a robust cost (half the points may find nothing), found
//! by a coarse logarithmic scan and a golden-section search.

use super::refine::{camera_points, Cloud};
use super::GeometryError;
use crate::scan::Scan;
use nalgebra::{IsometryMatrix3, Point3};
use rayon::prelude::*;

/// Depth points per frame for the scale search (a cost needs far fewer
/// than an alignment).
const POINTS_PER_FRAME: usize = 400;
/// The coarse scan covers scales from 1/RANGE to RANGE.
const RANGE: f64 = 20.0;
/// The coarse scan and the rough search use every this-many-th point: they
/// only have to find the basin around the answer, which the fine search,
/// on every point, then pins down (and every point judges the answer).
const COARSE_POINT_STRIDE: usize = 4;
const COARSE_STEPS: usize = 49;
/// The fine search looks within this factor of the rough estimate.
const NEAR: f64 = 1.05;
/// Neighbours that fit a plane in the fine search.
const PLANE_NEIGHBOURS: usize = 12;
/// Golden-section search stops at this relative bracket width.
const TOLERANCE: f64 = 1e-3;
/// Poses count as metric when the best scale is within this share of 1 ...
const METRIC_SHARE: f64 = 0.02;
/// ... or when scale 1 costs at most this much more than the best scale.
const METRIC_COST_RATIO: f64 = 1.1;

/// What the depth says about the scale of the poses.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ScaleEstimate {
    /// Factor that makes the camera positions metric.
    pub scale: f64,
    /// Median distance between a frame's depth and the other frames' depth,
    /// metres, at `scale` and at scale 1.
    pub cost_at_scale: f64,
    pub cost_at_one: f64,
    /// Relative rise of the cost 5 % either side of `scale`: how sharply the
    /// depth pins the scale down (near 0: the cameras barely move).
    pub sharpness: f64,
}

impl ScaleEstimate {
    /// Whether the poses are metric already (within what the depth can tell).
    pub fn looks_metric(&self) -> bool {
        (self.scale - 1.0).abs() <= METRIC_SHARE || self.cost_at_one <= METRIC_COST_RATIO * self.cost_at_scale
    }

    /// Whether the depth determines the scale at all.
    pub fn is_determined(&self) -> bool {
        self.cost_at_scale.is_finite() && self.sharpness > 0.02
    }

    /// A plain sentence.
    pub fn verdict(&self) -> String {
        if !self.cost_at_scale.is_finite() {
            "the frames' depth overlaps too little to tell the poses' scale".into()
        } else if !self.is_determined() {
            "the cameras move too little against the depth to tell the poses' scale".into()
        } else if self.looks_metric() {
            format!("poses look metric (best scale {:.3})", self.scale)
        } else {
            // At scale 1 the frames' depth may not meet at all (no finite cost).
            let without = if self.cost_at_one.is_finite() {
                format!("{:.1} mm without", self.cost_at_one * 1e3)
            } else {
                "not at all without".to_string()
            };
            format!(
                "poses are up to scale: estimated scale {:.3} (depth agrees to {:.1} mm with it, {without})",
                self.scale,
                self.cost_at_scale * 1e3,
            )
        }
    }
}

/// Camera-to-world poses with every camera position multiplied by `scale`
/// (about the world origin, so the world frame keeps its origin and axes).
pub fn scale_poses(poses: &[IsometryMatrix3<f64>], scale: f64) -> Vec<IsometryMatrix3<f64>> {
    poses
        .iter()
        .map(|p| {
            let mut q = *p;
            q.translation.vector *= scale;
            q
        })
        .collect()
}

/// Estimate the factor that makes the poses metric; `None` when fewer than
/// two frames have depth (see [`ScaleEstimate::is_determined`] for scans
/// whose depth cannot tell).
pub fn estimate_pose_scale(scan: &Scan) -> Result<Option<ScaleEstimate>, GeometryError> {
    let samples: Vec<Vec<Point3<f64>>> = scan
        .frames
        .par_iter()
        .enumerate()
        .map(|(i, f)| camera_points(f, POINTS_PER_FRAME, i as u64))
        .collect::<Result<_, _>>()?;
    if samples.iter().filter(|s| !s.is_empty()).count() < 2 {
        return Ok(None);
    }
    let poses = scan.poses();
    let sparse: Vec<Vec<Point3<f64>>> = samples
        .iter()
        .map(|s| s.iter().step_by(COARSE_POINT_STRIDE).copied().collect())
        .collect();
    // Far from the answer, the distance to the nearest point of another
    // frame; near it, the distance to the plane through the nearest points
    // (sharper: it does not bottom out at the sampling spacing).
    let coarse_cost = |scale: f64| disagreement(&sparse, &scale_poses(&poses, scale), false);
    let nearest_cost = |scale: f64| disagreement(&samples, &scale_poses(&poses, scale), false);
    let cost = |scale: f64| disagreement(&samples, &scale_poses(&poses, scale), true);
    let at = |k: usize| RANGE.powf(2.0 * k as f64 / (COARSE_STEPS - 1) as f64 - 1.0);
    let coarse: Vec<f64> = (0..COARSE_STEPS).into_par_iter().map(|k| coarse_cost(at(k))).collect();
    let best = (0..COARSE_STEPS)
        .min_by(|&a, &b| coarse[a].total_cmp(&coarse[b]))
        .unwrap_or(COARSE_STEPS / 2);
    let rough = golden_section(
        at(best.saturating_sub(1)),
        at((best + 1).min(COARSE_STEPS - 1)),
        0.01,
        &coarse_cost,
    );
    let fine = golden_section(rough / NEAR, rough * NEAR, TOLERANCE, &cost);
    // Frames that disagree by more than their planes' size (poses off by
    // centimetres) find too few planes: the rough estimate stands, judged
    // on every point (the sparse scan's distances bottom out higher).
    let (scale, cost): (f64, &dyn Fn(f64) -> f64) = if cost(fine).is_finite() {
        (fine, &cost)
    } else {
        (rough, &nearest_cost)
    };
    let cost_at_scale = cost(scale);
    let sharpness = if cost_at_scale.is_finite() {
        0.5 * (cost(scale * 1.05) + cost(scale / 1.05)) / cost_at_scale.max(f64::MIN_POSITIVE) - 1.0
    } else {
        0.0
    };
    Ok(Some(ScaleEstimate {
        scale,
        cost_at_scale,
        cost_at_one: cost(1.0),
        sharpness,
    }))
}

/// Minimum of `cost` over scales in [lo, hi] (logarithmic golden section),
/// to a relative bracket of `tolerance`.
fn golden_section(lo: f64, hi: f64, tolerance: f64, cost: &dyn Fn(f64) -> f64) -> f64 {
    let (mut lo, mut hi) = (lo.ln(), hi.ln());
    let golden = (5f64.sqrt() - 1.0) / 2.0;
    let (mut a, mut b) = (hi - golden * (hi - lo), lo + golden * (hi - lo));
    let (mut fa, mut fb) = (cost(a.exp()), cost(b.exp()));
    while hi - lo > tolerance {
        if fa < fb {
            (hi, b, fb) = (b, a, fa);
            a = hi - golden * (hi - lo);
            fa = cost(a.exp());
        } else {
            (lo, a, fa) = (a, b, fb);
            b = lo + golden * (hi - lo);
            fb = cost(b.exp());
        }
    }
    (0.5 * (lo + hi)).exp()
}

/// Median over all depth points of the distance to the nearest point another
/// frame measured, or (`to_planes`) to the plane through the nearest points
/// of other frames; infinite where there is none.
fn disagreement(samples: &[Vec<Point3<f64>>], poses: &[IsometryMatrix3<f64>], to_planes: bool) -> f64 {
    let cloud = Cloud::new(samples, poses);
    let distances: Vec<f64> = samples
        .par_iter()
        .zip(poses)
        .enumerate()
        .flat_map_iter(|(i, (s, pose))| {
            let cloud = &cloud;
            s.iter().map(move |p| {
                let x = pose * p;
                let d = if to_planes {
                    cloud
                        .plane_near(&x, i as u32, PLANE_NEIGHBOURS)
                        .map(|(c, n)| n.dot(&(x - c)).abs())
                } else {
                    cloud.nearest_other(&x, i as u32)
                };
                d.unwrap_or(f64::INFINITY)
            })
        })
        .collect();
    median_with_infinities(distances)
}

fn median_with_infinities(v: Vec<f64>) -> f64 {
    let n = v.len();
    let finite: Vec<f64> = v.into_iter().filter(|d| d.is_finite()).collect();
    if finite.len() * 2 <= n {
        return f64::INFINITY;
    }
    // The infinite ones sit above the median: take the median rank of all.
    let mut sorted = finite;
    sorted.sort_by(f64::total_cmp);
    sorted[n / 2]
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::poses::test_scene;

    /// Scale the camera positions of a room scan (metric depth) by a known
    /// factor: the estimate finds its inverse within 1 %.
    #[test]
    fn the_scale_of_scaled_poses_is_found() {
        let scan = test_scene::Room {
            frames: 24,
            ..Default::default()
        }
        .scan();
        for factor in [0.4, 2.5] {
            let mut scaled = scan.clone();
            scaled.set_poses(&scale_poses(&scan.poses(), factor));
            let e = estimate_pose_scale(&scaled).unwrap().expect("the scan has depth");
            assert!(
                (e.scale * factor - 1.0).abs() < 0.01,
                "x{factor}: estimated {}",
                e.scale
            );
            assert!(!e.looks_metric() && e.is_determined(), "x{factor}: {e:?}");
        }
        let e = estimate_pose_scale(&scan).unwrap().unwrap();
        assert!(e.looks_metric(), "{e:?}");
    }

    /// Poses so far off scale that the frames' depth never meets at scale 1
    /// are reported in words, not as "inf mm".
    #[test]
    fn a_verdict_without_any_agreement_at_scale_one_says_so() {
        let e = ScaleEstimate {
            scale: 2.5,
            cost_at_scale: 0.002,
            cost_at_one: f64::INFINITY,
            sharpness: 0.5,
        };
        let verdict = e.verdict();
        assert!(
            verdict.contains("estimated scale 2.500")
                && verdict.contains("not at all without")
                && !verdict.contains("inf"),
            "{verdict}"
        );
    }
}
