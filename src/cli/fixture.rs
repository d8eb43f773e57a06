//! `nerflabel fixture`: write a procedural scan with exact ground truth.

use super::verbosity::say;
use super::FixtureArgs;
use anyhow::Context;
use nerflabel::fixture::{generate, Corruptions, FixtureOptions, FixtureSummary};

/// Options from the command-line flags.
pub fn options(args: &FixtureArgs) -> anyhow::Result<FixtureOptions> {
    let mut options = FixtureOptions::new(args.scene);
    options.width = args.width;
    options.height = args.height;
    options.frames = args.frames;
    options.holdout = args.holdout;
    options.seed = args.seed;
    options.scale = args.scale;
    options.layout = args.layout;
    options.overwrite = args.overwrite;
    options.supersample = !args.no_supersample;
    let mut c = match (args.clean, args.realistic) {
        (true, _) => Corruptions::none(),
        (false, true) => Corruptions::realistic(),
        (false, false) => Corruptions::default(),
    };
    if let Some(q) = args.jpeg {
        c.jpeg_quality = q;
    }
    c.pose_noise |= args.pose_noise;
    if let Some(e) = args.exposure {
        c.exposure_change = e;
    }
    if let Some(v) = args.vignetting {
        c.vignetting = v;
    }
    if let Some(text) = &args.pose_error {
        let parsed: Option<(f64, f64)> = text
            .split_once(',')
            .and_then(|(mm, deg)| Some((mm.trim().parse().ok()?, deg.trim().parse().ok()?)));
        let Some((mm, deg)) = parsed.filter(|(mm, deg)| mm.is_finite() && deg.is_finite() && *mm >= 0.0 && *deg >= 0.0)
        else {
            anyhow::bail!(
                "--pose-error {text}: expected millimetres and degrees as two non-negative numbers, e.g. 10,0.5"
            );
        };
        (c.pose_noise, c.pose_sigma_m, c.pose_sigma_deg) = (true, mm * 1e-3, deg);
    }
    if let Some(mm) = args.pose_drift {
        if !(mm.is_finite() && mm >= 0.0) {
            anyhow::bail!("--pose-drift {mm}: expected non-negative millimetres");
        }
        (c.pose_noise, c.pose_drift_m) = (true, mm * 1e-3);
    }
    c.depth_noise &= !args.no_depth_noise;
    c.holes &= !args.no_holes;
    c.edge_dropout &= !args.no_edge_dropout;
    c.no_depth_objects &= !args.no_glass;
    c.border &= !args.no_border;
    c.colour_noise &= !args.no_colour_noise;
    c.low_res_depth &= !args.full_res_depth;
    options.corruptions = c;
    Ok(options)
}

/// Generate and report.
pub fn write(args: &FixtureArgs) -> anyhow::Result<FixtureSummary> {
    let options = options(args)?;
    let summary =
        generate(&args.out, &options).with_context(|| format!("cannot write the fixture {}", args.out.display()))?;
    for warning in &summary.warnings {
        eprintln!("warning: {warning}");
    }
    Ok(summary)
}

pub fn run(args: &FixtureArgs) -> anyhow::Result<()> {
    let s = write(args)?;
    say!(
        "wrote {} scene to {}: {} frames {}x{} ({} layout), {} held-out views, {} objects; ground truth in {}",
        s.scene.name(),
        s.out.display(),
        s.frames,
        s.size.0,
        s.size.1,
        s.layout,
        s.holdout,
        s.objects,
        s.out.join("gt").display()
    );
    Ok(())
}
