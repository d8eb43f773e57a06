//! nerflabel: turn a handheld RGB-D scan into training data for object
//! detectors and segmenters with a depth-supervised NeRF fitted on the CPU.
//!
//! Data flows `scan` (read any layout into one [`scan::Scan`]) -> `poses`
//! (bounds, normalisation, geometry) -> `nerf` (fit and render) -> `boxes`
//! (3D boxes to labels) -> `synth` (novel views to Parquet). `fixture` is the
//! project's own procedural scene generator with exact ground truth.
//! The library never prints; the CLI in `main.rs` owns all output.

pub mod boxes;
pub mod evaluate;
pub mod fixture;
pub mod nerf;
pub mod plot;
pub mod poses;
pub mod scan;
pub mod synth;
pub mod atomic;
pub mod mask;
pub mod outputs;
pub mod png_encode;
pub mod rng;
