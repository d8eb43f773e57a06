//! Project a box into a camera: the rectangle of pixels whose rays can meet
//! it, so labelling renders only those pixels. Boxes crossing the camera
//! plane are clipped against a near plane; boxes wholly behind give `None`.

use super::parse::Box3;
use crate::scan::Intrinsics;
use nalgebra::{IsometryMatrix3, Point3, Vector4};

/// A pixel rectangle `[x0, x1) x [y0, y1)` (integers are pixel centres).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct PixelRect {
    pub x0: u32,
    pub y0: u32,
    pub x1: u32,
    pub y1: u32,
}

impl PixelRect {
    /// Number of pixels.
    pub fn area(&self) -> u64 {
        (self.x1 - self.x0) as u64 * (self.y1 - self.y0) as u64
    }

    /// Whether pixel (x, y) lies inside.
    pub fn contains(&self, x: u32, y: u32) -> bool {
        (self.x0..self.x1).contains(&x) && (self.y0..self.y1).contains(&y)
    }

    /// Smallest rectangle holding both.
    pub fn union(&self, other: &PixelRect) -> PixelRect {
        PixelRect {
            x0: self.x0.min(other.x0),
            y0: self.y0.min(other.y0),
            x1: self.x1.max(other.x1),
            y1: self.y1.max(other.y1),
        }
    }
}

/// The 6 faces of a box as corner indices in cyclic order (bit k of a
/// corner index picks the + side of axis k).
const FACES: [[usize; 4]; 6] = [
    [0, 2, 6, 4],
    [1, 3, 7, 5],
    [0, 1, 5, 4],
    [2, 3, 7, 6],
    [0, 1, 3, 2],
    [4, 5, 7, 6],
];

/// Keep the part of a convex polygon where `plane . (p, 1) >= 0` (Sutherland-Hodgman).
fn clip(poly: &[Point3<f64>], plane: Vector4<f64>, out: &mut Vec<Point3<f64>>) {
    out.clear();
    let side = |p: Point3<f64>| plane.xyz().dot(&p.coords) + plane.w;
    for (i, &a) in poly.iter().enumerate() {
        let b = poly[(i + 1) % poly.len()];
        let (da, db) = (side(a), side(b));
        if da >= 0.0 {
            out.push(a);
        }
        if (da >= 0.0) != (db >= 0.0) {
            out.push(a + (b - a) * (da / (da - db)));
        }
    }
}

/// Pixels of a `size` image (with `k`, camera pose `camera_to_world`) whose
/// centre rays can meet `b`; `None` when no such pixel exists.
///
/// Each face is clipped to the view frustum (a near plane and the four planes
/// through the outermost pixel centres), so the rectangle bounds the part of
/// the box the image can see, not the unbounded projection of a box that
/// crosses the camera plane.
pub fn project_box(
    b: &Box3,
    camera_to_world: &IsometryMatrix3<f64>,
    k: &Intrinsics,
    size: (u32, u32),
) -> Option<PixelRect> {
    let (w, h) = size;
    if w == 0 || h == 0 {
        return None;
    }
    let world_to_camera = camera_to_world.inverse();
    let corners = b.corners().map(|c| world_to_camera * c);
    // Near plane far below any geometric scale of this box and camera, so
    // only points practically on the camera plane are cut.
    let reach = corners.iter().fold(0.0f64, |a, c| a.max(c.coords.abs().max()));
    let near = 1e-9 * reach.max(f64::MIN_POSITIVE);
    // Planes a hair beyond the outermost pixel centres (rounding keeps them).
    const MARGIN: f64 = 1e-3;
    let (u0, u1, v0, v1) = (-MARGIN, w as f64 - 1.0 + MARGIN, -MARGIN, h as f64 - 1.0 + MARGIN);
    let planes = [
        Vector4::new(0.0, 0.0, 1.0, -near),
        Vector4::new(k.fx, 0.0, k.cx - u0, 0.0),
        Vector4::new(-k.fx, 0.0, u1 - k.cx, 0.0),
        Vector4::new(0.0, k.fy, k.cy - v0, 0.0),
        Vector4::new(0.0, -k.fy, v1 - k.cy, 0.0),
    ];
    let (mut lo, mut hi) = ((f64::INFINITY, f64::INFINITY), (f64::NEG_INFINITY, f64::NEG_INFINITY));
    let (mut poly, mut next) = (Vec::with_capacity(12), Vec::with_capacity(12));
    for face in &FACES {
        poly.clear();
        poly.extend(face.iter().map(|&i| corners[i]));
        for &plane in &planes {
            clip(&poly, plane, &mut next);
            std::mem::swap(&mut poly, &mut next);
            if poly.is_empty() {
                break;
            }
        }
        for p in &poly {
            let z = p.z.max(near);
            let (u, v) = (k.fx * p.x / z + k.cx, k.fy * p.y / z + k.cy);
            lo = (lo.0.min(u), lo.1.min(v));
            hi = (hi.0.max(u), hi.1.max(v));
        }
    }
    if !(lo.0 <= hi.0 && lo.1 <= hi.1) {
        return None;
    }
    // Pixel centre i is covered when lo <= i <= hi; a hair of slack keeps
    // centres exactly on a silhouette edge.
    const SLACK: f64 = 1e-6;
    let first = |v: f64, n: u32| (v - SLACK).ceil().clamp(0.0, n as f64) as u32;
    let end = |v: f64, n: u32| ((v + SLACK).floor() + 1.0).clamp(0.0, n as f64) as u32;
    let rect = PixelRect {
        x0: first(lo.0, w),
        y0: first(lo.1, h),
        x1: end(hi.0, w),
        y1: end(hi.1, h),
    };
    (rect.x0 < rect.x1 && rect.y0 < rect.y1).then_some(rect)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::boxes::{BoxClassifier, BoxSet};
    use crate::rng::Rng;
    use nalgebra::{Quaternion, Rotation3, Translation3, UnitQuaternion, Vector3};

    fn random_rotation(rng: &mut Rng) -> Rotation3<f64> {
        let (x, y, z, w) = (rng.normal(), rng.normal(), rng.normal(), rng.normal());
        UnitQuaternion::from_quaternion(Quaternion::new(w, x, y, z)).to_rotation_matrix()
    }

    fn camera_pose(rng: &mut Rng) -> IsometryMatrix3<f64> {
        let r = random_rotation(rng);
        let t = Translation3::new(rng.range(-1.0, 1.0), rng.range(-1.0, 1.0), rng.range(-1.0, 1.0));
        IsometryMatrix3::from_parts(t, r)
    }

    /// Every pixel whose centre ray meets the box lies in the rectangle, and
    /// the rectangle is tight (within a pixel of the hit pixels' bounds).
    #[test]
    fn rectangle_holds_every_pixel_whose_ray_hits_and_is_tight() {
        let k = Intrinsics {
            fx: 60.0,
            fy: 62.0,
            cx: 39.7,
            cy: 30.2,
        };
        let (w, h) = (80u32, 60u32);
        let mut rng = Rng::new(21, 0);
        let (mut crossing, mut behind, mut visible) = (0, 0, 0);
        for _ in 0..400 {
            let pose = camera_pose(&mut rng);
            let origin = Point3::from(pose.translation.vector);
            let forward = pose.rotation * Vector3::z();
            // Boxes around the camera: in front, behind and across its plane.
            let center =
                origin + forward * rng.range(-1.5, 3.0) + Vector3::new(rng.normal(), rng.normal(), rng.normal()) * 0.5;
            let b = Box3 {
                label: "b".into(),
                instance_id: 1,
                center,
                size: Vector3::new(rng.range(0.05, 1.2), rng.range(0.05, 1.2), rng.range(0.05, 1.2)),
                rotation: random_rotation(&mut rng),
            };
            let z: Vec<f64> = b.corners().iter().map(|c| (c - origin).dot(&forward)).collect();
            let crosses = z.iter().any(|&z| z < 0.0) && z.iter().any(|&z| z > 0.0);
            crossing += crosses as usize;
            let set = BoxSet::from_boxes(vec![b.clone()]);
            let classifier = BoxClassifier::new(&set);
            let rect = project_box(&b, &pose, &k, (w, h));
            let mut hit_bounds: Option<PixelRect> = None;
            let rot = pose.rotation;
            for y in 0..h {
                for x in 0..w {
                    let dir = rot * k.unproject(x as f64, y as f64);
                    if classifier.ray_interval(&origin, &dir).is_some() {
                        let r = rect.unwrap_or_else(|| panic!("pixel ({x}, {y}) hits but no rectangle"));
                        assert!(r.contains(x, y), "pixel ({x}, {y}) outside {r:?}");
                        let p = PixelRect {
                            x0: x,
                            y0: y,
                            x1: x + 1,
                            y1: y + 1,
                        };
                        hit_bounds = Some(hit_bounds.map_or(p, |q| q.union(&p)));
                    }
                }
            }
            match (rect, hit_bounds) {
                (None, _) => behind += z.iter().all(|&z| z <= 0.0) as usize,
                (Some(r), Some(hb)) => {
                    visible += 1;
                    assert!(
                        r.x0 + 1 >= hb.x0 && r.y0 + 1 >= hb.y0 && r.x1 <= hb.x1 + 1 && r.y1 <= hb.y1 + 1,
                        "{r:?} vs hits {hb:?}"
                    );
                }
                (Some(r), None) => {
                    // A sliver between pixel centres may project without a hit.
                    assert!(r.area() <= 2 * (w + h) as u64 && !crosses, "{r:?} without any hit");
                }
            }
        }
        assert!(
            crossing > 50 && behind > 20 && visible > 100,
            "cases: crossing {crossing} behind {behind} visible {visible}"
        );
    }

    #[test]
    fn box_around_the_camera_covers_the_image_and_box_behind_is_none() {
        let k = Intrinsics {
            fx: 100.0,
            fy: 100.0,
            cx: 50.0,
            cy: 40.0,
        };
        let b = Box3 {
            label: "room".into(),
            instance_id: 1,
            center: Point3::origin(),
            size: Vector3::repeat(4.0),
            rotation: Rotation3::identity(),
        };
        assert_eq!(
            project_box(&b, &IsometryMatrix3::identity(), &k, (100, 80)),
            Some(PixelRect {
                x0: 0,
                y0: 0,
                x1: 100,
                y1: 80
            })
        );
        let behind = Box3 {
            center: Point3::new(0.0, 0.0, -3.0),
            size: Vector3::repeat(1.0),
            ..b.clone()
        };
        assert_eq!(project_box(&behind, &IsometryMatrix3::identity(), &k, (100, 80)), None);
        // 1 m box at 5 m straight ahead: 20 px wide around the principal point.
        let ahead = Box3 {
            center: Point3::new(0.0, 0.0, 5.5),
            size: Vector3::repeat(1.0),
            ..b
        };
        assert_eq!(
            project_box(&ahead, &IsometryMatrix3::identity(), &k, (100, 80)),
            Some(PixelRect {
                x0: 40,
                y0: 30,
                x1: 61,
                y1: 51
            })
        );
    }
}
