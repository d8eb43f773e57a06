//! 3D boxes to labels: read and validate `boxes.json`, classify surface
//! points into boxes, project boxes into cameras, render only the pixels
//! whose rays can meet a box, and write masks, depth, COCO and YOLO.
//!
//! Depends on `scan`, `poses` and `nerf` (to render depth); never on `synth`
//! or the CLI. Never prints.

pub mod classify;
pub mod parse;
pub mod project;
pub mod rle;

pub use classify::BoxClassifier;
pub use parse::{parse_boxes, read_boxes, Box3, BoxError, BoxSet};
