//! Scene geometry: robust scene bounds, the global-to-local similarity that
//! maps the scene into the NeRF's unit cube, ray/box intersection, and the
//! fused point cloud. Depends on `scan` only; knows nothing of the NeRF.

mod aabb;
mod error;

pub use aabb::{Aabb, DAabb};
pub use error::GeometryError;
