//! COCO run-length encoding of instance masks: column-major runs starting
//! with background, and the compressed string form pycocotools writes
//! (LEB128-like, 5 bits per character, counts after the third stored as the
//! difference to the count two places back).

use std::collections::BTreeMap;

/// Runs of one instance over a `height x width` mask.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Rle {
    pub height: u32,
    pub width: u32,
    /// Alternating run lengths, column-major, the first counting background (may be 0).
    pub counts: Vec<u32>,
}

impl Rle {
    /// Pixels inside the instance.
    pub fn area(&self) -> u64 {
        self.counts.iter().skip(1).step_by(2).map(|&c| c as u64).sum()
    }

    /// The compressed `counts` string of pycocotools.
    pub fn to_coco_string(&self) -> String {
        counts_to_string(&self.counts)
    }
}

/// Encode every instance of a row-major id mask (0 = background) at once.
pub fn encode_instances(mask: &[u16], width: u32, height: u32) -> BTreeMap<u16, Rle> {
    let (w, h) = (width as usize, height as usize);
    debug_assert_eq!(mask.len(), w * h);
    // Per instance: counts so far and where its current run began.
    let mut runs: BTreeMap<u16, (Vec<u32>, usize)> = BTreeMap::new();
    let mut prev = 0u16;
    let mut index = 0usize;
    for x in 0..w {
        for y in 0..h {
            let v = mask[y * w + x];
            if v != prev {
                if prev != 0 {
                    if let Some((counts, start)) = runs.get_mut(&prev) {
                        counts.push((index - *start) as u32);
                        *start = index;
                    }
                }
                if v != 0 {
                    let (counts, start) = runs.entry(v).or_insert_with(|| (Vec::new(), 0));
                    counts.push((index - *start) as u32);
                    *start = index;
                }
                prev = v;
            }
            index += 1;
        }
    }
    runs.into_iter()
        .map(|(id, (mut counts, start))| {
            counts.push((index - start) as u32);
            (id, Rle { height, width, counts })
        })
        .collect()
}

/// pycocotools' `rleToString`: each count (after the third, minus the count
/// two places back) as signed 5-bit groups, low first, in characters 48..=111;
/// bit 0x20 marks that more groups follow.
pub fn counts_to_string(counts: &[u32]) -> String {
    let mut s = String::with_capacity(counts.len() * 2);
    for (i, &c) in counts.iter().enumerate() {
        let mut x = c as i64;
        if i > 2 {
            x -= counts[i - 2] as i64;
        }
        loop {
            let mut group = (x & 0x1f) as u8;
            x >>= 5;
            // Stop once the remaining bits are pure sign extension of this group.
            let more = if group & 0x10 != 0 { x != -1 } else { x != 0 };
            if more {
                group |= 0x20;
            }
            s.push((group + 48) as char);
            if !more {
                break;
            }
        }
    }
    s
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::rng::Rng;

    /// Independent reference: decode the string by the COCO spec, then expand runs.
    fn decode_string(s: &str) -> Vec<u32> {
        let bytes = s.as_bytes();
        let mut counts: Vec<i64> = Vec::new();
        let mut p = 0;
        while p < bytes.len() {
            let (mut x, mut k) = (0i64, 0);
            loop {
                let c = bytes[p] as i64 - 48;
                x |= (c & 0x1f) << (5 * k);
                p += 1;
                k += 1;
                if c & 0x20 == 0 {
                    if c & 0x10 != 0 {
                        x |= -1i64 << (5 * k);
                    }
                    break;
                }
            }
            if counts.len() > 2 {
                x += counts[counts.len() - 2];
            }
            counts.push(x);
        }
        counts.into_iter().map(|c| u32::try_from(c).unwrap()).collect()
    }

    fn expand(counts: &[u32], width: usize, height: usize) -> Vec<bool> {
        let mut column_major = Vec::new();
        for (i, &c) in counts.iter().enumerate() {
            column_major.extend(std::iter::repeat_n(i % 2 == 1, c as usize));
        }
        assert_eq!(column_major.len(), width * height);
        let mut row_major = vec![false; width * height];
        for x in 0..width {
            for y in 0..height {
                row_major[y * width + x] = column_major[x * height + y];
            }
        }
        row_major
    }

    #[test]
    fn known_strings_derived_by_hand() {
        // 2x3 mask, rows [0 1 1] and [0 1 0]: column-major 0 0 | 1 1 | 1 0 -> [2, 3, 1] -> "231".
        let mask = [0u16, 1, 1, 0, 1, 0];
        let rle = &encode_instances(&mask, 3, 2)[&1];
        assert_eq!(rle.counts, vec![2, 3, 1]);
        assert_eq!(rle.to_coco_string(), "231");
        assert_eq!(rle.area(), 3);
        // [0, 40, 5, 100, 55]: 0 -> '0'; 40 = 8 + 1*32 -> 'X' (8|0x20 + 48) then '1';
        // 5 -> '5'; 100 - 40 = 60 = 28 + 32: 28 has bit 0x10 and 60 >> 5 = 1 != -1, so
        // 'l' (28|0x20 + 48) then '1'; 55 - 5 = 50 = 18 + 32 -> 'b' then '1'.
        assert_eq!(counts_to_string(&[0, 40, 5, 100, 55]), "0X15l1b1");
        // [3, 10, 2, 1]: 1 - 10 = -9 -> low group 23 (sign bit set), rest -1 -> 'G' alone.
        assert_eq!(counts_to_string(&[3, 10, 2, 1]), "3:2G");
        assert_eq!(decode_string("0X15l1b1"), vec![0, 40, 5, 100, 55]);
        assert_eq!(decode_string("3:2G"), vec![3, 10, 2, 1]);
        // The 10x20 mask behind the second string: ones at column-major 0..40 and 45..145.
        let (w, h) = (20usize, 10usize);
        let mut mask = vec![0u16; w * h];
        for i in (0..40).chain(45..145) {
            let (x, y) = (i / h, i % h);
            mask[y * w + x] = 7;
        }
        let rle = &encode_instances(&mask, w as u32, h as u32)[&7];
        assert_eq!(rle.to_coco_string(), "0X15l1b1");
        assert_eq!(rle.area(), 140);
    }

    #[test]
    fn random_masks_round_trip_through_the_reference_decoder() {
        let mut rng = Rng::new(9, 0);
        for round in 0..200 {
            let (w, h) = (1 + rng.below(40) as usize, 1 + rng.below(30) as usize);
            let ids = 1 + rng.below(5) as u16;
            // Blobby masks: runs of random length so long counts (multi-character) appear.
            let mut mask = vec![0u16; w * h];
            let mut v = 0u16;
            let mut i = 0;
            while i < w * h {
                let run = 1 + rng.below(if round % 2 == 0 { 4 } else { 200 }) as usize;
                for m in mask.iter_mut().skip(i).take(run) {
                    *m = v;
                }
                i += run;
                v = if rng.below(2) == 0 {
                    0
                } else {
                    1 + rng.below(ids as u64) as u16
                };
            }
            let encoded = encode_instances(&mask, w as u32, h as u32);
            for id in 1..=ids {
                let want: Vec<bool> = mask.iter().map(|&m| m == id).collect();
                match encoded.get(&id) {
                    None => assert!(!want.contains(&true), "instance {id} present but not encoded"),
                    Some(rle) => {
                        assert_eq!(rle.counts.iter().map(|&c| c as usize).sum::<usize>(), w * h);
                        let counts = decode_string(&rle.to_coco_string());
                        assert_eq!(counts, rle.counts);
                        assert_eq!(expand(&counts, w, h), want, "round {round} id {id}");
                        assert_eq!(rle.area(), want.iter().filter(|&&b| b).count() as u64);
                    }
                }
            }
        }
    }
}
