//! Axis-aligned boxes in f32 ([`Aabb`], for the renderer's hot ray test) and
//! f64 ([`DAabb`], for scene geometry), with a slab ray test that never
//! produces NaN and treats the box as closed (faces belong to it).

use nalgebra::{Point3, Vector3};

/// Where a line crosses a box: parameters of entry and exit and the axes
/// of the faces crossed there (see `line_crossing`).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct SlabCrossing<T> {
    pub t_near: T,
    pub t_far: T,
    pub near_axis: usize,
    pub far_axis: usize,
}

macro_rules! aabb_type {
    ($name:ident, $t:ident, $doc:literal) => {
        #[doc = $doc]
        #[derive(Clone, Copy, Debug, Default, PartialEq)]
        pub struct $name {
            pub min: Point3<$t>,
            pub max: Point3<$t>,
        }

        impl $name {
            /// Box from its two corners (not checked; see [`Self::is_valid`]).
            #[inline]
            pub const fn new(min: Point3<$t>, max: Point3<$t>) -> Self {
                Self { min, max }
            }

            /// The unit cube [0, 1]^3.
            pub const UNIT: Self = Self {
                min: Point3::new(0.0, 0.0, 0.0),
                max: Point3::new(1.0, 1.0, 1.0),
            };

            /// Smallest box holding every finite point; `None` when there is none.
            pub fn from_points<I: IntoIterator<Item = Point3<$t>>>(points: I) -> Option<Self> {
                let mut out: Option<Self> = None;
                for p in points.into_iter().filter(|p| p.iter().all(|x| x.is_finite())) {
                    out = Some(match out {
                        None => Self::new(p, p),
                        Some(b) => b.including(&p),
                    });
                }
                out
            }

            /// Finite corners with `min <= max` on every axis.
            #[inline]
            pub fn is_valid(&self) -> bool {
                self.min.iter().chain(self.max.iter()).all(|x| x.is_finite())
                    && (0..3).all(|a| self.min[a] <= self.max[a])
            }

            /// Edge lengths.
            #[inline]
            pub fn extent(&self) -> Vector3<$t> {
                self.max - self.min
            }

            /// Longest edge length.
            #[inline]
            pub fn max_extent(&self) -> $t {
                self.extent().max()
            }

            /// Centre point.
            #[inline]
            pub fn center(&self) -> Point3<$t> {
                nalgebra::center(&self.min, &self.max)
            }

            /// Volume (0 for flat boxes).
            #[inline]
            pub fn volume(&self) -> $t {
                let e = self.extent().sup(&Vector3::zeros());
                e.x * e.y * e.z
            }

            /// Whether `p` lies inside or on the boundary.
            #[inline]
            pub fn contains(&self, p: &Point3<$t>) -> bool {
                (0..3).all(|a| self.min[a] <= p[a] && p[a] <= self.max[a])
            }

            /// Whether `other` lies entirely inside this box.
            #[inline]
            pub fn contains_box(&self, other: &Self) -> bool {
                self.contains(&other.min) && self.contains(&other.max)
            }

            /// This box grown to hold `p`.
            #[inline]
            pub fn including(&self, p: &Point3<$t>) -> Self {
                Self::new(self.min.inf(p), self.max.sup(p))
            }

            /// Smallest box holding both boxes.
            #[inline]
            pub fn union(&self, other: &Self) -> Self {
                Self::new(self.min.inf(&other.min), self.max.sup(&other.max))
            }

            /// Overlap of both boxes; `None` when they are disjoint.
            pub fn intersection(&self, other: &Self) -> Option<Self> {
                let b = Self::new(self.min.sup(&other.min), self.max.inf(&other.max));
                (0..3).all(|a| b.min[a] <= b.max[a]).then_some(b)
            }

            /// This box grown by `margin` on every side.
            #[inline]
            pub fn padded(&self, margin: $t) -> Self {
                Self::new(
                    self.min - Vector3::repeat(margin),
                    self.max + Vector3::repeat(margin),
                )
            }

            /// The eight corners, bit i of the index selecting max on axis i.
            pub fn corners(&self) -> [Point3<$t>; 8] {
                std::array::from_fn(|i| {
                    Point3::new(
                        if i & 1 == 0 { self.min.x } else { self.max.x },
                        if i & 2 == 0 { self.min.y } else { self.max.y },
                        if i & 4 == 0 { self.min.z } else { self.max.z },
                    )
                })
            }

            /// Where the whole line `origin + t * dir` (any sign of t) is
            /// inside the closed box, with the axes of the faces it enters
            /// and leaves by; `None` for a miss. Axes the line runs parallel
            /// to (a zero component, or one so small its reciprocal
            /// overflows) only decide hit or miss, so nothing is NaN.
            #[inline]
            pub fn line_crossing(&self, origin: &Point3<$t>, dir: &Vector3<$t>) -> Option<SlabCrossing<$t>> {
                let (o, d) = (origin, dir);
                let (lo, hi) = (self.min, self.max);
                let mut c = SlabCrossing {
                    t_near: $t::NEG_INFINITY,
                    t_far: $t::INFINITY,
                    near_axis: 0,
                    far_axis: 0,
                };
                for a in 0..3 {
                    // One reciprocal per axis: this runs for every training ray.
                    let inv = 1.0 / d[a];
                    if d[a] == 0.0 || !inv.is_finite() {
                        if !(o[a] >= lo[a] && o[a] <= hi[a]) {
                            return None;
                        }
                        continue;
                    }
                    let (ta, tb) = ((lo[a] - o[a]) * inv, (hi[a] - o[a]) * inv);
                    let (near, far) = if ta > tb { (tb, ta) } else { (ta, tb) };
                    if near > c.t_near {
                        c.t_near = near;
                        c.near_axis = a;
                    }
                    if far < c.t_far {
                        c.t_far = far;
                        c.far_axis = a;
                    }
                }
                (c.t_near <= c.t_far).then_some(c)
            }

            /// Parameters `[t_near, t_far]` where the ray `origin + t * dir`
            /// (t >= 0) is inside the closed box, or `None` for a miss.
            ///
            /// `t_near` is 0 for origins inside; both ends are finite and
            /// never NaN. Rays that only touch an edge or run along a face
            /// count as hits. A zero direction, a non-finite input or an
            /// invalid box is a miss.
            #[inline]
            pub fn ray_interval(&self, origin: &Point3<$t>, dir: &Vector3<$t>) -> Option<($t, $t)> {
                if !self.is_valid() || !origin.iter().chain(dir.iter()).all(|x| x.is_finite()) {
                    return None;
                }
                let c = self.line_crossing(origin, dir)?;
                let t_near = c.t_near.max(0.0);
                // `+ 0.0` turns a -0.0 into +0.0.
                (t_near <= c.t_far && c.t_far.is_finite() && t_near.is_finite()).then_some((t_near + 0.0, c.t_far))
            }
        }
    };
}

aabb_type!(Aabb, f32, "Axis-aligned box in f32 (renderer, local units).");
aabb_type!(
    DAabb,
    f64,
    "Axis-aligned box in f64 (scene geometry, metres or local units)."
);

impl From<DAabb> for Aabb {
    fn from(b: DAabb) -> Self {
        Aabb::new(b.min.cast::<f32>(), b.max.cast::<f32>())
    }
}

impl From<Aabb> for DAabb {
    fn from(b: Aabb) -> Self {
        DAabb::new(b.min.cast::<f64>(), b.max.cast::<f64>())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::rng::Rng;
    use nalgebra::{Point3 as P, Vector3 as V};

    fn unit() -> DAabb {
        DAabb::UNIT
    }

    #[test]
    fn ray_from_outside_enters_and_leaves_at_the_faces() {
        let (t0, t1) = unit().ray_interval(&P::new(-1.0, 0.5, 0.5), &V::x()).unwrap();
        assert_eq!((t0, t1), (1.0, 2.0));
        let (t0, t1) = unit()
            .ray_interval(&P::new(2.0, 0.5, 0.5), &V::new(-2.0, 0.0, 0.0))
            .unwrap();
        assert_eq!((t0, t1), (0.5, 1.0));
    }

    #[test]
    fn origin_inside_clamps_near_to_zero() {
        let (t0, t1) = unit()
            .ray_interval(&P::new(0.5, 0.5, 0.5), &V::new(0.0, 0.0, 1.0))
            .unwrap();
        assert_eq!(t0, 0.0);
        assert!(t0.is_sign_positive());
        assert_eq!(t1, 0.5);
    }

    #[test]
    fn looking_away_misses() {
        assert_eq!(unit().ray_interval(&P::new(-1.0, 0.5, 0.5), &-V::x()), None);
        assert_eq!(unit().ray_interval(&P::new(2.0, 2.0, 2.0), &V::repeat(1.0)), None);
    }

    #[test]
    fn zero_and_negative_zero_components_inside_the_slab_hit() {
        for d in [V::new(1.0, 0.0, 0.0), V::new(1.0, -0.0, -0.0)] {
            let (t0, t1) = unit().ray_interval(&P::new(-1.0, 0.25, 0.75), &d).unwrap();
            assert_eq!((t0, t1), (1.0, 2.0));
        }
        for d in [V::new(0.0, 1.0, 0.0), V::new(-0.0, 1.0, 0.0)] {
            assert_eq!(unit().ray_interval(&P::new(1.5, -1.0, 0.5), &d), None);
        }
    }

    #[test]
    fn ray_along_a_face_with_origin_on_it_is_a_grazing_hit() {
        // Origin exactly on the x = 0 face, direction parallel to it.
        let hit = unit().ray_interval(&P::new(0.0, -1.0, 0.5), &V::new(-0.0, 1.0, 0.0));
        assert_eq!(hit, Some((1.0, 2.0)));
        // Along the x = 1, z = 1 edge.
        let hit = unit().ray_interval(&P::new(1.0, 3.0, 1.0), &V::new(0.0, -1.0, 0.0));
        assert_eq!(hit, Some((2.0, 3.0)));
        // Just outside the face: a miss.
        let o = P::new(-1e-12, -1.0, 0.5);
        assert_eq!(unit().ray_interval(&o, &V::y()), None);
    }

    #[test]
    fn ray_touching_only_an_edge_gives_a_point_interval() {
        // Passes through the edge x = 0, y = 1 at t = 1 and nowhere else.
        let hit = unit().ray_interval(&P::new(-1.0, 0.0, 0.5), &V::new(1.0, 1.0, 0.0));
        assert_eq!(hit, Some((1.0, 1.0)));
        // Same direction shifted off the edge: a miss.
        let hit = unit().ray_interval(&P::new(-1.0, 1.0, 0.5), &V::new(1.0, 1.0, 0.0));
        assert_eq!(hit, None);
    }

    #[test]
    fn degenerate_inputs_are_clean_misses() {
        let b = unit();
        assert_eq!(b.ray_interval(&P::new(0.5, 0.5, 0.5), &V::zeros()), None);
        assert_eq!(
            b.ray_interval(&P::new(0.5, 0.5, 0.5), &V::new(f64::NAN, 1.0, 0.0)),
            None
        );
        assert_eq!(b.ray_interval(&P::new(f64::NAN, 0.5, 0.5), &V::x()), None);
        assert_eq!(b.ray_interval(&P::new(f64::INFINITY, 0.5, 0.5), &-V::x()), None);
        let inverted = DAabb::new(P::new(1.0, 1.0, 1.0), P::origin());
        assert_eq!(inverted.ray_interval(&P::new(-1.0, -1.0, -1.0), &V::repeat(1.0)), None);
    }

    #[test]
    fn subnormal_and_huge_inputs_stay_finite_and_nan_free() {
        let b = Aabb::UNIT;
        // Origin on a face with a subnormal direction: 1/d would be inf; a
        // direction too small to move along any axis is a miss, like zero.
        assert_eq!(b.ray_interval(&P::new(0.0, 0.5, 0.5), &V::new(1e-40, 0.0, 0.0)), None);
        // With another axis moving, the subnormal one is parallel.
        let (t0, t1) = b
            .ray_interval(&P::new(0.0, 0.5, 0.5), &V::new(1e-40, 0.0, 1.0))
            .unwrap();
        assert_eq!((t0, t1), (0.0, 0.5));
        let (t0, t1) = b
            .ray_interval(&P::new(-1.0, 0.5, 0.5), &V::new(1e-40, 0.0, 0.0))
            .map_or((0.0, 0.0), |x| x);
        assert!(!t0.is_nan() && !t1.is_nan());
        let far = P::new(-f32::MAX, 0.5, 0.5);
        let hit = b.ray_interval(&far, &V::x());
        assert!(hit.is_none_or(|(a, c)| a.is_finite() && c.is_finite() && a <= c));
    }

    /// Brute-force reference: is the point at t inside, with a tolerance band
    /// of `eps` around the faces where the answer is not checked?
    fn classify(b: &DAabb, p: &P<f64>, eps: f64) -> Option<bool> {
        let inside = b.padded(-eps).contains(p);
        let outside = !b.padded(eps).contains(p);
        if inside {
            Some(true)
        } else if outside {
            Some(false)
        } else {
            None
        }
    }

    #[test]
    fn random_rays_match_a_brute_force_march() {
        let mut rng = Rng::new(42, 0);
        let mut hits = 0;
        for case in 0..2000 {
            let c = P::new(rng.range(-2.0, 2.0), rng.range(-2.0, 2.0), rng.range(-2.0, 2.0));
            let e = V::new(rng.range(0.1, 2.0), rng.range(0.1, 2.0), rng.range(0.1, 2.0));
            let b = DAabb::new(c - e, c + e);
            let mut o = P::new(rng.range(-5.0, 5.0), rng.range(-5.0, 5.0), rng.range(-5.0, 5.0));
            // Aim near the box half the time, else anywhere.
            let target = c + e.component_mul(&V::new(
                rng.range(-1.3, 1.3),
                rng.range(-1.3, 1.3),
                rng.range(-1.3, 1.3),
            ));
            let mut d = if rng.below(2) == 0 {
                (target - o) * rng.range(0.1, 3.0)
            } else {
                V::new(rng.normal(), rng.normal(), rng.normal())
            };
            // Axis-parallel rays, often with the origin inside the slab or
            // exactly on one of its faces.
            for a in 0..3 {
                if rng.below(4) == 0 {
                    d[a] = if rng.below(2) == 0 { 0.0 } else { -0.0 };
                    o[a] = match rng.below(4) {
                        0 => b.min[a],
                        1 => b.max[a],
                        2 => target[a],
                        _ => o[a],
                    };
                }
            }
            let got = b.ray_interval(&o, &d);
            let got32 = Aabb::from(b).ray_interval(&o.cast::<f32>(), &d.cast::<f32>());
            // The f32 box agrees with the f64 one up to rounding.
            match (got, got32) {
                (Some((a, c)), Some((a32, c32))) => {
                    let tol = 1e-4 * (1.0 + c.abs());
                    assert!(
                        (a - a32 as f64).abs() < tol && (c - c32 as f64).abs() < tol,
                        "case {case}"
                    );
                }
                (Some((a, c)), None) => assert!(c - a < 1e-4, "case {case}: f32 missed {got:?}"),
                (None, Some((a, c))) => assert!(c - a < 1e-4, "case {case}: f32 hit {got32:?}"),
                (None, None) => {}
            }
            let step = 1e-3 / d.norm().max(1e-9);
            let mut t = 0.0;
            while t < 20.0 / d.norm().max(1e-9) && d != V::zeros() {
                let p = o + d * t;
                // On-face origins of parallel rays sit in the tolerance band.
                match (classify(&b, &p, 1e-6), got) {
                    (Some(true), Some((t0, t1))) => assert!(t >= t0 - 1e-9 && t <= t1 + 1e-9, "case {case} t {t}"),
                    (Some(true), None) => panic!("case {case}: inside at t {t} but reported a miss"),
                    (Some(false), Some((t0, t1))) => assert!(t < t0 + 1e-6 || t > t1 - 1e-6, "case {case} t {t}"),
                    _ => {}
                }
                t += step;
            }
            if got.is_some() {
                hits += 1;
            }
        }
        assert!(hits > 200, "too few hits ({hits}) to mean anything");
    }

    #[test]
    fn from_points_ignores_non_finite_and_union_contains_both() {
        let one = P::new(1.0, 1.0, 1.0);
        let b = DAabb::from_points([one, P::new(f64::NAN, f64::NAN, f64::NAN), -one]).unwrap();
        assert_eq!(b, DAabb::new(-one, one));
        assert!(DAabb::from_points([P::new(f64::INFINITY, f64::INFINITY, f64::INFINITY)]).is_none());
        let u = b.union(&DAabb::new(P::new(2.0, 2.0, 2.0), P::new(3.0, 3.0, 3.0)));
        assert!(u.contains_box(&b) && u.contains(&P::new(3.0, 3.0, 3.0)));
        assert_eq!(b.volume(), 8.0);
        assert_eq!(b.corners()[5], P::new(1.0, -1.0, 1.0));
    }
}
