//! Occupancy grid over the unit cube: which cells may hold density, so the
//! marcher skips empty space. Seeded by carving free space with the sensor
//! depth (unobserved cells stay occupied), the space around each training
//! camera and the space no training camera sees; refreshed from the model
//! during training with a decaying maximum of sampled density.

pub mod from_field;
pub mod measured;

use crate::nerf::camera::{unit_cube_interval, LocalCamera};
use crate::nerf::field::simd::vectorised;
use crate::rng::Rng;
use rayon::prelude::*;

/// Default cells per axis.
pub const DEFAULT_RESOLUTION: usize = 128;

/// A ray with a measured surface, in local (unit-cube) coordinates.
#[derive(Clone, Copy, Debug)]
pub struct DepthRay {
    pub origin: [f32; 3],
    /// Unit direction.
    pub dir: [f32; 3],
    /// Distance along `dir` to the measured surface.
    pub t_hit: f32,
}

/// A training camera in local coordinates and the distance within which
/// it measured nothing (0 without depth).
#[derive(Clone, Copy, Debug)]
pub struct CameraSpace {
    pub origin: [f32; 3],
    pub free_distance: f32,
}

/// Index (x fastest) of the cell holding `p` in a grid of `res`^3 cells
/// over the unit cube, `None` outside it or for NaN.
#[inline]
pub(crate) fn cell_index(p: [f32; 3], res: usize) -> Option<usize> {
    let r = res as f32;
    let mut idx = [0usize; 3];
    for a in 0..3 {
        let c = p[a] * r;
        // Written so NaN fails the test.
        if !(c >= 0.0 && c < r) {
            return None;
        }
        idx[a] = c as usize;
    }
    Some((idx[2] * res + idx[1]) * res + idx[0])
}

/// Bit grid of possibly occupied cells plus the density estimate behind it.
#[derive(Clone, Debug)]
pub struct OccupancyGrid {
    res: usize,
    density: Vec<f32>,
    bits: Vec<u64>,
    /// One bit per group of GROUP^3 cells, set when any cell of the group
    /// is occupied: what the group distances are computed from (kept so a
    /// refresh reuses the buffer).
    groups: Vec<u64>,
    /// Per group, its Chebyshev distance in groups to the nearest occupied
    /// one (0 = occupied): rendering crosses the empty cube of groups around
    /// an empty one in a single step.
    group_distance: CoarseDistances,
    /// Cells the sensor saw as free space; they stay empty.
    carved: Vec<u64>,
    occupied: usize,
    /// Which 1/REFRESH_PARTS of the cells the next refresh evaluates.
    refresh_phase: usize,
}

/// Most cells per axis (the marchers' index arithmetic relies on it).
pub const MAX_RESOLUTION: usize = 512;

/// Cells per group edge of the coarse occupancy level.
pub const GROUP: usize = 2;

/// A refresh evaluates one of this many interleaved subsets of the cells.
const REFRESH_PARTS: usize = 8;
/// Rendering skips cells whose estimated optical depth across one cell is
/// below this (at most 1 % of the light lost per skipped cell).
pub(crate) const RENDER_MIN_CELL_OPTICAL_DEPTH: f32 = 0.01;
/// Never let fewer than this fraction of cells stay occupied.
const MIN_OCCUPIED_FRACTION: f64 = 1e-3;

/// A faint initial density estimate (0.1 % opacity per cell): seeding and
/// model refreshes replace it.
fn initial_density(res: usize) -> f32 {
    0.001 * res as f32
}

impl OccupancyGrid {
    /// Every cell occupied (nothing known yet).
    pub fn full(res: usize) -> Self {
        let res = res.clamp(4, MAX_RESOLUTION);
        let cells = res * res * res;
        let initial = initial_density(res);
        let words = cells.div_ceil(64);
        let mut grid = OccupancyGrid {
            res,
            carved: vec![0; words],
            density: vec![initial; cells],
            bits: vec![0; words],
            groups: Vec::new(),
            group_distance: CoarseDistances::default(),
            occupied: 0,
            refresh_phase: 0,
        };
        grid.rebuild_bits();
        grid
    }

    /// Cells per axis.
    pub fn resolution(&self) -> usize {
        self.res
    }

    /// Fraction of cells marked occupied.
    pub fn occupied_fraction(&self) -> f64 {
        self.occupied as f64 / self.res.pow(3) as f64
    }

    /// Index of the cell holding `p`, `None` outside the unit cube or NaN.
    #[inline]
    pub fn cell_of(&self, p: [f32; 3]) -> Option<usize> {
        cell_index(p, self.res)
    }

    /// Whether the cell with this index may hold density.
    #[inline]
    pub fn is_occupied_cell(&self, cell: usize) -> bool {
        (self.bits[cell >> 6] >> (cell & 63)) & 1 == 1
    }

    /// Groups per axis of the coarse level (the last may be partial).
    #[inline]
    pub fn group_resolution(&self) -> usize {
        self.res.div_ceil(GROUP)
    }

    /// How many groups from this one (group coordinates) the nearest
    /// occupied group lies, per axis at most (0: this one is occupied): the
    /// groups within one less than that on every axis are all empty.
    #[inline]
    pub fn empty_group_reach(&self, group: [usize; 3]) -> usize {
        self.group_distance.at(group) as usize
    }

    /// Count the occupied cells, mark the groups holding them and their distances.
    fn finish_bits(&mut self) {
        self.occupied = self.bits.iter().map(|w| w.count_ones() as usize).sum();
        self.groups = coarse_bits(&self.bits, self.res, GROUP, std::mem::take(&mut self.groups));
        self.group_distance.compute(&self.groups, self.group_resolution());
    }

    /// The density estimate of a cell (local units; 0 in a rendering grid,
    /// which keeps none).
    #[inline]
    pub fn cell_density(&self, cell: usize) -> f32 {
        self.density.get(cell).copied().unwrap_or(0.0)
    }

    /// Whether the point may hold density (false outside the cube).
    #[inline]
    pub fn is_occupied(&self, p: [f32; 3]) -> bool {
        self.cell_of(p).is_some_and(|c| self.is_occupied_cell(c))
    }

    /// Carve the free space seen by depth rays: a cell is emptied when rays
    /// passed through it well before their surface clearly more often than
    /// rays ended in it; cells no ray observed stay occupied. The space the
    /// training `cameras` vouch for is carved as well (see
    /// [`Self::camera_vouched`]).
    pub fn seed_from_depth(&mut self, rays: &[DepthRay], cameras: &[CameraSpace]) {
        self.seed_from_depth_and_no_return(rays, &[], cameras);
    }

    /// [`Self::seed_from_depth`], where the rays of pixels the sensor
    /// returned nothing for (`no_return`, their `t_hit` unused) also vote:
    /// the cells they cross may hold what the sensor cannot see (glass), so
    /// each pass through a cell's core offsets one depth ray's. A cell is
    /// coarse (5 cm on the tabletop scenes): rays grazing over a 9 cm glass
    /// pass through the core of the cell holding its top, and whether the
    /// cells beside it stayed unexplained (which alone kept it) flipped with
    /// a tenth of a pixel of pose: one of five fits of the SLAM-like
    /// tabletop with exact poses lost the glass's upper half. Weighed like surface votes (three depth rays
    /// each), they kept too much around it: the realistic tabletop (seed 3)
    /// labelled the glass 0.954 against 0.979, too small.
    pub fn seed_from_depth_and_no_return(
        &mut self,
        rays: &[DepthRay],
        no_return: &[DepthRay],
        cameras: &[CameraSpace],
    ) {
        let res = self.res;
        let cells = res * res * res;
        let surface_votes = self.surface_votes(rays);
        let cell = 1.0 / res as f32;
        let step = 0.25 * cell;
        let margin = 2.0 * cell;
        // Depth rays up to their surface, no-return rays through the cube.
        let free_votes = core_pass_votes(
            rays,
            cells,
            |ray, t1| (ray.t_hit.is_finite() && ray.t_hit > 0.0).then(|| (ray.t_hit - margin).min(t1)),
            step,
            res,
        );
        let unseen_votes = core_pass_votes(no_return, cells, |_, t1| Some(t1), step, res);
        let mut seen_free = vec![false; cells];
        for i in 0..cells {
            let free = free_votes[i] as u32;
            let (surface, unseen) = (surface_votes[i] as u32, unseen_votes[i] as u32);
            // A stray flying pixel cannot carve an object: need a clear majority.
            seen_free[i] = surface + unseen == 0 && free >= 2 || free > 3 * surface + unseen + 2;
        }
        // Erode by one cell next to unexplained space: a free cell beside
        // space that is neither seen free nor near a measured surface may
        // still hold part of an object the sensor missed (glass), which
        // carving would make unlearnable. Beside measured surfaces carving
        // stays tight, else silhouettes grow a fringe of haze.
        // Cameras are the exception: behind one all space is unobserved.
        let explained = |n: usize| seen_free[n] || surface_votes[n] > 0;
        let vouched = self.camera_vouched(cameras, rays);
        for i in 0..cells {
            let eroded = seen_free[i] && all_neighbours(i, res, explained);
            if eroded || vouched[i] && surface_votes[i] == 0 {
                self.carve(i);
            }
        }
        self.rebuild_bits();
    }

    /// Make the carved cells unknown again (the faint initial estimate),
    /// before seeding from depth seen through corrected poses.
    pub fn forget_carving(&mut self) {
        let initial = initial_density(self.res);
        for cell in 0..self.density.len() {
            if self.is_carved(cell) {
                self.density[cell] = initial;
            }
        }
        self.carved.iter_mut().for_each(|w| *w = 0);
        self.rebuild_bits();
    }

    /// Empty `cell` for good (until [`Self::forget_carving`]).
    fn carve(&mut self, cell: usize) {
        self.density[cell] = 0.0;
        self.carved[cell >> 6] |= 1 << (cell & 63);
    }

    /// Per cell, the depth rays that ended in it or in one of its 26 neighbours.
    fn surface_votes(&self, rays: &[DepthRay]) -> Vec<u16> {
        let res = self.res;
        let mut votes = vec![0u16; res * res * res];
        for ray in rays.iter().filter(|r| r.t_hit.is_finite() && r.t_hit > 0.0) {
            let Some(c) = self.cell_of(along(ray.origin, ray.dir, ray.t_hit)) else {
                continue;
            };
            let (x, y, z) = (c % res, (c / res) % res, c / (res * res));
            let span = |v: usize| v.saturating_sub(1)..=(v + 1).min(res - 1);
            for nz in span(z) {
                for ny in span(y) {
                    for nx in span(x) {
                        let n = (nz * res + ny) * res + nx;
                        votes[n] = votes[n].saturating_add(1);
                    }
                }
            }
        }
        votes
    }

    /// Cells the cameras vouch for as free: the cell each stood in, the
    /// cells its depth rays cross nearer than its `free_distance` (nothing
    /// it measured was that near), and the ball of the smallest such
    /// distance around every camera, held-out ones (free distance 0)
    /// included. Left occupied, the spot every ray of a view passes through
    /// can grow a floater that blinds that view: on the realistic tabletop a
    /// held-out view beside the training cameras' cones rendered a third of
    /// its pixels 1 cm away after 1505 steps.
    fn camera_vouched(&self, cameras: &[CameraSpace], rays: &[DepthRay]) -> Vec<bool> {
        let mut free = vec![false; self.density.len()];
        let key = |o: [f32; 3]| o.map(f32::to_bits);
        let mut free_distance = std::collections::HashMap::new();
        for cam in cameras {
            if let Some(c) = self.cell_of(cam.origin) {
                free[c] = true;
            }
            if cam.free_distance.is_finite() && cam.free_distance > 0.0 {
                free_distance.insert(key(cam.origin), cam.free_distance);
            }
        }
        // No camera came nearer to anything it measured than this: the ball
        // of that radius around every camera is free, beside and behind it too.
        let reach = free_distance.values().copied().fold(f32::INFINITY, f32::min);
        if reach.is_finite() {
            for cam in cameras {
                self.mark_ball(cam.origin, reach, &mut free);
            }
        }
        let step = 0.25 / self.res as f32;
        // A depth ray belongs to the camera it starts from (same origin bits).
        let march = |part: &[DepthRay]| {
            let mut crossed = Vec::new();
            for ray in part {
                let Some(&reach) = free_distance.get(&key(ray.origin)) else {
                    continue;
                };
                let Some((t0, t1)) = unit_cube_interval(ray.origin, ray.dir) else {
                    continue;
                };
                let mut t = t0;
                while t < reach.min(t1) {
                    if let Some(c) = self.cell_of(along(ray.origin, ray.dir, t)) {
                        crossed.push(c);
                    }
                    t += step;
                }
            }
            crossed
        };
        let part_len = rays.len().div_ceil(4 * rayon::current_num_threads().max(1)).max(1);
        let crossed: Vec<Vec<usize>> = rays.par_chunks(part_len).map(march).collect();
        for c in crossed.into_iter().flatten() {
            free[c] = true;
        }
        free
    }

    /// Set `marks` of the cells whose centres lie within `radius` of `centre`.
    fn mark_ball(&self, centre: [f32; 3], radius: f32, marks: &mut [bool]) {
        let res = self.res;
        let r = res as f32;
        let span = |c: f32| {
            let lo = ((c - radius) * r).floor().max(0.0) as usize;
            let hi = (((c + radius) * r).ceil().max(0.0) as usize).min(res);
            lo..hi
        };
        for z in span(centre[2]) {
            for y in span(centre[1]) {
                for x in span(centre[0]) {
                    let p = [x, y, z].map(|v| (v as f32 + 0.5) / r);
                    let d2: f32 = (0..3).map(|a| (p[a] - centre[a]).powi(2)).sum();
                    if d2 <= radius * radius {
                        marks[(z * res + y) * res + x] = true;
                    }
                }
            }
        }
    }

    /// Carve every cell no training camera sees (no part of it projects
    /// into any of their images): nothing supervises density there, so
    /// whatever the field holds is noise, and a view from elsewhere (a
    /// held-out frame, a synthesised pose) would render it as a floater.
    pub fn carve_unseen(&mut self, cameras: &[LocalCamera]) {
        if cameras.is_empty() {
            return;
        }
        let res = self.res;
        let cell = 1.0 / res as f32;
        // Radius of the sphere around a cell.
        let radius = 0.5 * 3f32.sqrt() * cell;
        let frusta: Vec<Frustum> = cameras.iter().map(Frustum::new).collect();
        let seen: Vec<bool> = (0..res * res * res)
            .into_par_iter()
            .map(|i| {
                let centre = [
                    (i % res) as f32 + 0.5,
                    ((i / res) % res) as f32 + 0.5,
                    (i / (res * res)) as f32 + 0.5,
                ]
                .map(|c| c * cell);
                frusta.iter().any(|f| f.may_hold_sphere(centre, radius))
            })
            .collect();
        for (i, _) in seen.iter().enumerate().filter(|&(_, &s)| !s) {
            self.carve(i);
        }
        self.rebuild_bits();
    }

    /// Re-estimate density in one interleaved subset of the cells from the
    /// model (`density_at` fills sigma for a batch of local points), decaying
    /// the old estimate, and rebuild the bits.
    pub fn refresh<F>(
        &mut self,
        decay: f32,
        rng: &mut Rng,
        positions: &mut Vec<[f32; 3]>,
        sigmas: &mut Vec<f32>,
        mut density_at: F,
    ) where
        F: FnMut(&[[f32; 3]], &mut [f32]),
    {
        let res = self.res;
        let cells = res * res * res;
        let phase = self.refresh_phase;
        self.refresh_phase = (phase + 1) % REFRESH_PARTS;
        positions.clear();
        let inv = 1.0 / res as f32;
        let mut cell = phase;
        while cell < cells {
            let (x, y, z) = (cell % res, (cell / res) % res, cell / (res * res));
            positions.push([
                (x as f32 + rng.f32()) * inv,
                (y as f32 + rng.f32()) * inv,
                (z as f32 + rng.f32()) * inv,
            ]);
            cell += REFRESH_PARTS;
        }
        sigmas.clear();
        sigmas.resize(positions.len(), 0.0);
        density_at(positions, sigmas);
        for (k, &sigma) in sigmas.iter().enumerate() {
            let c = phase + k * REFRESH_PARTS;
            let sigma = if sigma.is_finite() { sigma.max(0.0) } else { 0.0 };
            self.density[c] = (self.density[c] * decay).max(sigma);
        }
        self.rebuild_bits();
    }

    /// Whether the sensor saw this cell as free space.
    #[inline]
    fn is_carved(&self, cell: usize) -> bool {
        (self.carved[cell >> 6] >> (cell & 63)) & 1 == 1
    }

    /// Recompute the bit mask from the density estimates (carved cells need
    /// the higher threshold); keeps a minimum fraction of the densest cells
    /// so the grid never empties.
    fn rebuild_bits(&mut self) {
        let cells = self.density.len();
        let min_occupied = ((cells as f64 * MIN_OCCUPIED_FRACTION) as usize).max(1);
        self.bits.iter_mut().for_each(|w| *w = 0);
        let mut count = 0;
        for i in 0..cells {
            // Space the sensor never saw free stays occupied (objects without
            // depth must keep their samples); space it saw free stays empty,
            // so floaters grown there by colour-only rays are never rendered.
            if !self.is_carved(i) {
                self.bits[i >> 6] |= 1 << (i & 63);
                count += 1;
            }
        }
        if count < min_occupied {
            // Keep the densest cells (ties by index) rather than an empty grid.
            let mut order: Vec<(f32, usize)> = self.density.iter().copied().zip(0..).collect();
            order.select_nth_unstable_by(min_occupied - 1, |a, b| b.0.total_cmp(&a.0).then(a.1.cmp(&b.1)));
            for &(_, i) in &order[..min_occupied] {
                self.bits[i >> 6] |= 1 << (i & 63);
            }
        }
        self.finish_bits();
    }

    /// Grid for rendering: every cell re-sampled once more from the model
    /// (keeping the running maximum of earlier refreshes, so thin surfaces
    /// a single sample misses survive), then cells whose estimated optical
    /// depth is negligible dropped. Untrained haze behind surfaces and in
    /// space no camera saw is never marched; carved space stays empty.
    pub fn prune_for_rendering<F>(
        &mut self,
        rng: &mut Rng,
        positions: &mut Vec<[f32; 3]>,
        sigmas: &mut Vec<f32>,
        mut density_at: F,
    ) where
        F: FnMut(&[[f32; 3]], &mut [f32]),
    {
        for _ in 0..REFRESH_PARTS {
            self.refresh(1.0, rng, positions, sigmas, &mut density_at);
        }
        self.restrict_to_rendering();
    }

    /// Keep only cells dense enough to matter in a render (see
    /// [`Self::prune_for_rendering`]); a grid whose estimates are all
    /// negligible (nothing trained) is left as it is.
    pub fn restrict_to_rendering(&mut self) {
        let min_density = RENDER_MIN_CELL_OPTICAL_DEPTH * self.res as f32;
        let cells = self.density.len();
        let min_occupied = ((cells as f64 * MIN_OCCUPIED_FRACTION) as usize).max(1);
        let dense_count = (0..cells)
            .filter(|&i| !self.is_carved(i) && self.density[i] >= min_density)
            .count();
        if dense_count < min_occupied {
            // Nothing trained yet: keep the full training grid.
            return;
        }
        // One cell of margin around dense cells: a thin surface inside a
        // cell can be missed by the cell's samples while the cell behind it
        // is dense, and skipping it would put the surface a cell too far.
        let dense: Vec<bool> = (0..cells)
            .map(|i| !self.is_carved(i) && self.density[i] >= min_density)
            .collect();
        let res = self.res;
        self.bits.iter_mut().for_each(|w| *w = 0);
        for i in 0..cells {
            if !self.is_carved(i) && (dense[i] || !all_neighbours(i, res, |n| !dense[n])) {
                self.bits[i >> 6] |= 1 << (i & 63);
            }
        }
        self.finish_bits();
    }

    /// Carved-cell mask (for the model file).
    pub fn carved_words(&self) -> &[u64] {
        &self.carved
    }

    /// Distance along a ray from `p` to where it leaves the cell holding `p`.
    #[inline]
    pub fn distance_to_cell_exit(&self, p: [f32; 3], dir: [f32; 3]) -> f32 {
        let r = self.res as f32;
        let mut best = f32::INFINITY;
        for a in 0..3 {
            let d = dir[a];
            if d == 0.0 {
                continue;
            }
            let c = (p[a] * r).floor();
            let boundary = if d > 0.0 { (c + 1.0) / r } else { c / r };
            let t = (boundary - p[a]) / d;
            if t < best {
                best = t;
            }
        }
        best.max(0.0)
    }

    /// Packed occupancy bits (for the model file).
    pub fn bits(&self) -> &[u64] {
        &self.bits
    }

    /// Density estimates (for the model file).
    pub fn densities(&self) -> &[f32] {
        &self.density
    }

    /// Which interleaved subset of cells the next refresh evaluates (for checkpoints).
    pub fn refresh_phase(&self) -> usize {
        self.refresh_phase
    }

    /// Continue refreshing from a saved phase (taken modulo the number of subsets).
    pub fn set_refresh_phase(&mut self, phase: usize) {
        self.refresh_phase = phase % REFRESH_PARTS;
    }

    /// A grid for rendering only, from its occupancy bits (x-fastest cells,
    /// 64 per word): it keeps no density estimates, so it can be marched but
    /// not refreshed or saved. `None` when the sizes do not match.
    pub fn from_occupied_bits(res: usize, bits: Vec<u64>) -> Option<Self> {
        let words = res.checked_pow(3)?.div_ceil(64);
        if !(4..=MAX_RESOLUTION).contains(&res) || bits.len() != words {
            return None;
        }
        let mut grid = OccupancyGrid {
            res,
            density: Vec::new(),
            bits,
            groups: Vec::new(),
            group_distance: CoarseDistances::default(),
            carved: vec![0; words],
            occupied: 0,
            refresh_phase: 0,
        };
        grid.finish_bits();
        Some(grid)
    }

    /// A grid keeping exactly the cells `(x, y, z)` for which `keep` holds
    /// (density 1 there), for tests.
    #[cfg(test)]
    pub(crate) fn keeping(res: usize, keep: impl Fn([usize; 3]) -> bool) -> Self {
        let mut carved = vec![0u64; (res * res * res).div_ceil(64)];
        for cell in 0..res * res * res {
            if !keep([cell % res, (cell / res) % res, cell / (res * res)]) {
                carved[cell >> 6] |= 1 << (cell & 63);
            }
        }
        OccupancyGrid::from_saved(res, vec![1.0; res * res * res], carved).expect("a valid test grid")
    }

    /// Rebuild a grid from saved density estimates and carved mask.
    pub fn from_saved(res: usize, density: Vec<f32>, carved: Vec<u64>) -> Option<Self> {
        let mut grid = OccupancyGrid::full(res);
        if density.len() != grid.density.len() || carved.len() != grid.carved.len() {
            return None;
        }
        grid.carved = carved;
        grid.density = density
            .into_iter()
            .map(|d| if d.is_finite() { d.max(0.0) } else { 0.0 })
            .collect();
        grid.rebuild_bits();
        Some(grid)
    }
}

/// The bit of coarse cell `at` in a level of `cr` cells per axis built by [`coarse_bits`].
#[inline]
fn coarse_bit(words: &[u64], cr: usize, at: [usize; 3]) -> bool {
    let i = (at[2] * cr + at[1]) * cr + at[0];
    (words[i >> 6] >> (i & 63)) & 1 == 1
}

/// One bit per `size`^3 cells of a `res`^3 bit grid, set when any of its
/// cells is (reusing `buf`).
fn coarse_bits(bits: &[u64], res: usize, size: usize, mut buf: Vec<u64>) -> Vec<u64> {
    let cr = res.div_ceil(size);
    buf.clear();
    buf.resize((cr * cr * cr).div_ceil(64), 0);
    for (w, &word) in bits.iter().enumerate() {
        let mut rest = word;
        while rest != 0 {
            let bit = rest.trailing_zeros() as usize;
            let cell = w * 64 + bit;
            let (x, y, z) = (cell % res, (cell / res) % res, cell / (res * res));
            let c = ((z / size) * cr + y / size) * cr + x / size;
            buf[c >> 6] |= 1 << (c & 63);
            // The next cells along x up to the coarse cell's edge are in the same one.
            let run = (size - x % size).min(res - x);
            rest &= if bit + run >= 64 { 0 } else { !0u64 << (bit + run) };
        }
    }
    buf
}

/// Per coarse cell of a level of `cr` cells per axis, the Chebyshev
/// distance to the nearest set one: 0 when set, saturating at 255, `cr`
/// when none is set. Stored with one never-set cell of padding on every
/// side, so the passes need no edge tests.
#[derive(Clone, Debug, Default)]
struct CoarseDistances {
    side: usize,
    values: Vec<u8>,
}

impl CoarseDistances {
    /// Distance of coarse cell `at` (each coordinate below `cr`).
    #[inline]
    fn at(&self, at: [usize; 3]) -> u8 {
        self.values[((at[2] + 1) * self.side + at[1] + 1) * self.side + at[0] + 1]
    }

    /// Recompute from the level's bits (as built by [`coarse_bits`]),
    /// reusing the buffer. Two chamfer passes over the 26 neighbours, each
    /// at distance 1, are exact for this metric.
    fn compute(&mut self, words: &[u64], cr: usize) {
        let far = cr.min(255) as u8;
        let side = cr + 2;
        self.side = side;
        let values = &mut self.values;
        values.clear();
        values.resize(side * side * side, far);
        for z in 0..cr {
            for y in 0..cr {
                let padded = ((z + 1) * side + y + 1) * side + 1;
                for x in 0..cr {
                    if coarse_bit(words, cr, [x, y, z]) {
                        values[padded + x] = 0;
                    }
                }
            }
        }
        // The neighbours met before a cell in x-fastest order, as index
        // offsets: the 12 in earlier rows (vectorisable along the row), then
        // the previous cell of the row (a running scan).
        let mut earlier_rows = Vec::with_capacity(12);
        for dz in -1isize..=0 {
            for dy in -1isize..=1 {
                if (dz, dy) < (0, 0) {
                    for dx in -1isize..=1 {
                        earlier_rows.push(((-dz * side as isize - dy) * side as isize - dx) as usize);
                    }
                }
            }
        }
        let row_start = |z: usize, y: usize| (z * side + y) * side + 1;
        for z in 1..=cr {
            for y in 1..=cr {
                let start = row_start(z, y);
                let (before, row) = values.split_at_mut(start);
                for &o in &earlier_rows {
                    relax_row(&mut row[..cr], &before[start - o..start - o + cr]);
                }
                for i in start..start + cr {
                    values[i] = values[i].min(values[i - 1].saturating_add(1));
                }
            }
        }
        for z in (1..=cr).rev() {
            for y in (1..=cr).rev() {
                let start = row_start(z, y);
                let (row, after) = values.split_at_mut(start + cr);
                for &o in &earlier_rows {
                    relax_row(&mut row[start..], &after[o - cr..o]);
                }
                for i in (start..start + cr).rev() {
                    values[i] = values[i].min(values[i + 1].saturating_add(1));
                }
            }
        }
    }
}

/// `row[i] = min(row[i], from[i] + 1)`: one neighbour's offer to a row.
#[inline]
fn relax_row(row: &mut [u8], from: &[u8]) {
    for (r, f) in row.iter_mut().zip(from) {
        *r = (*r).min(f.saturating_add(1));
    }
}

/// Whether `keep` holds for every cell of the 3x3x3 block around `cell`
/// that lies inside the grid.
fn all_neighbours(cell: usize, res: usize, keep: impl Fn(usize) -> bool) -> bool {
    let (x, y, z) = (cell % res, (cell / res) % res, cell / (res * res));
    let span = |v: usize| v.saturating_sub(1)..=(v + 1).min(res - 1);
    span(z).all(|nz| span(y).all(|ny| span(x).all(|nx| keep((nz * res + ny) * res + nx))))
}

/// Half-width (in cells, per axis) of the core a free-space ray must cross.
const CORE_RADIUS: f32 = 0.3;

// Cell indices fit in u32: MAX_RESOLUTION^3 < 2^32.
const _: () = assert!(MAX_RESOLUTION * MAX_RESOLUTION * MAX_RESOLUTION <= u32::MAX as usize);

/// Samples placed per batch by [`count_free_passes`].
const PASS_BATCH: usize = 64;

/// Marker of a sample outside every cell's core.
const NO_CORE: u32 = u32::MAX;

/// Adds one vote to each cell whose core the samples `t0, t0 + step, ...`
/// below `t_end` of `ray` pass through (once per pass, not per sample).
/// Only a pass through the core of a cell counts as seeing it free: a ray
/// grazing a thin object in a corner must not carve it. The samples are
/// placed in batches, and each batch's cells are found in one branch-free
/// loop (AVX2 where the CPU has it, see [`vectorised`]): the same votes as testing the samples
/// one by one, at a fraction of the time.
fn count_free_passes(ray: &DepthRay, t0: f32, t_end: f32, step: f32, res: usize, votes: &mut [u16]) {
    let mut ts = [0.0f32; PASS_BATCH];
    let mut cells = [NO_CORE; PASS_BATCH];
    let mut t = t0;
    let mut last = NO_CORE;
    while t < t_end {
        let mut n = 0;
        // Sequential sums, as a sample-by-sample march would place them.
        while n < PASS_BATCH && t < t_end {
            ts[n] = t;
            t += step;
            n += 1;
        }
        vectorised(|| core_cells(ray.origin, ray.dir, &ts[..n], res, &mut cells[..n]));
        for &c in &cells[..n] {
            if c != NO_CORE && c != last {
                votes[c as usize] = votes[c as usize].saturating_add(1);
                last = c;
            }
        }
    }
}

/// Per cell, how many of `rays` pass through its core, each from where it
/// enters the unit cube to where `end` (given the ray and its exit) says,
/// or not at all (`None`). One vote array per thread, summed after:
/// saturating sums of the parts equal the saturating count, so the result
/// is the serial one.
fn core_pass_votes<E>(rays: &[DepthRay], cells: usize, end: E, step: f32, res: usize) -> Vec<u16>
where
    E: Fn(&DepthRay, f32) -> Option<f32> + Sync,
{
    let march = |part: &[DepthRay]| {
        let mut votes = vec![0u16; cells];
        for ray in part {
            let Some((t0, t1)) = unit_cube_interval(ray.origin, ray.dir) else {
                continue;
            };
            if let Some(t_end) = end(ray, t1) {
                count_free_passes(ray, t0, t_end, step, res, &mut votes);
            }
        }
        votes
    };
    let part_len = rays.len().div_ceil(rayon::current_num_threads().max(1)).max(1);
    rays.par_chunks(part_len)
        .map(march)
        .reduce_with(|mut a, b| {
            for (x, y) in a.iter_mut().zip(&b) {
                *x = x.saturating_add(*y);
            }
            a
        })
        .unwrap_or_else(|| vec![0u16; cells])
}

/// For each `t`, the cell whose core holds `o + t d`, or [`NO_CORE`]: a lane
/// loop written without branches so that it vectorises, the same arithmetic
/// as [`cell_index`] per sample plus the core test.
#[inline(always)]
fn core_cells(o: [f32; 3], d: [f32; 3], ts: &[f32], res: usize, cells: &mut [u32]) {
    let r = res as f32;
    let res = res as u32;
    for (cell, &t) in cells.iter_mut().zip(ts) {
        let p = along(o, d, t);
        let mut inside = true;
        let mut idx = [0u32; 3];
        for a in 0..3 {
            let c = p[a] * r;
            // `c` in [0, r): truncation is its floor (NaN fails the range test).
            let i = c as u32;
            inside &= (c >= 0.0) & (c < r) & ((c - i as f32 - 0.5).abs() <= CORE_RADIUS);
            idx[a] = i;
        }
        let index = (idx[2].wrapping_mul(res).wrapping_add(idx[1]))
            .wrapping_mul(res)
            .wrapping_add(idx[0]);
        *cell = if inside { index } else { NO_CORE };
    }
}

#[inline]
fn along(o: [f32; 3], d: [f32; 3], t: f32) -> [f32; 3] {
    [o[0] + t * d[0], o[1] + t * d[1], o[2] + t * d[2]]
}

/// A camera's view frustum: its centre, its axes and the unit normals of
/// the four planes through the centre and an image edge (camera axes,
/// pointing inwards).
struct Frustum {
    origin: [f32; 3],
    /// Camera-to-local rotation, row-major.
    rotation: [[f32; 3]; 3],
    planes: [[f32; 3]; 4],
}

impl Frustum {
    fn new(cam: &LocalCamera) -> Frustum {
        // u >= -0.5 <=> fx x + (cx + 0.5) z >= 0 in front of the camera;
        // the other edges alike.
        let (w, h) = (cam.width as f32 - 0.5, cam.height as f32 - 0.5);
        let planes = [
            [cam.fx, 0.0, cam.cx + 0.5],
            [-cam.fx, 0.0, w - cam.cx],
            [0.0, cam.fy, cam.cy + 0.5],
            [0.0, -cam.fy, h - cam.cy],
        ]
        .map(|n| {
            let len = (n[0] * n[0] + n[1] * n[1] + n[2] * n[2]).sqrt();
            n.map(|c| c / len)
        });
        Frustum {
            origin: cam.origin,
            rotation: cam.rotation,
            planes,
        }
    }

    /// Whether the sphere (`centre`, `radius`) may reach into the frustum:
    /// it is not wholly behind the camera nor wholly outside one of the four
    /// planes (conservative near the frustum's edges, exact on its faces).
    fn may_hold_sphere(&self, centre: [f32; 3], radius: f32) -> bool {
        let o = self.origin;
        let d = [centre[0] - o[0], centre[1] - o[1], centre[2] - o[2]];
        let r = &self.rotation;
        // Camera-to-local rotation transposed: local offset -> camera axes.
        let [x, y, z] = [0, 1, 2].map(|a| r[0][a] * d[0] + r[1][a] * d[1] + r[2][a] * d[2]);
        z >= -radius && self.planes.iter().all(|n| n[0] * x + n[1] * y + n[2] * z >= -radius)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The march `seed_from_depth` made before its samples were batched:
    /// one sample at a time, testing the cell and its core per sample.
    fn free_passes_one_by_one(ray: &DepthRay, t0: f32, t_end: f32, step: f32, res: usize, votes: &mut [u16]) {
        let near_centre = |p: [f32; 3]| {
            p.iter().all(|&c| {
                let x = c * res as f32;
                (x - x as u32 as f32 - 0.5).abs() <= CORE_RADIUS
            })
        };
        let (mut t, mut last) = (t0, usize::MAX);
        while t < t_end {
            let p = along(ray.origin, ray.dir, t);
            if let Some(c) = cell_index(p, res) {
                if c != last && near_centre(p) {
                    votes[c] = votes[c].saturating_add(1);
                    last = c;
                }
            }
            t += step;
        }
    }

    #[test]
    fn batched_free_passes_vote_as_the_sample_by_sample_march() {
        let mut rng = Rng::new(41, 0);
        let mut passes = 0usize;
        for res in [4usize, 7, 32, 128] {
            let cells = res * res * res;
            let (mut batched, mut reference) = (vec![0u16; cells], vec![0u16; cells]);
            for k in 0..400 {
                // Origins inside and around the cube, some rays along an axis
                // (samples on cell faces), and one NaN direction.
                let origin = [0; 3].map(|_| 1.4 * rng.f32() - 0.2);
                let mut dir = [0; 3].map(|_| rng.f32() - 0.5);
                if k % 7 == 0 {
                    dir = [1.0, 0.0, 0.0];
                }
                if k == 5 {
                    dir[1] = f32::NAN;
                }
                let norm = dir.iter().map(|d| d * d).sum::<f32>().sqrt();
                let ray = DepthRay {
                    origin,
                    dir: dir.map(|d| d / norm),
                    t_hit: 2.0 * rng.f32(),
                };
                let step = 0.25 / res as f32 * (0.5 + rng.f32());
                let t0 = -0.3 * rng.f32();
                count_free_passes(&ray, t0, ray.t_hit, step, res, &mut batched);
                free_passes_one_by_one(&ray, t0, ray.t_hit, step, res, &mut reference);
            }
            assert_eq!(batched, reference, "res {res}");
            passes += reference.iter().map(|&v| v as usize).sum::<usize>();
        }
        assert!(passes > 5_000, "the rays pass through cores: {passes} votes");
    }

    /// Three depth rays along +z through the centre of each cell column
    /// (x, y) in 8..24 of a 32^3 grid whose x passes `seen`, hitting at `t_hit`.
    fn wall_rays(t_hit: f32, seen: impl Fn(usize) -> bool) -> Vec<DepthRay> {
        let mut rays = Vec::new();
        for i in (8..24).filter(|&i| seen(i)) {
            for j in 8..24 {
                let (x, y) = ((i as f32 + 0.5) / 32.0, (j as f32 + 0.5) / 32.0);
                for _ in 0..3 {
                    rays.push(DepthRay {
                        origin: [x, y, 0.0],
                        dir: [0.0, 0.0, 1.0],
                        t_hit,
                    });
                }
            }
        }
        rays
    }

    #[test]
    fn coarse_distances_are_the_chebyshev_distance_to_the_nearest_set_cell() {
        let mut rng = crate::rng::Rng::new(5, 0);
        let cr = 11;
        for density in [0.0, 0.002, 0.02, 0.3] {
            let set: Vec<bool> = (0..cr * cr * cr).map(|_| rng.f32() < density).collect();
            let mut words = vec![0u64; set.len().div_ceil(64)];
            for (i, _) in set.iter().enumerate().filter(|(_, s)| **s) {
                words[i >> 6] |= 1 << (i & 63);
            }
            let mut dist = CoarseDistances::default();
            dist.compute(&words, cr);
            let at = |i: usize| [i % cr, (i / cr) % cr, i / (cr * cr)];
            for i in 0..set.len() {
                let found = dist.at(at(i));
                let brute = (0..set.len())
                    .filter(|&j| set[j])
                    .map(|j| (0..3).map(|a| at(i)[a].abs_diff(at(j)[a])).max().unwrap())
                    .min()
                    .unwrap_or(cr);
                assert_eq!(found as usize, brute, "density {density}, group {:?}", at(i));
            }
        }
    }

    #[test]
    fn seeding_gives_the_same_grid_on_any_number_of_threads() {
        // Rays from a camera in front of the wall (it vouches for the space
        // near it), some ending at the wall, some without depth.
        let mut rays = wall_rays(0.5, |i| i % 3 != 0);
        rays.extend(wall_rays(f32::INFINITY, |i| i % 3 == 0));
        for (k, ray) in rays.iter_mut().enumerate() {
            ray.origin = [0.5, 0.5, 0.05];
            ray.dir = [((k % 7) as f32 - 3.0) * 0.05, ((k % 5) as f32 - 2.0) * 0.05, 1.0];
            let n = ray.dir.iter().map(|d| d * d).sum::<f32>().sqrt();
            ray.dir = ray.dir.map(|d| d / n);
        }
        let cameras = [CameraSpace {
            origin: [0.5, 0.5, 0.05],
            free_distance: 0.2,
        }];
        let seeded = |threads: usize| {
            let pool = rayon::ThreadPoolBuilder::new().num_threads(threads).build().unwrap();
            pool.install(|| {
                let mut grid = OccupancyGrid::full(32);
                grid.seed_from_depth(&rays, &cameras);
                grid
            })
        };
        let one = seeded(1);
        assert!(one.occupied_fraction() < 1.0, "something was carved");
        for threads in [2, 3] {
            let many = seeded(threads);
            assert_eq!(one.carved, many.carved, "{threads} threads");
            assert_eq!(one.density, many.density, "{threads} threads");
        }
    }

    #[test]
    fn carving_empties_seen_free_space_and_keeps_surfaces_and_unseen_cells() {
        let mut grid = OccupancyGrid::full(32);
        // Rays along +z through cell centres of the middle, hitting a wall at z = 0.5.
        grid.seed_from_depth(&wall_rays(0.5, |_| true), &[]);
        assert!(
            !grid.is_occupied([0.5, 0.5, 0.2]),
            "free space before the wall is carved"
        );
        assert!(grid.is_occupied([0.5, 0.5, 0.5]), "surface stays");
        assert!(grid.is_occupied([0.5, 0.5, 0.8]), "behind the wall is unobserved");
        assert!(grid.is_occupied([0.05, 0.05, 0.2]), "never seen stays occupied");
        assert!(grid.occupied_fraction() > 0.5 && grid.occupied_fraction() < 1.0);
    }

    #[test]
    fn carving_forgotten_and_seeded_again_is_the_carving_of_the_new_rays_alone() {
        // Rays first seen through a pose 4 cells off along x: they carve
        // columns the corrected rays leave alone (an object without depth there).
        let shifted: Vec<DepthRay> = wall_rays(0.5, |_| true)
            .into_iter()
            .map(|r| DepthRay {
                origin: [r.origin[0] - 4.0 / 32.0, r.origin[1], r.origin[2]],
                ..r
            })
            .collect();
        let corrected = wall_rays(0.5, |i| i >= 12);
        let mut grid = OccupancyGrid::full(32);
        grid.seed_from_depth(&shifted, &[]);
        let object = [5.5 / 32.0, 0.5, 0.2];
        assert!(!grid.is_occupied(object), "the shifted rays carved the object's column");
        let cell = grid.cell_of([0.5, 0.5, 0.5]).unwrap();
        grid.density[cell] = 7.0;
        grid.forget_carving();
        assert_eq!(grid.occupied_fraction(), 1.0, "nothing is carved once forgotten");
        assert_eq!(grid.density[cell], 7.0, "estimates of cells never carved are kept");
        let carved = grid.cell_of(object).unwrap();
        assert_eq!(
            grid.density[carved],
            initial_density(32),
            "carved cells are unknown again"
        );
        grid.seed_from_depth(&corrected, &[]);
        let mut fresh = OccupancyGrid::full(32);
        fresh.seed_from_depth(&corrected, &[]);
        assert_eq!(grid.carved, fresh.carved);
        assert_eq!(grid.bits, fresh.bits);
        assert!(grid.is_occupied(object), "the object's column is back");
    }

    #[test]
    fn cells_the_sensor_returned_nothing_through_are_not_carved_by_a_few_grazing_rays() {
        // Depth rays along +x through the cores of rows z = 3..8 (space in
        // front of a glass, nine rays each) and z = 10..15 (where the glass
        // stands in columns x, y = 14..18: three rays each, grazing it
        // within coarse cells), hitting a wall at x = 0.9.
        let centre = |i: usize| (i as f32 + 0.5) / 32.0;
        let mut rays = Vec::new();
        for (rows, count) in [(3..8, 9), (10..15, 3)] {
            for z in rows {
                for y in 8..24 {
                    for _ in 0..count {
                        rays.push(DepthRay {
                            origin: [0.0, centre(y), centre(z)],
                            dir: [1.0, 0.0, 0.0],
                            t_hit: 0.9,
                        });
                    }
                }
            }
        }
        // The glass seen from below: the sensor returned nothing.
        let no_return: Vec<DepthRay> = (14..18)
            .flat_map(|x| {
                (14..18).map(move |y| DepthRay {
                    origin: [centre(x), centre(y), 0.0],
                    dir: [0.0, 0.0, 1.0],
                    t_hit: f32::INFINITY,
                })
            })
            .collect();
        let (glass, in_front) = (
            [centre(16), centre(16), centre(12)],
            [centre(16), centre(16), centre(5)],
        );
        let mut depth_only = OccupancyGrid::full(32);
        depth_only.seed_from_depth(&rays, &[]);
        assert!(!depth_only.is_occupied(glass), "grazing rays alone carve the glass");
        let mut grid = OccupancyGrid::full(32);
        grid.seed_from_depth_and_no_return(&rays, &no_return, &[]);
        assert!(grid.is_occupied(glass), "the glass the sensor did not see stays");
        assert!(
            !grid.is_occupied(in_front),
            "free space seen clearly more often is still carved"
        );
        assert!(
            !grid.is_occupied([centre(4), centre(16), centre(12)]),
            "rows the no-return rays miss carve as before"
        );
    }

    #[test]
    fn free_space_beside_a_measured_surface_is_carved_tight() {
        let mut grid = OccupancyGrid::full(32);
        // A wall inside cell 16 seen along +z: cells 15..=17 hold the surface
        // neighbourhood, cells up to 14 were crossed well before it.
        grid.seed_from_depth(&wall_rays(0.53, |_| true), &[]);
        let at = |z_cell: f32| [0.5, 0.5, (z_cell + 0.5) / 32.0];
        // No haze layer in front of a measured surface (it would fringe silhouettes).
        assert!(
            !grid.is_occupied(at(14.0)),
            "the free cell touching the surface neighbourhood is carved"
        );
        assert!(
            grid.is_occupied(at(15.0)) && grid.is_occupied(at(16.0)),
            "the surface neighbourhood stays"
        );
    }

    #[test]
    fn space_next_to_a_region_without_depth_stays_occupied() {
        let mut grid = OccupancyGrid::full(32);
        // A wall at z = 0.5 seen along +z, except a column x in cells 14..18
        // where the sensor returned nothing (a glass object stands there).
        grid.seed_from_depth(&wall_rays(0.5, |i| !(14..18).contains(&i)), &[]);
        let at = |cell_x: f32| [(cell_x + 0.5) / 32.0, 16.5 / 32.0, 0.2];
        assert!(
            !grid.is_occupied(at(10.0)),
            "free space well away from the column is carved"
        );
        assert!(grid.is_occupied(at(15.0)), "the column itself was never seen free");
        // The object may reach into the neighbouring cells that rays crossed.
        assert!(
            grid.is_occupied(at(13.0)) && grid.is_occupied(at(18.0)),
            "cells bordering the column stay"
        );
        assert!(
            !grid.is_occupied(at(12.0)) && !grid.is_occupied(at(19.0)),
            "one cell of margin, not more"
        );
    }

    /// Occupied groups (reach 0) against a cell-by-cell count, on an odd
    /// size (neither a multiple of the group edge nor of the 64-bit word),
    /// sparse and dense.
    #[test]
    fn a_group_is_occupied_exactly_when_one_of_its_cells_is() {
        let mut rng = Rng::new(31, 0);
        let res: usize = 45;
        let size = GROUP;
        for keep in [0.02, 0.1] {
            let mut carved = vec![0u64; (res * res * res).div_ceil(64)];
            for cell in 0..res * res * res {
                if rng.f32() >= keep {
                    carved[cell >> 6] |= 1 << (cell & 63);
                }
            }
            let grid = OccupancyGrid::from_saved(res, vec![1.0; res * res * res], carved).unwrap();
            let cr = res.div_ceil(size);
            let mut want = vec![false; cr * cr * cr];
            for c in (0..res * res * res).filter(|&c| grid.is_occupied_cell(c)) {
                let (x, y, z) = (c % res, (c / res) % res, c / (res * res));
                want[((z / size) * cr + y / size) * cr + x / size] = true;
            }
            let (mut occupied, mut empty) = (0, 0);
            for (i, &any) in want.iter().enumerate() {
                let at = [i % cr, (i / cr) % cr, i / (cr * cr)];
                assert_eq!(grid.empty_group_reach(at) == 0, any, "keep {keep}: {at:?}");
                (occupied, empty) = if any {
                    (occupied + 1, empty)
                } else {
                    (occupied, empty + 1)
                };
            }
            assert!(
                occupied > 20 && empty > 20,
                "keep {keep}: {occupied} occupied and {empty} empty"
            );
        }
    }

    #[test]
    fn rendering_grid_keeps_dense_cells_and_their_neighbours_only() {
        let res = 16;
        let index = |x: usize, y: usize, z: usize| (z * res + y) * res + x;
        let mut density = vec![0.01f32; res * res * res];
        for (x, y, z) in (0..8).map(|k| (8 + (k & 1), 8 + ((k >> 1) & 1), 8 + (k >> 2))) {
            density[index(x, y, z)] = 100.0;
        }
        let trained = OccupancyGrid::from_saved(res, density.clone(), vec![0; (res * res * res).div_ceil(64)]).unwrap();
        let mut grid = trained;
        grid.restrict_to_rendering();
        let centre = |x: usize, y: usize, z: usize| {
            [
                (x as f32 + 0.5) / 16.0,
                (y as f32 + 0.5) / 16.0,
                (z as f32 + 0.5) / 16.0,
            ]
        };
        assert!(grid.is_occupied(centre(8, 9, 8)), "a dense cell");
        assert!(
            grid.is_occupied(centre(7, 8, 8)) && grid.is_occupied(centre(10, 10, 10)),
            "its neighbours (a thin surface may sit there)"
        );
        assert!(
            !grid.is_occupied(centre(5, 8, 8)) && !grid.is_occupied(centre(0, 0, 0)),
            "negligible haze is skipped"
        );
        assert_eq!(grid.occupied_fraction(), 64.0 / 4096.0);
        // Nothing dense at all (an untrained model): the grid is left full.
        let mut flat = OccupancyGrid::from_saved(res, vec![0.01; res * res * res], vec![0; 64]).unwrap();
        flat.restrict_to_rendering();
        assert_eq!(flat.occupied_fraction(), 1.0);
    }

    #[test]
    fn rays_grazing_a_cell_corner_do_not_carve_it() {
        let mut grid = OccupancyGrid::full(32);
        // Through cell corners only (x, y on cell boundaries).
        let rays: Vec<DepthRay> = (0..10)
            .map(|_| DepthRay {
                origin: [16.0 / 32.0, 16.0 / 32.0, 0.0],
                dir: [0.0, 0.0, 1.0],
                t_hit: 0.9,
            })
            .collect();
        grid.seed_from_depth(&rays, &[]);
        assert!(grid.is_occupied([16.2 / 32.0, 16.2 / 32.0, 0.3]));
    }

    #[test]
    fn single_flying_pixel_ray_does_not_carve_a_surface() {
        let mut grid = OccupancyGrid::full(32);
        let mut rays: Vec<DepthRay> = (0..5)
            .map(|_| DepthRay {
                origin: [0.5, 0.5, 0.0],
                dir: [0.0, 0.0, 1.0],
                t_hit: 0.3,
            })
            .collect();
        rays.push(DepthRay {
            origin: [0.5, 0.5, 0.0],
            dir: [0.0, 0.0, 1.0],
            t_hit: 0.9,
        });
        grid.seed_from_depth(&rays, &[]);
        assert!(grid.is_occupied([0.5, 0.5, 0.3]));
    }

    #[test]
    fn carved_space_stays_empty_whatever_the_model_says_and_the_grid_never_empties() {
        let mut grid = OccupancyGrid::full(16);
        // Carve the whole cube: rays through every cell centre column, surface far outside.
        let rays: Vec<DepthRay> = (0..16 * 16)
            .flat_map(|k| {
                let (x, y) = (((k % 16) as f32 + 0.5) / 16.0, ((k / 16) as f32 + 0.5) / 16.0);
                (0..3).map(move |_| DepthRay {
                    origin: [x, y, -0.5],
                    dir: [0.0, 0.0, 1.0],
                    t_hit: 5.0,
                })
            })
            .collect();
        grid.seed_from_depth(&rays, &[]);
        assert!(grid.occupied_fraction() < 0.01);
        assert!(grid.occupied_fraction() > 0.0, "grid must never empty");
        let mut rng = Rng::new(1, 0);
        let (mut pos, mut sig) = (Vec::new(), Vec::new());
        // A model with a dense floater in the lower half of x.
        for _ in 0..40 {
            grid.refresh(0.5, &mut rng, &mut pos, &mut sig, |p, s| {
                for (pi, si) in p.iter().zip(s.iter_mut()) {
                    *si = if pi[0] < 0.5 { 100.0 } else { 0.0 };
                }
            });
        }
        assert!(
            !grid.is_occupied([0.25, 0.5, 0.5]),
            "a floater in seen-free space is not rendered"
        );
        assert!(grid.occupied_fraction() < 0.01);
        // The density estimates follow the model (used to stop colour-only rays).
        let cell = grid.cell_of([0.25, 0.5, 0.5]).unwrap();
        assert!(grid.cell_density(cell) > 50.0);
        // NaN densities are ignored rather than poisoning the grid.
        grid.refresh(0.5, &mut rng, &mut pos, &mut sig, |_, s| {
            s.iter_mut().for_each(|x| *x = f32::NAN)
        });
        assert!(grid.densities().iter().all(|d| d.is_finite()));
    }

    #[test]
    fn cameras_carve_where_they_stood_and_what_they_saw_nearer_than_anything() {
        let mut grid = OccupancyGrid::full(16);
        let eye = [0.53, 0.53, 0.1];
        // A fan of rays from the camera to a wall 0.6 ahead.
        let rays: Vec<DepthRay> = (0..49)
            .flat_map(|k| {
                let (a, b) = ((k % 7) as f32 * 0.03 - 0.09, (k / 7) as f32 * 0.03 - 0.09);
                let n = (a * a + b * b + 1.0).sqrt();
                (0..3).map(move |_| DepthRay {
                    origin: eye,
                    dir: [a / n, b / n, 1.0 / n],
                    t_hit: 0.6 * n,
                })
            })
            .collect();
        grid.seed_from_depth(&rays, &[]);
        // Behind the camera nothing was seen, so carving alone keeps its cell.
        assert!(grid.is_occupied(eye));
        // A camera without depth whose cell holds another view's surface.
        let beside = [0.2, 0.2, 0.5];
        let hits = [DepthRay {
            origin: [0.2, 0.2, 0.0],
            dir: [0.0, 0.0, 1.0],
            t_hit: 0.5,
        }; 3];
        let cameras = [
            CameraSpace {
                origin: eye,
                free_distance: 0.3,
            },
            CameraSpace {
                origin: beside,
                free_distance: 0.0,
            },
        ];
        let all: Vec<DepthRay> = rays.iter().chain(&hits).copied().collect();
        let mut grid = OccupancyGrid::full(16);
        grid.seed_from_depth(&all, &cameras);
        assert!(!grid.is_occupied(eye), "the camera's own cell");
        assert!(!grid.is_occupied([0.53, 0.53, 0.35]), "nearer than the free distance");
        assert!(grid.is_occupied([0.53, 0.53, 0.66]), "the wall");
        assert!(grid.is_occupied(beside), "a measured surface is never carved");
        // A camera without depth carves only its own cell.
        let mut bare = OccupancyGrid::full(16);
        bare.seed_from_depth(
            &[],
            &[CameraSpace {
                origin: eye,
                free_distance: 0.0,
            }],
        );
        assert_eq!(bare.occupied, 16 * 16 * 16 - 1);
        assert!(!bare.is_occupied(eye));
    }

    #[test]
    fn the_ball_no_camera_measured_anything_in_is_carved_around_every_camera() {
        // A training camera whose nearest measurement vouches for 0.2, and a
        // held-out camera (position only) 0.3 to its side.
        let eye = [0.3, 0.5, 0.1];
        let held_out = [0.6, 0.5, 0.1];
        let rays = [DepthRay {
            origin: eye,
            dir: [0.0, 0.0, 1.0],
            t_hit: 0.4,
        }; 3];
        let cameras = [
            CameraSpace {
                origin: eye,
                free_distance: 0.2,
            },
            CameraSpace {
                origin: held_out,
                free_distance: 0.0,
            },
        ];
        let mut grid = OccupancyGrid::full(32);
        grid.seed_from_depth(&rays, &cameras);
        for p in [[0.6, 0.5, 0.05], [0.7, 0.55, 0.15], [0.6, 0.38, 0.1], [0.45, 0.5, 0.1]] {
            assert!(!grid.is_occupied(p), "{p:?} lies within 0.2 of a camera");
        }
        for p in [[0.6, 0.5, 0.35], [0.9, 0.5, 0.1]] {
            assert!(grid.is_occupied(p), "{p:?} lies beyond 0.2 of every camera");
        }
        assert!(grid.is_occupied([0.3, 0.5, 0.5]), "the measured surface");
    }

    #[test]
    fn cells_no_training_camera_sees_are_carved_and_every_cell_it_sees_is_kept() {
        use crate::scan::Intrinsics;
        let res = 16;
        let mut grid = OccupancyGrid::full(res);
        // At (0.5, 0.5, 0.1) looking +z, 90 degrees wide: tan = 32 / 32.
        let pose = nalgebra::IsometryMatrix3::translation(0.5, 0.5, 0.1);
        let k = Intrinsics {
            fx: 32.0,
            fy: 32.0,
            cx: 31.5,
            cy: 31.5,
        };
        let cam = LocalCamera::new(&pose, &k, 64, 64);
        grid.carve_unseen(&[cam]);
        let cell = 1.0 / res as f32;
        let radius = 0.5 * 3f32.sqrt() * cell;
        for i in 0..res * res * res {
            let c = [
                (i % res) as f32 + 0.5,
                ((i / res) % res) as f32 + 0.5,
                (i / (res * res)) as f32 + 0.5,
            ]
            .map(|v| v * cell);
            let d = [c[0] - 0.5, c[1] - 0.5, c[2] - 0.1];
            let dist = (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt();
            // Distance outside the frustum's side planes (|x| <= z, |y| <= z).
            let outside = ((d[0].abs() - d[2]) / 2f32.sqrt()).max((d[1].abs() - d[2]) / 2f32.sqrt());
            if dist <= radius || (d[2] > radius && outside <= 0.0) {
                assert!(grid.is_occupied_cell(i), "cell {i} at {c:?} is in view");
            }
            if d[2] < -radius || outside > 2.0 * radius {
                assert!(!grid.is_occupied_cell(i), "cell {i} at {c:?} is out of view");
            }
        }
        // No camera: nothing is known, nothing carved.
        let mut untouched = OccupancyGrid::full(res);
        untouched.carve_unseen(&[]);
        assert_eq!(untouched.occupied, res * res * res);
    }

    #[test]
    fn cell_exit_distance_is_exact_on_axes() {
        let grid = OccupancyGrid::full(4);
        let d = grid.distance_to_cell_exit([0.1, 0.1, 0.1], [1.0, 0.0, 0.0]);
        assert!((d - 0.15).abs() < 1e-6);
        let d = grid.distance_to_cell_exit([0.1, 0.1, 0.1], [0.0, -1.0, 0.0]);
        assert!((d - 0.1).abs() < 1e-6);
    }
}
