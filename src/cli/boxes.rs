//! `nerflabel boxes import|export`: boxes from and to other labelling tools.

use super::verbosity::say;
use clap::{Args, Subcommand};
use nerflabel::atomic;
use nerflabel::boxes::interop::{boxes_json, export_boxes, import_boxes, ExportFormat, ImportFormat};
use nerflabel::boxes::read_boxes;
use nerflabel::outputs::{check_outputs, resolve, Output};
use std::path::{Path, PathBuf};

#[derive(Args, Debug)]
pub struct BoxesArgs {
    #[command(subcommand)]
    pub command: BoxesCommand,
}

#[derive(Subcommand, Debug)]
pub enum BoxesCommand {
    /// Read boxes placed in labelCloud, KITTI labels or CVAT and write a nerflabel boxes.json.
    Import(ImportArgs),
    /// Write a boxes.json as a labelCloud label file (to check or adjust the boxes there).
    Export(ExportArgs),
}

/// Boxes in the point cloud's (the scan's world) frame: export the scan
/// with `nerflabel cloud`, place the boxes in the tool, import its file.
#[derive(Args, Debug)]
pub struct ImportArgs {
    /// The other tool's label file.
    pub file: PathBuf,
    /// Its format. labelcloud: a labelCloud `centroid_rel` file (angles in
    /// radians); labelcloud-abs: `centroid_abs` (degrees); kitti: a KITTI
    /// `label_2` text file (camera-0 frame, bottom-centre origin, rotation_y
    /// about the camera's y axis; DontCare lines skipped); cvat: one
    /// annotation file `ds0/ann/<name>.pcd.json` of CVAT's "Sly Point Cloud
    /// Format 1.0" export of a 3D task (cuboids; rotation as three.js XYZ
    /// Euler angles).
    #[arg(long = "from", value_enum, value_name = "FORMAT")]
    pub format: ImportFormat,
    /// KITTI only: the rigid camera-to-world matrix that places the camera-0
    /// frame in the scan's world, 4 rows of 4 numbers (or the top 3 rows),
    /// whitespace separated. Without it the camera frame is the world frame.
    /// (A native scan's pose/N.txt is world-to-camera: give its inverse.)
    #[arg(long, value_name = "FILE")]
    pub calib: Option<PathBuf>,
    /// Output boxes.json.
    #[arg(long, default_value = "boxes.json")]
    pub out: PathBuf,
    /// Replace the output file when it exists.
    #[arg(long)]
    pub overwrite: bool,
}

#[derive(Args, Debug)]
pub struct ExportArgs {
    /// The boxes.json to export.
    pub boxes: PathBuf,
    /// Target format: labelcloud (`centroid_rel`, radians) or labelcloud-abs
    /// (`centroid_abs`, degrees); choose the one labelCloud is set to read.
    #[arg(long = "to", value_enum, value_name = "FORMAT")]
    pub format: ExportFormat,
    /// The point cloud the boxes belong to (recorded in the file; labelCloud
    /// looks for labels/<cloud stem>.json).
    #[arg(long, value_name = "PCD", default_value = "cloud.ply")]
    pub cloud: PathBuf,
    /// Output file (default: <cloud stem>.json in the current folder).
    #[arg(long)]
    pub out: Option<PathBuf>,
    /// Replace the output file when it exists.
    #[arg(long)]
    pub overwrite: bool,
}

pub fn run(args: &BoxesArgs) -> anyhow::Result<()> {
    match &args.command {
        BoxesCommand::Import(a) => import(a),
        BoxesCommand::Export(a) => export(a),
    }
}

/// Refuse an output that is an input or exists (without --overwrite).
fn check_out(out: &Path, inputs: &[&Path], what: &str, overwrite: bool) -> anyhow::Result<()> {
    check_outputs(&[Output::file(out, what)], None)?;
    if let Some(input) = inputs.iter().find(|i| resolve(i) == resolve(out)) {
        anyhow::bail!(
            "{}: is also an input ({}); choose another --out",
            out.display(),
            input.display()
        );
    }
    if out.exists() && !overwrite {
        anyhow::bail!(
            "{}: exists; pass --overwrite to replace it, or choose another --out",
            out.display()
        );
    }
    Ok(())
}

fn import(args: &ImportArgs) -> anyhow::Result<()> {
    let mut inputs = vec![args.file.as_path()];
    inputs.extend(args.calib.as_deref());
    check_out(&args.out, &inputs, "the boxes", args.overwrite)?;
    let imported = import_boxes(&args.file, args.format, args.calib.as_deref())?;
    for warning in &imported.warnings {
        eprintln!("warning: {warning}");
    }
    let text = boxes_json(&imported.boxes);
    atomic::write_file(&args.out, text.as_bytes())
        .map_err(|e| anyhow::anyhow!("{}: cannot write the boxes: {e}", args.out.display()))?;
    say!(
        "imported {} boxes ({} labels) from {} ({}) into {}",
        imported.boxes.boxes.len(),
        imported.boxes.categories.len(),
        args.file.display(),
        args.format.name(),
        args.out.display()
    );
    Ok(())
}

fn export(args: &ExportArgs) -> anyhow::Result<()> {
    let out = args.out.clone().unwrap_or_else(|| {
        let stem = args
            .cloud
            .file_stem()
            .map(|s| s.to_string_lossy().into_owned())
            .unwrap_or_else(|| "cloud".into());
        PathBuf::from(format!("{stem}.json"))
    });
    check_out(&out, &[args.boxes.as_path()], "the labelCloud file", args.overwrite)?;
    let boxes = read_boxes(&args.boxes)?;
    let text = export_boxes(&boxes, args.format, &args.cloud);
    atomic::write_file(&out, text.as_bytes())
        .map_err(|e| anyhow::anyhow!("{}: cannot write the labelCloud file: {e}", out.display()))?;
    say!(
        "exported {} boxes from {} to {} ({})",
        boxes.boxes.len(),
        args.boxes.display(),
        out.display(),
        args.format.name()
    );
    Ok(())
}
