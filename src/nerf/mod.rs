//! The depth-supervised NeRF: multi-resolution hash encoding, small MLPs
//! with fused SIMD kernels, occupancy-skipped volume rendering, training and
//! the model file. Knows nothing of boxes, COCO or Parquet.

pub mod adam;
pub mod checkpoint;
pub mod composite;
pub mod hash_grid;
pub mod march;
pub mod measured;
pub mod mlp;
pub mod occupancy;
pub mod sh;
pub mod simd;
pub mod camera;
pub mod field;
pub mod metrics;
pub mod model_file;
pub mod render;
pub mod render_grid;
pub mod train;
pub mod config;
pub mod dataset;
pub mod evaluate;
pub mod fit;
pub mod view;
