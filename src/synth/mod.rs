//! Synthetic training views (`nerflabel synth`): viewpoints sampled around
//! the labelled objects (or given in a poses file), rendered with a trained
//! model to colour, depth and instance masks, and streamed into one Parquet
//! file. Depends on `nerf`, `boxes`, `poses` and `scan`; nothing depends on it
//! except the CLI.

mod error;
pub mod parquet;
pub mod poses_file;
pub mod sampling;
pub mod triplet;

pub use error::{PosesFileError, Rejections, SynthError};
pub use parquet::{synth_schema, SynthWriter};
pub use poses_file::{parse_poses, read_poses, ViewSpec};
pub use sampling::{Candidate, Cloud, PoseSampler, Target};
pub use triplet::{Box2d, Instances, PointClassifier, SynthView};
pub mod synthesize;
pub mod viewpoints;

pub use synthesize::{
    support_planes, synthesize, synthesize_objects, view_size, Objects, SynthOptions, SynthProgress, SynthSummary,
};
pub use viewpoints::{probe, Verdict, ViewStream};
