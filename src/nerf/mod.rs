//! The depth-supervised NeRF: multi-resolution hash encoding, small MLPs
//! with fused SIMD kernels, occupancy-skipped volume rendering, training and
//! the model file. Knows nothing of boxes, COCO or Parquet.

pub mod adam;
pub mod composite;
pub mod hash_grid;
pub mod march;
pub mod mlp;
pub mod occupancy;
pub mod sh;
pub mod simd;
// pub mod camera; (enabled once the kernels land)
// pub mod field; (enabled once the kernels land)
pub mod metrics;
// pub mod model_file; (enabled once the kernels land)
// pub mod render; (enabled once the kernels land)
// pub mod train; (enabled once the kernels land)
