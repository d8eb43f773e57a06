//! Scene geometry: robust scene bounds, the global-to-local similarity that
//! maps the scene into the NeRF's unit cube, ray/box intersection, and the
//! fused point cloud. Depends on `scan` only; knows nothing of the NeRF.

mod aabb;
mod bounds;
pub(crate) use bounds::depth_intrinsics;
mod cloud;
mod error;
mod normalize;
mod orient;
mod pairwise;
mod refine;
mod scale;
#[cfg(test)]
mod test_scene;

pub use aabb::{Aabb, DAabb, SlabCrossing};
pub use bounds::{
    sample_depth_points, scene_bounds, BoundsOptions, BoundsSource, DepthSamples, PointStats, SceneBounds,
};
pub use cloud::{fuse_cloud, fuse_depth_maps, write_ply, CloudOptions, PointCloud, MAX_VOXELS_PER_AXIS};
pub use error::GeometryError;
pub use normalize::{normalize, Normalization, NormalizeOptions, Orientation, SceneTransform};
pub(crate) use orient::symmetric_eigen;
pub use pairwise::{align_pairs, PairwiseOptions};
pub(crate) use refine::{away_from_edges, stored_pixel_reach};
pub use refine::{
    gauss_newton_solve, median, pose_difference, refine_poses, trajectory_alignment, FrameCorrection, PoseRefinement,
    RefineOptions,
};
pub use scale::{estimate_pose_scale, scale_poses, ScaleEstimate};
