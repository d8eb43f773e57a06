//! Optional mask clean-up: fill small holes enclosed by one instance and
//! drop small specks detached from an instance's main part. Both are
//! bounded by a size relative to the instance, so real openings and small
//! objects survive.

use crate::mask::components;

/// Fill background holes enclosed by a single instance and smaller than
/// `fraction` of that instance's pixels; remove instance parts smaller than
/// `fraction` of the instance's largest part. Returns pixels changed.
pub fn clean_mask(mask: &mut [u16], width: u32, height: u32, fraction: f64) -> usize {
    let (w, h) = (width as usize, height as usize);
    if mask.len() != w * h || mask.is_empty() {
        return 0;
    }
    let c = components(mask, w, h);
    let n = c.value.len();
    let mut instance_pixels = std::collections::HashMap::<u16, usize>::new();
    let mut largest = std::collections::HashMap::<u16, usize>::new();
    for k in 0..n {
        if c.value[k] != 0 {
            *instance_pixels.entry(c.value[k]).or_default() += c.size[k];
            let l = largest.entry(c.value[k]).or_default();
            *l = (*l).max(c.size[k]);
        }
    }
    // Neighbouring values of each component: None = none yet, Some(v) = one value, Some(MAX)... kept as a small set.
    let mut neighbour: Vec<Option<u16>> = vec![None; n];
    let mut mixed = vec![false; n];
    for y in 0..h {
        for x in 0..w {
            let i = y * w + x;
            let a = c.label[i] as usize;
            for j in [(x + 1 < w).then(|| i + 1), (y + 1 < h).then(|| i + w)]
                .into_iter()
                .flatten()
            {
                let b = c.label[j] as usize;
                if a == b {
                    continue;
                }
                for (p, q) in [(a, j), (b, i)] {
                    let v = mask[q];
                    match neighbour[p] {
                        None => neighbour[p] = Some(v),
                        Some(u) if u != v => mixed[p] = true,
                        _ => {}
                    }
                }
            }
        }
    }
    let mut replace: Vec<Option<u16>> = vec![None; n];
    for k in 0..n {
        let v = c.value[k];
        if v == 0 {
            // A hole: background enclosed by exactly one instance, away from the border.
            if let (false, false, Some(owner)) = (c.border[k], mixed[k], neighbour[k]) {
                if owner != 0 && (c.size[k] as f64) < fraction * instance_pixels[&owner] as f64 {
                    replace[k] = Some(owner);
                }
            }
        } else if c.size[k] < largest[&v] && (c.size[k] as f64) < fraction * largest[&v] as f64 {
            replace[k] = Some(0);
        }
    }
    let mut changed = 0;
    for (m, &l) in mask.iter_mut().zip(&c.label) {
        if let Some(v) = replace[l as usize] {
            *m = v;
            changed += 1;
        }
    }
    changed
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn small_holes_fill_and_specks_vanish_but_openings_and_borders_stay() {
        let (w, h) = (20usize, 12usize);
        let mut mask = vec![0u16; w * h];
        // Instance 1: a 8x8 block with a 1-pixel hole and a 3x3 opening; a 1-pixel speck of 1 far away.
        for y in 1..9 {
            for x in 1..9 {
                mask[y * w + x] = 1;
            }
        }
        mask[3 * w + 3] = 0;
        for y in 5..8 {
            for x in 5..8 {
                mask[y * w + x] = 0;
            }
        }
        mask[10 * w + 15] = 1;
        // Instance 2 touching the border with a hole on the border: stays.
        mask[w - 1] = 2;
        mask[w + w - 1] = 2;
        let before = mask.clone();
        let changed = clean_mask(&mut mask, w as u32, h as u32, 0.05);
        assert_eq!(mask[3 * w + 3], 1, "1-pixel hole filled (1 < 5 % of 54)");
        assert_eq!(mask[6 * w + 6], 0, "9-pixel opening kept (9 > 5 % of 54)");
        assert_eq!(mask[10 * w + 15], 0, "speck removed");
        assert_eq!(mask[w - 1], 2, "a lone instance is its own largest part");
        assert_eq!(changed, 2);
        assert_eq!(before.iter().zip(&mask).filter(|(a, b)| a != b).count(), 2);
    }
}
