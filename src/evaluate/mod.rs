//! Scores against a fixture's exact ground truth, for the demo, the
//! end-to-end tests and the benchmarks. Depends on `fixture`, `nerf` and
//! `boxes`; nothing in the product pipeline depends on it.

mod holdout;
mod labels;
mod written;

pub use holdout::{score_holdout, HoldoutScore};
pub use labels::{evaluate_labels, fixture_truth, read_gray16, LabelEvaluation, TruthMask};
pub use written::{score_written_labels, WrittenLabelScore, EVALUATION_FILE};
