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
//! the two objects meet. A pixel no object reaches stays with the smallest
//! box (FORMATS.md section 2), and so does a box's pixel where that box
//! holds nothing alone in the frame and is smaller than the nearest
//! object's box: a box nested in another (a lid on a crate) keeps its part.

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
    /// Metres between neighbouring pixels' rays per metre of depth (1 / focal).
    pub footprint_per_m: f64,
    /// Depth error of the surfaces, metres (rendered surfaces: a grid cell).
    pub surface_error_m: f64,
}

impl SurfaceSteps {
    /// Largest depth step between neighbouring pixels of one surface at
    /// depth `z` (see [`REACH_STEP_PIXELS`]).
    fn max_step(&self, z: f64) -> f64 {
        self.surface_error_m + REACH_STEP_PIXELS * z * self.footprint_per_m
    }

    /// Distance along the surface between neighbouring pixels at depths
    /// `a` and `b`, or `None` across a depth step (two surfaces).
    fn across(&self, a: f64, b: f64) -> Option<f64> {
        let near = a.min(b);
        let step = (a - b).abs();
        (step <= self.max_step(near)).then(|| (near * self.footprint_per_m).hypot(step))
    }
}

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
    let height = mask.len() / width;
    let mut ids: Vec<u32> = contested.holders.iter().flatten().copied().collect();
    ids.sort_unstable();
    ids.dedup();
    // Per contested pixel, the nearest object's distance and id so far.
    let mut nearest: Vec<Option<(f64, u32)>> = vec![None; contested.pixels.len()];
    let mut seedless: Vec<u32> = Vec::new();
    let mut distance = vec![f64::INFINITY; contested.pixels.len()];
    let mut queue = BinaryHeap::new();
    let neighbours = |p: usize| {
        let (x, y) = (p % width, p / width);
        [
            (x > 0).then(|| p - 1),
            (x + 1 < width).then(|| p + 1),
            (y > 0).then(|| p - width),
            (y + 1 < height).then(|| p + width),
        ]
        .into_iter()
        .flatten()
    };
    for &id in &ids {
        let holds = |q: usize| contested.slot_of(q).filter(|&s| contested.holders[s].contains(&id));
        // Seeds: the surface only this box holds, where it borders its contested pixels.
        queue.clear();
        distance.fill(f64::INFINITY);
        let mut has_seeds = false;
        for p in (0..mask.len()).filter(|&p| mask[p] as u32 == id && contested.slot_of(p).is_none()) {
            has_seeds = true;
            if neighbours(p).any(|q| holds(q).is_some()) {
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
            for q in neighbours(p) {
                let Some(slot) = holds(q) else {
                    continue;
                };
                let Some(along) = steps.across(z[p], z[q]) else {
                    continue;
                };
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
        footprint_per_m: 0.002,
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
