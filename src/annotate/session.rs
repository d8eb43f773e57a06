//! What the server holds while it runs: the scan, the optional model, the
//! surface points boxes are fitted to, the encoded page cloud, and the
//! boxes file it reads and replaces. With a model, the page's cloud and the
//! fit points are completed by its rendered surface, so objects the sensor
//! missed (glass) show and can be fitted.

use super::cloud_bin;
use super::fit_box::FitPoints;
use super::ground::Ground;
use crate::boxes::completed::{completed_cloud, CloudError};
use crate::boxes::{read_boxes, BoxError, BoxSet};
use crate::nerf::model_file::Model;
use crate::poses::{fuse_cloud, sample_depth_points, CloudOptions, DepthSamples, GeometryError};
use crate::scan::Scan;
use nalgebra::Point3;
use std::path::PathBuf;
use std::sync::Mutex;

/// Surface points sampled from the scan's depth for fitting and support planes.
const SURFACE_POINTS: usize = 1_500_000;
/// Voxels along the scene's longest edge of the page's cloud.
const CLOUD_VOXELS: u32 = 320;
/// Most points sent to the page.
const CLOUD_POINTS: usize = 400_000;

/// Why the annotation session could not start.
#[derive(Debug, thiserror::Error)]
pub enum SessionError {
    #[error("cannot build the scan's point cloud: {0}")]
    Geometry(#[from] GeometryError),
    #[error(transparent)]
    Boxes(#[from] BoxError),
    #[error("{0}: the scan has no depth to fit boxes to")]
    NoDepth(String),
    #[error("cannot complete the scan's point cloud with the model: {0}")]
    Completed(#[from] CloudError),
}

/// The state behind the HTTP API.
pub struct Session {
    pub scan: Scan,
    pub scan_dir: PathBuf,
    /// The boxes file (`GET`/`PUT /api/boxes`); created on the first save.
    pub boxes_path: PathBuf,
    /// The fitted model previews render depth from; `None`: sensor depth.
    pub model: Option<Model>,
    pub fit: FitPoints,
    /// Surface points (world metres) for the previews' support planes, and
    /// the camera centres they were seen from.
    pub surface: Vec<Point3<f64>>,
    pub cameras: Vec<Point3<f64>>,
    /// `GET /api/cloud.bin`.
    pub cloud_bin: Vec<u8>,
    /// Serialises writes of the boxes file.
    pub(crate) writing: Mutex<()>,
}

impl Session {
    /// Prepare a session: sample the surface, find the up axis, fuse the
    /// page's cloud and check that an existing boxes file is valid.
    pub fn open(
        scan: Scan,
        scan_dir: PathBuf,
        boxes_path: PathBuf,
        model: Option<Model>,
    ) -> Result<Session, SessionError> {
        Session::open_reporting(scan, scan_dir, boxes_path, model, &|_| {})
    }

    /// [`Session::open`]; with a model (whose fitted poses the scan must
    /// already carry), the cloud and the fit points are completed by its
    /// rendered depth, and `progress` hears the frames rendered.
    pub fn open_reporting(
        scan: Scan,
        scan_dir: PathBuf,
        boxes_path: PathBuf,
        model: Option<Model>,
        progress: &(dyn Fn(usize) + Sync),
    ) -> Result<Session, SessionError> {
        if boxes_path.exists() {
            read_existing(&boxes_path)?;
        }
        let samples = sample_depth_points(&scan, SURFACE_POINTS)?;
        if samples.points.is_empty() {
            return Err(SessionError::NoDepth(scan_dir.display().to_string()));
        }
        let points = samples.points.clone();
        let ground = Ground::estimate(&scan, &points);
        let options = CloudOptions {
            voxels_per_extent: CLOUD_VOXELS,
            ..CloudOptions::default()
        };
        let cell = consistency_cell(&scan, &samples);
        let (fit, cloud) = match &model {
            Some(model) => {
                let cloud = completed_cloud(&scan, model, &options, progress)?;
                let rendered: Vec<Point3<f64>> = (cloud.positions.iter())
                    .map(|p| Point3::from(p.map(f64::from)))
                    .collect();
                // Two voxels: the averaged point of a voxel the sensor saw
                // lies within one of the sensor's own samples.
                let near = 2.0 * cloud.voxel_size;
                let fit = FitPoints::with_unseen(ground, &points, cell, &rendered, near);
                (fit, cloud)
            }
            None => (FitPoints::new(ground, &points, cell), fuse_cloud(&scan, &options)?),
        };
        let cloud_bin = cloud_bin::encode(&cloud, &ground.up, CLOUD_POINTS);
        let cameras = scan.frames.iter().map(|f| f.camera_center()).collect();
        Ok(Session {
            scan,
            scan_dir,
            boxes_path,
            model,
            fit,
            surface: points,
            cameras,
            cloud_bin,
            writing: Mutex::new(()),
        })
    }

    /// The saved boxes (none before the first save).
    pub fn saved_boxes(&self) -> Result<BoxSet, BoxError> {
        if self.boxes_path.exists() {
            read_existing(&self.boxes_path)
        } else {
            Ok(BoxSet::from_boxes(Vec::new()))
        }
    }

    /// Name of the depth the previews use.
    pub fn source_name(&self) -> &'static str {
        if self.model.is_some() {
            "nerf"
        } else {
            "sensor"
        }
    }
}

/// Cell for the multi-view consistency of the surface points: two depth
/// pixels' footprint at the median depth (wider when the samples skip pixels).
fn consistency_cell(scan: &Scan, samples: &DepthSamples) -> f64 {
    let mut depths: Vec<f32> = samples.depths.iter().copied().filter(|d| d.is_finite()).collect();
    let mut focal: Vec<f64> = (scan.frames.iter())
        .filter_map(|f| {
            let (w, _) = f.depth_size?;
            Some(f.intrinsics.fx * f64::from(w) / f64::from(f.rgb.width().max(1)))
        })
        .filter(|f| f.is_finite() && *f > 0.0)
        .collect();
    if depths.is_empty() || focal.is_empty() {
        return 0.0;
    }
    let mid = depths.len() / 2;
    let depth = f64::from(*depths.select_nth_unstable_by(mid, f32::total_cmp).1);
    let mid = focal.len() / 2;
    let fx = *focal.select_nth_unstable_by(mid, f64::total_cmp).1;
    2.0 * depth / fx * (samples.stride as f64).sqrt()
}

/// A boxes file; an empty `boxes` list (everything deleted) is read as no boxes.
fn read_existing(path: &std::path::Path) -> Result<BoxSet, BoxError> {
    match read_boxes(path) {
        Err(BoxError::Format { problem, .. }) if problem.starts_with("`boxes` is empty") => {
            Ok(BoxSet::from_boxes(Vec::new()))
        }
        other => other,
    }
}
