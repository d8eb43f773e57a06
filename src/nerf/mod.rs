//! The depth-supervised NeRF: multi-resolution hash encoding, small MLPs
//! with fused SIMD kernels, occupancy-skipped volume rendering, training and
//! the model file. Knows nothing of boxes, COCO or Parquet.
//!
//! Data flows `field` (what the network computes) -> `occupancy` (where it
//! may be non-empty) -> `render` (rays through both) -> `train` (fitting a
//! scan, which renders); `model_file` stores what training produced for
//! `render` to load, in the `container` the training checkpoint shares.
//! Nothing in `field`, `occupancy` or `render` imports `train`'s driver.

pub mod appearance;
pub mod camera;
pub mod container;
pub mod environment;
pub mod field;
pub mod model_file;
pub mod occupancy;
pub mod render;
pub mod train;
