//! Rendering a fitted field: cameras and rays in the unit cube, marching
//! with empty space skipped, stable compositing, packets of rays and whole
//! views in the scan's metric frame.

pub mod composite;
pub mod march;
pub mod rays;
pub mod view;
