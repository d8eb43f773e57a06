//! Stable fingerprints: a 64-bit FNV-1a hash (std's hasher may change
//! between releases) and the fingerprint of a scan's geometry, stored in
//! models and checkpoints so they are never used with another scan.

use super::Scan;

/// 64-bit FNV-1a: a stable hash (std's hasher may change between releases).
pub struct Fnv(u64);

impl Fnv {
    pub fn new() -> Fnv {
        Fnv(0xcbf2_9ce4_8422_2325)
    }
    pub fn bytes(&mut self, b: &[u8]) {
        for &x in b {
            self.0 = (self.0 ^ x as u64).wrapping_mul(0x0100_0000_01b3);
        }
    }
    pub fn u64(&mut self, v: u64) {
        self.bytes(&v.to_le_bytes());
    }
    pub fn finish(&self) -> u64 {
        self.0
    }
}

impl Default for Fnv {
    fn default() -> Fnv {
        Fnv::new()
    }
}

/// Fingerprint of a scan's geometry: frame count, names, sizes, intrinsics,
/// poses and which frames have depth (not the pixels).
pub fn scan_fingerprint(scan: &Scan) -> u64 {
    let mut h = Fnv::new();
    h.u64(scan.frames.len() as u64);
    for f in &scan.frames {
        h.u64(f.name.len() as u64);
        h.bytes(f.name.as_bytes());
        let (w, hgt) = f.size();
        h.u64(((w as u64) << 32) | hgt as u64);
        let k = f.intrinsics;
        for v in [k.fx, k.fy, k.cx, k.cy]
            .into_iter()
            .chain(f.camera_to_world.to_homogeneous().iter().copied())
        {
            h.u64(v.to_bits());
        }
        h.u64(f.depth.is_some() as u64);
    }
    h.finish()
}
