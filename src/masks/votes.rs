//! A sparse 3D vote volume: labelled pixels lifted to their surface points
//! vote for their object id (0 = background) in voxels of two sizes; a
//! point is classified by the votes around it, trilinearly weighted, at the
//! finest level that saw its neighbourhood.

use nalgebra::{Point3, Vector3};
use std::collections::HashMap;
use std::hash::{BuildHasherDefault, Hasher};

/// Each coarser level's voxels are this many times larger.
const LEVEL_FACTOR: f64 = 4.0;
/// Levels: the finest voxel and one coarser, for surfaces a given frame saw
/// only from afar or at a grazing angle.
const LEVELS: usize = 2;
/// A level answers when the voxels around a point that hold votes carry at
/// least this share of the trilinear weight.
const MIN_COVER: f64 = 0.25;

/// Hash of voxel keys: a multiply-xorshift (the default SipHash is several
/// times slower on millions of keys, and keys are not adversarial).
#[derive(Default)]
struct KeyHasher(u64);

impl Hasher for KeyHasher {
    fn finish(&self) -> u64 {
        self.0
    }
    fn write(&mut self, bytes: &[u8]) {
        for &b in bytes {
            self.write_u64(b as u64);
        }
    }
    fn write_i32(&mut self, v: i32) {
        self.write_u64(v as u32 as u64);
    }
    fn write_u64(&mut self, v: u64) {
        let x = (self.0 ^ v).wrapping_mul(0x9E37_79B9_7F4A_7C15);
        self.0 = x ^ (x >> 29);
    }
}

type Cells = HashMap<[i32; 3], Votes, BuildHasherDefault<KeyHasher>>;

/// Weighted votes of one voxel.
#[derive(Clone, Debug, Default)]
struct Votes {
    /// (object id, summed weight); few entries per voxel.
    by_id: Vec<(u16, f32)>,
    total: f32,
}

impl Votes {
    fn add(&mut self, id: u16, weight: f32) {
        match self.by_id.iter_mut().find(|(i, _)| *i == id) {
            Some((_, w)) => *w += weight,
            None => self.by_id.push((id, weight)),
        }
        self.total += weight;
    }
}

struct Level {
    inv_voxel: f64,
    cells: Cells,
}

/// Votes of lifted labelled pixels.
pub struct VoteVolume {
    levels: Vec<Level>,
    voxel_m: f64,
}

impl VoteVolume {
    /// An empty volume with finest voxels of `voxel_m` metres.
    pub fn new(voxel_m: f64) -> VoteVolume {
        let levels = (0..LEVELS)
            .map(|l| Level {
                inv_voxel: 1.0 / (voxel_m * LEVEL_FACTOR.powi(l as i32)),
                cells: Cells::default(),
            })
            .collect();
        VoteVolume { levels, voxel_m }
    }

    /// The finest voxel size, metres.
    pub fn voxel_m(&self) -> f64 {
        self.voxel_m
    }

    /// One labelled surface point votes for `id` (0 = background).
    pub fn add(&mut self, point: &Point3<f64>, id: u16, weight: f32) {
        if !is_finite(point) || !(weight > 0.0) {
            return;
        }
        for level in &mut self.levels {
            let key = voxel_key(&(point.coords * level.inv_voxel));
            level.cells.entry(key).or_default().add(id, weight);
        }
    }

    /// The object id the votes around `point` favour (0 = background or
    /// never seen), and the share of the weight it won.
    pub fn classify(&self, point: &Point3<f64>) -> (u16, f32) {
        if !is_finite(point) {
            return (0, 0.0);
        }
        let mut score: Vec<(u16, f64)> = Vec::new();
        for level in &self.levels {
            // Trilinear weights over the 8 voxel centres around the point.
            let p = point.coords * level.inv_voxel - Vector3::repeat(0.5);
            let base = p.map(f64::floor);
            let frac = p - base;
            score.clear();
            let mut cover = 0.0;
            for corner in 0..8u32 {
                let bit = |axis: u32| (corner >> axis) & 1 == 1;
                let weight = (0..3)
                    .map(|a| {
                        if bit(a) {
                            frac[a as usize]
                        } else {
                            1.0 - frac[a as usize]
                        }
                    })
                    .product::<f64>();
                let key = [
                    base.x as i32 + bit(0) as i32,
                    base.y as i32 + bit(1) as i32,
                    base.z as i32 + bit(2) as i32,
                ];
                let Some(votes) = level.cells.get(&key) else {
                    continue;
                };
                if !(votes.total > 0.0) {
                    continue;
                }
                cover += weight;
                for &(id, w) in &votes.by_id {
                    let share = weight * (w / votes.total) as f64;
                    match score.iter_mut().find(|(i, _)| *i == id) {
                        Some((_, s)) => *s += share,
                        None => score.push((id, share)),
                    }
                }
            }
            if cover >= MIN_COVER {
                // Ties go to the lower id (background first): deterministic.
                score.sort_by_key(|&(id, _)| id);
                let best = score.iter().fold(
                    (0u16, f64::NEG_INFINITY),
                    |best, &(id, s)| {
                        if s > best.1 {
                            (id, s)
                        } else {
                            best
                        }
                    },
                );
                return (best.0, (best.1 / cover) as f32);
            }
        }
        (0, 0.0)
    }
}

fn is_finite(p: &Point3<f64>) -> bool {
    p.iter().all(|x| x.is_finite())
}

fn voxel_key(p: &Vector3<f64>) -> [i32; 3] {
    let clamp = |v: f64| v.floor().clamp(i32::MIN as f64, i32::MAX as f64) as i32;
    [clamp(p.x), clamp(p.y), clamp(p.z)]
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_point_takes_the_majority_of_the_votes_around_it() {
        let mut v = VoteVolume::new(0.01);
        for i in 0..10 {
            let p = Point3::new(0.1 + i as f64 * 0.001, 0.2, 0.3);
            v.add(&p, 3, 1.0);
            if i < 3 {
                v.add(&p, 0, 1.0);
            }
        }
        assert_eq!(v.classify(&Point3::new(0.105, 0.2, 0.3)).0, 3);
        // Far from every vote: background, never seen.
        assert_eq!(v.classify(&Point3::new(5.0, 5.0, 5.0)), (0, 0.0));
    }

    #[test]
    fn unseen_fine_neighbourhoods_fall_back_to_the_coarse_level() {
        let mut v = VoteVolume::new(0.01);
        v.add(&Point3::new(0.005, 0.005, 0.005), 7, 1.0);
        // Two fine voxels away: no fine votes around it, but coarse ones.
        assert_eq!(v.classify(&Point3::new(0.025, 0.005, 0.005)).0, 7);
    }

    #[test]
    fn non_finite_points_and_weights_are_ignored() {
        let mut v = VoteVolume::new(0.01);
        v.add(&Point3::new(f64::NAN, 0.0, 0.0), 1, 1.0);
        v.add(&Point3::origin(), 1, f32::NAN);
        assert_eq!(v.classify(&Point3::origin()), (0, 0.0));
        assert_eq!(
            v.classify(&Point3::new(f64::INFINITY, f64::INFINITY, f64::INFINITY)),
            (0, 0.0)
        );
    }
}
