//! Learning the colour beyond the cube (`nerf::environment`) beside the field.

use crate::nerf::environment::{Environment, ENVIRONMENT_PARAMS};
use crate::nerf::train::adam::Adam;
use crate::nerf::train::settings::DEFAULT_LEARNING_RATE;

/// The environment's learning rate at full schedule: the default field's,
/// and not `--learning-rate`'s. A sigmoid of 48 coefficients saturates
/// under steps the field still takes (100 times the default field rate
/// left the small fixture at 15.3 dB held-out instead of 22.6), and ten
/// times the default let it take the scene's colour early in one tabletop
/// fit (22.6 dB against 26.9).
pub const LEARNING_RATE: f32 = DEFAULT_LEARNING_RATE;

/// The environment and its optimiser.
#[derive(Clone, Debug)]
pub struct EnvironmentLearner {
    pub environment: Environment,
    pub adam: Adam,
}

impl EnvironmentLearner {
    /// Starts as `background` in every direction.
    pub fn new(background: [f32; 3]) -> Self {
        EnvironmentLearner {
            environment: Environment::uniform(background),
            adam: Adam::new(ENVIRONMENT_PARAMS),
        }
    }

    /// One Adam update at learning rate `lr`.
    pub fn step(&mut self, grads: &[f32], lr: f32) {
        self.adam.step_dense(&mut self.environment.coeffs, grads, lr, 0.0);
    }
}
