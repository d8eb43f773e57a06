//! Depth-only first-crossing renderer for labelling: march each ray through
//! the occupancy grid, composite density only, and stop a ray as soon as its
//! accumulated opacity crosses a threshold (the surface point), so no sample
//! behind the surface is ever evaluated.

use crate::nerf::composite::{sanitize_tau, TERMINATION_TRANSMITTANCE};
use crate::nerf::field::{Field, FieldWorkspace};
use crate::nerf::march::{march, Segment, StepRule};
use crate::nerf::occupancy::OccupancyGrid;
use crate::nerf::render::RenderRay;

/// Samples evaluated per round across all active rays.
const ROUND_SAMPLES: usize = 8192;

#[derive(Clone, Copy, Default)]
struct State {
    t: f32,
    opacity: f32,
    log_t: f32,
    samples: u32,
}

/// Buffers reused across calls.
#[derive(Default)]
pub struct SurfaceWorkspace {
    field: FieldWorkspace,
    active: Vec<usize>,
    state: Vec<State>,
    segments: Vec<Segment>,
    owner: Vec<(usize, usize, usize)>,
    positions: Vec<[f32; 3]>,
    sigma: Vec<f32>,
}

/// For each ray, the distance where accumulated opacity first reaches
/// `threshold` (interpolated inside the sample), `None` when it never does
/// within `[t_min, t_max)`.
pub fn first_crossings(
    field: &Field,
    grid: &OccupancyGrid,
    rays: &[RenderRay],
    rule: &StepRule,
    threshold: f32,
    max_samples: usize,
    ws: &mut SurfaceWorkspace,
    out: &mut [Option<f32>],
) {
    debug_assert_eq!(rays.len(), out.len());
    out.iter_mut().for_each(|o| *o = None);
    ws.state.clear();
    ws.state.extend(rays.iter().map(|r| State { t: r.t_min, ..State::default() }));
    ws.active.clear();
    ws.active.extend((0..rays.len()).filter(|&i| rays[i].t_max > rays[i].t_min));
    while !ws.active.is_empty() {
        let per_ray = (ROUND_SAMPLES / ws.active.len()).clamp(4, 64);
        ws.segments.clear();
        ws.owner.clear();
        ws.positions.clear();
        for &r in &ws.active {
            let st = &mut ws.state[r];
            let budget = per_ray.min(max_samples.saturating_sub(st.samples as usize));
            let first = ws.segments.len();
            st.t = march(&rays[r].ray, st.t, rays[r].t_max, grid, rule, 0.0, budget, &mut ws.segments);
            let count = ws.segments.len() - first;
            st.samples += count as u32;
            ws.owner.push((r, first, count));
            ws.positions.extend(ws.segments[first..].iter().map(|s| rays[r].ray.at(s.mid())));
        }
        ws.sigma.resize(ws.positions.len(), 0.0);
        field.density_only(&ws.positions, &mut ws.field, &mut ws.sigma);
        let mut keep = Vec::with_capacity(ws.owner.len());
        for &(r, first, count) in &ws.owner {
            let st = &mut ws.state[r];
            let mut done = count == 0;
            for i in first..first + count {
                let seg = ws.segments[i];
                let tau = sanitize_tau(ws.sigma[i] * seg.dt);
                let w = st.log_t.exp() * -(-tau).exp_m1();
                if st.opacity + w >= threshold {
                    let frac = if w > 0.0 { (threshold - st.opacity) / w } else { 0.0 };
                    out[r] = Some(seg.t + frac.clamp(0.0, 1.0) * seg.dt);
                    done = true;
                    break;
                }
                st.opacity += w;
                st.log_t -= tau;
            }
            done |= st.t >= rays[r].t_max
                || st.log_t.exp() < TERMINATION_TRANSMITTANCE
                || st.samples as usize >= max_samples;
            if !done {
                keep.push(r);
            }
        }
        ws.active = keep;
    }
}
