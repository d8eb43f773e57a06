//! Fitting a scan: settings derived from the scene, training views, the
//! training step and its optimiser, held-out evaluation, the fit driver and
//! its resumable checkpoint.

pub mod adam;
pub mod appearance;
pub mod checkpoint;
pub mod dataset;
pub mod detail;
pub mod environment;
pub mod fit;
pub mod metrics;
pub mod photometric;
pub mod pose_learning;
pub mod report;
pub mod settings;
pub mod step;
pub mod validation;
