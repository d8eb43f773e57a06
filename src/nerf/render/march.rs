//! Ray marching inside the unit cube: step size growing with distance,
//! empty cells of the occupancy grid skipped whole.

use crate::nerf::camera::{unit_cube_interval, LocalRay};
use crate::nerf::occupancy::{OccupancyGrid, GROUP};

/// One volume-rendering sample: interval [t, t + dt), evaluated at its middle.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct Segment {
    pub t: f32,
    pub dt: f32,
}

impl Segment {
    /// Where the field is evaluated.
    #[inline]
    pub fn mid(&self) -> f32 {
        self.t + 0.5 * self.dt
    }
}

/// How far apart samples are (stored in the model file as is).
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct StepRule {
    /// Smallest step (local units), about half the finest grid cell.
    pub min_step: f32,
    /// Largest step.
    pub max_step: f32,
    /// Step grows as `t * cone` far from the camera (0 = constant).
    pub cone: f32,
}

impl StepRule {
    /// Step length at distance `t`.
    #[inline]
    pub fn at(&self, t: f32) -> f32 {
        (t * self.cone).clamp(self.min_step, self.max_step)
    }
}

/// Parameter interval of the ray inside the unit cube, starting no closer
/// than `near`; `None` when the ray misses.
pub fn ray_interval(ray: &LocalRay, near: f32) -> Option<(f32, f32)> {
    let (t0, t1) = unit_cube_interval(ray.origin, ray.dir)?;
    let t0 = t0.max(near);
    (t0 < t1).then_some((t0, t1))
}

/// March `ray` over [t0, t1), appending occupied segments to `out`, at most
/// `max_samples`. `jitter` in [0, 1) offsets the first sample (training).
/// Returns the t where marching stopped.
#[allow(clippy::too_many_arguments)]
pub fn march(
    ray: &LocalRay,
    t0: f32,
    t1: f32,
    grid: &OccupancyGrid,
    rule: &StepRule,
    jitter: f32,
    max_samples: usize,
    out: &mut Vec<Segment>,
) -> f32 {
    // No optical-depth bound: the grid's density estimates are never read.
    march_impl::<false>(ray, t0, t1, grid, rule, jitter, max_samples, f32::INFINITY, None, out)
}

/// Longer steps where the grid's density estimate says the medium is thin:
/// in a cell where a step `factor` times the rule's (at most `max_cells`
/// cells of the grid) would gather less than `max_optical_depth`, that
/// longer step is taken. A sum of samples is off by a fraction of the
/// optical depth it spans, so thin space loses little by coarse samples,
/// while surfaces keep the rule's step. The grid's cells decide, so a step
/// never crosses more of them than its checked points (start, middle, end)
/// can see.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ThinSteps {
    pub factor: f32,
    pub max_optical_depth: f32,
    pub max_cells: f32,
}

/// Like [`march`], but also stops once the optical depth estimated from the
/// grid's density exceeds `max_optical_depth` (the ray is surely absorbed):
/// training rays without measured depth stop behind the first surface.
/// With `thin`, thin cells take longer steps (see [`ThinSteps`]).
#[allow(clippy::too_many_arguments)]
pub fn march_until(
    ray: &LocalRay,
    t0: f32,
    t1: f32,
    grid: &OccupancyGrid,
    rule: &StepRule,
    jitter: f32,
    max_samples: usize,
    max_optical_depth: f32,
    thin: Option<ThinSteps>,
    out: &mut Vec<Segment>,
) -> f32 {
    march_impl::<true>(
        ray,
        t0,
        t1,
        grid,
        rule,
        jitter,
        max_samples,
        max_optical_depth,
        thin,
        out,
    )
}

/// The marching loop; `BOUNDED` reads the grid's density for the optical-depth stop.
#[allow(clippy::too_many_arguments)]
#[inline(always)]
fn march_impl<const BOUNDED: bool>(
    ray: &LocalRay,
    t0: f32,
    t1: f32,
    grid: &OccupancyGrid,
    rule: &StepRule,
    jitter: f32,
    max_samples: usize,
    max_optical_depth: f32,
    thin: Option<ThinSteps>,
    out: &mut Vec<Segment>,
) -> f32 {
    let res = grid.resolution();
    let r = res as f32;
    let mut t = t0 + jitter * rule.at(t0);
    let mut taken = 0;
    let mut optical_depth = 0.0f32;
    while t < t1 && taken < max_samples && (!BOUNDED || optical_depth < max_optical_depth) {
        let dt = rule.at(t);
        let p = ray.at(t + 0.5 * dt);
        // The cell of `p`, computed exactly as `OccupancyGrid::cell_of` does.
        let c = [p[0] * r, p[1] * r, p[2] * r];
        // Written so NaN fails the test.
        if !(c[0] >= 0.0 && c[0] < r && c[1] >= 0.0 && c[1] < r && c[2] >= 0.0 && c[2] < r) {
            t += dt;
            continue;
        }
        // In [0, r) with r <= 512: the i32 conversion is exact (and cheaper than to usize).
        let idx = [c[0] as i32 as usize, c[1] as i32 as usize, c[2] as i32 as usize];
        let cell = (idx[2] * res + idx[1]) * res + idx[0];
        if grid.is_occupied_cell(cell) {
            let mut dt = dt;
            if BOUNDED {
                let density = grid.cell_density(cell);
                if let Some(thin) = thin {
                    let long = (dt * thin.factor).min(thin.max_cells / r).max(dt);
                    // The cells at the longer step's middle and end must be
                    // thin too, so it never reaches into a surface.
                    let thin_at = |d: f32| {
                        let cell = grid.cell_of(ray.at(t + d));
                        // Written so NaN keeps the rule's step.
                        cell.is_none_or(|c| grid.cell_density(c) * long < thin.max_optical_depth)
                    };
                    // No checks when the cap leaves the rule's step as it is.
                    if long > dt && density * long < thin.max_optical_depth && thin_at(0.5 * long) && thin_at(long) {
                        dt = long;
                    }
                }
                optical_depth += density * dt;
            }
            out.push(Segment { t, dt: dt.min(t1 - t) });
            taken += 1;
            t += dt;
        } else {
            // Skip the empty cell in whole steps so samples stay on the step lattice.
            let gap = cell_exit(p, ray.dir, idx, r) + 0.5 * dt;
            t += ceil_positive(gap / dt).max(1.0) * dt;
        }
    }
    t
}

/// March for rendering: the samples [`march`] takes in occupied cells, but a
/// run of empty cells is crossed in one jump. From an empty cell the cells
/// along the ray are walked (a few multiplications per step, where
/// [`march`] pays a division and a libm call per cell), a cube of empty
/// groups of [`GROUP`]^3 cells in one step, and
/// marching resumes past the run, within one smallest step of its end. With
/// constant steps that is [`march`]'s lattice; with growing steps the
/// landing points differ from [`march`]'s (rendering only; training keeps
/// [`march`]).
pub fn march_skipping(
    ray: &LocalRay,
    t0: f32,
    t1: f32,
    grid: &OccupancyGrid,
    rule: &StepRule,
    max_samples: usize,
    out: &mut Vec<Segment>,
) -> f32 {
    let res = grid.resolution();
    let r = res as f32;
    let mut t = t0;
    let mut taken = 0;
    while t < t1 && taken < max_samples {
        let dt = rule.at(t);
        let mid = t + 0.5 * dt;
        let p = ray.at(mid);
        let c = [p[0] * r, p[1] * r, p[2] * r];
        // Written so NaN fails the test.
        if !(c[0] >= 0.0 && c[0] < r && c[1] >= 0.0 && c[1] < r && c[2] >= 0.0 && c[2] < r) {
            t += dt;
            continue;
        }
        // In [0, r) with r <= 512: the i32 conversion is exact.
        let idx = [c[0] as i32, c[1] as i32, c[2] as i32];
        if grid.is_occupied_cell(cell_index_of(idx, res)) {
            out.push(Segment { t, dt: dt.min(t1 - t) });
            taken += 1;
            t += dt;
            continue;
        }
        // No need to walk past the end of the interval.
        let exit = empty_run_length(grid, p, ray.dir, idx, t1 - mid);
        let gap = exit.max(0.0) + 0.5 * dt;
        // Land in whole smallest steps: at most one of them past the run's
        // end, where a whole current step could pass over a surface.
        let m = rule.min_step;
        t += ceil_positive(gap / m).max(1.0) * m;
    }
    t
}

/// Most steps a cone takes through empty space.
const MAX_CONE_STEPS: usize = 256;
/// A cone stops once a step gains less than this many cells.
const MIN_CONE_STEP_CELLS: f32 = 1.0;

/// How far every ray of a bundle can go without entering a cell the grid
/// keeps: the rays leave `origin` with unit directions within `spread`
/// (Euclidean, `|d - axis|`) of the unit `axis`, and the result `t` (at least
/// `t0`, at most `t1`) leaves each of them nothing to sample over [t0, t).
/// It steps along the axis by the clearance of the empty cube of groups
/// around it ([`OccupancyGrid::empty_group_reach`]): a point at distance `u`
/// on a ray lies within `u * spread + (u - s)` of the axis point at `s`, so
/// the step from `s` to `(s + clearance) / (1 + spread)` stays inside. Stops
/// at an occupied group or the edge of the grid; conservative, never exact.
pub fn cone_clear_until(grid: &OccupancyGrid, origin: [f32; 3], axis: [f32; 3], spread: f32, t0: f32, t1: f32) -> f32 {
    if !(spread.is_finite() && spread >= 0.0 && t0.is_finite()) {
        return t0;
    }
    let res = grid.resolution();
    let r = res as f32;
    let mut s = t0;
    for _ in 0..MAX_CONE_STEPS {
        if s >= t1 {
            return t1;
        }
        let q: [f32; 3] = std::array::from_fn(|a| (origin[a] + s * axis[a]) * r);
        if q.iter().any(|v| v.is_nan()) {
            return s;
        }
        // Outside the grid, the nearest point of the grid is no farther from
        // any cell than the point itself (projection onto a box), so its
        // clearance holds there too.
        let q = q.map(|v| v.clamp(0.0, r * (1.0 - f32::EPSILON)));
        let group = q.map(|v| v as usize / GROUP);
        let reach = grid.empty_group_reach(group);
        if reach == 0 {
            return s;
        }
        // Cells per side from q to the faces of the empty cube of groups
        // within reach - 1; a face at or past the grid's edge bounds nothing.
        let clearance_cells = (0..3)
            .map(|a| {
                let below = if group[a] + 1 > reach {
                    q[a] - ((group[a] + 1 - reach) * GROUP) as f32
                } else {
                    f32::INFINITY
                };
                let hi = (group[a] + reach) * GROUP;
                let above = if hi < res { hi as f32 - q[a] } else { f32::INFINITY };
                below.min(above)
            })
            .fold(f32::INFINITY, f32::min);
        // A hair less than the clearance, for the rounding of q.
        let clearance = (clearance_cells - 1e-3) / r;
        let next = (s + clearance) / (1.0 + spread);
        if !(next > s) {
            return s;
        }
        // Near a surface the steps shrink geometrically: the rays' own walks are cheaper there.
        if next - s < MIN_CONE_STEP_CELLS / r {
            return next.min(t1);
        }
        s = next;
    }
    s.min(t1)
}

#[inline(always)]
fn cell_index_of(i: [i32; 3], res: usize) -> usize {
    (i[2] as usize * res + i[1] as usize) * res + i[0] as usize
}

/// Distance from `p` (in the empty cell `idx`) along `dir` to the first
/// occupied cell, the grid's edge, or `limit`, whichever comes first. Each
/// step crosses the largest empty region holding the current cell: the
/// cube of groups of [`GROUP`]^3 cells around its group that holds no
/// occupied one (as wide as the grid's group distances allow), or the cell
/// itself, so wide empty space costs a few steps and so does the space
/// near a surface, until the ray reaches a group beside an occupied one.
#[inline(always)]
fn empty_run_length(grid: &OccupancyGrid, p: [f32; 3], dir: [f32; 3], mut idx: [i32; 3], limit: f32) -> f32 {
    let res = grid.resolution();
    let cell_size = 1.0 / res as f32;
    let last = res as i32 - 1;
    let step: [i32; 3] = dir.map(|d| {
        if d > 0.0 {
            1
        } else if d < 0.0 {
            -1
        } else {
            0
        }
    });
    let inv: [f32; 3] = dir.map(|d| 1.0 / d);
    // The group size as a shift (indices are never negative inside the grid).
    const GROUP_SHIFT: u32 = GROUP.trailing_zeros();
    const _: () = assert!(GROUP.is_power_of_two());
    let mut d = 0.0f32;
    // Every step leaves a cell for one further along an axis, so a walk
    // across the grid takes under 3 res steps; stopping early is safe (the
    // march resumes there).
    for _ in 0..4 * res {
        let group = idx.map(|i| i >> GROUP_SHIFT);
        let reach = grid.empty_group_reach(group.map(|g| g as usize)) as i32;
        // Read unconditionally (the cell is inside the grid) so that only
        // the walk's end is a branch.
        let occupied = grid.is_occupied_cell(cell_index_of(idx, res));
        if (reach == 0) & occupied {
            return d;
        }
        // The empty region to leave, cells `lo..lo + size` per axis: the
        // cube of groups within `reach - 1` of this one, else the cell.
        let in_group = reach > 0;
        let size = if in_group { (2 * reach - 1) << GROUP_SHIFT } else { 1 };
        let lo: [i32; 3] = std::array::from_fn(|a| {
            if in_group {
                (group[a] - (reach - 1)) << GROUP_SHIFT
            } else {
                idx[a]
            }
        });
        // Distance to the exit face on each axis (none on an axis the ray
        // runs parallel to), the nearest first on ties; written without
        // branches, which the walk mispredicted.
        let exits: [f32; 3] = std::array::from_fn(|a| {
            let face = if step[a] > 0 { lo[a] + size } else { lo[a] } as f32 * cell_size;
            if step[a] != 0 {
                (face - p[a]) * inv[a]
            } else {
                f32::INFINITY
            }
        });
        let (exit, axis) = if exits[0] <= exits[1] && exits[0] <= exits[2] {
            (exits[0], 0)
        } else if exits[1] <= exits[2] {
            (exits[1], 1)
        } else {
            (exits[2], 2)
        };
        d = exit.max(d);
        if d >= limit {
            return d;
        }
        // The next cell: across the exit face on `axis`; on the other axes
        // where the ray is, kept inside the cell just left (the point lies
        // on its face, where rounding may fall either side).
        idx = std::array::from_fn(|a| {
            let across = if step[a] > 0 { lo[a] + size } else { lo[a] - 1 };
            let q = ((p[a] + d * dir[a]) * res as f32).max(0.0) as i32;
            let along = q.clamp(lo[a], (lo[a] + size - 1).min(last));
            if a == axis {
                across
            } else {
                along
            }
        });
        if idx[axis] < 0 || idx[axis] > last {
            return d;
        }
    }
    d
}

/// `OccupancyGrid::distance_to_cell_exit` for a point inside the cube whose
/// cell coordinates `idx` are known: the same operations, with the floor of
/// `p * r` (in [0, r)) taken from `idx` instead of a libm call.
#[inline(always)]
fn cell_exit(p: [f32; 3], dir: [f32; 3], idx: [usize; 3], r: f32) -> f32 {
    let mut best = f32::INFINITY;
    for a in 0..3 {
        let d = dir[a];
        if d == 0.0 {
            continue;
        }
        let c = idx[a] as f32;
        let boundary = if d > 0.0 { (c + 1.0) / r } else { c / r };
        let t = (boundary - p[a]) / d;
        if t < best {
            best = t;
        }
    }
    best.max(0.0)
}

/// `x.ceil()` for `x >= 0` (or NaN) without a libm call.
#[inline(always)]
fn ceil_positive(x: f32) -> f32 {
    if x < 8_388_608.0 {
        // Below 2^23 the truncation is exact; NaN falls through to 0 like `max(1.0)` expects.
        let i = x as u32 as f32;
        if i < x {
            i + 1.0
        } else {
            i
        }
    } else {
        x.ceil()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::nerf::occupancy::DepthRay;

    fn rule() -> StepRule {
        StepRule {
            min_step: 1.0 / 256.0,
            max_step: 1.0 / 16.0,
            cone: 0.0,
        }
    }

    #[test]
    fn full_grid_samples_the_whole_interval_contiguously() {
        let grid = OccupancyGrid::full(32);
        let ray = LocalRay {
            origin: [0.5, 0.5, -0.5],
            dir: [0.0, 0.0, 1.0],
        };
        let (t0, t1) = ray_interval(&ray, 0.0).unwrap();
        let mut out = Vec::new();
        march(&ray, t0, t1, &grid, &rule(), 0.0, 10_000, &mut out);
        assert_eq!(out.len(), 256);
        for w in out.windows(2) {
            assert!((w[0].t + w[0].dt - w[1].t).abs() < 1e-5);
        }
    }

    #[test]
    fn empty_space_is_skipped_but_the_surface_is_sampled() {
        let mut grid = OccupancyGrid::full(32);
        let mut rays = Vec::new();
        for i in 0..32 {
            for j in 0..32 {
                let (x, y) = ((i as f32 + 0.5) / 32.0, (j as f32 + 0.5) / 32.0);
                for _ in 0..3 {
                    rays.push(DepthRay {
                        origin: [x, y, 0.0],
                        dir: [0.0, 0.0, 1.0],
                        t_hit: 0.8,
                    });
                }
            }
        }
        grid.seed_from_depth(&rays, &[]);
        let ray = LocalRay {
            origin: [0.5, 0.5, -0.5],
            dir: [0.0, 0.0, 1.0],
        };
        let (t0, t1) = ray_interval(&ray, 0.0).unwrap();
        let mut out = Vec::new();
        march(&ray, t0, t1, &grid, &rule(), 0.3, 10_000, &mut out);
        assert!(out.len() < 256 / 2, "half the ray is carved: {}", out.len());
        assert!(
            out.iter().any(|s| (s.mid() - 1.3).abs() < 0.02),
            "surface at local z = 0.8 is sampled"
        );
    }

    /// The marcher as first written, on the grid's own cell queries.
    fn march_reference(
        ray: &LocalRay,
        t0: f32,
        t1: f32,
        grid: &OccupancyGrid,
        rule: &StepRule,
        out: &mut Vec<Segment>,
    ) {
        let mut t = t0;
        while t < t1 {
            let dt = rule.at(t);
            let p = ray.at(t + 0.5 * dt);
            match grid.cell_of(p) {
                Some(cell) if grid.is_occupied_cell(cell) => {
                    out.push(Segment { t, dt: dt.min(t1 - t) });
                    t += dt;
                }
                Some(_) => {
                    let gap = grid.distance_to_cell_exit(p, ray.dir) + 0.5 * dt;
                    t += (gap / dt).ceil().max(1.0) * dt;
                }
                None => t += dt,
            }
        }
    }

    /// A 32^3 grid carved by 20 000 random depth rays cast along +z from z = 0.
    fn randomly_carved_grid(rng: &mut crate::rng::Rng) -> OccupancyGrid {
        let mut grid = OccupancyGrid::full(32);
        let depth_rays: Vec<DepthRay> = (0..20_000)
            .map(|_| {
                let origin = [rng.f32(), rng.f32(), 0.0];
                let d = [rng.f32() - 0.5, rng.f32() - 0.5, 1.0];
                let n = (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt();
                DepthRay {
                    origin,
                    dir: d.map(|v| v / n),
                    t_hit: 0.3 + 0.5 * rng.f32(),
                }
            })
            .collect();
        grid.seed_from_depth(&depth_rays, &[]);
        grid
    }

    /// Ray number `i` from a random origin around the unit cube; every 7th
    /// has a zero direction component (skipped in the exit test).
    fn random_ray(rng: &mut crate::rng::Rng, i: usize) -> LocalRay {
        let origin = [
            rng.range(-0.5, 1.5) as f32,
            rng.range(-0.5, 1.5) as f32,
            rng.range(-0.5, 1.5) as f32,
        ];
        let mut d = [rng.f32() - 0.5, rng.f32() - 0.5, rng.f32() - 0.5];
        if i.is_multiple_of(7) {
            d[i % 3] = 0.0;
        }
        let n = (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt();
        LocalRay {
            origin,
            dir: d.map(|v| v / n),
        }
    }

    #[test]
    fn marching_gives_bit_identical_samples_to_the_grids_cell_queries() {
        // Carve a seeded grid with random depth rays, then march random rays through it.
        let mut rng = crate::rng::Rng::new(17, 0);
        let grid = randomly_carved_grid(&mut rng);
        assert!(grid.occupied_fraction() < 0.9, "{}", grid.occupied_fraction());
        let rule = StepRule {
            min_step: 1.0 / 300.0,
            max_step: 1.0 / 20.0,
            cone: 1.0 / 128.0,
        };
        let full = OccupancyGrid::full(32);
        let mut skipped_some = 0;
        for i in 0..500 {
            let ray = random_ray(&mut rng, i);
            let Some((t0, t1)) = ray_interval(&ray, 0.0) else {
                continue;
            };
            let (mut fast, mut slow) = (Vec::new(), Vec::new());
            march(&ray, t0, t1, &grid, &rule, 0.0, usize::MAX, &mut fast);
            march_reference(&ray, t0, t1, &grid, &rule, &mut slow);
            assert_eq!(fast, slow, "ray {i}");
            let mut all = Vec::new();
            march(&ray, t0, t1, &full, &rule, 0.0, usize::MAX, &mut all);
            skipped_some += usize::from(fast.len() < all.len());
        }
        assert!(skipped_some > 30, "few rays crossed carved space: {skipped_some}");
    }

    /// Asserts that `samples` lie in occupied cells, in order, and pass over
    /// no occupied point except within half a step after the last sample (or
    /// the start) and within one step before the next (`which` names the marcher).
    fn check_skips(ray: &LocalRay, t0: f32, grid: &OccupancyGrid, rule: &StepRule, samples: &[Segment], which: &str) {
        let mut from = t0;
        for s in samples {
            assert!(s.t >= from - 1e-6, "{which}: samples out of order");
            assert!(
                grid.is_occupied(ray.at(s.mid())),
                "{which}: sample at {} in an empty cell",
                s.t
            );
            let mut x = from + 0.5 * rule.at(from);
            while x < s.t - 1.01 * rule.at(s.t) {
                assert!(
                    !grid.is_occupied(ray.at(x)),
                    "{which}: occupied point at {x} passed over before the sample at {}",
                    s.t
                );
                x += 0.05 * rule.min_step;
            }
            from = s.t + s.dt;
        }
    }

    #[test]
    fn skipping_runs_of_empty_cells_takes_the_same_samples_on_full_grids_and_misses_no_occupied_cell() {
        let mut rng = crate::rng::Rng::new(23, 0);
        let full = OccupancyGrid::full(32);
        let carved = randomly_carved_grid(&mut rng);
        let (mut fast_total, mut slow_total, mut differing) = (0, 0, 0);
        for (k, rule) in [
            StepRule {
                min_step: 1.0 / 300.0,
                max_step: 1.0 / 20.0,
                cone: 0.0,
            },
            StepRule {
                min_step: 1.0 / 300.0,
                max_step: 1.0 / 20.0,
                cone: 1.0 / 64.0,
            },
        ]
        .iter()
        .enumerate()
        {
            for i in 0..400 {
                let ray = random_ray(&mut rng, i);
                let Some((t0, t1)) = ray_interval(&ray, 0.0) else {
                    continue;
                };
                let (mut a, mut b) = (Vec::new(), Vec::new());
                march_skipping(&ray, t0, t1, &full, rule, usize::MAX, &mut a);
                march(&ray, t0, t1, &full, rule, 0.0, usize::MAX, &mut b);
                assert_eq!(a, b, "rule {k} ray {i}: a full grid has nothing to skip");
                let (mut fast, mut slow) = (Vec::new(), Vec::new());
                march_skipping(&ray, t0, t1, &carved, rule, usize::MAX, &mut fast);
                march(&ray, t0, t1, &carved, rule, 0.0, usize::MAX, &mut slow);
                check_skips(&ray, t0, &carved, rule, &fast, "march_skipping");
                check_skips(&ray, t0, &carved, rule, &slow, "march");
                if k == 0 {
                    // Constant steps: the same lattice, up to rounding (one jump against
                    // several), which can move a midpoint lying on a cell face across it.
                    let on_lattice = |s: &Segment| slow.iter().any(|b| (s.t - b.t).abs() < 1e-5);
                    let same = fast.len() == slow.len() && fast.iter().all(on_lattice);
                    if !same {
                        differing += 1;
                        let off: Vec<&Segment> = fast.iter().filter(|s| !on_lattice(s)).collect();
                        assert!(off.is_empty(), "ray {i}: samples off the lattice: {off:?}");
                        assert!(
                            fast.len().abs_diff(slow.len()) <= 1,
                            "ray {i}: {} against {}",
                            fast.len(),
                            slow.len()
                        );
                    }
                }
                // Stopping after a budget and resuming gives the same samples.
                let mut resumed = Vec::new();
                let mut t = t0;
                while t < t1 {
                    let before = resumed.len();
                    t = march_skipping(&ray, t, t1, &carved, rule, 3, &mut resumed);
                    if resumed.len() == before {
                        break;
                    }
                }
                assert_eq!(resumed, fast, "rule {k} ray {i}: resuming changed the samples");
                fast_total += fast.len();
                slow_total += slow.len();
            }
        }
        assert!(
            slow_total > 5000 && fast_total as f64 > 0.95 * slow_total as f64,
            "{fast_total} vs {slow_total}"
        );
        assert!(differing <= 4, "{differing} of 400 rays took other samples than march");
    }

    /// A 64^3 grid empty but for a spherical shell and a few solid 3^3
    /// clusters: most groups are far from occupied ones, so rays cross
    /// cubes of them whole.
    fn shell_grid(rng: &mut crate::rng::Rng) -> OccupancyGrid {
        let res: usize = 64;
        let clusters: Vec<[f32; 3]> = (0..30).map(|_| [rng.f32(), rng.f32(), rng.f32()]).collect();
        let mut carved = vec![0u64; (res * res * res).div_ceil(64)];
        for cell in 0..res * res * res {
            let p = [cell % res, (cell / res) % res, cell / (res * res)].map(|i| (i as f32 + 0.5) / res as f32);
            let radius = p.iter().map(|v| (v - 0.5) * (v - 0.5)).sum::<f32>().sqrt();
            let in_cluster = clusters
                .iter()
                .any(|c| (0..3).all(|a| (p[a] - c[a]).abs() < 1.6 / res as f32));
            let keep = (radius - 0.3).abs() < 0.03 || in_cluster;
            if !keep {
                carved[cell >> 6] |= 1 << (cell & 63);
            }
        }
        OccupancyGrid::from_saved(res, vec![1.0; res * res * res], carved).unwrap()
    }

    #[test]
    fn crossing_empty_groups_whole_takes_the_samples_of_the_cell_by_cell_march() {
        let mut rng = crate::rng::Rng::new(29, 0);
        let grid = shell_grid(&mut rng);
        let gr = grid.group_resolution();
        let far_groups = (0..gr * gr * gr)
            .filter(|&i| grid.empty_group_reach([i % gr, (i / gr) % gr, i / (gr * gr)]) >= 3)
            .count();
        assert!(
            far_groups > 1000,
            "the test needs wide empty space: {far_groups} groups"
        );
        let rule = StepRule {
            min_step: 1.0 / 300.0,
            max_step: 1.0 / 20.0,
            cone: 0.0,
        };
        let (mut total, mut differing) = (0, 0);
        for i in 0..600 {
            let ray = random_ray(&mut rng, i);
            let Some((t0, t1)) = ray_interval(&ray, 0.0) else {
                continue;
            };
            let (mut fast, mut slow) = (Vec::new(), Vec::new());
            march_skipping(&ray, t0, t1, &grid, &rule, usize::MAX, &mut fast);
            march(&ray, t0, t1, &grid, &rule, 0.0, usize::MAX, &mut slow);
            check_skips(&ray, t0, &grid, &rule, &fast, "march_skipping");
            // The same step lattice; rounding may move one midpoint lying on a cell face.
            let on_lattice = |s: &Segment| slow.iter().any(|b| (s.t - b.t).abs() < 1e-5);
            assert!(fast.iter().all(on_lattice), "ray {i}: samples off the lattice");
            assert!(
                fast.len().abs_diff(slow.len()) <= 1,
                "ray {i}: {} against {}",
                fast.len(),
                slow.len()
            );
            differing += usize::from(fast.len() != slow.len());
            total += fast.len();
        }
        assert!(total > 800, "rays must meet the shell: {total} samples");
        assert!(differing <= 6, "{differing} of 600 rays took other samples than march");
    }

    #[test]
    fn cone_steps_grow_with_distance_and_cap_the_count() {
        let grid = OccupancyGrid::full(32);
        let ray = LocalRay {
            origin: [0.0, 0.5, 0.5],
            dir: [1.0, 0.0, 0.0],
        };
        let r = StepRule {
            min_step: 1e-3,
            max_step: 0.1,
            cone: 0.05,
        };
        let mut out = Vec::new();
        march(&ray, 0.0, 1.0, &grid, &r, 0.0, 10_000, &mut out);
        assert!(out.last().unwrap().dt > 5.0 * out[0].dt);
        let mut capped = Vec::new();
        march(&ray, 0.0, 1.0, &grid, &r, 0.0, 7, &mut capped);
        assert_eq!(capped.len(), 7);
    }
    /// Every ray of a fan, sampled densely over [t0, clear), stays in empty
    /// cells; and on the shell grid the cone does skip most of the space in
    /// front of the shell.
    #[test]
    fn a_cone_never_passes_an_occupied_cell_of_its_rays() {
        let mut rng = crate::rng::Rng::new(31, 0);
        let grid = shell_grid(&mut rng);
        let r = grid.resolution() as f32;
        let (mut cleared, mut total) = (0.0f32, 0.0f32);
        for fan in 0..300 {
            let origin = [rng.range(-0.3, 1.3) as f32, rng.range(-0.3, 1.3) as f32, -0.2];
            let target = [rng.f32(), rng.f32(), rng.f32()];
            let axis = unit(std::array::from_fn(|a| target[a] - origin[a]));
            // Up to 0.05 rad apart: far wider than a pixel row's eight rays.
            let width = 0.05 * rng.f32();
            let side = unit([axis[1], -axis[0], 0.3]);
            let dirs: Vec<[f32; 3]> = (0..8)
                .map(|k| {
                    unit(std::array::from_fn(|a| {
                        axis[a] + width * (k as f32 / 7.0 - 0.5) * side[a]
                    }))
                })
                .collect();
            let sum = dirs
                .iter()
                .fold([0.0f32; 3], |acc, d| std::array::from_fn(|a| acc[a] + d[a]));
            let centre = unit(sum);
            let spread = dirs
                .iter()
                .map(|d| (0..3).map(|a| (d[a] - centre[a]).powi(2)).sum::<f32>().sqrt())
                .fold(0.0f32, f32::max);
            let Some((t0, t1)) = ray_interval(&LocalRay { origin, dir: centre }, 0.0) else {
                continue;
            };
            let clear = cone_clear_until(&grid, origin, centre, spread, t0, t1);
            assert!(clear >= t0 && clear <= t1, "fan {fan}: {clear} outside [{t0}, {t1}]");
            cleared += clear - t0;
            total += t1 - t0;
            for (k, dir) in dirs.iter().enumerate() {
                let ray = LocalRay { origin, dir: *dir };
                for j in 0..2000 {
                    let t = t0 + (clear - t0) * j as f32 / 2000.0;
                    let p = ray.at(t);
                    let q = p.map(|v| v * r);
                    if q.iter().all(|&v| v >= 0.0 && v < r) {
                        let cell = cell_index_of(q.map(|v| v as i32), grid.resolution());
                        assert!(
                            !grid.is_occupied_cell(cell),
                            "fan {fan} ray {k}: occupied cell at t = {t} < {clear}"
                        );
                    }
                }
            }
        }
        assert!(
            cleared > 0.3 * total,
            "the cones should clear much of the way: {cleared} of {total}"
        );
        // A NaN spread or start leaves the start where it was.
        assert_eq!(
            cone_clear_until(&grid, [0.5; 3], [0.0, 0.0, 1.0], f32::NAN, 0.1, 1.0),
            0.1
        );
    }

    fn unit(v: [f32; 3]) -> [f32; 3] {
        let n = (v[0] * v[0] + v[1] * v[1] + v[2] * v[2]).sqrt();
        v.map(|x| x / n)
    }

    /// With steps growing along the ray, a jump over empty space still lands
    /// within one smallest step past the run's end: a whole current step
    /// could pass over the surface at the front of the occupied cells.
    #[test]
    fn a_skip_lands_within_one_smallest_step_of_the_occupied_cells() {
        // Occupied: 0.5 <= z < 0.6.
        let grid = OccupancyGrid::keeping(64, |[_, _, z]| (32..38).contains(&z));
        let rule = StepRule {
            min_step: 1.0 / 1024.0,
            max_step: 1.0 / 16.0,
            cone: 0.05,
        };
        for k in 0..50 {
            let ray = LocalRay {
                origin: [0.3 + 0.004 * k as f32, 0.5, -0.5 + 0.002 * k as f32],
                dir: [0.0, 0.0, 1.0],
            };
            let (t0, t1) = ray_interval(&ray, 0.0).unwrap();
            let mut out = Vec::new();
            march_skipping(&ray, t0, t1, &grid, &rule, 1, &mut out);
            let front = 0.5 - ray.origin[2];
            // Steps there are about 0.05, 50 smallest steps.
            assert!(rule.at(front) > 20.0 * rule.min_step);
            let t = out[0].t;
            assert!(
                t >= front - 1e-5 && t < front + rule.min_step + 1e-5,
                "ray {k}: first sample at {t}, front at {front}"
            );
        }
    }

    /// Haze (density 1) below z = 0.5, a surface (density 1000) over two
    /// cells above it, nothing carved; a ray straight up through both.
    fn haze_then_surface() -> (OccupancyGrid, LocalRay) {
        let res = 32;
        let density = (0..res * res * res)
            .map(|c| {
                if (16..18).contains(&(c / (res * res))) {
                    1000.0
                } else {
                    1.0
                }
            })
            .collect();
        let grid = OccupancyGrid::from_saved(res, density, vec![0; (res * res * res).div_ceil(64)]).unwrap();
        let ray = LocalRay {
            origin: [0.51, 0.52, -0.5],
            dir: [0.0, 0.0, 1.0],
        };
        (grid, ray)
    }

    #[test]
    fn long_steps_cross_thin_space_and_the_rules_step_samples_the_surface() {
        let (grid, ray) = haze_then_surface();
        let (t0, t1) = ray_interval(&ray, 0.0).unwrap();
        let rule = rule();
        let thin = ThinSteps {
            factor: 4.0,
            max_optical_depth: 0.1,
            max_cells: 2.0,
        };
        let surface = 0.5 - ray.origin[2];
        // Jittered by half a step: the long steps do not end on the surface.
        let jitter = 0.5;
        let mut plain = Vec::new();
        let stop_plain = march_until(&ray, t0, t1, &grid, &rule, jitter, 10_000, 20.0, None, &mut plain);
        let mut out = Vec::new();
        let stop = march_until(&ray, t0, t1, &grid, &rule, jitter, 10_000, 20.0, Some(thin), &mut out);

        // The haze: 128 samples at the rule's step, about a quarter as many
        // long ones, none of which reaches into the surface.
        let in_haze = |v: &[Segment]| v.iter().filter(|s| s.t < surface).count();
        assert_eq!(in_haze(&plain), 128);
        let long = 4.0 * rule.min_step;
        assert!(
            (30..=36).contains(&in_haze(&out)),
            "{} samples in the haze",
            in_haze(&out)
        );
        for s in out.iter().filter(|s| s.dt > 1.5 * rule.min_step) {
            assert!((s.dt - long).abs() < 1e-6 && s.t + s.dt <= surface + 1e-6, "{s:?}");
        }
        // The surface: the rule's step, and the ray stops inside it after
        // the same samples as without long steps (optical depth 20 reached).
        let at_surface = |v: &[Segment]| v.iter().filter(|s| s.t >= surface).map(|s| s.dt).collect::<Vec<_>>();
        assert_eq!(at_surface(&out), at_surface(&plain));
        assert!(!at_surface(&out).is_empty() && at_surface(&out).iter().all(|&dt| dt == rule.min_step));
        assert!(stop < surface + 2.0 / 32.0 && (stop - stop_plain).abs() < 2.0 * rule.min_step);

        // A threshold the haze exceeds keeps the rule's step everywhere.
        let dense_haze = ThinSteps {
            max_optical_depth: 0.01,
            ..thin
        };
        let mut strict = Vec::new();
        march_until(
            &ray,
            t0,
            t1,
            &grid,
            &rule,
            jitter,
            10_000,
            20.0,
            Some(dense_haze),
            &mut strict,
        );
        assert_eq!(strict, plain);
    }

    #[test]
    fn long_steps_cross_at_most_the_cells_they_check_and_never_shorten_the_rules() {
        let (grid, ray) = haze_then_surface();
        let (t0, t1) = ray_interval(&ray, 0.0).unwrap();
        let cell = 1.0 / 32.0;
        let thin = ThinSteps {
            factor: 8.0,
            max_optical_depth: 1.0,
            max_cells: 2.0,
        };
        // 8 steps of half a cell would span 4 cells: 2 are taken.
        let fine = StepRule {
            min_step: cell / 2.0,
            max_step: 1.0,
            cone: 0.0,
        };
        let mut out = Vec::new();
        march_until(&ray, t0, t1, &grid, &fine, 0.0, 10_000, 20.0, Some(thin), &mut out);
        let longest = out.iter().map(|s| s.dt).fold(0.0, f32::max);
        assert!((longest - 2.0 * cell).abs() < 1e-6, "longest step {longest}");
        // A rule already stepping over 2 cells keeps its own step.
        let coarse = StepRule {
            min_step: 3.0 * cell,
            max_step: 1.0,
            cone: 0.0,
        };
        let (mut plain, mut with_thin) = (Vec::new(), Vec::new());
        march_until(&ray, t0, t1, &grid, &coarse, 0.0, 10_000, 20.0, None, &mut plain);
        march_until(
            &ray,
            t0,
            t1,
            &grid,
            &coarse,
            0.0,
            10_000,
            20.0,
            Some(thin),
            &mut with_thin,
        );
        assert_eq!(with_thin, plain);
    }
}
