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
        log_y: false,
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
            log_y: false,
        },
        Panel {
            title: "Depth MAE".into(),
            x_label: "training time (s)".into(),
            y_label: "depth MAE (mm)".into(),
            series: vec![series("held-out", mae, [44, 160, 44])],
            log_y: true,
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
        // Two rows below the middle: the log panel has its 10 mm tick there.
        let mid = (a.y + a.h / 2 + 2) as u32;
        assert_ne!(img.get_pixel(a.x as u32, mid).0, WHITE, "no frame at x = {}", a.x);
        assert_eq!(img.get_pixel(a.x as u32 - 1, mid).0, WHITE);
    }
    if let Some(path) = std::env::var_os("NERFLABEL_PLOT_PREVIEW") {
        write_png(Path::new(&path), &img).unwrap();
    }
}

/// The depth panel of a fit whose error falls from metres to millimetres.
fn depth_panel() -> Panel {
    let mae = (0..=12)
        .map(|i| (i as f64 * 10.0, 2.0 + 1500.0 * (-(i as f64) / 1.5).exp()))
        .collect();
    Panel {
        title: "Held-out depth error".into(),
        x_label: "training time (s)".into(),
        y_label: "depth MAE (mm, log)".into(),
        series: vec![series("held-out", mae, [44, 160, 44])],
        log_y: true,
    }
}

/// Rows of the y tick marks (grey runs left of the plot frame) in `a`.
fn y_tick_rows(img: &RgbImage, a: Rect) -> Vec<i64> {
    (a.y..=a.bottom())
        .filter(|&y| img.get_pixel(a.x as u32 - 2, y as u32).0 == [110, 110, 110])
        .collect()
}

#[test]
fn log_depth_axis_places_1_mm_and_10_mm_a_decade_apart() {
    let p = depth_panel();
    let (w, h) = (1000, 400);
    let frame = panel::layout(&p, full_rect(w, h), text_scale(w, h), 0).unwrap();
    assert!(frame.y.log);
    // 2 mm .. 1.5 m: decades 1 mm .. 10 m, ticked at 1, 10, 100, 1000, 10000 mm.
    assert_eq!((frame.y.lo, frame.y.hi), (0.0, 4.0));
    let labels: Vec<String> = frame.y.ticks.iter().map(|&t| frame.y.label(t)).collect();
    assert_eq!(labels, ["1", "10", "100", "1000", "10000"]);
    let a = frame.area;
    let (_, y1) = frame.to_px(0.0, 1.0);
    let (_, y10) = frame.to_px(0.0, 10.0);
    let (_, y100) = frame.to_px(0.0, 100.0);
    let decade = (a.h - 1) as f64 / 4.0;
    assert!(
        (y1 - a.bottom() as f64).abs() < 1e-9,
        "1 mm at row {y1}, bottom {}",
        a.bottom()
    );
    assert!((y1 - y10 - decade).abs() < 1e-9 && (y10 - y100 - decade).abs() < 1e-9);
    // In the image: one tick mark per decade, evenly a decade apart, the
    // lowest at the 1 mm row and the next at the 10 mm row.
    let img = render_panels(std::slice::from_ref(&p), w, h);
    let rows = y_tick_rows(&img, a);
    assert_eq!(rows.len(), 5, "tick rows {rows:?}");
    assert_eq!(rows[4], y1.round() as i64);
    assert_eq!(rows[3], y10.round() as i64);
    for pair in rows.windows(2) {
        assert!(((pair[1] - pair[0]) as f64 - decade).abs() <= 1.0, "{rows:?}");
    }
    // The millimetre range is not flattened: 2 mm sits more than 7 % of the
    // height above the bottom (on a linear axis up to 1.5 m: 0.13 %).
    let (_, y_last) = frame.to_px(120.0, 2.0);
    assert!(a.bottom() as f64 - y_last > 0.07 * a.h as f64);
    // A point at or below zero is left out rather than drawn at -infinity.
    let mut zero = depth_panel();
    zero.series[0].points.push((130.0, 0.0));
    let frame0 = panel::layout(&zero, full_rect(w, h), text_scale(w, h), 0).unwrap();
    assert_eq!((frame0.y.lo, frame0.y.hi), (0.0, 4.0));
    assert!(count_color(&render_panels(&[zero], w, h), [44, 160, 44]) > 500);
}

#[test]
fn report_plot_draws_an_ssim_panel_between_psnr_and_depth() {
    const RED: [u8; 3] = [214, 39, 40];
    let t: Vec<f64> = (0..=12).map(|i| i as f64 * 10.0).collect();
    let ssim = t.iter().map(|&s| (s, 0.4 + 0.5 * (1.0 - (-s / 30.0).exp()))).collect();
    let mut panels = fit_panels();
    panels.insert(
        1,
        Panel {
            title: "Held-out SSIM".into(),
            x_label: "training time (s)".into(),
            y_label: "SSIM".into(),
            series: vec![series("held-out", ssim, RED)],
            log_y: false,
        },
    );
    let (w, h) = (1000, 1050);
    let img = render_panels(&panels, w, h);
    let third = |y: u32| (y * 3 / h) as usize;
    // The SSIM curve's colour is inked in the middle third only, plenty of it.
    let red: Vec<usize> = (0..3)
        .map(|k| {
            img.enumerate_pixels()
                .filter(|(_, y, p)| p.0 == RED && third(*y) == k)
                .count()
        })
        .collect();
    assert!(red[0] == 0 && red[2] == 0 && red[1] > 500, "{red:?}");
    // Its frame, tick marks and title are drawn: the title row band at the
    // top of the middle third holds dark text pixels near the centre.
    let rect = Rect {
        x: 0,
        y: 350,
        w: 1000,
        h: 350,
    };
    let frame = panel::layout(&panels[1], rect, text_scale(w, 350), 0).unwrap();
    assert_eq!((frame.y.lo, frame.y.hi), (0.4, 0.9));
    let title_ink = (350..frame.area.y as u32)
        .flat_map(|y| (400..600).map(move |x| (x, y)))
        .filter(|&(x, y)| img.get_pixel(x, y).0 == [34, 34, 34])
        .count();
    assert!(title_ink > 100, "{title_ink} title pixels");
    assert!(y_tick_rows(&img, frame.area).len() >= 3);
}
