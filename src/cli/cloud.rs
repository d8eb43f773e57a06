//! `nerflabel cloud`: fused coloured point cloud as binary PLY.

use super::common::load_scan;
use super::CloudArgs;
use anyhow::Context;
use nerflabel::outputs::{check_outputs, Output, ProtectedInputs};
use nerflabel::poses::{fuse_cloud, write_ply, CloudOptions};

pub fn run(args: &CloudArgs) -> anyhow::Result<()> {
    let outputs = [Output::file(&args.output, "the point cloud")];
    check_outputs(&outputs, None)?;
    let scan = load_scan(&args.scan)?;
    check_outputs(&outputs, Some(&ProtectedInputs::of(&scan)))?;
    let options = CloudOptions {
        voxel_size: args.voxel,
        ..CloudOptions::default()
    };
    let cloud = fuse_cloud(&scan, &options).context("cannot fuse the point cloud")?;
    write_ply(&args.output, &cloud).with_context(|| format!("cannot write {}", args.output.display()))?;
    println!("wrote {} points to {}", cloud.len(), args.output.display());
    Ok(())
}
