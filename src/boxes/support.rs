//! Loosely drawn boxes: users draw boxes with centimetres of margin that
//! dip into the table, floor or shelf the object stands on, or reach the
//! wall behind it. A plane of the measured surface that runs through such a
//! box and continues well outside it (a support or a wall; the object ends
//! at the box) is excluded from the box: points on it, within its measured
//! thickness, or behind it never belong to the object. A box drawn snug
//! to its support (ending just above it) has its support excluded too:
//! the labeller gives a box the surface points just in front of it (within
//! its tolerance), and those would be the support around the object.
//!
//! Every threshold comes from the scan: a plane's band is three robust
//! standard deviations of its own points' residuals (for rendered depth,
//! half a finest grid cell: see `Labeler::plane_band`), and a plane counts
//! only when a fifth of the surface around the box lies on it (of the
//! surface not on larger planes that were set aside: on a shelf, the side
//! and back panels around a box outnumber the board). Up to four planes are
//! found first and judged largest first, so the order the random search
//! found them in does not matter.
//!
//! A plane counts only when it continues on at least three of the four sides
//! of the box (a table around an object, a wall beside and above it): the
//! object's own face, or the faces of neighbours lined up with it, do not.
//! And it counts only when the box's points off it lie on one side (the
//! object stands on a support or in front of a wall, never on both sides),
//! and the cameras are on that side too (a row of neighbouring faces in
//! the middle of a scene is walked around; a table or a wall is not).
//!
//! Limits: an object at a table's corner has the table on two sides only,
//! so a loose box there keeps the table; an object flat on its support (a sheet of paper) has no point
//! off the plane, so its box keeps everything; an object thinner than the
//! band loses its pixels to the support; a curved support is no plane and
//! is not excluded; without sensor depth near the box nothing is found.

use super::parse::{Box3, BoxSet};
use crate::rng::Rng;
use nalgebra::{Matrix3, Point3, SymmetricEigen, Vector3};

/// The shell around a box that shows whether a plane continues outside it:
/// the box grown by this fraction of its size on every side.
const SHELL_GROWTH: f64 = 0.5;
/// A plane counts when at least this share of the shell's points lie on it
/// (of those not on larger planes examined before it and not excluded).
const MIN_SHELL_SHARE: f64 = 0.2;
/// Fewer shell points than this say nothing about the surroundings.
const MIN_SHELL_POINTS: usize = 50;
/// Planes excluded per box at most (a support, and a wall behind the object).
const MAX_PLANES: usize = 2;
/// Planes examined per box, largest first: a box on a shelf board sees the
/// back and a side panel too, which can be larger in its shell than the board.
const MAX_CANDIDATES: usize = 4;
/// RANSAC hypotheses per plane.
const RANSAC_TRIALS: usize = 300;
/// A side of the box counts as surrounded by a plane holding 1/this of the plane's shell points.
const SIDE_SHARE: usize = 20;
/// Band half-width in robust standard deviations of the plane's residuals.
const BAND_SIGMAS: f64 = 3.0;
/// A support or wall has the object on one side: a plane with more than
/// this share of the box's points on its other side (beyond its band) cuts
/// through the object (for example a "plane" through the tops of the
/// neighbours around a taller object). A share of all the box's points, as
/// the object may be seen by few of them (glass) and edge noise falls on both sides.
const MAX_FAR_SIDE_SHARE: f64 = 0.1;
/// A support or wall is seen from the object's side: a plane with more than
/// this share of the scan's cameras behind it is walked around (a row of
/// neighbouring faces mid-scene), not a wall. A share, not none: a camera
/// may stand beyond the plane of a wall past its end.
const MAX_CAMERAS_BEHIND: f64 = 0.1;

/// A plane excluded from one box: `normal . p + offset` is the signed
/// distance, positive on the object's side.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ExcludedPlane {
    pub normal: Vector3<f64>,
    pub offset: f64,
    /// Points closer to the plane than this (or behind it) are excluded.
    pub band: f64,
}

impl ExcludedPlane {
    /// Signed distance of `p` to the plane, positive on the object's side.
    pub fn distance(&self, p: &Point3<f64>) -> f64 {
        self.normal.dot(&p.coords) + self.offset
    }

    /// Whether `p` lies on the plane (within its band) or behind it.
    pub fn excludes(&self, p: &Point3<f64>) -> bool {
        self.distance(p) <= self.band
    }
}

/// The planes excluded from each box of `boxes` (indexed like `boxes.boxes`),
/// found among `points`, surface points of the scan in world metres.
/// `cameras`: where the points were seen from (camera centres; empty when
/// unknown). `tolerance`: how far outside a box the labeller still gives
/// surface points to it; a plane that near the box is excluded as well.
pub fn excluded_planes(
    boxes: &BoxSet,
    points: &[Point3<f64>],
    cameras: &[Point3<f64>],
    seed: u64,
    tolerance: f64,
) -> Vec<Vec<ExcludedPlane>> {
    (boxes.boxes.iter().enumerate())
        .map(|(i, b)| planes_of_box(b, points, cameras, seed.wrapping_add(i as u64), tolerance))
        .collect()
}

fn planes_of_box(
    b: &Box3,
    points: &[Point3<f64>],
    cameras: &[Point3<f64>],
    seed: u64,
    tolerance: f64,
) -> Vec<ExcludedPlane> {
    let half = b.size * 0.5;
    let grown = half + b.size * SHELL_GROWTH;
    let (mut shell, mut inner) = (Vec::new(), Vec::new());
    for &p in points {
        let q = b.to_local(&p);
        if within(&q, &half) {
            inner.push(p);
        } else if within(&q, &grown) {
            shell.push(p);
        }
    }
    // Every shell point, to tell a side nothing was seen on (where the
    // views end) from a side that shows something other than the plane.
    let seen = shell.clone();
    let mut rng = Rng::new(seed, 0x5u64);
    let reach = half.x.max(half.y).max(half.z);
    let mut candidates = Vec::new();
    while candidates.len() < MAX_CANDIDATES && shell.len() >= MIN_SHELL_POINTS {
        // Hypotheses from three shell points; scored with a threshold a
        // fiftieth of the box's half-extent, refined from the data below.
        let coarse = reach / 50.0;
        let Some((normal, offset)) = ransac(&shell, coarse, &mut rng) else {
            break;
        };
        let Some((normal, offset, sigma)) = refine(&shell, normal, offset, coarse) else {
            break;
        };
        let band = BAND_SIGMAS * sigma;
        let on_plane: Vec<Point3<f64>> = shell
            .iter()
            .copied()
            .filter(|p| (normal.dot(&p.coords) + offset).abs() <= band)
            .collect();
        if on_plane.len() < MIN_SHELL_POINTS {
            break;
        }
        shell.retain(|p| (normal.dot(&p.coords) + offset).abs() > band);
        candidates.push(Candidate {
            normal,
            offset,
            band,
            on_plane,
        });
    }
    // Largest first, whatever order the random search found them in: a
    // plane's share is of the shell points not on larger planes that were
    // set aside (a shelf's back and side panels around a box on its board).
    candidates.sort_by_key(|c| std::cmp::Reverse(c.on_plane.len()));
    let mut counted = seen.len();
    let mut planes = Vec::new();
    for candidate in &candidates {
        let needed = ((counted as f64 * MIN_SHELL_SHARE) as usize).max(MIN_SHELL_POINTS);
        let excluded = (candidate.on_plane.len() >= needed)
            .then(|| support_or_wall(b, candidate, &inner, &seen, cameras, tolerance))
            .flatten();
        match excluded {
            Some(plane) => planes.push(plane),
            None => counted -= candidate.on_plane.len(),
        }
        if planes.len() == MAX_PLANES {
            break;
        }
    }
    planes
}

/// A plane found among a box's shell points.
struct Candidate {
    normal: Vector3<f64>,
    offset: f64,
    band: f64,
    on_plane: Vec<Point3<f64>>,
}

/// The candidate as a plane excluded from the box, if it is a support or a
/// wall: it surrounds the box, runs through it or within the tolerance of
/// it, the box holds something off it, on one side only (the object's), and
/// the cameras are on that side too: a table or a wall is seen from the
/// side the object stands on, where a row of neighbouring faces in the
/// middle of a scene is walked around.
fn support_or_wall(
    b: &Box3,
    candidate: &Candidate,
    inner: &[Point3<f64>],
    seen: &[Point3<f64>],
    cameras: &[Point3<f64>],
    tolerance: f64,
) -> Option<ExcludedPlane> {
    let Candidate {
        normal,
        offset,
        band,
        ref on_plane,
    } = *candidate;
    if !surrounds(b, &normal, on_plane, seen) {
        return None;
    }
    let centre = normal.dot(&b.center.coords) + offset;
    if centre.abs() > b.reach(&normal) + band + tolerance {
        return None;
    }
    let off: Vec<f64> = inner
        .iter()
        .map(|p| normal.dot(&p.coords) + offset)
        .filter(|d| d.abs() > band)
        .collect();
    if off.len() < (inner.len() / 100).max(10) {
        return None;
    }
    let above = off.iter().filter(|&&d| d > 0.0).count();
    let far_side = above.min(off.len() - above);
    if far_side as f64 > MAX_FAR_SIDE_SHARE * inner.len() as f64 {
        return None;
    }
    let sign = if 2 * above >= off.len() { 1.0 } else { -1.0 };
    let behind = cameras
        .iter()
        .filter(|c| sign * (normal.dot(&c.coords) + offset) < 0.0)
        .count();
    if behind as f64 > MAX_CAMERAS_BEHIND * cameras.len() as f64 {
        return None;
    }
    Some(ExcludedPlane {
        normal: normal * sign,
        offset: offset * sign,
        band,
    })
}

/// Whether `q` lies within `half` of the origin on every axis (false for NaN).
fn within(q: &Vector3<f64>, half: &Vector3<f64>) -> bool {
    q.x.abs() <= half.x && q.y.abs() <= half.y && q.z.abs() <= half.z
}

/// A unit vector orthogonal to the unit vector `n` (Duff et al. 2017,
/// "Building an orthonormal basis, revisited"; glam's `any_orthonormal_vector`,
/// kept so the sides a plane is tested on stay the same).
fn any_orthonormal(n: &Vector3<f64>) -> Vector3<f64> {
    let sign = n.z.signum();
    let a = -1.0 / (sign + n.z);
    Vector3::new(n.x * n.y * a, sign + n.y * n.y * a, -n.y)
}

/// Whether a plane's points lie around the box on at least three of the four
/// sides within the plane, as a support or a wall does. A face of the object
/// itself, or faces of neighbours lined up with it, continue on fewer sides.
/// A side counts when it holds a twentieth of the plane's shell points, or
/// a quarter of what was seen beyond it (`seen`: every shell point) and a
/// quarter of that twentieth: beside neighbouring objects, or where the
/// views end, a support shows less of itself.
fn surrounds(b: &Box3, normal: &Vector3<f64>, on_plane: &[Point3<f64>], seen: &[Point3<f64>]) -> bool {
    let u = any_orthonormal(normal);
    let v = normal.cross(&u);
    let (ru, rv) = (b.reach(&u), b.reach(&v));
    let per_side = |points: &[Point3<f64>]| {
        let mut sides = [0usize; 4];
        for p in points {
            let d = p - b.center;
            let (du, dv) = (d.dot(&u), d.dot(&v));
            for (side, beyond) in [du > ru, du < -ru, dv > rv, dv < -rv].into_iter().enumerate() {
                sides[side] += beyond as usize;
            }
        }
        sides
    };
    let (on_sides, seen_sides) = (per_side(on_plane), per_side(seen));
    let enough = (on_plane.len() / SIDE_SHARE).max(1);
    (on_sides.iter().zip(&seen_sides))
        .filter(|&(&on, &all)| on >= enough || (4 * on >= all && 4 * on >= enough))
        .count()
        >= 3
}

/// The plane with the most points within `threshold`, from random triples.
fn ransac(points: &[Point3<f64>], threshold: f64, rng: &mut Rng) -> Option<(Vector3<f64>, f64)> {
    let n = points.len();
    // Score on a subsample: plenty to rank hypotheses, bounded cost.
    let step = (n / 2000).max(1);
    let mut best: Option<(usize, Vector3<f64>, f64)> = None;
    for _ in 0..RANSAC_TRIALS {
        let pick = |rng: &mut Rng| points[(rng.f64() * n as f64) as usize % n];
        let (a, b, c) = (pick(rng), pick(rng), pick(rng));
        let normal = (b - a).cross(&(c - a));
        let len = normal.norm();
        if !(len > 1e-12) {
            continue;
        }
        let normal = normal / len;
        let offset = -normal.dot(&a.coords);
        let score = points
            .iter()
            .step_by(step)
            .filter(|p| (normal.dot(&p.coords) + offset).abs() <= threshold)
            .count();
        if best.is_none_or(|(s, _, _)| score > s) {
            best = Some((score, normal, offset));
        }
    }
    best.map(|(_, normal, offset)| (normal, offset))
}

/// Least-squares plane through the points near a hypothesis, iterated with
/// a band of three robust standard deviations; returns the plane and the
/// robust standard deviation of its points' residuals.
fn refine(
    points: &[Point3<f64>],
    mut normal: Vector3<f64>,
    mut offset: f64,
    threshold: f64,
) -> Option<(Vector3<f64>, f64, f64)> {
    let mut band = threshold;
    let mut sigma = threshold / BAND_SIGMAS;
    for _ in 0..3 {
        let near: Vec<Point3<f64>> = points
            .iter()
            .copied()
            .filter(|p| (normal.dot(&p.coords) + offset).abs() <= band)
            .collect();
        if near.len() < 3 {
            return None;
        }
        (normal, offset) = fit_plane(&near)?;
        let mut residuals: Vec<f64> = near.iter().map(|p| (normal.dot(&p.coords) + offset).abs()).collect();
        residuals.sort_by(|a, b| a.total_cmp(b));
        // 1.4826 x median absolute residual: the standard deviation of Gaussian noise.
        sigma = (1.4826 * residuals[residuals.len() / 2]).max(f64::EPSILON);
        band = BAND_SIGMAS * sigma;
    }
    Some((normal, offset, sigma))
}

/// Least-squares plane: the eigenvector of the smallest eigenvalue of the
/// points' covariance.
fn fit_plane(points: &[Point3<f64>]) -> Option<(Vector3<f64>, f64)> {
    let n = points.len() as f64;
    let mean = points.iter().fold(Vector3::zeros(), |s, p| s + p.coords) / n;
    let mut cov = Matrix3::zeros();
    for p in points {
        let d = p.coords - mean;
        cov += d * d.transpose();
    }
    cov *= 1.0 / n;
    if !cov.iter().all(|x| x.is_finite()) {
        return None;
    }
    let eigen = SymmetricEigen::new(cov);
    let smallest = eigen.eigenvalues.imin();
    let v = eigen.eigenvectors.column(smallest).into_owned();
    // The side the inverse iteration this replaced converged to (it started
    // at (1, 1, 1)): the normal picks the in-plane axes `surrounds` tests.
    let v = if v.sum() < 0.0 { -v } else { v };
    Some((v, -v.dot(&mean)))
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::Rotation3;

    fn box3(center: Point3<f64>, size: Vector3<f64>) -> Box3 {
        Box3 {
            label: "obj".into(),
            instance_id: 1,
            center,
            size,
            rotation: Rotation3::identity(),
        }
    }

    /// A table (z = 0, 2 mm noise) with a 10 cm cube on it and a wall at y = 0.1.
    fn scene(rng: &mut Rng) -> Vec<Point3<f64>> {
        let mut points = Vec::new();
        let noise = |rng: &mut Rng| (rng.f64() - 0.5) * 0.004;
        for _ in 0..40_000 {
            let (x, y) = (rng.f64() - 0.5, rng.f64() * 0.8 - 0.5);
            if y < 0.1 && !(x.abs() < 0.05 && y.abs() < 0.05) {
                points.push(Point3::new(x, y, noise(rng)));
            }
        }
        for _ in 0..20_000 {
            points.push(Point3::new(rng.f64() - 0.5, 0.1 + noise(rng), rng.f64() * 0.5));
        }
        for _ in 0..10_000 {
            // The cube's top and sides.
            let (u, v) = (rng.f64() * 0.1 - 0.05, rng.f64() * 0.1);
            points.push(Point3::new(u, -0.05, v));
            points.push(Point3::new(u, 0.05, v));
            points.push(Point3::new(u, rng.f64() * 0.1 - 0.05, 0.1));
        }
        points
    }

    #[test]
    fn a_loose_box_excludes_the_table_and_the_wall_and_keeps_the_cube() {
        let mut rng = Rng::new(3, 0);
        let points = scene(&mut rng);
        // 3 cm margins, bottom 2 cm into the table, back 1 cm into the wall.
        let loose = box3(Point3::new(0.0, 0.03, 0.045), Vector3::new(0.16, 0.16, 0.17));
        let planes = excluded_planes(&BoxSet::from_boxes(vec![loose.clone()]), &points, &[], 1, 0.0).remove(0);
        assert_eq!(planes.len(), 2, "{planes:?}");
        let kept: Vec<&Point3<f64>> = points
            .iter()
            .filter(|p| loose.contains(p) && !planes.iter().any(|pl| pl.excludes(p)))
            .collect();
        let table_or_wall = kept
            .iter()
            .filter(|p| p.z.abs() < 0.003 || (p.y - 0.1).abs() < 0.003)
            .count();
        let cube_in_box = points
            .iter()
            .filter(|p| loose.contains(p) && p.z > 0.01 && p.y < 0.09)
            .count();
        assert_eq!(table_or_wall, 0, "no table or wall point is kept");
        assert!(
            kept.len() as f64 >= 0.95 * cube_in_box as f64,
            "the cube is kept: {} of {cube_in_box}",
            kept.len()
        );
        for plane in &planes {
            assert!(
                plane.band > 0.001 && plane.band < 0.01,
                "band from the 2 mm noise: {}",
                plane.band
            );
            assert!(
                plane.distance(&Point3::new(0.0, 0.0, 0.05)) > 0.0,
                "the cube's centre is on the kept side"
            );
        }
    }

    /// A support or wall is seen from the object's side. Cameras in front of
    /// the wall and above the table keep both planes excluded; cameras
    /// walking around the "wall" (as around a row of neighbouring faces in
    /// the middle of a table) leave it alone, and the table is still excluded.
    #[test]
    fn a_plane_the_cameras_walk_around_is_no_wall() {
        let mut rng = Rng::new(3, 0);
        let points = scene(&mut rng);
        let loose = box3(Point3::new(0.0, 0.03, 0.045), Vector3::new(0.16, 0.16, 0.17));
        let boxes = BoxSet::from_boxes(vec![loose]);
        let ring = |from: f64, to: f64| -> Vec<Point3<f64>> {
            (0..20)
                .map(|i| from + (to - from) * i as f64 / 19.0)
                .map(|a: f64| Point3::new(0.6 * a.cos(), 0.6 * a.sin(), 0.5))
                .collect()
        };
        let pi = std::f64::consts::PI;
        let in_front = excluded_planes(&boxes, &points, &ring(-0.9 * pi, -0.1 * pi), 1, 0.0).remove(0);
        assert_eq!(in_front.len(), 2, "table and wall: {in_front:?}");
        let around = excluded_planes(&boxes, &points, &ring(-pi, pi), 1, 0.0).remove(0);
        assert_eq!(around.len(), 1, "the table only: {around:?}");
        assert!(around[0].normal.z > 0.99, "{around:?}");
    }

    /// Found on an unseen room scene: a ball on a shelf's middle board, seen
    /// at a grazing angle, has the shelf's side and back panels around its
    /// box too, each holding more of the shell's points than the board.
    #[test]
    fn a_box_on_a_shelf_board_excludes_the_board_that_the_panels_outnumber() {
        let mut rng = Rng::new(7, 0);
        let noise = |rng: &mut Rng| (rng.f64() - 0.5) * 0.004;
        let mut points = Vec::new();
        for _ in 0..3_000 {
            // The board (z = 0), sparse, beside the 10 cm cube.
            let (x, y) = (rng.f64() * 0.49 - 0.14, rng.f64() * 0.28 - 0.14);
            if !(x.abs() < 0.05 && y.abs() < 0.05) {
                points.push(Point3::new(x, y, noise(&mut rng)));
            }
        }
        for _ in 0..20_000 {
            // The side panel (x = -0.14) and the back panel (y = 0.14), dense.
            let (u, z) = (rng.f64() * 0.28 - 0.14, rng.f64() - 0.5);
            points.push(Point3::new(-0.14 + noise(&mut rng), u, z));
            points.push(Point3::new(rng.f64() * 0.7 - 0.35, 0.14 + noise(&mut rng), z));
        }
        for _ in 0..5_000 {
            let (u, v) = (rng.f64() * 0.1 - 0.05, rng.f64() * 0.1);
            points.push(Point3::new(u, -0.05, v));
            points.push(Point3::new(u, rng.f64() * 0.1 - 0.05, 0.1));
        }
        let loose = box3(Point3::new(0.0, 0.0, 0.045), Vector3::new(0.16, 0.16, 0.17));
        let planes = excluded_planes(&BoxSet::from_boxes(vec![loose.clone()]), &points, &[], 1, 0.0).remove(0);
        assert_eq!(planes.len(), 1, "{planes:?}");
        assert!(planes[0].normal.z > 0.99, "the board, object side up: {:?}", planes[0]);
        let board_in_box = points.iter().filter(|p| loose.contains(p) && p.z.abs() < 0.003);
        assert!(board_in_box.clone().count() > 50);
        assert!(board_in_box.clone().all(|p| planes[0].excludes(p)));
        assert!(
            !planes[0].excludes(&Point3::new(0.0, -0.05, 0.02)),
            "the cube's foot is kept"
        );
    }

    /// Found on an unseen room scene (seed 2): behind the back panel, the
    /// side panel holds a little more of the shell than the board but less
    /// than a fifth of what is left; it is set aside like the back panel,
    /// and the board is examined next and excluded.
    #[test]
    fn a_board_smaller_than_a_panel_too_small_to_count_is_still_examined() {
        let mut rng = Rng::new(8, 0);
        let noise = |rng: &mut Rng| (rng.f64() - 0.5) * 0.002;
        let loose = box3(Point3::new(0.0, 0.0, 0.045), Vector3::new(0.16, 0.16, 0.17));
        let grown = |rng: &mut Rng| {
            Point3::new(
                rng.f64() * 0.32 - 0.16,
                rng.f64() * 0.32 - 0.16,
                rng.f64() * 0.34 - 0.125,
            )
        };
        let mut points = Vec::new();
        let add = |points: &mut Vec<Point3<f64>>, n: usize, rng: &mut Rng, f: &dyn Fn(&mut Rng) -> Point3<f64>| {
            while points.len() < n {
                let p = f(rng);
                if !loose.contains(&p) {
                    points.push(p);
                }
            }
        };
        let back = |rng: &mut Rng| Point3::new(rng.f64() * 0.32 - 0.16, 0.14 + noise(rng), rng.f64() * 0.34 - 0.125);
        let side = |rng: &mut Rng| Point3::new(-0.14 + noise(rng), rng.f64() * 0.28 - 0.14, rng.f64() * 0.34 - 0.125);
        let board = |rng: &mut Rng| Point3::new(rng.f64() * 0.30 - 0.14, rng.f64() * 0.28 - 0.14, noise(rng));
        let (mut b, mut s, mut d, mut r) = (Vec::new(), Vec::new(), Vec::new(), Vec::new());
        add(&mut b, 8_000, &mut rng, &back);
        add(&mut s, 1_150, &mut rng, &side);
        add(&mut d, 1_000, &mut rng, &board);
        // Surface that is no plane (edge noise, curved things) everywhere in the shell.
        add(&mut r, 3_800, &mut rng, &grown);
        points.extend(b.into_iter().chain(s).chain(d).chain(r));
        for _ in 0..3_000 {
            // The 10 cm cube's top and front.
            let (u, v) = (rng.f64() * 0.1 - 0.05, rng.f64() * 0.1);
            points.push(Point3::new(u, -0.05, v));
            points.push(Point3::new(u, rng.f64() * 0.1 - 0.05, 0.1));
        }
        let planes = excluded_planes(&BoxSet::from_boxes(vec![loose.clone()]), &points, &[], 1, 0.0).remove(0);
        assert_eq!(planes.len(), 1, "{planes:?}");
        assert!(planes[0].normal.z > 0.99, "the board, object side up: {:?}", planes[0]);
        assert!(
            planes[0].excludes(&Point3::new(0.07, -0.07, 0.0)),
            "board in the box kept"
        );
        assert!(
            !planes[0].excludes(&Point3::new(0.0, -0.05, 0.02)),
            "the cube's foot excluded"
        );
    }

    #[test]
    fn a_snug_box_excludes_the_table_its_tolerance_reaches_and_not_the_far_wall() {
        let mut rng = Rng::new(5, 0);
        let points = scene(&mut rng);
        // 1 cm margins, bottom 1 mm above the table; the wall is 5 cm behind the cube.
        let snug = box3(Point3::new(0.0, 0.0, 0.0555), Vector3::new(0.12, 0.12, 0.109));
        let tolerance = 0.008;
        let planes = excluded_planes(&BoxSet::from_boxes(vec![snug.clone()]), &points, &[], 1, tolerance).remove(0);
        assert_eq!(planes.len(), 1, "{planes:?}");
        assert!(planes[0].normal.z > 0.99, "the table, object side up: {:?}", planes[0]);
        // Table points just in front of the box, which the tolerance would give it, are excluded.
        let beside = Point3::new(0.065, 0.0, 0.0);
        assert!(planes[0].excludes(&beside));
        let cube_top = Point3::new(0.0, 0.0, 0.1);
        assert!(!planes[0].excludes(&cube_top));
        // A box ending 3 cm above the table is beyond the tolerance: nothing is excluded.
        let high = box3(Point3::new(0.0, 0.0, 0.085), Vector3::new(0.12, 0.12, 0.11));
        let found = excluded_planes(&BoxSet::from_boxes(vec![high]), &points, &[], 1, tolerance).remove(0);
        assert!(found.is_empty(), "{found:?}");
    }

    /// A 14 cm pack among 9 cm neighbours on all four sides, 2 mm away: the
    /// neighbours' tops form a plane around the pack's box that cuts through
    /// the pack. Only the table may be excluded; the pack's top half stays.
    #[test]
    fn the_tops_of_shorter_neighbours_are_not_excluded_from_a_taller_object() {
        let mut rng = Rng::new(6, 0);
        let noise = |rng: &mut Rng| (rng.f64() - 0.5) * 0.002;
        let (hx, hy, height) = (0.06, 0.03, 0.14);
        let pack = |p: Point3<f64>| p.x.abs() <= hx && p.y.abs() <= hy;
        let mut points = Vec::new();
        for _ in 0..40_000 {
            let p = Point3::new(rng.f64() * 0.6 - 0.3, rng.f64() * 0.6 - 0.3, noise(&mut rng));
            let neighbour = p.x.abs() <= hx + 0.1 && p.y.abs() <= hy + 0.1;
            if !neighbour {
                points.push(p);
            }
            // Tops of the neighbours (a 10 cm ring around the pack, 2 mm gap).
            let top = Point3::new(p.x, p.y, 0.09 + noise(&mut rng));
            if neighbour && !(p.x.abs() <= hx + 0.002 && p.y.abs() <= hy + 0.002) {
                points.push(top);
            }
        }
        for _ in 0..10_000 {
            // The pack's faces and top.
            let (u, z) = (rng.f64() * 2.0 - 1.0, rng.f64() * height);
            points.push(Point3::new(u * hx, -hy, z));
            points.push(Point3::new(u * hx, hy, z));
            points.push(Point3::new(u * hx, (rng.f64() * 2.0 - 1.0) * hy, height));
        }
        let snug = box3(Point3::new(0.0, 0.0, 0.0755), Vector3::new(0.14, 0.08, 0.149));
        let planes = excluded_planes(&BoxSet::from_boxes(vec![snug]), &points, &[], 1, 0.008).remove(0);
        assert!(planes.len() <= 1, "{planes:?}");
        for plane in &planes {
            assert!(plane.offset.abs() < 0.003, "only the table: {plane:?}");
        }
        let upper_face = Point3::new(0.0, -hy, 0.12);
        assert!(pack(upper_face) && !planes.iter().any(|p| p.excludes(&upper_face)));
    }

    /// Found on a real YCB-Video scan: the table is seen densely in front of
    /// and beside the object, but sparsely on its two other sides (seen from
    /// afar, at a grazing angle, or where the views end), each with fewer
    /// than a twentieth of the table's shell points.
    #[test]
    fn a_table_seen_sparsely_on_two_sides_is_still_excluded() {
        let mut rng = Rng::new(5, 0);
        let noise = |rng: &mut Rng| (rng.f64() - 0.5) * 0.002;
        let mut points = Vec::new();
        for _ in 0..60_000 {
            let (x, y) = (rng.f64() * 0.4 - 0.2, rng.f64() * 0.4 - 0.2);
            // One point in 16 beyond the box on its +x and +y sides.
            let sparse = x > 0.05 || y > 0.05;
            if (x.abs() > 0.03 || y.abs() > 0.03) && (!sparse || rng.below(16) == 0) {
                points.push(Point3::new(x, y, noise(&mut rng)));
            }
        }
        for _ in 0..5_000 {
            // The 6 cm cube's top and the sides facing the dense table.
            let (u, v) = (rng.f64() * 0.06 - 0.03, rng.f64() * 0.06);
            points.push(Point3::new(u, -0.03, v));
            points.push(Point3::new(-0.03, u, v));
            points.push(Point3::new(u, rng.f64() * 0.06 - 0.03, 0.06));
        }
        // 2.5 cm margins, bottom 2.5 cm into the table.
        let loose = box3(Point3::new(0.0, 0.0, 0.03), Vector3::new(0.11, 0.11, 0.11));
        let planes = excluded_planes(&BoxSet::from_boxes(vec![loose]), &points, &[], 1, 0.0).remove(0);
        assert_eq!(planes.len(), 1, "the table: {planes:?}");
        assert!(
            planes[0].excludes(&Point3::new(0.045, 0.045, 0.0)),
            "table kept: {planes:?}"
        );
        assert!(
            !planes[0].excludes(&Point3::new(0.0, 0.0, 0.06)),
            "cube top excluded: {planes:?}"
        );
    }

    #[test]
    fn a_box_around_a_flat_sheet_keeps_it() {
        // A sheet flat on the table has nothing off the plane: nothing is excluded.
        let mut rng = Rng::new(4, 0);
        let points: Vec<Point3<f64>> = (0..30_000)
            .map(|_| Point3::new(rng.f64() - 0.5, rng.f64() - 0.5, 0.0))
            .collect();
        let sheet = box3(Point3::new(0.0, 0.0, 0.0), Vector3::new(0.2, 0.3, 0.02));
        assert!(excluded_planes(&BoxSet::from_boxes(vec![sheet]), &points, &[], 1, 0.0)[0].is_empty());
    }

    #[test]
    fn a_box_with_no_surface_around_it_excludes_nothing() {
        let points = vec![Point3::new(5.0, 5.0, 5.0); 100];
        let b = box3(Point3::origin(), Vector3::repeat(0.1));
        assert!(excluded_planes(&BoxSet::from_boxes(vec![b]), &points, &[], 1, 0.0)[0].is_empty());
    }
}
