//! Scores against a fixture's exact ground truth, for the demo, the
//! end-to-end tests and the benchmarks. Depends on `fixture`, `nerf` and
//! (later) `boxes`; nothing in the product pipeline depends on it.

mod holdout;

pub use holdout::{score_holdout, HoldoutScore};
