//! Render a fixture's held-out views with a model next to the exact ground
//! truth, for eyeballing: OUT/holdout_N.png = [truth | render | depth error].
//!
//! cargo run --release --example render_holdout -- FIXTURE_DIR MODEL OUT_DIR

use nerflabel::fixture::{read_meta, trajectory};
use nerflabel::nerf::model_file::Model;
use nerflabel::nerf::render::view::ViewRenderer;
use std::path::PathBuf;

fn main() -> anyhow::Result<()> {
    let args: Vec<PathBuf> = std::env::args().skip(1).map(PathBuf::from).collect();
    let [fixture, model_path, out] = args.as_slice() else {
        anyhow::bail!("usage: render_holdout FIXTURE MODEL OUT_DIR")
    };
    let meta = read_meta(fixture)?;
    let scene = meta.build_scene();
    let model = Model::load(model_path)?;
    let renderer = ViewRenderer::new(&model)?;
    let path = trajectory(&scene, meta.frames, meta.holdout, meta.seed);
    std::fs::create_dir_all(out)?;
    let (w, h) = (meta.width, meta.height);
    for (i, pose) in path.holdout.iter().enumerate().take(4) {
        let truth = scene.render(pose, &meta.intrinsics, w, h);
        let view = renderer.render_view(pose, &meta.intrinsics, w, h, true);
        let mut img = image::RgbImage::new(3 * w, h);
        for y in 0..h {
            for x in 0..w {
                let p = (y * w + x) as usize;
                img.put_pixel(x, y, *truth.rgb.get_pixel(x, y));
                img.put_pixel(
                    w + x,
                    y,
                    image::Rgb([view.rgb[3 * p], view.rgb[3 * p + 1], view.rgb[3 * p + 2]]),
                );
                let err = (view.depth_m[p] - truth.depth[p]).abs();
                let e = (err / 0.05 * 255.0).min(255.0) as u8;
                img.put_pixel(
                    2 * w + x,
                    y,
                    if truth.depth[p] > 0.0 && view.depth_m[p] <= 0.0 {
                        image::Rgb([0, 0, 255])
                    } else {
                        image::Rgb([e, e, e])
                    },
                );
            }
        }
        img.save(out.join(format!("holdout_{i}.png")))?;
    }
    Ok(())
}
