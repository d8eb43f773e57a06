//! Where the sensor measured a surface: a bit grid over the unit cube of
//! the cells holding a depth point of a training view (grown by one cell so
//! sparse samples cannot step over it). Training uses it to read a pixel
//! without depth as evidence: a ray that the sensor could not measure but
//! that would end on a surface the sensor measured from elsewhere most
//! likely ends earlier, on something the sensor cannot see (glass).

use crate::nerf::occupancy::{cell_index, DepthRay};

/// Cells per axis at most (512^3 bits = 16 MiB).
pub const MAX_RESOLUTION: usize = 512;

/// Bit grid of cells that hold (or touch) a measured surface point.
#[derive(Clone, Debug)]
pub struct MeasuredSurfaces {
    res: usize,
    bits: Vec<u64>,
}

impl MeasuredSurfaces {
    /// Cells hit by `rays` at `res` cells per axis (clamped to 4..=[`MAX_RESOLUTION`]), dilated by one cell.
    pub fn from_depth_rays(rays: &[DepthRay], res: usize) -> Self {
        let res = res.clamp(4, MAX_RESOLUTION);
        let mut grid = MeasuredSurfaces {
            res,
            bits: vec![0; (res * res * res).div_ceil(64)],
        };
        for ray in rays {
            let hit = [0, 1, 2].map(|a| ray.origin[a] + ray.t_hit * ray.dir[a]);
            if let Some(c) = grid.cell_of(hit) {
                grid.bits[c >> 6] |= 1 << (c & 63);
            }
        }
        grid.dilate();
        grid
    }

    /// Whether `p` (local coordinates) lies in a measured cell (false outside the cube).
    #[inline]
    pub fn contains(&self, p: [f32; 3]) -> bool {
        self.cell_of(p)
            .is_some_and(|c| (self.bits[c >> 6] >> (c & 63)) & 1 == 1)
    }

    /// Fraction of cells marked.
    pub fn marked_fraction(&self) -> f64 {
        let marked: u64 = self.bits.iter().map(|w| w.count_ones() as u64).sum();
        marked as f64 / (self.res * self.res * self.res) as f64
    }

    #[inline]
    fn cell_of(&self, p: [f32; 3]) -> Option<usize> {
        cell_index(p, self.res)
    }

    /// Grow the marked cells by one along each axis in turn (3x3x3 overall).
    fn dilate(&mut self) {
        let res = self.res;
        let get = |bits: &[u64], c: usize| (bits[c >> 6] >> (c & 63)) & 1 == 1;
        for stride in [1, res, res * res] {
            let src = self.bits.clone();
            for c in 0..res * res * res {
                if get(&src, c) {
                    continue;
                }
                let coord = (c / stride) % res;
                let below = coord > 0 && get(&src, c - stride);
                let above = coord + 1 < res && get(&src, c + stride);
                if below || above {
                    self.bits[c >> 6] |= 1 << (c & 63);
                }
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn marks_the_hit_cells_and_their_neighbours_only() {
        // Hits on the plane z = 0.5 over x, y in [0.25, 0.75).
        let rays: Vec<DepthRay> = (0..50)
            .flat_map(|i| (0..50).map(move |j| (i, j)))
            .map(|(i, j)| DepthRay {
                origin: [0.25 + i as f32 * 0.01, 0.25 + j as f32 * 0.01, 0.1],
                dir: [0.0, 0.0, 1.0],
                t_hit: 0.4,
            })
            .collect();
        let grid = MeasuredSurfaces::from_depth_rays(&rays, 64);
        let cell = 1.0 / 64.0;
        assert!(grid.contains([0.5, 0.5, 0.5]));
        // One cell above and below the plane's cell (z = 0.5 starts cell 32) is marked, two are not.
        assert!(grid.contains([0.5, 0.5, 0.5 + 1.5 * cell]) && grid.contains([0.5, 0.5, 0.5 - 0.5 * cell]));
        assert!(!grid.contains([0.5, 0.5, 0.5 + 2.5 * cell]) && !grid.contains([0.5, 0.5, 0.5 - 1.5 * cell]));
        assert!(!grid.contains([0.1, 0.5, 0.5]) && !grid.contains([0.9, 0.9, 0.5]));
        assert!(!grid.contains([f32::NAN, 0.5, 0.5]) && !grid.contains([1.5, 0.5, 0.5]));
        // Plane 33 x 33 cells (x, y in cells 16..=47, grown by one) times 3 layers.
        let want = 34.0 * 34.0 * 3.0 / 64f64.powi(3);
        assert!(
            (grid.marked_fraction() - want).abs() < 2.0 * 34.0 * 3.0 / 64f64.powi(3),
            "{} vs {want}",
            grid.marked_fraction()
        );
    }
}
