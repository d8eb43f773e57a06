//! Camera poses learnt with the field (as BARF and nerfstudio's camera
//! optimiser do): every training step also moves each training view's camera
//! along the gradient of the same losses, taken through the hash grid's
//! spatial derivative at the samples of the view's rays.
//!
//! A view's correction is a small rotation about its camera centre and a
//! translation, in the field's local frame. Moving every camera by one rigid
//! motion (and the field with them) leaves the losses unchanged, so the
//! common rigid part of each step is removed: the scene stays in the frame
//! the boxes were drawn in. So is what every camera's step shares in its own
//! frame: no motion of the scene looks like that, only something all images
//! share (colour registered a few pixels off the depth); followed, it bends
//! the scene away from the depth.

use nalgebra::{Matrix3, Matrix6, Vector3, Vector6};
use serde::{Deserialize, Serialize};

const BETA1: f64 = 0.9;
const BETA2: f64 = 0.999;
const EPS: f64 = 1e-12;

/// Gradient of the losses with respect to one view's pose correction:
/// rotation about the camera centre (first three) and translation (last
/// three), local units.
pub type PoseGradient = [f64; 6];

/// Per-view Adam on pose corrections.
#[derive(Clone, Debug)]
pub struct PoseLearner {
    m: Vec<[f64; 6]>,
    v: Vec<[f64; 6]>,
    steps: u64,
    /// Step sizes at the full learning rate: radians, local units.
    rotation_lr: f64,
    translation_lr: f64,
    /// Hash-grid levels whose spatial derivative moves the cameras.
    pub levels: usize,
    /// Training steps before the cameras start to move (the field must
    /// first hold a surface to align to).
    pub start_step: u64,
    /// Sum of the steps taken per view (rotation, translation): the size of
    /// what was learnt, for the report.
    pub moved: Vec<[f64; 6]>,
}

impl PoseLearner {
    /// Learner for `views` training views; `rotation_lr` and
    /// `translation_lr` are the largest step per training step.
    pub fn new(views: usize, rotation_lr: f64, translation_lr: f64, levels: usize, start_step: u64) -> PoseLearner {
        PoseLearner {
            m: vec![[0.0; 6]; views],
            v: vec![[0.0; 6]; views],
            steps: 0,
            rotation_lr,
            translation_lr,
            levels,
            start_step,
            moved: vec![[0.0; 6]; views],
        }
    }

    /// Sets the largest step per training step (radians, local units).
    pub fn set_rates(&mut self, rotation_lr: f64, translation_lr: f64) {
        if rotation_lr > 0.0 && translation_lr > 0.0 {
            (self.rotation_lr, self.translation_lr) = (rotation_lr, translation_lr);
        }
    }

    /// Number of views.
    pub fn views(&self) -> usize {
        self.m.len()
    }

    /// One Adam step from `grads` (one per view, any common scale) with the
    /// learning rate multiplied by `rate`; returns each view's step with the
    /// common rigid motion of all cameras (centres `centres`, rotation about
    /// `pivot`) and the motion they share in their own frames (`rotations`,
    /// camera-to-local) removed. Views whose gradient is zero (no ray drawn)
    /// stay.
    pub fn step(
        &mut self,
        grads: &[PoseGradient],
        rate: f64,
        centres: &[[f64; 3]],
        rotations: &[Matrix3<f64>],
        pivot: [f64; 3],
    ) -> Vec<[f64; 6]> {
        assert_eq!(grads.len(), self.views(), "PoseLearner::step: one gradient per view");
        self.steps += 1;
        let (c1, c2) = (1.0 - BETA1.powi(self.steps as i32), 1.0 - BETA2.powi(self.steps as i32));
        let mut out = vec![[0.0; 6]; grads.len()];
        for (i, g) in grads.iter().enumerate() {
            if g.iter().all(|&x| x == 0.0) || !g.iter().all(|x| x.is_finite()) {
                continue;
            }
            for k in 0..6 {
                let lr = if k < 3 { self.rotation_lr } else { self.translation_lr };
                self.m[i][k] = BETA1 * self.m[i][k] + (1.0 - BETA1) * g[k];
                self.v[i][k] = BETA2 * self.v[i][k] + (1.0 - BETA2) * g[k] * g[k];
                let (m, v) = (self.m[i][k] / c1, self.v[i][k] / c2);
                out[i][k] = -rate * lr * m / (v.sqrt() + EPS);
            }
        }
        let lever = self.translation_lr / self.rotation_lr.max(1e-30);
        // The two motions overlap a little: twice over leaves no measurable
        // rest, and the scene's own motion goes last.
        for _ in 0..2 {
            remove_shared_camera_motion(&mut out, rotations);
            remove_common_motion(&mut out, centres, pivot, lever);
        }
        for (moved, s) in self.moved.iter_mut().zip(&out) {
            for k in 0..6 {
                moved[k] += s[k];
            }
        }
        out
    }
}

/// A [`PoseLearner`]'s optimiser state as f64 bit patterns (exact round
/// trip through a checkpoint's JSON header).
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct PoseLearnerState {
    pub m: Vec<[u64; 6]>,
    pub v: Vec<[u64; 6]>,
    pub moved: Vec<[u64; 6]>,
    pub steps: u64,
}

impl PoseLearner {
    /// The optimiser state, for a checkpoint.
    pub fn state(&self) -> PoseLearnerState {
        let bits = |x: &[[f64; 6]]| x.iter().map(|r| r.map(f64::to_bits)).collect();
        PoseLearnerState {
            m: bits(&self.m),
            v: bits(&self.v),
            moved: bits(&self.moved),
            steps: self.steps,
        }
    }

    /// Restores a checkpoint's state; false when it has another number of views.
    pub fn restore(&mut self, state: &PoseLearnerState) -> bool {
        let n = self.views();
        if state.m.len() != n || state.v.len() != n || state.moved.len() != n {
            return false;
        }
        let floats = |x: &[[u64; 6]]| x.iter().map(|r| r.map(f64::from_bits)).collect();
        (self.m, self.v, self.moved, self.steps) =
            (floats(&state.m), floats(&state.v), floats(&state.moved), state.steps);
        true
    }
}

/// Removes from per-camera steps (rotation about the camera centre,
/// translation) the rigid motion of the whole scene that fits them best:
/// a rotation `w` about `pivot` and a translation `u` move a camera at `c`
/// by rotation `w` and translation `u + w x (c - pivot)`. Rotations are
/// weighed as translations of `lever` (local units per radian), so both
/// count alike.
pub fn remove_common_motion(steps: &mut [[f64; 6]], centres: &[[f64; 3]], pivot: [f64; 3], lever: f64) {
    // Least squares over the moved cameras: J_i [w; u] = step_i, with
    // J_i = [[lever I, 0], [-[r_i]x, I]] (rows: rotation scaled by lever, translation).
    let mut normal = Matrix6::<f64>::zeros();
    let mut rhs = Vector6::<f64>::zeros();
    let mut used = 0;
    for (s, c) in steps.iter().zip(centres) {
        if is_still(s) {
            continue;
        }
        used += 1;
        let j = jacobian(c, pivot, lever);
        let y = Vector6::new(lever * s[0], lever * s[1], lever * s[2], s[3], s[4], s[5]);
        normal += j.transpose() * j;
        rhs += j.transpose() * y;
    }
    if used < 2 {
        return;
    }
    let Some(motion) = normal.cholesky().map(|ch| ch.solve(&rhs)) else {
        return;
    };
    for (s, c) in steps.iter_mut().zip(centres) {
        if is_still(s) {
            continue;
        }
        let common = jacobian(c, pivot, lever) * motion;
        for k in 0..3 {
            s[k] -= common[k] / lever;
            s[k + 3] -= common[k + 3];
        }
    }
}

/// Removes from per-camera steps the motion they share in their own frames
/// (the mean over the moved cameras of each step seen from its camera,
/// `rotations` camera-to-local): every camera turning or moving the same
/// way in its own frame is no motion of the scene, only of what all images
/// share (a colour image registered off its depth, a principal point), and
/// following it bends the scene away from the depth.
pub fn remove_shared_camera_motion(steps: &mut [[f64; 6]], rotations: &[Matrix3<f64>]) {
    let mut shared = [Vector3::zeros(), Vector3::zeros()];
    let mut used = 0;
    for (s, r) in steps.iter().zip(rotations) {
        if is_still(s) {
            continue;
        }
        used += 1;
        shared[0] += r.transpose() * Vector3::new(s[0], s[1], s[2]);
        shared[1] += r.transpose() * Vector3::new(s[3], s[4], s[5]);
    }
    if used < 2 {
        return;
    }
    let shared = shared.map(|v| v / used as f64);
    for (s, r) in steps.iter_mut().zip(rotations) {
        if is_still(s) {
            continue;
        }
        let (turn, shift) = (r * shared[0], r * shared[1]);
        for k in 0..3 {
            s[k] -= turn[k];
            s[k + 3] -= shift[k];
        }
    }
}

/// A view that took no step (no ray of it was drawn) is left out of the
/// motions removed and keeps its zero step.
fn is_still(step: &[f64; 6]) -> bool {
    step.iter().all(|&x| x == 0.0)
}

/// Rows: the camera's rotation (times `lever`) and translation caused by a
/// scene rotation `w` about `pivot` and translation `u` (columns w, u).
fn jacobian(c: &[f64; 3], pivot: [f64; 3], lever: f64) -> Matrix6<f64> {
    let r = Vector3::new(c[0] - pivot[0], c[1] - pivot[1], c[2] - pivot[2]);
    let mut j = Matrix6::<f64>::zeros();
    for k in 0..3 {
        j[(k, k)] = lever;
        j[(k + 3, k + 3)] = 1.0;
    }
    // w x r = -[r]x w.
    let cross = -r.cross_matrix();
    j.fixed_view_mut::<3, 3>(3, 0).copy_from(&cross);
    j
}

/// Adds one sample's contribution to its view's pose gradient: `g` is the
/// loss gradient at the sample `x` of a ray from `origin`.
#[inline]
pub fn accumulate(grad: &mut PoseGradient, origin: [f32; 3], x: [f32; 3], g: [f32; 3]) {
    let r = [
        (x[0] - origin[0]) as f64,
        (x[1] - origin[1]) as f64,
        (x[2] - origin[2]) as f64,
    ];
    let g = [g[0] as f64, g[1] as f64, g[2] as f64];
    // A rotation w about the origin moves x by w x r: d/dw = r x g.
    grad[0] += r[1] * g[2] - r[2] * g[1];
    grad[1] += r[2] * g[0] - r[0] * g[2];
    grad[2] += r[0] * g[1] - r[1] * g[0];
    grad[3] += g[0];
    grad[4] += g[1];
    grad[5] += g[2];
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_common_motion_is_removed_and_a_single_camera_step_kept() {
        // Eight cameras on a ring around the scene, at two heights.
        let centres: Vec<[f64; 3]> = (0..8)
            .map(|i| {
                let a = i as f64 * std::f64::consts::TAU / 8.0;
                [0.5 + 0.4 * a.cos(), 0.5 + 0.4 * a.sin(), 0.6 + 0.1 * (i % 2) as f64]
            })
            .collect();
        let pivot = [0.5, 0.5, 0.5];
        // Every camera moved by one scene rotation about z and a shift.
        let (w, u) = (Vector3::new(0.0, 0.0, 0.01), Vector3::new(0.002, -0.001, 0.0));
        let mut steps: Vec<[f64; 6]> = centres
            .iter()
            .map(|c| {
                let r = Vector3::new(c[0] - pivot[0], c[1] - pivot[1], c[2] - pivot[2]);
                let t = u + w.cross(&r);
                [w.x, w.y, w.z, t.x, t.y, t.z]
            })
            .collect();
        // Plus one camera's own correction.
        steps[2][3] += 0.004;
        remove_common_motion(&mut steps, &centres, pivot, 0.5);
        let own: f64 = steps[2].iter().map(|x| x * x).sum::<f64>().sqrt();
        let others: f64 = (0..8)
            .filter(|&i| i != 2)
            .map(|i| steps[i].iter().map(|x| x * x).sum::<f64>().sqrt())
            .fold(0.0, f64::max);
        // The lone step is shared out a little (least squares), the scene
        // motion (0.01 rad, shifts of a few thousandths) is gone.
        assert!(own > 0.003, "own step {own}");
        assert!(others < 0.001, "others {others}");
    }

    #[test]
    fn a_turn_every_camera_shares_in_its_own_frame_is_removed() {
        // Eight cameras looking in different directions.
        let rotations: Vec<Matrix3<f64>> = (0..8)
            .map(|i| {
                let axis = Vector3::new(0.3, 1.0, 0.2 * i as f64).normalize();
                *nalgebra::Rotation3::from_axis_angle(&nalgebra::Unit::new_normalize(axis), 0.7 * i as f64).matrix()
            })
            .collect();
        // Each tilts down 0.006 rad and steps 0.002 forward in its own frame.
        let (tilt, forward) = (Vector3::new(0.006, 0.0, 0.0), Vector3::new(0.0, 0.0, 0.002));
        let mut steps: Vec<[f64; 6]> = rotations
            .iter()
            .map(|r| {
                let (w, t) = (r * tilt, r * forward);
                [w.x, w.y, w.z, t.x, t.y, t.z]
            })
            .collect();
        // Plus one camera's own turn.
        steps[5][2] += 0.004;
        remove_shared_camera_motion(&mut steps, &rotations);
        let size = |s: &[f64; 6]| s.iter().map(|x| x * x).sum::<f64>().sqrt();
        let others = (0..8).filter(|&i| i != 5).map(|i| size(&steps[i])).fold(0.0, f64::max);
        // The shared part (0.006 rad, 0.002) is gone; the own turn is kept
        // but for its share of the mean (an eighth).
        assert!(others < 0.001, "others {others}");
        assert!((steps[5][2] - 0.0035).abs() < 0.0006, "own {:?}", steps[5]);
    }

    #[test]
    fn the_state_round_trips_exactly() {
        let mut learner = PoseLearner::new(2, 1e-3, 2e-3, 4, 0);
        let centres = [[0.2, 0.5, 0.5], [0.8, 0.5, 0.5]];
        let grads = [[0.3, -0.1, 0.0, 1.0, 2.0, -0.5], [0.0, 0.2, 0.0, 0.0, -1.0, 0.1]];
        learner.step(&grads, 1.0, &centres, &[Matrix3::identity(); 2], [0.5; 3]);
        let mut copy = PoseLearner::new(2, 1e-3, 2e-3, 4, 0);
        assert!(copy.restore(&learner.state()));
        assert_eq!(
            copy.step(&grads, 0.5, &centres, &[Matrix3::identity(); 2], [0.5; 3]),
            learner.step(&grads, 0.5, &centres, &[Matrix3::identity(); 2], [0.5; 3])
        );
        assert!(!PoseLearner::new(3, 1e-3, 2e-3, 4, 0).restore(&learner.state()));
    }

    #[test]
    fn adam_steps_follow_the_gradient_at_the_learning_rate() {
        let mut learner = PoseLearner::new(3, 1e-3, 2e-3, 4, 0);
        let grads = [
            [1.0, 0.0, 0.0, 0.0, 0.0, -5.0],
            [0.0; 6],
            [0.0, 0.0, 0.0, 0.0, 0.0, 0.0],
        ];
        let centres = [[0.2, 0.5, 0.5], [0.8, 0.5, 0.5], [0.5, 0.5, 0.9]];
        let steps = learner.step(&grads, 1.0, &centres, &[Matrix3::identity(); 3], [0.5, 0.5, 0.5]);
        // One view only: nothing common to remove.
        assert!((steps[0][0] + 1e-3).abs() < 1e-9, "{:?}", steps[0]);
        assert!((steps[0][5] - 2e-3).abs() < 1e-9, "{:?}", steps[0]);
        assert_eq!(steps[1], [0.0; 6]);
    }

    #[test]
    fn the_gradient_of_a_rotation_is_the_moment_of_the_sample_gradients() {
        // A loss sum(g . x) over samples of rays from o: rotating them about
        // o by w changes it by w . sum(r x g).
        let o = [0.5f32, 0.5, 0.2];
        let samples = [
            ([0.5f32, 0.6, 0.7], [1.0f32, 0.0, 0.0]),
            ([0.4, 0.5, 0.8], [0.0, 2.0, 1.0]),
        ];
        let mut grad = [0.0; 6];
        for (x, g) in samples {
            accumulate(&mut grad, o, x, g);
        }
        let loss = |w: Vector3<f64>| -> f64 {
            let rot = nalgebra::Rotation3::new(w);
            samples
                .iter()
                .map(|(x, g)| {
                    let r = Vector3::new((x[0] - o[0]) as f64, (x[1] - o[1]) as f64, (x[2] - o[2]) as f64);
                    let moved = rot * r;
                    moved.x * g[0] as f64 + moved.y * g[1] as f64 + moved.z * g[2] as f64
                })
                .sum()
        };
        for k in 0..3 {
            let mut e = Vector3::zeros();
            e[k] = 1e-6;
            let numeric = (loss(e) - loss(-e)) / 2e-6;
            assert!((grad[k] - numeric).abs() < 1e-6, "axis {k}: {} vs {numeric}", grad[k]);
        }
        assert_eq!(&grad[3..], &[1.0, 2.0, 1.0]);
    }
}
