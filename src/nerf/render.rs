//! Inference rendering: rays marched in rounds over a shrinking set of
//! active rays (compaction), density for every sample, colour only for
//! samples that contribute, early stop once transmittance < 1e-4.

use super::composite::{sanitize_tau, MIN_SURFACE_WEIGHT, TERMINATION_TRANSMITTANCE};
use super::field::{Field, FieldWorkspace};
use super::march::{march, ray_interval, LocalRay, Segment, StepRule};
use super::occupancy::OccupancyGrid;

/// Samples below this weight do not get a colour evaluation.
const COLOR_WEIGHT_EPS: f32 = 1e-4;
/// Samples evaluated per round across all active rays of a packet.
const ROUND_SAMPLES: usize = 8192;

/// What to compute.
#[derive(Clone, Copy, Debug)]
pub struct RenderOptions {
    /// Evaluate the colour branch (false = depth only).
    pub color: bool,
    pub rule: StepRule,
    /// Hard cap per ray so nothing can hang.
    pub max_samples_per_ray: usize,
    /// Colour behind rays that stay transparent.
    pub background: [f32; 3],
}

/// A ray to render with the interval to march (local units).
#[derive(Clone, Copy, Debug)]
pub struct RenderRay {
    pub ray: LocalRay,
    pub t_min: f32,
    pub t_max: f32,
}

impl RenderRay {
    /// The ray over its whole interval inside the unit cube (`None` on a miss).
    pub fn through_cube(ray: LocalRay, near: f32) -> Option<RenderRay> {
        ray_interval(&ray, near).map(|(t_min, t_max)| RenderRay { ray, t_min, t_max })
    }
}

/// Result for one ray (distances along the ray in local units).
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct RayOutput {
    pub rgb: [f32; 3],
    pub opacity: f32,
    /// Weight-averaged distance of the visible surface (normalised by opacity).
    pub depth_expected: f32,
    /// First crossing of accumulated weight 0.5; `None` = no surface.
    pub depth_median: Option<f32>,
    pub samples: u32,
}

#[derive(Clone, Copy, Default)]
struct RayState {
    t: f32,
    log_t: f32,
    rgb: [f32; 3],
    depth: f32,
    opacity: f32,
    median: Option<f32>,
    samples: u32,
    /// The last round produced no sample: the ray left the occupied space.
    exhausted: bool,
}

/// Buffers reused across packets.
#[derive(Default)]
pub struct RenderWorkspace {
    field: FieldWorkspace,
    active: Vec<usize>,
    state: Vec<RayState>,
    segments: Vec<Segment>,
    owner: Vec<(usize, usize, usize)>,
    positions: Vec<[f32; 3]>,
    dirs: Vec<[f32; 3]>,
    sigma: Vec<f32>,
    weight: Vec<f32>,
    color_idx: Vec<usize>,
    color_pos: Vec<[f32; 3]>,
    color_dir: Vec<[f32; 3]>,
    sample_rgb: Vec<[f32; 3]>,
}

/// Render `rays` into `out` (same length) on the calling thread.
pub fn render_rays(
    field: &Field,
    grid: &OccupancyGrid,
    rays: &[RenderRay],
    opts: &RenderOptions,
    ws: &mut RenderWorkspace,
    out: &mut [RayOutput],
) {
    ws.state.clear();
    ws.state.extend(rays.iter().map(|r| RayState { t: r.t_min, ..Default::default() }));
    ws.active.clear();
    ws.active.extend((0..rays.len()).filter(|&i| rays[i].t_max > rays[i].t_min));
    while !ws.active.is_empty() {
        let per_ray = (ROUND_SAMPLES / ws.active.len()).clamp(4, 128);
        ws.segments.clear();
        ws.owner.clear();
        ws.positions.clear();
        ws.dirs.clear();
        for &r in &ws.active {
            let rr = &rays[r];
            let st = &mut ws.state[r];
            let budget = per_ray.min(opts.max_samples_per_ray.saturating_sub(st.samples as usize));
            let first = ws.segments.len();
            st.t = march(&rr.ray, st.t, rr.t_max, grid, &opts.rule, 0.0, budget, &mut ws.segments);
            let count = ws.segments.len() - first;
            st.samples += count as u32;
            st.exhausted = count == 0;
            ws.owner.push((r, first, count));
            for s in &ws.segments[first..] {
                ws.positions.push(rr.ray.at(s.mid()));
                ws.dirs.push(rr.ray.dir);
            }
        }
        ws.sigma.resize(ws.positions.len(), 0.0);
        field.density_only(&ws.positions, &mut ws.field, &mut ws.sigma);
        ws.weight.resize(ws.positions.len(), 0.0);
        // Composite this round's samples ray by ray.
        for &(r, first, count) in &ws.owner {
            let st = &mut ws.state[r];
            for i in first..first + count {
                let seg = ws.segments[i];
                let t_before = st.log_t.exp();
                if t_before < TERMINATION_TRANSMITTANCE {
                    ws.weight[i] = 0.0;
                    continue;
                }
                let tau = sanitize_tau(ws.sigma[i] * seg.dt);
                let w = t_before * -(-tau).exp_m1();
                ws.weight[i] = w;
                if st.median.is_none() && st.opacity + w >= MIN_SURFACE_WEIGHT {
                    let frac = if w > 0.0 { (MIN_SURFACE_WEIGHT - st.opacity) / w } else { 0.0 };
                    st.median = Some(seg.t + frac.clamp(0.0, 1.0) * seg.dt);
                }
                st.opacity += w;
                st.depth += w * seg.mid();
                st.log_t -= tau;
            }
        }
        if opts.color {
            shade_contributing(field, ws);
        }
        // Drop finished rays.
        let state = &ws.state;
        ws.active.retain(|&r| {
            let st = &state[r];
            !st.exhausted
                && st.t < rays[r].t_max
                && st.log_t.exp() >= TERMINATION_TRANSMITTANCE
                && (st.samples as usize) < opts.max_samples_per_ray
        });
    }
    for (o, st) in out.iter_mut().zip(&ws.state) {
        let transmittance = st.log_t.exp();
        let opacity = st.opacity.clamp(0.0, 1.0);
        let bg = opts.background;
        *o = RayOutput {
            rgb: [
                (st.rgb[0] + transmittance * bg[0]).clamp(0.0, 1.0),
                (st.rgb[1] + transmittance * bg[1]).clamp(0.0, 1.0),
                (st.rgb[2] + transmittance * bg[2]).clamp(0.0, 1.0),
            ],
            opacity,
            depth_expected: if opacity > 1e-6 { st.depth / st.opacity } else { 0.0 },
            depth_median: st.median,
            samples: st.samples,
        };
    }
}

/// Colour only for samples whose weight matters, added to their rays.
fn shade_contributing(field: &Field, ws: &mut RenderWorkspace) {
    ws.color_idx.clear();
    ws.color_pos.clear();
    ws.color_dir.clear();
    for (i, &w) in ws.weight.iter().enumerate().take(ws.positions.len()) {
        if w > COLOR_WEIGHT_EPS {
            ws.color_idx.push(i);
            ws.color_pos.push(ws.positions[i]);
            ws.color_dir.push(ws.dirs[i]);
        }
    }
    if ws.color_idx.is_empty() {
        return;
    }
    field.forward(&ws.color_pos, &ws.color_dir, &mut ws.field, false);
    let n = ws.color_idx.len();
    ws.sample_rgb.clear();
    ws.sample_rgb.extend((0..n).map(|k| [ws.field.rgb[k], ws.field.rgb[n + k], ws.field.rgb[2 * n + k]]));
    // Map sample index -> owning ray through the owner ranges (sorted by first).
    let mut o = 0;
    for (k, &i) in ws.color_idx.iter().enumerate() {
        while ws.owner[o].1 + ws.owner[o].2 <= i {
            o += 1;
        }
        let r = ws.owner[o].0;
        let w = ws.weight[i];
        let st = &mut ws.state[r];
        for c in 0..3 {
            st.rgb[c] += w * ws.sample_rgb[k][c];
        }
    }
}

/// Rays per parallel work item.
const PACKET: usize = 2048;

/// Render the given pixel positions of a camera in parallel (deterministic).
pub fn render_pixels(
    field: &Field,
    grid: &OccupancyGrid,
    opts: &RenderOptions,
    camera: &super::camera::LocalCamera,
    pixels: &[(f32, f32)],
) -> Vec<RayOutput> {
    use rayon::prelude::*;
    let near = opts.rule.min_step;
    let mut out = vec![RayOutput::default(); pixels.len()];
    pixels.par_chunks(PACKET).zip(out.par_chunks_mut(PACKET)).for_each_init(
        || (RenderWorkspace::default(), Vec::new(), Vec::new(), Vec::new()),
        |(ws, rays, index, results), (px, out)| {
            rays.clear();
            index.clear();
            for (k, &(u, v)) in px.iter().enumerate() {
                if let Some(r) = RenderRay::through_cube(camera.ray(u, v).0, near) {
                    rays.push(r);
                    index.push(k);
                }
            }
            results.clear();
            results.resize(rays.len(), RayOutput::default());
            render_rays(field, grid, rays, opts, ws, results);
            for o in out.iter_mut() {
                *o = RayOutput { rgb: opts.background, ..Default::default() };
            }
            for (&k, r) in index.iter().zip(results.iter()) {
                out[k] = *r;
            }
        },
    );
    out
}
