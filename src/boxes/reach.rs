//! Overlapping boxes: which object a contested surface point belongs to.
//!
//! Boxes of neighbouring objects overlap by their margins, so a point in
//! several boxes is often a face of the neighbour that a box merely
//! encloses. A box's object is the surface its box alone holds and what
//! that surface reaches in the image: neighbouring pixels that the box
//! also holds, with no depth step between them larger than a surface seen
//! obliquely makes. A contested pixel goes to the object nearest to it
//! along the surface (3D distance over pixel neighbours), the smaller box
//! on a tie: neighbours' margins overlap about equally, so on a surface
//! no depth step cuts, the objects' own surfaces are equally far where
//! the two objects meet. Where two objects touch, their surfaces meet in
//! a valley seen from the camera (most objects are convex): no object
//! reaches across one, and the pixels beside it that no object reached
//! go to the side of its deepest pair they lie on. A pixel no object
//! reaches stays with the smallest box (FORMATS.md section 2), and so does
//! a box's pixel where that box holds nothing alone in the frame and is
//! smaller than the nearest object's box: a box nested in another (a lid
//! on a crate) keeps its part.

use crate::scan::Intrinsics;
use nalgebra::Point3;
use std::cmp::Ordering;
use std::collections::BinaryHeap;

/// Pixels whose surface point lies in several boxes, with those boxes.
#[derive(Debug, Default)]
pub struct Contested {
    /// Per pixel of the frame: the pixel's index in `pixels`, or `NONE`.
    slot: Vec<u32>,
    pixels: Vec<usize>,
    /// Per contested pixel, the instance ids of the boxes holding its
    /// point, smallest box first.
    holders: Vec<Vec<u32>>,
}

impl Contested {
    const NONE: u32 = u32::MAX;

    /// Record pixel `index` of a frame of `frame_pixels` pixels as held by
    /// `holders` (at least two instance ids, smallest box first).
    pub fn push(&mut self, frame_pixels: usize, index: usize, holders: Vec<u32>) {
        if self.slot.is_empty() {
            self.slot = vec![Self::NONE; frame_pixels];
        }
        self.slot[index] = self.pixels.len() as u32;
        self.pixels.push(index);
        self.holders.push(holders);
    }

    /// Whether no pixel is contested.
    pub fn is_empty(&self) -> bool {
        self.pixels.is_empty()
    }

    fn slot_of(&self, pixel: usize) -> Option<usize> {
        match self.slot[pixel] {
            Self::NONE => None,
            s => Some(s as usize),
        }
    }
}

/// How surfaces meet between neighbouring pixels, for [`resolve`].
#[derive(Clone, Copy, Debug)]
pub struct SurfaceSteps {
    /// The frame's camera.
    pub camera: Intrinsics,
    /// Depth error of the surfaces, metres (rendered surfaces: a grid cell).
    pub surface_error_m: f64,
}

impl SurfaceSteps {
    /// Metres between neighbouring pixels' rays per metre of depth (1 / focal).
    fn footprint_per_m(&self) -> f64 {
        2.0 / (self.camera.fx + self.camera.fy)
    }

    /// Largest depth step between neighbouring pixels of one surface at
    /// depth `z` (see [`REACH_STEP_PIXELS`]).
    fn max_step(&self, z: f64) -> f64 {
        self.surface_error_m + REACH_STEP_PIXELS * z * self.footprint_per_m()
    }

    /// Whether the surface folds inward (a valley seen from the camera)
    /// between neighbouring pixels `p` and `q`: where two convex objects
    /// touch, or an object meets a face behind it. Judged over
    /// [`CREASE_REACH`] pixels on either side: the midpoint of p and q lies
    /// behind the chord of the outer points by more than a bend of
    /// [`CREASE_MIN_BEND_DEG`] makes and more than half the surface error
    /// (the band of an excluded plane, [`super::support`]). Every pair
    /// within the reach of a valley folds; `deepest` asks for the pair at
    /// its bottom (the crease), which folds more than the pairs beside it.
    fn folds_inward(&self, z: &[f64], width: usize, p: usize, q: usize, deepest: bool) -> bool {
        let height = z.len() / width;
        let (x, y) = ((p % width) as i64, (p / width) as i64);
        let (dx, dy) = ((q % width) as i64 - x, (q / width) as i64 - y);
        let sag_at = |i: i64| self.sag(z, width, height, (x + i * dx, y + i * dy), (dx, dy));
        sag_at(0).is_some_and(|(sag, bend)| {
            sag > bend
                && (!deepest
                    || [-1, 1]
                        .iter()
                        .all(|&i| sag_at(i).is_none_or(|(beside, _)| sag >= beside)))
        })
    }

    /// How far the midpoint of the pixel pair starting at `start` and going
    /// `step` lies behind the chord of the points [`CREASE_REACH`] pixels
    /// out on either side, and the least sag of a crease there, metres.
    fn sag(&self, z: &[f64], width: usize, height: usize, start: (i64, i64), step: (i64, i64)) -> Option<(f64, f64)> {
        let k = CREASE_REACH as i64;
        let at = |i: i64| -> Option<Point3<f64>> {
            let (x, y) = (start.0 + i * step.0, start.1 + i * step.1);
            if x < 0 || y < 0 || x >= width as i64 || y >= height as i64 {
                return None;
            }
            let depth = z[y as usize * width + x as usize];
            (depth > 0.0).then(|| Point3::from(self.camera.unproject(x as f64, y as f64) * depth))
        };
        // The outer points must lie on the same surfaces as p and q: no
        // depth step between neighbours on the way out.
        let on_surface = |from: i64, to: i64| -> Option<()> {
            let mut previous = at(from)?.z;
            for i in from + 1..=to {
                let z = at(i)?.z;
                self.across(previous, z)?;
                previous = z;
            }
            Some(())
        };
        on_surface(-k, 0)?;
        on_surface(1, 1 + k)?;
        let (a, p, q, b) = (at(-k)?, at(0)?, at(1)?, at(1 + k)?);
        let s = (k as f64 + 0.5) / (2 * k + 1) as f64;
        let chord = a + (b - a) * s;
        let mid = Point3::from((p.coords + q.coords) * 0.5);
        let sag = (mid - chord).dot(&mid.coords.normalize());
        let bend = 0.5 * (0.5 * CREASE_MIN_BEND_DEG.to_radians()).tan() * (b - a).norm();
        Some((sag, bend.max(0.5 * self.surface_error_m)))
    }

    /// Distance along the surface between neighbouring pixels at depths
    /// `a` and `b`, or `None` across a depth step (two surfaces).
    fn across(&self, a: f64, b: f64) -> Option<f64> {
        let near = a.min(b);
        let step = (a - b).abs();
        (step <= self.max_step(near)).then(|| (near * self.footprint_per_m()).hypot(step))
    }
}

/// Pixels on either side of a pixel pair over which a crease is judged.
const CREASE_REACH: usize = 3;

/// A fold of less than this (degrees) is a curved or noisy surface, not a crease.
const CREASE_MIN_BEND_DEG: f64 = 20.0;

/// Largest depth step, in pixel footprints, between neighbouring pixels of
/// one surface: a surface seen at up to 76 degrees from its normal
/// (tan 76 deg = 4) steps by less.
const REACH_STEP_PIXELS: f64 = 4.0;

/// Give each contested pixel of `mask` (row-major, `width` wide; every
/// contested pixel holds its smallest box's id) to the object nearest to it
/// along the surface (module doc). `z` is each pixel's surface depth.
pub fn resolve(mask: &mut [u16], z: &[f64], width: usize, contested: &Contested, steps: SurfaceSteps) {
    if contested.is_empty() || width == 0 {
        return;
    }
    let grid = PixelGrid {
        width,
        height: mask.len() / width,
    };
    let (mut nearest, seedless) = reach_from_own_surfaces(mask, z, grid, contested, &steps);
    fill_beside_valleys(mask, z, grid, contested, &steps, &mut nearest);
    for (slot, &p) in contested.pixels.iter().enumerate() {
        let holders = &contested.holders[slot];
        // A box whose object shows nothing alone keeps what it holds where
        // it is smaller than the nearest object's box (a lid on a crate),
        // and a pixel no object reaches stays with the smallest box.
        let winner = match nearest[slot] {
            None => holders[0],
            Some((_, id)) => {
                let rank = |id: &u32| holders.iter().position(|h| h == id);
                seedless
                    .iter()
                    .filter(|s| holders.contains(s))
                    .min_by_key(|s| rank(s))
                    .filter(|s| rank(s) < rank(&id))
                    .copied()
                    .unwrap_or(id)
            }
        };
        mask[p] = winner as u16;
    }
}

/// The size of a frame's pixel grid, for its 4-neighbours.
#[derive(Clone, Copy, Debug)]
struct PixelGrid {
    width: usize,
    height: usize,
}

impl PixelGrid {
    fn neighbours(self, p: usize) -> impl Iterator<Item = usize> {
        let (x, y) = (p % self.width, p / self.width);
        [
            (x > 0).then(|| p - 1),
            (x + 1 < self.width).then(|| p + 1),
            (y > 0).then(|| p - self.width),
            (y + 1 < self.height).then(|| p + self.width),
        ]
        .into_iter()
        .flatten()
    }
}

/// Per contested pixel, the nearest object that reaches it from the surface
/// its box alone holds (distance, instance id), without crossing a depth
/// step or a valley; and the boxes that hold nothing alone in the frame.
fn reach_from_own_surfaces(
    mask: &[u16],
    z: &[f64],
    grid: PixelGrid,
    contested: &Contested,
    steps: &SurfaceSteps,
) -> (Vec<Option<(f64, u32)>>, Vec<u32>) {
    let mut ids: Vec<u32> = contested.holders.iter().flatten().copied().collect();
    ids.sort_unstable();
    ids.dedup();
    let mut nearest: Vec<Option<(f64, u32)>> = vec![None; contested.pixels.len()];
    let mut seedless: Vec<u32> = Vec::new();
    let mut distance = vec![f64::INFINITY; contested.pixels.len()];
    let mut queue = BinaryHeap::new();
    for &id in &ids {
        let holds = |q: usize| contested.slot_of(q).filter(|&s| contested.holders[s].contains(&id));
        // Seeds: the surface only this box holds, where it borders its contested pixels.
        queue.clear();
        distance.fill(f64::INFINITY);
        let mut has_seeds = false;
        for p in (0..mask.len()).filter(|&p| mask[p] as u32 == id && contested.slot_of(p).is_none()) {
            has_seeds = true;
            if grid.neighbours(p).any(|q| holds(q).is_some()) {
                queue.push(Reached {
                    distance: 0.0,
                    pixel: p,
                });
            }
        }
        if !has_seeds {
            // Nothing shows this box's object alone (a box nested in
            // another, or its own part hidden).
            seedless.push(id);
            continue;
        }
        // Dijkstra over the contested pixels this box holds.
        while let Some(Reached { distance: d, pixel: p }) = queue.pop() {
            if contested.slot_of(p).is_some_and(|s| d > distance[s]) {
                continue;
            }
            for q in grid.neighbours(p) {
                let Some(slot) = holds(q) else {
                    continue;
                };
                let Some(along) = steps.across(z[p], z[q]) else {
                    continue;
                };
                if steps.folds_inward(z, grid.width, p, q, false) {
                    continue;
                }
                if d + along < distance[slot] {
                    distance[slot] = d + along;
                    queue.push(Reached {
                        distance: d + along,
                        pixel: q,
                    });
                }
            }
        }
        for (slot, &d) in distance.iter().enumerate() {
            let rank = |id: u32| contested.holders[slot].iter().position(|&h| h == id);
            // Ties go to the smaller box.
            let better = match nearest[slot] {
                None => d.is_finite(),
                Some((best, best_id)) => d < best || (d == best && rank(id) < rank(best_id)),
            };
            if better {
                nearest[slot] = Some((d, id));
            }
        }
    }
    (nearest, seedless)
}

/// Pixels near a valley, which no object reached across it, go to the side
/// of its crease they lie on: filled from the reached pixels and the
/// objects' own surfaces around them, nearest first, stopping only at the
/// valley's deepest pair. Filled pixels enter `nearest` at an infinite
/// distance.
fn fill_beside_valleys(
    mask: &[u16],
    z: &[f64],
    grid: PixelGrid,
    contested: &Contested,
    steps: &SurfaceSteps,
    nearest: &mut [Option<(f64, u32)>],
) {
    let mut queue = BinaryHeap::new();
    let mut distance = vec![f64::INFINITY; contested.pixels.len()];
    let label_of = |p: usize, nearest: &[Option<(f64, u32)>]| match contested.slot_of(p) {
        Some(slot) => nearest[slot].map(|(_, id)| id),
        None => Some(mask[p] as u32).filter(|&id| id > 0),
    };
    for (slot, &p) in contested.pixels.iter().enumerate() {
        if nearest[slot].is_none() {
            for q in grid.neighbours(p) {
                if label_of(q, nearest).is_some() {
                    queue.push(Reached {
                        distance: 0.0,
                        pixel: q,
                    });
                }
            }
        }
    }
    let mut filled: Vec<Option<u32>> = vec![None; contested.pixels.len()];
    while let Some(Reached { distance: d, pixel: p }) = queue.pop() {
        let id = match contested.slot_of(p) {
            Some(slot) if nearest[slot].is_none() => {
                if d > distance[slot] {
                    continue;
                }
                filled[slot]
            }
            _ => label_of(p, nearest),
        };
        let Some(id) = id else {
            continue;
        };
        for q in grid.neighbours(p) {
            let Some(slot) = contested.slot_of(q).filter(|&s| nearest[s].is_none()) else {
                continue;
            };
            if !contested.holders[slot].contains(&id) || steps.folds_inward(z, grid.width, p, q, true) {
                continue;
            }
            let Some(along) = steps.across(z[p], z[q]) else {
                continue;
            };
            if d + along < distance[slot] {
                distance[slot] = d + along;
                filled[slot] = Some(id);
                queue.push(Reached {
                    distance: d + along,
                    pixel: q,
                });
            }
        }
    }
    for (slot, id) in filled.iter().enumerate() {
        if let (None, Some(id)) = (nearest[slot], id) {
            nearest[slot] = Some((f64::INFINITY, *id));
        }
    }
}

/// A pixel reached at some distance along the surface, for Dijkstra's
/// queue: nearest first, then the lower pixel index (a fixed order).
#[derive(Clone, Copy, Debug, PartialEq)]
struct Reached {
    distance: f64,
    pixel: usize,
}

impl Eq for Reached {}

impl Ord for Reached {
    fn cmp(&self, other: &Self) -> Ordering {
        other
            .distance
            .total_cmp(&self.distance)
            .then(other.pixel.cmp(&self.pixel))
    }
}

impl PartialOrd for Reached {
    fn partial_cmp(&self, other: &Self) -> Option<Ordering> {
        Some(self.cmp(other))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A 12 x 3 frame: box 1 (small) holds columns 0-7, box 2 holds 4-11;
    /// columns 4-7 are contested. Depths per column.
    fn strip(z_of_column: impl Fn(usize) -> f64) -> (Vec<u16>, Vec<f64>, Contested) {
        let (w, h) = (12, 3);
        let mut mask = vec![0u16; w * h];
        let mut z = vec![0.0; w * h];
        let mut contested = Contested::default();
        for y in 0..h {
            for x in 0..w {
                let p = y * w + x;
                z[p] = z_of_column(x);
                mask[p] = if x < 8 { 1 } else { 2 };
                if (4..8).contains(&x) {
                    contested.push(w * h, p, vec![1, 2]);
                }
            }
        }
        (mask, z, contested)
    }

    fn columns(mask: &[u16]) -> Vec<u16> {
        mask[..12].to_vec()
    }

    const STEPS: SurfaceSteps = SurfaceSteps {
        camera: Intrinsics {
            fx: 500.0,
            fy: 500.0,
            cx: 6.0,
            cy: 1.5,
        },
        surface_error_m: 0.001,
    };

    #[test]
    fn a_neighbours_face_behind_a_depth_step_goes_to_the_neighbour() {
        // Box 1's object ends at column 5; columns 6-11 are a surface 5 cm behind.
        let (mut mask, z, contested) = strip(|x| if x < 6 { 0.50 } else { 0.55 });
        resolve(&mut mask, &z, 12, &contested, STEPS);
        assert_eq!(columns(&mask), [1, 1, 1, 1, 1, 1, 2, 2, 2, 2, 2, 2]);
    }

    #[test]
    fn a_continuous_surface_splits_where_the_objects_are_equally_far() {
        // No depth step: both objects reach every contested pixel; each
        // takes the half of the overlap nearer its own surface.
        let (mut mask, z, contested) = strip(|x| 0.5 + 0.001 * x as f64);
        resolve(&mut mask, &z, 12, &contested, STEPS);
        assert_eq!(columns(&mask), [1, 1, 1, 1, 1, 1, 2, 2, 2, 2, 2, 2]);
        // Steeper on box 2's side: its pixels lie farther apart, so box 1
        // reaches one more pixel first.
        let (mut mask, z, contested) = strip(|x| 0.5 + if x < 6 { 0.0 } else { 0.003 * (x - 5) as f64 });
        resolve(&mut mask, &z, 12, &contested, STEPS);
        assert_eq!(columns(&mask), [1, 1, 1, 1, 1, 1, 1, 2, 2, 2, 2, 2]);
    }

    #[test]
    fn objects_meeting_in_a_valley_split_at_the_valley() {
        // Two faces at 45 degrees meet in a valley between columns 4 and 5,
        // nearer box 1's own surface than the overlap's middle: box 1's
        // object does not reach past the valley.
        let valley = |x: usize| 0.6 - 0.001 * (x as f64 - 4.5).abs();
        let (mut mask, z, contested) = strip(valley);
        resolve(&mut mask, &z, 12, &contested, STEPS);
        assert_eq!(columns(&mask), [1, 1, 1, 1, 1, 2, 2, 2, 2, 2, 2, 2]);
        // A ridge there (a convex edge of one object) splits in the middle as a plane does.
        let (mut mask, z, contested) = strip(|x| 0.5 + 0.001 * (x as f64 - 4.5).abs());
        resolve(&mut mask, &z, 12, &contested, STEPS);
        assert_eq!(columns(&mask), [1, 1, 1, 1, 1, 1, 2, 2, 2, 2, 2, 2]);
    }

    #[test]
    fn an_unreached_pixel_stays_with_the_smallest_box() {
        // Column 6 stands out of both surfaces: no object reaches it.
        let (mut mask, z, contested) = strip(|x| if x == 6 { 0.4 } else { 0.5 });
        resolve(&mut mask, &z, 12, &contested, STEPS);
        assert_eq!(columns(&mask), [1, 1, 1, 1, 1, 1, 1, 2, 2, 2, 2, 2]);
    }

    #[test]
    fn a_box_without_a_surface_of_its_own_keeps_the_smallest_rule() {
        // A nested box (id 1) holds nothing alone; the larger box's surface
        // runs on into it without a step, or behind one: either way its
        // pixels stay with the nested box.
        for step in [0.0, 0.1] {
            let (w, h) = (6, 2);
            let nested = [2, 3, 8, 9];
            let mut mask = vec![2u16; w * h];
            let mut contested = Contested::default();
            for p in nested {
                mask[p] = 1;
                contested.push(w * h, p, vec![1, 2]);
            }
            let z: Vec<f64> = (0..w * h)
                .map(|p| if nested.contains(&p) { 0.5 - step } else { 0.5 })
                .collect();
            let before = mask.clone();
            resolve(&mut mask, &z, w, &contested, STEPS);
            assert_eq!(mask, before, "step {step}");
        }
    }

    #[test]
    fn a_larger_box_with_nothing_of_its_own_does_not_take_a_smaller_ones_object() {
        // Box 2 (larger) shows nothing alone; box 1's object reaches every
        // contested pixel, so they stay box 1's.
        let (w, h) = (6, 1);
        let mut mask = vec![1u16; w];
        let mut contested = Contested::default();
        for p in 3..6 {
            contested.push(w * h, p, vec![1, 2]);
        }
        resolve(&mut mask, &[0.5; 6], w, &contested, STEPS);
        assert_eq!(mask, [1; 6]);
    }
}
