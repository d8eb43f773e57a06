//! Given 2D instance masks of a few frames (drawn by hand, or from a
//! promptable segmenter such as SAM 2) carried to every frame through the
//! scan's 3D surface: [`read`] (the SAM 2 / DAVIS layouts) -> [`votes`]
//! (labelled pixels lifted to surface points vote per voxel) ->
//! [`propagate`] (every frame's surface points labelled by the votes, written
//! by `boxes::output` like box labels).
//!
//! Depends on `scan`, `nerf` (rendered depth) and `boxes` (the labelling
//! machinery and outputs); never on `synth` or the CLI. Never prints.

pub mod propagate;
pub mod read;
pub mod votes;

pub use propagate::{lift, objects_and_boxes, Lifted, MaskLabeler, PointLabels};
pub use read::{read_masks, GivenMasks, MaskError, MaskLayout};
pub use votes::VoteVolume;
