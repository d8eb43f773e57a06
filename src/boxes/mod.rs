//! 3D boxes to labels: read and validate `boxes.json`, classify surface
//! points into boxes, project boxes into cameras, render only the pixels
//! whose rays can meet a box, and write masks, depth, COCO and YOLO.
//!
//! Flow: [`parse`] (boxes.json) -> [`classify`] (point in smallest box, ray
//! intervals) and [`project`] (pixel rectangles) -> [`label`] (per-frame
//! depth from [`surface`] and/or the sensor fused over frames in [`tsdf`], mask, [`cleanup`], 2D boxes,
//! object poses) -> [`rle`], [`coco`], [`contour`] and [`yolo`] and
//! [`output`] (files, swapped in at the end). [`metrics`] scores masks
//! against ground truth; [`interop`] reads boxes placed in other labelling
//! tools and writes them back.
//!
//! Depends on `scan`, `poses` and `nerf` (to render depth); never on `synth`
//! or the CLI. Never prints.

pub mod boundary;
pub mod classify;
pub mod cleanup;
pub mod coco;
pub mod completed;
pub mod contour;
pub mod interop;
pub mod label;
pub mod metrics;
pub mod options;
pub mod output;
pub mod parse;
pub mod project;
pub mod reach;
pub mod rle;
pub mod support;
pub mod surface;
pub mod tsdf;
pub mod wireframe;
pub mod yolo;

pub use classify::{BoxClassifier, Overlap};
pub use label::{FrameLabel, InstanceLabel, Labeler};
pub use options::{DepthSource, FrameRange, LabelError, LabelOptions, DEFAULT_SOURCE};
pub use output::{write_labels, LabelSummary, OutputOptions};
pub use parse::{parse_boxes, read_boxes, Box3, BoxError, BoxSet};
pub use project::{project_box, PixelRect};
pub use yolo::{ImageMode, YoloOptions};
