//! `nerflabel annotate`: a local web page to place 3D boxes on the scan's
//! point cloud and see at once the masks they would produce.
//!
//! [`session`] holds the scan, model and surface points; [`ground`] finds
//! the up axis the top view looks along; [`fit_box`] fits a box to the
//! object inside a marked region; [`preview`] draws a frame's labels;
//! [`api`] answers the HTTP API as plain functions; [`server`] routes
//! requests and runs the `tiny_http` loop; [`cloud_bin`] encodes the page's
//! cloud. The page (`page/`) is compiled into the binary.
//!
//! Depends on `scan`, `poses`, `boxes` and `nerf`; never on the CLI. Never prints.

pub mod api;
pub mod cloud_bin;
pub mod fit_box;
pub mod ground;
pub mod preview;
pub mod server;
pub mod session;

pub use fit_box::{FitError, FitPoints, FittedBox, Region};
pub use ground::Ground;
pub use server::{route, serve, ServeError};
pub use session::{Session, SessionError};
