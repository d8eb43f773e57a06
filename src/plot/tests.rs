//! Rendering tests: pixel mapping, line pixels, legend, degenerate input
//! and the PNG round trip.

use super::*;

const WHITE: [u8; 3] = [255, 255, 255];
const BLUE: [u8; 3] = [31, 119, 180];
const ORANGE: [u8; 3] = [230, 85, 13];

fn series(name: &str, points: Vec<(f64, f64)>, color: [u8; 3]) -> Series {
    Series {
        name: name.into(),
        points,
        color,
    }
}

fn panel(series: Vec<Series>) -> Panel {
    Panel {
        title: "Held-out PSNR".into(),
        x_label: "training time (s)".into(),
        y_label: "PSNR (dB)".into(),
        series,
    }
}

/// A fit-like curve: PSNR rising and depth MAE falling over 120 s.
fn fit_panels() -> Vec<Panel> {
    let t: Vec<f64> = (0..=12).map(|i| i as f64 * 10.0).collect();
    let psnr = t
        .iter()
        .map(|&s| (s, 14.0 + 14.5 * (1.0 - (-s / 35.0).exp())))
        .collect();
    let psnr_train = t
        .iter()
        .map(|&s| (s, 15.0 + 17.0 * (1.0 - (-s / 30.0).exp())))
        .collect();
    let mae = t.iter().map(|&s| (s, 6.0 + 90.0 * (-s / 25.0).exp())).collect();
    vec![
        Panel {
            title: "Held-out PSNR".into(),
            x_label: "training time (s)".into(),
            y_label: "PSNR (dB)".into(),
            series: vec![series("held-out", psnr, BLUE), series("training", psnr_train, ORANGE)],
        },
        Panel {
            title: "Depth MAE".into(),
            x_label: "training time (s)".into(),
            y_label: "depth MAE (mm)".into(),
            series: vec![series("held-out", mae, [44, 160, 44])],
        },
    ]
}

fn count_color(img: &RgbImage, color: [u8; 3]) -> usize {
    img.pixels().filter(|p| p.0 == color).count()
}

fn full_rect(w: u32, h: u32) -> Rect {
    Rect {
        x: 0,
        y: 0,
        w: i64::from(w),
        h: i64::from(h),
    }
}

#[test]
fn x_range_max_maps_to_right_edge_of_plot_area() {
    let p = panel(vec![series("a", vec![(0.0, 10.0), (50.0, 30.0), (100.0, 40.0)], BLUE)]);
    let frame = panel::layout(&p, full_rect(800, 400), 2, 0).unwrap();
    assert_eq!((frame.x.lo, frame.x.hi), (0.0, 100.0));
    assert_eq!((frame.y.lo, frame.y.hi), (10.0, 40.0));
    let a = frame.area;
    assert!(a.x > 0 && a.right() < 799 && a.y > 0 && a.bottom() < 399, "{a:?}");
    assert_eq!(frame.to_px(100.0, 40.0), (a.right() as f64, a.y as f64));
    assert_eq!(frame.to_px(0.0, 10.0), (a.x as f64, a.bottom() as f64));
    let (mx, my) = frame.to_px(50.0, 25.0);
    assert!((mx - (a.x + a.right()) as f64 / 2.0).abs() < 1e-9);
    assert!((my - (a.y + a.bottom()) as f64 / 2.0).abs() < 1e-9);
}

#[test]
fn line_between_two_points_has_series_colour() {
    let p = panel(vec![series("a", vec![(0.0, 0.0), (10.0, 5.0)], BLUE)]);
    let img = render_panels(std::slice::from_ref(&p), 800, 400);
    assert_eq!(img.dimensions(), (800, 400));
    let frame = panel::layout(&p, full_rect(800, 400), text_scale(800, 400), 0).unwrap();
    let (a, b) = (frame.to_px(0.0, 0.0), frame.to_px(10.0, 5.0));
    // Every sample along the segment, away from the end markers, is blue.
    for i in 1..20 {
        let t = i as f64 / 20.0;
        let (x, y) = (a.0 + t * (b.0 - a.0), a.1 + t * (b.1 - a.1));
        let (x, y) = (x.round() as u32, y.round() as u32);
        let near = (y.saturating_sub(1)..=y + 1).any(|yy| img.get_pixel(x, yy).0 == BLUE);
        assert!(near, "no series colour near ({x}, {y}) at t = {t}");
    }
    // A 2-pixel line plus two markers: bounded amount of ink in the colour.
    let len = ((b.0 - a.0).powi(2) + (b.1 - a.1).powi(2)).sqrt();
    let blue = count_color(&img, BLUE) as f64;
    assert!(
        blue > 1.8 * len && blue < 3.2 * len + 200.0,
        "{blue} blue pixels for a {len:.0} px line"
    );
}

#[test]
fn legend_appears_only_with_several_series() {
    let one = panel(vec![series("held-out", vec![(0.0, 20.0), (60.0, 28.0)], BLUE)]);
    let mut two = one.clone();
    two.series
        .push(series("training", vec![(0.0, 21.0), (60.0, 30.0)], ORANGE));
    let (w, h) = (800, 400);
    let frame = panel::layout(&two, full_rect(w, h), 2, 0).unwrap();
    let img1 = render_panels(&[one], w, h);
    let img2 = render_panels(&[two], w, h);
    // The legend swatches: a horizontal run of the colour at least 16*2 px
    // long, which the rising lines cannot make. Returns (length, last x, y).
    let longest_run = |img: &RgbImage, color: [u8; 3]| {
        let mut best = (0, 0, 0);
        for y in 0..h {
            let mut run = 0;
            for x in 0..w {
                run = if img.get_pixel(x, y).0 == color { run + 1 } else { 0 };
                if run > best.0 {
                    best = (run, x, y);
                }
            }
        }
        best
    };
    assert!(longest_run(&img1, BLUE).0 < 20);
    for color in [BLUE, ORANGE] {
        let (len, x, y) = longest_run(&img2, color);
        assert!(len >= 32, "swatch of {color:?} is {len} px");
        let a = frame.area;
        assert!(a.contains(i64::from(x), i64::from(y)) && a.contains(i64::from(x) - len as i64 + 1, i64::from(y)));
    }
}

#[test]
fn degenerate_inputs_render_without_panicking() {
    let nan_mix = vec![
        (f64::NAN, 1.0),
        (0.0, 2.0),
        (1.0, f64::INFINITY),
        (2.0, 3.0),
        (f64::NEG_INFINITY, 0.0),
    ];
    let cases: Vec<(&str, Vec<Panel>)> = vec![
        ("no panels", vec![]),
        ("no series", vec![panel(vec![])]),
        (
            "empty series",
            vec![panel(vec![series("a", vec![], BLUE), series("b", vec![], ORANGE)])],
        ),
        (
            "all non-finite",
            vec![panel(vec![series(
                "a",
                vec![(f64::NAN, f64::NAN), (f64::INFINITY, 1.0)],
                BLUE,
            )])],
        ),
        ("one point", vec![panel(vec![series("a", vec![(3.0, 25.0)], BLUE)])]),
        (
            "all equal",
            vec![panel(vec![series("a", vec![(1.0, 5.0), (1.0, 5.0), (1.0, 5.0)], BLUE)])],
        ),
        (
            "flat y",
            vec![panel(vec![series("a", vec![(0.0, 7.0), (9.0, 7.0)], BLUE)])],
        ),
        ("nan mix", vec![panel(vec![series("a", nan_mix, BLUE)])]),
        (
            "huge values",
            vec![panel(vec![series(
                "a",
                vec![(-f64::MAX, f64::MAX), (f64::MAX, -f64::MAX), (0.0, 1e-300)],
                BLUE,
            )])],
        ),
        (
            "many series",
            vec![panel(
                (0..200)
                    .map(|i| series(&"n".repeat(i), vec![(i as f64, 1.0)], BLUE))
                    .collect(),
            )],
        ),
        (
            "many panels",
            (0..500)
                .map(|_| panel(vec![series("a", vec![(0.0, 1.0), (1.0, 2.0)], BLUE)]))
                .collect(),
        ),
        (
            "long text",
            vec![Panel {
                title: "T".repeat(10_000),
                x_label: "\u{2603}".repeat(500),
                ..panel(vec![series("a", vec![(0.0, 1.0)], BLUE)])
            }],
        ),
    ];
    for (name, panels) in &cases {
        for (w, h) in [(0, 0), (64, 64), (100, 3000), (800, 600), (u32::MAX, 10)] {
            let img = render_panels(panels, w, h);
            let want = (w.clamp(MIN_SIZE, MAX_SIZE), h.clamp(MIN_SIZE, MAX_SIZE));
            assert_eq!(img.dimensions(), want, "{name} at {w}x{h}");
        }
        let img = render_panels(panels, 800, 600);
        assert!(img.pixels().any(|p| p.0 != WHITE), "{name}: blank image");
    }
    // A single point or all-equal data still shows its marker.
    for (name, panels) in &cases[4..6] {
        assert!(
            count_color(&render_panels(panels, 800, 600), BLUE) > 10,
            "{name}: no marker"
        );
    }
    // No finite data: no series colour, and "no data" inked in the middle of the area.
    for (name, panels) in &cases[1..4] {
        let img = render_panels(panels, 800, 600);
        assert_eq!(count_color(&img, BLUE), 0, "{name}");
        let centre = (380..420).flat_map(|x| (280..320).map(move |y| (x, y)));
        assert!(
            centre.filter(|&(x, y)| img.get_pixel(x, y).0 != WHITE).count() > 50,
            "{name}: no 'no data' text"
        );
    }
}

#[test]
fn write_png_round_trips() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("plots").join("curve.png");
    let img = render_panels(&fit_panels(), 1000, 800);
    write_png(&path, &img).unwrap();
    let back = image::open(&path).unwrap().into_rgb8();
    assert_eq!(back, img);
    // Writing below a regular file fails and names the path.
    let bad = dir.path().join("plots").join("curve.png").join("x.png");
    let err = write_png(&bad, &img).unwrap_err();
    assert!(matches!(err, PlotError::Write { .. }));
    assert!(err.to_string().contains("x.png"), "{err}");
}

#[test]
fn fit_curve_renders_both_panels() {
    let img = render_panels(&fit_panels(), 1000, 800);
    // Each panel's series colour appears in its own half only.
    let in_half = |color: [u8; 3], top: bool| {
        img.enumerate_pixels()
            .filter(|(_, y, p)| p.0 == color && (*y < 400) == top)
            .count()
    };
    assert!(in_half(BLUE, true) > 500 && in_half(BLUE, false) == 0);
    assert!(in_half([44, 160, 44], false) > 500 && in_half([44, 160, 44], true) == 0);
    // Stacked panels share the left edge of their plot areas.
    let panels = fit_panels();
    let w = panels.iter().map(|p| panel::y_labels_width(p, 2)).max().unwrap();
    let top = panel::layout(
        &panels[0],
        Rect {
            x: 0,
            y: 0,
            w: 1000,
            h: 400,
        },
        2,
        w,
    )
    .unwrap()
    .area;
    let bottom = panel::layout(
        &panels[1],
        Rect {
            x: 0,
            y: 400,
            w: 1000,
            h: 400,
        },
        2,
        w,
    )
    .unwrap()
    .area;
    assert_eq!((top.x, top.w), (bottom.x, bottom.w));
    for a in [top, bottom] {
        let mid = (a.y + a.h / 2) as u32;
        assert_ne!(img.get_pixel(a.x as u32, mid).0, WHITE, "no frame at x = {}", a.x);
        assert_eq!(img.get_pixel(a.x as u32 - 1, mid).0, WHITE);
    }
    if let Some(path) = std::env::var_os("NERFLABEL_PLOT_PREVIEW") {
        write_png(Path::new(&path), &img).unwrap();
    }
}
