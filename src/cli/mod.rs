//! Argument definitions and the dispatch of each subcommand.

mod annotate;
mod batch;
mod boxes;
mod cloud;
mod common;
mod demo;
mod fit;
mod fixture;
mod info;
mod label;
mod report;
mod synth;
pub(crate) mod verbosity;

use clap::{Args, Parser, Subcommand};
pub use common::interrupted_status;
use nerflabel::boxes::{DepthSource, ImageMode, Overlap, DEFAULT_SOURCE};
use nerflabel::fixture::{FixtureLayout, SceneKind};
use nerflabel::nerf::train::settings::FitSettings;
use nerflabel::scan::{Layout, LoadOptions};
use std::path::PathBuf;

/// Turn a handheld RGB-D scan into training data for object detectors:
/// fit a depth-supervised NeRF on the CPU, then label 3D boxes into masks,
/// 2D boxes, object poses and COCO, or render novel views to Parquet.
#[derive(Parser, Debug)]
#[command(name = "nerflabel", version, about, long_about = None, propagate_version = true)]
pub struct Cli {
    #[command(subcommand)]
    pub command: Command,
    /// Worker threads (default: one per core). Fewer leave cores to other
    /// jobs on a shared machine or a cluster node; a fit's result depends
    /// on the count, so compare runs made with the same one.
    #[arg(long, global = true, value_name = "N")]
    pub threads: Option<usize>,
    /// Print only warnings, errors and what the command exists to print (no progress, no summaries).
    #[arg(short, long, global = true, conflicts_with = "verbose")]
    pub quiet: bool,
    /// Also print details: every held-out evaluation and checkpoint of a fit.
    #[arg(short, long, global = true)]
    pub verbose: bool,
}

#[derive(Subcommand, Debug)]
pub enum Command {
    /// Validate a scan fully and print a summary (layout, frames, depth coverage, bounds).
    Info(InfoArgs),
    /// Write the coloured point cloud as binary PLY to place boxes in (completed by the fitted model when there is one).
    Cloud(CloudArgs),
    /// Generate a procedural scan with exact ground truth (for tests and demos).
    Fixture(FixtureArgs),
    /// Generate a fixture scan and run every stage on it, printing accuracy against ground truth.
    Demo(DemoArgs),
    /// Fit the depth-supervised NeRF of a scan (writes SCAN/nerflabel/model.nlf).
    Fit(FitArgs),
    /// Print the error-against-run-time curve of the last fit.
    Report(ReportArgs),
    /// Label 3D boxes into instance masks, 2D boxes, object poses and COCO for every frame.
    Label(LabelArgs),
    /// Render novel views (colour, depth, mask) to one Parquet file.
    Synth(SynthArgs),
    /// Serve a local page to place 3D boxes on the scan and check the masks they give.
    Annotate(AnnotateArgs),
    /// Import boxes from labelCloud, KITTI or CVAT into a boxes.json, or export one to labelCloud.
    Boxes(boxes::BoxesArgs),
    /// Run many scans from a manifest (one a Slurm array task), write its sbatch script, or merge the results.
    Batch(BatchArgs),
}

/// How to read the scan.
#[derive(Args, Debug, Clone)]
pub struct ScanArgs {
    /// Scan folder (any supported layout).
    #[arg(default_value = ".")]
    pub scan: PathBuf,
    /// Force the layout instead of detecting it.
    #[arg(long, value_name = "LAYOUT", value_enum, ignore_case = true)]
    pub format: Option<Layout>,
    /// Re-orthonormalise slightly non-orthonormal pose rotations (with a warning) instead of failing.
    #[arg(long)]
    pub fix_poses: bool,
}

impl ScanArgs {
    pub fn load_options(&self) -> LoadOptions {
        LoadOptions {
            layout: self.format,
            fix_poses: self.fix_poses,
        }
    }
}

#[derive(Args, Debug)]
pub struct InfoArgs {
    #[command(flatten)]
    pub scan: ScanArgs,
}

#[derive(Args, Debug)]
pub struct CloudArgs {
    #[command(flatten)]
    pub scan: ScanArgs,
    /// Output PLY file (default: SCAN/nerflabel/cloud.ply).
    #[arg(short, long)]
    pub output: Option<PathBuf>,
    /// Voxel size in metres (default: derived from the scene size).
    #[arg(long)]
    pub voxel: Option<f64>,
    /// Fitted model whose surfaces complete the sensor depth, so objects the
    /// sensor missed appear (default: SCAN/nerflabel/model.nlf when it exists).
    #[arg(long, value_name = "PATH")]
    pub model: Option<PathBuf>,
    /// Sensor depth only, even where a fitted model exists.
    #[arg(long, conflicts_with = "model")]
    pub sensor: bool,
    /// Draw these boxes (boxes.json) into the cloud as points along their edges.
    #[arg(long, value_name = "FILE")]
    pub boxes: Option<PathBuf>,
    /// Use a model that belongs to another scan (or to this one before its poses changed).
    #[arg(long)]
    pub force: bool,
}

#[derive(Args, Debug)]
pub struct FixtureArgs {
    /// Output folder for the scan (ground truth goes to OUT/gt).
    pub out: PathBuf,
    /// Scene to generate.
    #[arg(long, value_enum, ignore_case = true, default_value_t = SceneKind::Tabletop)]
    pub scene: SceneKind,
    /// Number of scan frames (default: tabletop 120, small 24, cabinet 60).
    #[arg(long)]
    pub frames: Option<usize>,
    /// Number of held-out ground-truth views (default: frames / 10).
    #[arg(long)]
    pub holdout: Option<usize>,
    /// Colour image width.
    #[arg(long, default_value_t = 640)]
    pub width: u32,
    /// Colour image height.
    #[arg(long, default_value_t = 480)]
    pub height: u32,
    /// Random seed (trajectory jitter, sensor noise).
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
    /// Multiply all geometry by this factor.
    #[arg(long, default_value_t = 1.0)]
    pub scale: f64,
    /// Layout to write (nerfstudio when millimetre PNG depth cannot hold the scale).
    #[arg(long, value_enum, ignore_case = true, default_value_t = FixtureLayout::Native)]
    pub layout: FixtureLayout,
    /// No depth noise.
    #[arg(long)]
    pub no_depth_noise: bool,
    /// No random depth holes.
    #[arg(long)]
    pub no_holes: bool,
    /// No depth dropout at depth edges.
    #[arg(long)]
    pub no_edge_dropout: bool,
    /// Give the glass-like object sensor depth like every other object.
    #[arg(long)]
    pub no_glass: bool,
    /// No black border in the depth images.
    #[arg(long)]
    pub no_border: bool,
    /// No colour noise.
    #[arg(long)]
    pub no_colour_noise: bool,
    /// Depth at the colour resolution (default: 1/2.5 of it).
    #[arg(long)]
    pub full_res_depth: bool,
    /// No anti-aliasing of colour.
    #[arg(long)]
    pub no_supersample: bool,
    /// No sensor corruption at all.
    #[arg(long)]
    pub clean: bool,
    /// Write colour as JPEG of this quality (1-100) instead of PNG.
    #[arg(long, value_parser = clap::value_parser!(u8).range(1..=100))]
    pub jpeg: Option<u8>,
    /// Write scan poses with SLAM-like error (RMS 1.5 mm and 0.075 degrees per frame); gt/pose keeps the exact ones.
    #[arg(long)]
    pub pose_noise: bool,
    /// Pose error per frame as RMS millimetres and degrees, e.g. `10,0.5` (implies --pose-noise).
    #[arg(long, value_name = "MM,DEG")]
    pub pose_error: Option<String>,
    /// Slow drift of the written camera positions, RMS millimetres over the scan (implies --pose-noise).
    #[arg(long, value_name = "MM")]
    pub pose_drift: Option<f64>,
    /// Exposure and white balance drifting along the capture, as auto-exposure does: RMS of the log
    /// gain over the scan (e.g. 0.2 for about +-20 %); white balance per channel a third of it.
    #[arg(long, value_name = "LOG_GAIN")]
    pub exposure: Option<f64>,
    /// A lens that darkens the image towards its corners: share of the light lost in the farthest
    /// corner (e.g. 0.2 for corners at 80 %), falling off with the squared angle off the axis.
    #[arg(long, value_name = "LOSS")]
    pub vignetting: Option<f64>,
    /// As hard as a real handheld scan: JPEG colour (quality 85) and pose error on top of the default corruptions.
    #[arg(long, conflicts_with = "clean")]
    pub realistic: bool,
    /// Replace an earlier fixture in OUT.
    #[arg(long)]
    pub overwrite: bool,
}

#[derive(Args, Debug)]
pub struct DemoArgs {
    /// Folder for the demo scan and its outputs.
    #[arg(default_value = "nerflabel-demo")]
    pub out: PathBuf,
    /// Training time budget in seconds.
    #[arg(long, default_value_t = 60.0)]
    pub time: f64,
}

#[derive(Args, Debug)]
pub struct FitArgs {
    #[command(flatten)]
    pub scan: ScanArgs,
    /// Wall time of the whole command, seconds: loading the scan, preparation,
    /// training, held-out evaluation and writing the model all fit inside it.
    #[arg(long)]
    pub time: Option<f64>,
    /// Stop after this many steps.
    #[arg(long)]
    pub steps: Option<u64>,
    /// Model file (default SCAN/nerflabel/model.nlf).
    #[arg(long)]
    pub model: Option<PathBuf>,
    #[command(flatten)]
    pub settings: FitSettings,
    /// Continue from the checkpoint beside the model (MODEL with extension .checkpoint).
    ///
    /// Every fit writes that checkpoint every ~10 s of training and at the end, and keeps it.
    /// --steps and --time count what was already trained; without them the original budget
    /// applies. So an interrupted fit finishes where it would have, and a finished one is
    /// extended by a larger budget. The scan and every setting above that shapes training
    /// (--seed to --pose-scale) must be the same. Delete the checkpoint to reclaim its disk space.
    #[arg(long)]
    pub resume: bool,
}

#[derive(Args, Debug)]
pub struct ReportArgs {
    /// Scan folder.
    #[arg(default_value = ".")]
    pub scan: PathBuf,
    /// Draw PSNR, SSIM and depth error against seconds into this PNG, and the labels' mIoU when `label` scored them against the scan's ground truth (gt/masks of a generated scan).
    #[arg(long)]
    pub plot: Option<PathBuf>,
    /// Model file whose report to read (MODEL.report.json, or fit_report.json beside it from earlier versions; default SCAN/nerflabel/model.nlf).
    #[arg(long)]
    pub model: Option<PathBuf>,
}

#[derive(Args, Debug)]
pub struct LabelArgs {
    #[command(flatten)]
    pub scan: ScanArgs,
    /// boxes.json with oriented 3D boxes in the scan's world frame.
    #[arg(long, required_unless_present = "masks")]
    pub boxes: Option<PathBuf>,
    /// Instance masks of some frames to carry to every frame (e.g. from
    /// SAM 2 or drawn by hand): DIR/<stem>.png (8-bit palette or grayscale,
    /// 16-bit for ids above 255; value = object id, 0 = background) or
    /// DIR/<id>/<stem>.png (one binary mask per object and frame), with an
    /// optional DIR/labels.json ({"1": "mug"}) naming the objects. Given
    /// frames are written as given. With --boxes too, the boxes label what
    /// the masks leave as background and take the ids after the largest
    /// mask id.
    #[arg(long, value_name = "DIR")]
    pub masks: Option<PathBuf>,
    /// Output folder (default SCAN/nerflabel/labels).
    #[arg(long)]
    pub out: Option<PathBuf>,
    /// Write the images' file_name in coco.json relative to DIR (default:
    /// the scan folder); an image outside DIR gets `..` components. The
    /// absolute DIR is recorded as info.image_root.
    #[arg(long, value_name = "DIR")]
    pub image_root: Option<PathBuf>,
    /// Also write completed depth for every pixel (depth/*.png, mm).
    #[arg(long)]
    pub depth: bool,
    /// Model file (default SCAN/nerflabel/model.nlf).
    #[arg(long)]
    pub model: Option<PathBuf>,
    /// Only frames A..B (ids, inclusive start, exclusive end).
    #[arg(long)]
    pub frames: Option<String>,
    /// Depth source.
    #[arg(long, value_enum, ignore_case = true, default_value_t = DEFAULT_SOURCE)]
    pub source: DepthSource,
    /// Also write a dataset ultralytics trains on as it is, in OUT/yolo:
    /// images/ (the colour frames), labels/ (one `class cx cy w h` line per
    /// visible object, normalised), data.yaml (dataset path and class names),
    /// train.txt and val.txt (frames split by contiguous blocks, so that
    /// near-identical neighbouring frames do not straddle the split).
    #[arg(long)]
    pub yolo: bool,
    /// YOLO segmentation labels: one outline polygon per visible object
    /// instead of its box (implies --yolo). An object split by an occluder
    /// gets one polygon whose parts are joined by zero-width bridges, as
    /// ultralytics joins multi-part COCO polygons; holes are not cut out.
    #[arg(long)]
    pub yolo_seg: bool,
    /// How the colour frames get into OUT/yolo/images [default: link].
    #[arg(long, value_enum, value_name = "MODE")]
    pub yolo_images: Option<ImageMode>,
    /// Share of the labelled frames listed in val.txt, at least 0 and below 1
    /// [default: 0.2]. The frames are cut into 10 contiguous blocks and this
    /// share of the blocks, drawn with --seed, is the validation set.
    #[arg(long, value_name = "FRACTION", value_parser = parse_val_fraction)]
    pub yolo_val: Option<f64>,
    /// Seed of the YOLO train/val split.
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
    /// Use the model even if it was fitted to another scan or to this scan before its poses changed (warns).
    #[arg(long)]
    pub force: bool,
    /// Label exactly what each box encloses. By default a plane of the
    /// measured surface that runs through a box and continues well outside
    /// it (the table, floor or shelf under a loosely drawn box, a wall
    /// behind it) is excluded from the box, with what lies behind it. An
    /// object lying flat on its support (a sheet) keeps its box whole; one
    /// thinner than the plane's measured noise band is lost to the support.
    /// Also by default, where boxes overlap, a surface point in several
    /// boxes goes to the object nearest to it along the surface (each
    /// box's object is the surface that box alone holds; depth steps and
    /// valleys where objects touch separate surfaces), not simply to the
    /// smaller box. With --masks, the same planes are excluded from the
    /// masks' objects (a mask that bleeds onto the table around an object).
    #[arg(long)]
    pub exact_boxes: bool,
    /// Which box a point inside several boxes belongs to.
    #[arg(long, value_enum, default_value_t = Overlap::Smallest)]
    pub overlap: Overlap,
    /// Keep silhouettes exactly where depth and poses put them. By default
    /// pixels next to a silhouette take the label whose nearby pixels match
    /// their colour clearly better, pass after pass, so a contour moves up
    /// to 4 px onto the frame's edges (on soft, blurred frames a first pass
    /// looks 2 px either side): the frame's own image shows where the
    /// object is, while a pose error of a millimetre moves the depth-based
    /// silhouette by about a pixel.
    #[arg(long)]
    pub no_colour_snap: bool,
}

#[derive(Args, Debug)]
pub struct AnnotateArgs {
    #[command(flatten)]
    pub scan: ScanArgs,
    /// boxes.json to edit (default SCAN/boxes.json; created on the first save).
    #[arg(long, value_name = "FILE")]
    pub boxes: Option<PathBuf>,
    /// Model whose rendered depth the previews use (default SCAN/nerflabel/model.nlf
    /// when it exists; otherwise the sensor depth).
    #[arg(long)]
    pub model: Option<PathBuf>,
    /// Use the model even if it was fitted to another scan or to this scan before its poses changed (warns).
    #[arg(long)]
    pub force: bool,
    /// Port to listen on (default: a free one).
    #[arg(long, value_name = "N", default_value_t = 0)]
    pub port: u16,
    /// Address to listen on (127.0.0.1: this machine only).
    #[arg(long, value_name = "ADDR", default_value = "127.0.0.1")]
    pub host: String,
}

#[derive(Args, Debug)]
pub struct SynthArgs {
    #[command(flatten)]
    pub scan: ScanArgs,
    /// boxes.json (default SCAN/boxes.json).
    #[arg(long)]
    pub boxes: Option<PathBuf>,
    /// Instance masks of some frames (the layouts of `label --masks`): their
    /// objects appear in the synthetic masks. SCAN/boxes.json is then not
    /// read by default; boxes given with --boxes take the ids after the
    /// largest mask id.
    #[arg(long, value_name = "DIR")]
    pub masks: Option<PathBuf>,
    /// Label exactly what each box encloses. By default the support and
    /// wall planes `label` excludes from a box (the table under a loosely
    /// drawn box) are excluded from the synthetic masks too.
    #[arg(long)]
    pub exact_boxes: bool,
    /// Number of views to sample.
    #[arg(long, default_value_t = 500)]
    pub n: usize,
    /// Image width (default: the scan's).
    #[arg(long)]
    pub width: Option<u32>,
    /// Image height (default: the scan's).
    #[arg(long)]
    pub height: Option<u32>,
    /// Random seed.
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
    /// Render the views listed in this JSON file instead of sampling.
    #[arg(long)]
    pub poses: Option<PathBuf>,
    /// Output Parquet file (default SCAN/nerflabel/synth.parquet).
    #[arg(long)]
    pub out: Option<PathBuf>,
    /// Replace the output file when it exists (otherwise an existing file is refused).
    #[arg(long)]
    pub overwrite: bool,
    /// Use the model even if it was fitted to another scan or to this scan before its poses changed (warns).
    #[arg(long)]
    pub force: bool,
    /// Model file (default SCAN/nerflabel/model.nlf).
    #[arg(long)]
    pub model: Option<PathBuf>,
    /// Minimum distance of a sampled camera to the scanned surface, metres (default: scaled to the scene).
    #[arg(long)]
    pub clearance: Option<f64>,
    /// Exposure and white balance of the rendered colour: `neutral` (the
    /// scan's average, what the model learnt) or a frame's stem (e.g.
    /// 000042) to render as that frame was captured.
    #[arg(long, value_name = "neutral|FRAME", default_value = "neutral")]
    pub appearance: String,
}

#[derive(Args, Debug)]
pub struct BatchArgs {
    /// Manifest: JSON Lines, one scan a line, e.g. `{"scan": "scans/kitchen",
    /// "boxes": "scans/kitchen/boxes.json", "time": 300, "synth_views": 200}`.
    /// Fields: scan (required), id (default: the folder's name), boxes,
    /// masks, time, steps, seed, preset, synth_views (default 500, 0 = no
    /// synth), synth_width, synth_height. Relative paths are taken from the
    /// manifest's folder.
    pub manifest: PathBuf,
    /// Run only the scan at this index (0-based, blank lines not counted).
    /// Default: $SLURM_ARRAY_TASK_ID, else $JOB_COMPLETION_INDEX, else every
    /// scan in turn. Finished stages are skipped, a stopped fit resumes; a
    /// scan another run is working on is refused.
    #[arg(long, value_name = "N")]
    pub index: Option<usize>,
    /// Print an sbatch script of a job array over the manifest (one task a
    /// scan; limits derived from the scans unless given below).
    #[arg(long, conflicts_with_all = ["merge", "index"])]
    pub sbatch: bool,
    /// CPUs per array task [default: 4].
    #[arg(long, requires = "sbatch", value_name = "N")]
    pub cpus: Option<u32>,
    /// Memory per array task: megabytes or e.g. 16G [default: from the largest scan].
    #[arg(long, requires = "sbatch", value_name = "SIZE")]
    pub mem: Option<String>,
    /// Time limit per array task: seconds, H:MM:SS or D-HH:MM:SS [default: from the scans' budgets].
    #[arg(long, requires = "sbatch", value_name = "TIME")]
    pub time_limit: Option<String>,
    /// Most array tasks running at once (`--array=0-(N-1)%K`) [default: 8].
    #[arg(long, requires = "sbatch", value_name = "K")]
    pub parallel: Option<usize>,
    /// Slurm partition.
    #[arg(long, requires = "sbatch")]
    pub partition: Option<String>,
    /// Merge the finished scans into OUT: synth/scan=<id>/part-0.parquet
    /// (hive-partitioned, `scan` column), coco/train.json and coco/val.json
    /// (split by scan; image paths relative to OUT), splits.json, summary.csv.
    #[arg(long, value_name = "OUT", conflicts_with = "index")]
    pub merge: Option<PathBuf>,
    /// Share of the scans in the validation split [default: 0.2].
    #[arg(long, requires = "merge", value_name = "FRACTION")]
    pub val: Option<f64>,
    /// Share of the scans in a test split (coco/test.json) [default: 0].
    #[arg(long, requires = "merge", value_name = "FRACTION")]
    pub test: Option<f64>,
    /// Seed of the split [default: 0].
    #[arg(long, requires = "merge", value_name = "N")]
    pub seed: Option<u64>,
}

/// `--yolo-val`: a fraction in [0, 1).
fn parse_val_fraction(text: &str) -> Result<f64, String> {
    let value: f64 = text.trim().parse().map_err(|_| format!("`{text}` is not a number"))?;
    if !(0.0..1.0).contains(&value) {
        return Err(format!(
            "{value} is not a share of the frames: expected at least 0 and below 1 (e.g. 0.2)"
        ));
    }
    Ok(value)
}

/// Run one parsed command.
pub fn run(cli: Cli) -> anyhow::Result<()> {
    verbosity::set(match (cli.quiet, cli.verbose) {
        (true, _) => verbosity::QUIET,
        (false, true) => verbosity::VERBOSE,
        (false, false) => verbosity::NORMAL,
    });
    if let Some(threads) = cli.threads {
        if threads == 0 {
            anyhow::bail!("--threads must be at least 1");
        }
        rayon::ThreadPoolBuilder::new()
            .num_threads(threads)
            .build_global()
            .map_err(|e| anyhow::anyhow!("cannot start {threads} worker threads (--threads): {e}"))?;
    }
    // Tiny late-training gradients must not take x86's slow path.
    nerflabel::nerf::field::simd::flush_subnormals_on_all_threads();
    match cli.command {
        Command::Info(args) => info::run(&args),
        Command::Cloud(args) => cloud::run(&args),
        Command::Fit(args) => fit::run(&args),
        Command::Report(args) => report::run(&args),
        Command::Fixture(args) => fixture::run(&args),
        Command::Demo(args) => demo::run(&args),
        Command::Label(args) => label::run(&args),
        Command::Synth(args) => synth::run(&args),
        Command::Boxes(args) => boxes::run(&args),
        Command::Annotate(args) => annotate::run(&args),
        Command::Batch(args) => batch::run(&args),
    }
}
