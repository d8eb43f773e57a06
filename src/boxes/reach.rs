//! Overlapping boxes: which object a contested surface point belongs to.
//!
//! Boxes of neighbouring objects overlap by their margins, so a point in
//! several boxes is often a face of the neighbour that a box merely
//! encloses. A box's object is the surface its box alone holds and what
//! that surface reaches in the image: neighbouring pixels that the box
//! also holds, with no depth step between them larger than a surface seen
//! obliquely makes. A contested pixel goes to the smallest box whose object
//! reaches it; a pixel that the smallest box's object reaches, or that no
//! object reaches, stays with the smallest box (FORMATS.md section 2), and
//! so does every pixel of a box that holds nothing alone in the frame. So
//! a box nested in another (a lid on a crate) keeps its part, and a face
//! flush with its neighbour's, which no depth step separates, follows the
//! smallest-box rule as before.

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

/// Give each contested pixel of `mask` (row-major, `width` wide; every
/// contested pixel holds its smallest box's id) to the smallest box whose
/// object reaches it (module doc). `z` is each pixel's surface depth and
/// `max_step(z)` the largest depth difference between neighbouring pixels
/// of one surface at depth `z`.
pub fn resolve(mask: &mut [u16], z: &[f64], width: usize, contested: &Contested, max_step: impl Fn(f64) -> f64) {
    if contested.is_empty() || width == 0 {
        return;
    }
    let height = mask.len() / width;
    let mut ids: Vec<u32> = contested.holders.iter().flatten().copied().collect();
    ids.sort_unstable();
    ids.dedup();
    // Per contested pixel, the boxes whose object reaches it.
    let mut reached: Vec<Vec<u32>> = vec![Vec::new(); contested.pixels.len()];
    let mut queue = Vec::new();
    for &id in &ids {
        // Seeds: the surface only this box holds.
        queue.clear();
        queue.extend((0..mask.len()).filter(|&p| mask[p] as u32 == id && contested.slot_of(p).is_none()));
        if queue.is_empty() {
            // Nothing shows this box's object alone (a box nested in
            // another, or its own part hidden): it keeps the smallest-box rule.
            for (slot, holders) in contested.holders.iter().enumerate() {
                if holders.contains(&id) {
                    reached[slot].push(id);
                }
            }
            continue;
        }
        while let Some(p) = queue.pop() {
            let (x, y) = (p % width, p / width);
            let neighbours = [
                (x > 0).then(|| p - 1),
                (x + 1 < width).then(|| p + 1),
                (y > 0).then(|| p - width),
                (y + 1 < height).then(|| p + width),
            ];
            for q in neighbours.into_iter().flatten() {
                let Some(slot) = contested.slot_of(q) else {
                    continue;
                };
                if reached[slot].contains(&id) || !contested.holders[slot].contains(&id) {
                    continue;
                }
                if (z[q] - z[p]).abs() <= max_step(z[p].min(z[q])) {
                    reached[slot].push(id);
                    queue.push(q);
                }
            }
        }
    }
    for (slot, &p) in contested.pixels.iter().enumerate() {
        let (holders, reached) = (&contested.holders[slot], &reached[slot]);
        if reached.is_empty() || reached.contains(&holders[0]) {
            continue;
        }
        if let Some(&id) = holders.iter().find(|id| reached.contains(id)) {
            mask[p] = id as u16;
        }
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

    #[test]
    fn a_neighbours_face_behind_a_depth_step_goes_to_the_neighbour() {
        // Box 1's object ends at column 5; columns 6-11 are a surface 5 cm behind.
        let (mut mask, z, contested) = strip(|x| if x < 6 { 0.50 } else { 0.55 });
        resolve(&mut mask, &z, 12, &contested, |_| 0.01);
        assert_eq!(columns(&mask), [1, 1, 1, 1, 1, 1, 2, 2, 2, 2, 2, 2]);
    }

    #[test]
    fn a_continuous_surface_stays_with_the_smallest_box() {
        // No depth step: both objects reach every contested pixel.
        let (mut mask, z, contested) = strip(|x| 0.5 + 0.001 * x as f64);
        let before = mask.clone();
        resolve(&mut mask, &z, 12, &contested, |_| 0.01);
        assert_eq!(mask, before);
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
            resolve(&mut mask, &z, w, &contested, |_| 0.01);
            assert_eq!(mask, before, "step {step}");
        }
    }
}
