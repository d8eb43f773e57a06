//! The global-to-local similarity: world (metres, scan frame) to the NeRF's
//! local frame, where the scene's oriented box sits centred in [0, 1]^3 with
//! a margin. `local = scale * (rotation * world) + translation`.
//!
//! Orientation (as in Inspection-NeRF, an oriented box of the point cloud):
//! the robust point set is reduced to the mean points of the occupied cells
//! of a 64^3 grid (so densely filmed areas do not dominate); its principal
//! axes, and the world axes, each start a descent on the volume of the
//! rotated bounding box, and the smaller result wins. [`Orientation::Auto`]
//! keeps the world axes unless the oriented box is at least 10 % smaller in
//! volume (an unrotated frame is easier to read). User (`bbox.txt`) and
//! frustum-fallback bounds keep the world axes.

use super::bounds::{pad_relative, robust_box};
use super::orient::{min_volume_rotation, principal_axes};
use super::{BoundsSource, DAabb, GeometryError, SceneBounds};
use nalgebra::{IsometryMatrix3, Point3, Quaternion, Similarity3, Translation3, UnitQuaternion, Vector3};
use std::collections::HashMap;

/// Cells per side of the grid the orientation is measured on.
const ORIENT_CELLS: f64 = 64.0;
/// Auto orientation rotates only if that shrinks the box volume below this fraction.
const ROTATE_IF_VOLUME_BELOW: f64 = 0.9;

/// How to orient the local frame.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Default)]
pub enum Orientation {
    /// The oriented box when it is clearly smaller, else the world axes.
    #[default]
    Auto,
    /// Always the oriented (minimal-volume) box of the depth points.
    Oriented,
    /// Always the world axes.
    Identity,
}

/// Options of the normalisation.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct NormalizeOptions {
    /// Free space left on each side of the unit cube, in local units.
    pub margin: f64,
    /// How to orient the local axes.
    pub orientation: Orientation,
}

impl Default for NormalizeOptions {
    fn default() -> Self {
        NormalizeOptions {
            margin: 0.05,
            orientation: Orientation::Auto,
        }
    }
}

/// Similarity `local = scale * (rotation * world) + translation` (f64).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct SceneTransform {
    /// World to local.
    pub world_to_local: Similarity3<f64>,
}

/// The normalisation of one scene.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Normalization {
    /// World-to-local similarity.
    pub transform: SceneTransform,
    /// The scene's box in local coordinates (inside [margin, 1 - margin]^3).
    pub local_aabb: DAabb,
    /// Whether the oriented box was used (else the world axes).
    pub rotated: bool,
}

impl SceneTransform {
    /// Number of f64 values in [`Self::to_array`].
    pub const ARRAY_LEN: usize = 8;

    /// The identity mapping.
    pub fn identity() -> SceneTransform {
        SceneTransform::new(UnitQuaternion::identity(), Vector3::zeros(), 1.0)
    }

    /// `local = scale * (rotation * world) + translation`.
    pub fn new(rotation: UnitQuaternion<f64>, translation: Vector3<f64>, scale: f64) -> SceneTransform {
        SceneTransform {
            world_to_local: Similarity3::from_parts(Translation3::from(translation), rotation, scale),
        }
    }

    /// World-to-local rotation.
    #[inline]
    pub fn rotation(&self) -> UnitQuaternion<f64> {
        self.world_to_local.isometry.rotation
    }

    /// Local-frame offset, applied after rotation and scaling.
    #[inline]
    pub fn translation(&self) -> Vector3<f64> {
        self.world_to_local.isometry.translation.vector
    }

    /// Local units per metre.
    #[inline]
    pub fn scale(&self) -> f64 {
        self.world_to_local.scaling()
    }

    /// Map that rotates by `rotation` and places `rotated_box` (a box in
    /// rotated world coordinates, metres) centred in [0, 1]^3, its longest
    /// edge spanning `1 - 2 * margin`.
    pub fn fit(
        rotation: UnitQuaternion<f64>,
        rotated_box: &DAabb,
        margin: f64,
    ) -> Result<SceneTransform, GeometryError> {
        let extent = rotated_box.max_extent();
        if !(rotated_box.is_valid() && extent > 0.0) {
            return Err(GeometryError::InvalidTransform(format!(
                "cannot fit a box with corners {rotated_box:?}"
            )));
        }
        if !(0.0..0.5).contains(&margin) {
            return Err(GeometryError::InvalidTransform(format!(
                "margin {margin} is outside [0, 0.5)"
            )));
        }
        let scale = (1.0 - 2.0 * margin) / extent;
        let translation = Vector3::repeat(0.5) - rotated_box.center().coords * scale;
        Ok(SceneTransform::new(
            UnitQuaternion::new_normalize(rotation.into_inner()),
            translation,
            scale,
        ))
    }

    /// World point (metres) to local coordinates.
    #[inline]
    pub fn world_to_local_point(&self, p: &Point3<f64>) -> Point3<f64> {
        self.world_to_local.transform_point(p)
    }

    /// Local point to world coordinates (metres).
    #[inline]
    pub fn local_to_world_point(&self, p: &Point3<f64>) -> Point3<f64> {
        self.world_to_local.inverse_transform_point(p)
    }

    /// World direction to local (rotation only; lengths are kept).
    #[inline]
    pub fn world_to_local_direction(&self, d: &Vector3<f64>) -> Vector3<f64> {
        self.rotation() * d
    }

    /// Local direction to world (rotation only; lengths are kept).
    #[inline]
    pub fn local_to_world_direction(&self, d: &Vector3<f64>) -> Vector3<f64> {
        self.rotation().inverse_transform_vector(d)
    }

    /// Metres to local units.
    #[inline]
    pub fn world_to_local_distance(&self, metres: f64) -> f64 {
        metres * self.scale()
    }

    /// Local units to metres.
    #[inline]
    pub fn local_to_world_distance(&self, local: f64) -> f64 {
        local / self.scale()
    }

    /// World camera-to-world pose to a local camera-to-local pose (the
    /// rotation part stays orthonormal; the camera axes are unchanged).
    pub fn world_to_local_pose(&self, camera_to_world: &IsometryMatrix3<f64>) -> IsometryMatrix3<f64> {
        let r = self.rotation().to_rotation_matrix() * camera_to_world.rotation;
        let t = self.world_to_local_point(&Point3::from(camera_to_world.translation.vector));
        IsometryMatrix3::from_parts(Translation3::from(t.coords), r)
    }

    /// Local camera-to-local pose back to a world camera-to-world pose.
    pub fn local_to_world_pose(&self, camera_to_local: &IsometryMatrix3<f64>) -> IsometryMatrix3<f64> {
        let r = self.rotation().inverse().to_rotation_matrix() * camera_to_local.rotation;
        let t = self.local_to_world_point(&Point3::from(camera_to_local.translation.vector));
        IsometryMatrix3::from_parts(Translation3::from(t.coords), r)
    }

    /// The inverse similarity (local to world).
    pub fn inverse(&self) -> SceneTransform {
        SceneTransform {
            world_to_local: self.world_to_local.inverse(),
        }
    }

    /// `[qx, qy, qz, qw, tx, ty, tz, scale]` for the model file.
    pub fn to_array(&self) -> [f64; Self::ARRAY_LEN] {
        let q = self.rotation();
        let t = self.translation();
        [q.i, q.j, q.k, q.w, t.x, t.y, t.z, self.scale()]
    }

    /// Read [`Self::to_array`] back, checking that it is a valid similarity.
    pub fn from_array(a: &[f64; Self::ARRAY_LEN]) -> Result<SceneTransform, GeometryError> {
        if a.iter().any(|x| !x.is_finite()) {
            return Err(GeometryError::InvalidTransform(format!("non-finite value in {a:?}")));
        }
        let q = Quaternion::new(a[3], a[0], a[1], a[2]);
        if (q.norm() - 1.0).abs() > 1e-6 {
            return Err(GeometryError::InvalidTransform(format!(
                "rotation quaternion has length {}",
                q.norm()
            )));
        }
        if a[7] <= 0.0 {
            return Err(GeometryError::InvalidTransform(format!(
                "scale {} is not positive",
                a[7]
            )));
        }
        // Keep an already unit quaternion bit for bit, so save/load/save is exact.
        let rotation = if (q.norm_squared() - 1.0).abs() < 1e-14 {
            UnitQuaternion::new_unchecked(q)
        } else {
            UnitQuaternion::new_normalize(q)
        };
        Ok(SceneTransform::new(rotation, Vector3::new(a[4], a[5], a[6]), a[7]))
    }
}

/// Fit the world-to-local similarity of a scene (module doc for the rule).
pub fn normalize(bounds: &SceneBounds, options: &NormalizeOptions) -> Result<Normalization, GeometryError> {
    let world_box = bounds.aabb;
    let mut chosen = (UnitQuaternion::identity(), world_box, false);
    let point_box = bounds.stats.point_box.filter(|_| bounds.source == BoundsSource::Depth);
    if let (Some(point_box), true) = (point_box, options.orientation != Orientation::Identity) {
        let inliers: Vec<Point3<f64>> = bounds
            .samples
            .iter()
            .copied()
            .filter(|p| point_box.contains(p))
            .collect();
        let cells = cell_centroids(&inliers, &point_box);
        if cells.len() >= 2 {
            let mut best = min_volume_rotation(&cells, UnitQuaternion::identity());
            if let Some(axes) = principal_axes(&cells) {
                let pca = min_volume_rotation(&cells, UnitQuaternion::from_rotation_matrix(&axes.inverse()));
                if pca.1 < best.1 {
                    best = pca;
                }
            }
            let rotation = best.0;
            let opts = &bounds.options;
            let rotated = robust_box(
                &bounds.samples,
                |p| rotation * p,
                opts.low_percentile,
                opts.high_percentile,
            );
            if let Some(b) = rotated {
                let b = bounds.cameras.iter().fold(b, |b, c| b.including(&(rotation * c)));
                let b = pad_relative(&b, opts.padding);
                let smaller = b.volume() < ROTATE_IF_VOLUME_BELOW * world_box.volume();
                if options.orientation == Orientation::Oriented || smaller {
                    chosen = (rotation, b, true);
                }
            }
        }
    }
    let (rotation, rotated_box, rotated) = chosen;
    let transform = SceneTransform::fit(rotation, &rotated_box, options.margin)?;
    let (s, t) = (transform.scale(), transform.translation());
    let local_aabb = DAabb::new(rotated_box.min * s + t, rotated_box.max * s + t);
    Ok(Normalization {
        transform,
        local_aabb,
        rotated,
    })
}

/// Mean point of every occupied cell of a `ORIENT_CELLS`^3 grid over `b`, in
/// cell order (deterministic).
fn cell_centroids(points: &[Point3<f64>], b: &DAabb) -> Vec<Point3<f64>> {
    let cell = b.max_extent() / ORIENT_CELLS;
    if !(cell.is_finite() && cell > 0.0) {
        return points.to_vec();
    }
    let mut cells: HashMap<[i64; 3], (Vector3<f64>, u64)> = HashMap::new();
    for p in points {
        let k = ((p - b.min) / cell).map(|x| x.floor() as i64).into();
        let e = cells.entry(k).or_insert((Vector3::zeros(), 0));
        e.0 += p.coords;
        e.1 += 1;
    }
    let mut sorted: Vec<_> = cells.into_iter().collect();
    sorted.sort_unstable_by_key(|(k, _)| *k);
    sorted
        .into_iter()
        .map(|(_, (sum, n))| Point3::from(sum / n as f64))
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::rng::Rng;

    fn random_transform(rng: &mut Rng) -> SceneTransform {
        let q = UnitQuaternion::new_normalize(Quaternion::new(rng.normal(), rng.normal(), rng.normal(), rng.normal()));
        let t = Vector3::new(rng.normal(), rng.normal(), rng.normal());
        SceneTransform::new(q, t, rng.range(0.01, 100.0))
    }

    #[test]
    fn composition_inverse_and_matrix_agree() {
        let mut rng = Rng::new(3, 0);
        for _ in 0..100 {
            let (a, b) = (random_transform(&mut rng), random_transform(&mut rng));
            let p = Point3::from(Vector3::new(rng.normal(), rng.normal(), rng.normal()) * 10.0);
            let tol = 1e-9 * (1.0 + a.scale() * b.scale() * p.coords.norm());
            let ab = SceneTransform {
                world_to_local: a.world_to_local * b.world_to_local,
            };
            assert!((ab.world_to_local_point(&p) - a.world_to_local_point(&b.world_to_local_point(&p))).norm() < tol);
            let m = a.world_to_local.to_homogeneous();
            assert!((m.transform_point(&p) - a.world_to_local_point(&p)).norm() < tol);
            let inverse = a.inverse();
            assert!(
                (inverse.world_to_local_point(&a.world_to_local_point(&p)) - p).norm() < 1e-9 * (1.0 + p.coords.norm())
            );
            assert!((a.local_to_world_point(&a.world_to_local_point(&p)) - p).norm() < 1e-9 * (1.0 + p.coords.norm()));
        }
    }

    #[test]
    fn array_round_trip_and_invalid_arrays() {
        let t = random_transform(&mut Rng::new(4, 0));
        assert_eq!(
            SceneTransform::from_array(&t.to_array()).unwrap().to_array(),
            t.to_array()
        );
        let mut bad = t.to_array();
        bad[7] = 0.0;
        assert!(SceneTransform::from_array(&bad).is_err());
        bad = t.to_array();
        bad[0] += 0.5;
        assert!(SceneTransform::from_array(&bad).is_err());
        bad = t.to_array();
        bad[5] = f64::NAN;
        assert!(SceneTransform::from_array(&bad).is_err());
    }

    #[test]
    fn fit_centres_the_box_with_the_margin() {
        let b = DAabb::new(Point3::new(-3.0, 10.0, 0.0), Point3::new(1.0, 12.0, 1.0));
        let id = UnitQuaternion::identity();
        let t = SceneTransform::fit(id, &b, 0.05).unwrap();
        let lo = t.world_to_local_point(&b.min);
        let hi = t.world_to_local_point(&b.max);
        assert!((lo - Point3::new(0.05, 0.275, 0.3875)).norm() < 1e-12, "{lo}");
        assert!((hi - Point3::new(0.95, 0.725, 0.6125)).norm() < 1e-12, "{hi}");
        let one = Point3::new(1.0, 1.0, 1.0);
        assert!(SceneTransform::fit(id, &DAabb::new(one, one), 0.05).is_err());
        assert!(SceneTransform::fit(id, &b, 0.5).is_err());
    }

    #[test]
    fn rotated_room_is_aligned_with_its_walls() {
        use crate::poses::test_scene::Room;
        use crate::poses::{scene_bounds, BoundsOptions};
        let room = Room {
            rotation: UnitQuaternion::from_scaled_axis(Vector3::z() * 0.5)
                * UnitQuaternion::from_scaled_axis(Vector3::x() * 0.2),
            ..Room::default()
        };
        let bounds = scene_bounds(&room.scan(), &BoundsOptions::default()).unwrap();
        let n = normalize(&bounds, &NormalizeOptions::default()).unwrap();
        assert!(n.rotated);
        // The oriented box is the padded room: 4 x 3 x 2.5 m plus 2 x 5 % of 4 m.
        let e = n.local_aabb.extent() / n.transform.scale();
        assert!((e - Vector3::new(4.4, 3.4, 2.9)).amax() < 0.05, "{e}");
        // Room axes map onto the local axes.
        for axis in [Vector3::x(), Vector3::y(), Vector3::z()] {
            let local = n.transform.world_to_local_direction(&(room.rotation * axis));
            assert!(local.dot(&axis) > 0.999, "{axis} -> {local}");
        }
        let straight = normalize(
            &scene_bounds(&Room::default().scan(), &BoundsOptions::default()).unwrap(),
            &NormalizeOptions::default(),
        );
        assert!(!straight.unwrap().rotated, "an axis-aligned room keeps the world axes");
    }

    /// Bounds as `scene_bounds` would make them from these points and cameras.
    fn bounds_from(samples: Vec<Point3<f64>>, cameras: Vec<Point3<f64>>) -> SceneBounds {
        use crate::poses::{BoundsOptions, PointStats};
        let options = BoundsOptions::default();
        let point_box = robust_box(&samples, |p| *p, options.low_percentile, options.high_percentile);
        let b = cameras.iter().fold(point_box.unwrap(), |b, c| b.including(c));
        SceneBounds {
            aabb: pad_relative(&b, options.padding),
            source: BoundsSource::Depth,
            stats: PointStats {
                point_box,
                ..PointStats::default()
            },
            samples,
            cameras,
            options,
        }
    }

    #[test]
    fn planar_and_collinear_scenes_normalise_to_finite_thin_boxes() {
        // A tilted plane, cameras in it too: no thickness at all.
        let mut rng = Rng::new(8, 0);
        let plane = |x: f64, y: f64| Point3::new(x, y, 0.3 * x - 0.2 * y);
        let samples: Vec<Point3<f64>> = (0..20_000)
            .map(|_| plane(rng.range(-2.0, 2.0), rng.range(-1.0, 1.0)))
            .collect();
        let cameras = vec![plane(-0.5, 0.0), plane(0.5, 0.2)];
        let b = bounds_from(samples.clone(), cameras);
        let n = normalize(&b, &NormalizeOptions::default()).unwrap();
        assert!(n.rotated, "the plane's own frame is much thinner than the world box");
        assert!(DAabb::UNIT.contains_box(&n.local_aabb));
        let e = n.local_aabb.extent();
        assert!(e.min() < 0.2 * e.max(), "{e}");
        assert!(samples
            .iter()
            .all(|p| n.local_aabb.padded(1e-9).contains(&n.transform.world_to_local_point(p))));
        // A line of points: still a valid similarity.
        let line: Vec<Point3<f64>> = (0..1000)
            .map(|i| Point3::new(1.0, 2.0, -1.0) * (i as f64 / 999.0))
            .collect();
        let n = normalize(&bounds_from(line, vec![Point3::origin()]), &NormalizeOptions::default()).unwrap();
        assert!(n.transform.scale().is_finite() && n.transform.scale() > 0.0);
        assert!(DAabb::UNIT.contains_box(&n.local_aabb));
    }
}
