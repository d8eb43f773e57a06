//! "Nice" axis ranges: ticks on 1-2-5 steps that cover the data (linear), or
//! at 1, 2 and 5 times each power of ten (logarithmic), and their labels
//! printed with just enough decimals.

/// Most ticks an axis gets; the step is the smallest 1-2-5 value that fits.
const MAX_TICKS: f64 = 7.0;

/// An axis range snapped to tick values.
#[derive(Clone, Debug, PartialEq)]
pub struct Axis {
    /// First tick: the value at the start of the axis.
    pub lo: f64,
    /// Last tick: the value at the end of the axis.
    pub hi: f64,
    /// Distance between ticks, 1, 2 or 5 times a power of ten.
    pub step: f64,
    /// Tick values from `lo` to `hi` inclusive (3 to 10 of them on a linear
    /// axis).
    pub ticks: Vec<f64>,
    /// Logarithmic: `lo`, `hi` and `ticks` are base-10 logarithms of the
    /// values (`step` is one decade).
    pub log: bool,
}

/// Decades a logarithmic axis spans at most (its ends are clamped).
const MAX_DECADES: i32 = 40;
/// Up to this many decades a log axis ticks 1, 2 and 5 of each; beyond, 1 only.
const MAX_1_2_5_DECADES: i32 = 3;

impl Axis {
    /// Where `v` lies on the axis: `v` itself, or its logarithm on a log
    /// axis (non-finite for `v <= 0`).
    pub fn coord(&self, v: f64) -> f64 {
        if self.log {
            v.log10()
        } else {
            v
        }
    }

    /// Label of tick `t` (an axis coordinate, see [`Axis::coord`]).
    pub fn label(&self, t: f64) -> String {
        if self.log {
            format_log_tick(t)
        } else {
            format_tick(t, self.step)
        }
    }
}

/// A logarithmic axis over the positive range `[lo, hi]` (given in any
/// order; non-positive or non-finite bounds fall back to 1..10): whole
/// decades that cover it, ticks at 1, 2 and 5 times each power of ten (the
/// powers of ten only when it spans more than three decades).
pub fn log_axis(lo: f64, hi: f64) -> Axis {
    let ok = |v: f64| v.is_finite() && v > 0.0;
    let (lo, hi) = if ok(lo) && ok(hi) {
        (lo.min(hi), lo.max(hi))
    } else {
        (1.0, 10.0)
    };
    // A hair of slack so 10.000000000000002 does not open a new decade.
    let first = ((lo.log10() + 1e-9).floor() as i32).clamp(-300, 300);
    let mut last = ((hi.log10() - 1e-9).ceil() as i32).clamp(-300, 300);
    if last <= first {
        last = first + 1;
    }
    let last = last.min(first + MAX_DECADES);
    let multiples: &[f64] = if last - first > MAX_1_2_5_DECADES {
        &[1.0]
    } else {
        &[1.0, 2.0, 5.0]
    };
    let mut ticks = Vec::new();
    for exp in first..last {
        ticks.extend(multiples.iter().map(|m| f64::from(exp) + m.log10()));
    }
    ticks.push(f64::from(last));
    Axis {
        lo: f64::from(first),
        hi: f64::from(last),
        step: 1.0,
        ticks,
        log: true,
    }
}

/// Label of the log-axis tick at `10^t`: plain decimals from 0.001 to
/// 999999 (`0.5`, `20`, `1000`), scientific beyond (`2e-5`, `1e7`).
pub fn format_log_tick(t: f64) -> String {
    if !t.is_finite() {
        return format!("{t}");
    }
    let exp = t.floor();
    // The 1, 2 or 5 in front of the power of ten.
    let m = 10f64.powf(t - exp).round();
    if !(-3.0..6.0).contains(&exp) {
        return format!("{m}e{exp}");
    }
    let decimals = (-exp).max(0.0) as usize;
    format!("{:.decimals$}", tick_value(1.0, m, exp as i32))
}

/// `x / step` with floating noise next to an integer snapped onto it, so
/// 1.1 / 0.1 counts as 11 rather than a hair above it.
fn quotient(x: f64, step: f64) -> f64 {
    let q = x / step;
    let r = q.round();
    if (q - r).abs() < (r.abs() * 1e-12).max(1e-9) {
        r
    } else {
        q
    }
}

/// `k * m * 10^exp`, dividing by the power of ten for negative exponents so
/// that e.g. 6 * 0.2 comes out as exactly 1.2 rather than 1.2000000000000002.
fn tick_value(k: f64, m: f64, exp: i32) -> f64 {
    if exp >= 0 {
        k * m * 10f64.powi(exp)
    } else {
        k * m / 10f64.powi(-exp)
    }
}

/// Ticks covering `[lo, hi]` (given in any order). Non-finite bounds fall
/// back to 0..1; an empty or near-empty range is widened around its value.
pub fn nice_axis(lo: f64, hi: f64) -> Axis {
    let (mut lo, mut hi) = if lo.is_finite() && hi.is_finite() {
        (lo.min(hi), lo.max(hi))
    } else {
        (0.0, 1.0)
    };
    // Halves keep the span finite even for values near f64::MAX.
    let half_span = hi * 0.5 - lo * 0.5;
    let mid = lo * 0.5 + hi * 0.5;
    if half_span <= mid.abs() * 1e-9 {
        let pad = if mid == 0.0 { 1.0 } else { mid.abs() * 0.1 };
        lo = mid - pad;
        hi = mid + pad;
    }
    // Keep headroom so lo/step and the tick values never overflow.
    lo = lo.max(-1e306);
    hi = hi.min(1e306);
    let raw = (hi * 0.5 - lo * 0.5) * (2.0 / (MAX_TICKS - 1.0));
    // Start a decade below the raw step and walk up the 1-2-5 ladder.
    let start = raw.log10().floor();
    let first_exp = if start.is_finite() { start as i32 - 1 } else { 0 };
    for exp in first_exp..first_exp + 12 {
        for m in [1.0, 2.0, 5.0] {
            let step = tick_value(1.0, m, exp);
            let first = quotient(lo, step).floor();
            let last = quotient(hi, step).ceil();
            let count = last - first + 1.0;
            if count <= MAX_TICKS {
                let ticks: Vec<f64> = (0..count as usize)
                    .map(|i| tick_value(first + i as f64, m, exp))
                    .collect();
                return Axis {
                    lo: tick_value(first, m, exp),
                    hi: tick_value(last, m, exp),
                    step,
                    ticks,
                    log: false,
                };
            }
        }
    }
    // Unreachable for finite input; keep a valid three-tick axis anyway.
    Axis {
        lo,
        hi,
        step: hi * 0.5 - lo * 0.5,
        ticks: vec![lo, mid, hi],
        log: false,
    }
}

/// Label for tick `v` on an axis with tick spacing `step`: fixed-point with
/// as many decimals as the step needs, or scientific for very large or very
/// small magnitudes. Zero prints as "0", never "-0".
pub fn format_tick(v: f64, step: f64) -> String {
    if !v.is_finite() || !step.is_finite() || step <= 0.0 {
        return format!("{v}");
    }
    if (v / step).round() == 0.0 {
        return "0".into();
    }
    let step_exp = step.log10().floor();
    if v.abs() >= 1e6 || step < 1e-4 {
        let exp = v.abs().log10().floor();
        let decimals = (exp - step_exp).clamp(0.0, 6.0) as usize;
        return format!("{v:.decimals$e}");
    }
    let decimals = (-step_exp).clamp(0.0, 10.0) as usize;
    format!("{v:.decimals$}")
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::rng::Rng;

    fn is_nice(step: f64) -> bool {
        let m = step / 10f64.powf(step.log10().floor());
        [1.0, 2.0, 5.0, 10.0].iter().any(|n| (m - n).abs() < 1e-9)
    }

    fn check(lo: f64, hi: f64) {
        let a = nice_axis(lo, hi);
        let n = a.ticks.len();
        assert!((3..=10).contains(&n), "{lo}..{hi}: {n} ticks {:?}", a.ticks);
        assert!(is_nice(a.step), "{lo}..{hi}: step {}", a.step);
        // Rounding of values far from zero is a few ulps of their magnitude.
        let tol = a.step * 1e-9 + lo.abs().max(hi.abs()) * 1e-15;
        assert!(
            a.lo <= lo.min(hi) + tol && a.hi >= lo.max(hi) - tol,
            "{lo}..{hi} not covered by {:?}",
            a.ticks
        );
        assert_eq!(a.ticks.first(), Some(&a.lo));
        assert_eq!(a.ticks.last(), Some(&a.hi));
        for w in a.ticks.windows(2) {
            assert!((w[1] - w[0] - a.step).abs() <= tol, "uneven ticks {:?}", a.ticks);
        }
    }

    #[test]
    fn ticks_use_nice_steps_and_cover_the_data() {
        let a = nice_axis(0.0, 100.0);
        assert_eq!((a.lo, a.hi, a.step), (0.0, 100.0, 20.0));
        let a = nice_axis(12.3, 31.7);
        assert_eq!((a.lo, a.hi, a.step), (10.0, 35.0, 5.0));
        let a = nice_axis(0.0, 1.1);
        assert_eq!((a.lo, a.hi, a.step), (0.0, 1.2, 0.2));
        for (lo, hi) in [
            (0.0, 1.0),
            (-3.0, 7.0),
            (0.001, 0.0013),
            (1e6, 5e9),
            (-1e-7, 1e-7),
            (17.0, 17.5),
        ] {
            check(lo, hi);
        }
        let mut rng = Rng::new(7, 0);
        for _ in 0..2000 {
            let scale = 10f64.powf(rng.range(-8.0, 8.0));
            let lo = rng.range(-1.0, 1.0) * scale;
            let hi = lo + rng.f64() * scale * 10f64.powf(rng.range(-6.0, 1.0));
            check(lo, hi);
        }
    }

    #[test]
    fn degenerate_ranges_are_widened() {
        for v in [0.0, 25.0, -3.5, 1e-12, 1e300] {
            let a = nice_axis(v, v);
            assert!(a.lo < v && a.hi > v, "{v}: {:?}", a);
            check(v, v);
        }
        let a = nice_axis(-1e308, f64::MAX);
        assert!(
            a.ticks.iter().all(|t| t.is_finite()) && (3..=10).contains(&a.ticks.len()),
            "{a:?}"
        );
        let a = nice_axis(-1e-320, 1e-320);
        assert!(
            a.lo <= -1e-320 && a.hi >= 1e-320 && (3..=10).contains(&a.ticks.len()),
            "{a:?}"
        );
        let a = nice_axis(f64::NAN, f64::INFINITY);
        assert_eq!((a.lo, a.hi), (0.0, 1.0));
        check(5.0, 1.0);
    }

    #[test]
    fn log_axes_tick_1_2_5_per_decade_and_label_the_values() {
        let a = log_axis(3.2, 1500.0);
        assert_eq!((a.lo, a.hi, a.log), (0.0, 4.0, true));
        let labels: Vec<String> = a.ticks.iter().map(|&t| a.label(t)).collect();
        assert_eq!(labels, ["1", "10", "100", "1000", "10000"]);
        let a = log_axis(0.8, 40.0);
        assert_eq!((a.lo, a.hi), (-1.0, 2.0));
        let labels: Vec<String> = a.ticks.iter().map(|&t| a.label(t)).collect();
        assert_eq!(labels, ["0.1", "0.2", "0.5", "1", "2", "5", "10", "20", "50", "100"]);
        // Exact decades stay on their own decade; one value gets one decade.
        assert_eq!((log_axis(10.0, 100.0).lo, log_axis(10.0, 100.0).hi), (1.0, 2.0));
        assert_eq!((log_axis(7.0, 7.0).lo, log_axis(7.0, 7.0).hi), (0.0, 1.0));
        for (lo, hi) in [(0.0, 5.0), (-1.0, f64::NAN), (1e-320, f64::MAX)] {
            let a = log_axis(lo, hi);
            assert!(
                a.hi > a.lo && a.ticks.iter().all(|t| t.is_finite()),
                "{lo}..{hi}: {a:?}"
            );
        }
        assert_eq!(format_log_tick(-5.0 + 2f64.log10()), "2e-5");
        assert_eq!(format_log_tick(7.0), "1e7");
    }

    #[test]
    fn tick_labels_use_the_step_precision() {
        assert_eq!(format_tick(0.30000000000000004, 0.1), "0.3");
        assert_eq!(format_tick(20.0, 5.0), "20");
        assert_eq!(format_tick(2.5, 0.5), "2.5");
        assert_eq!(format_tick(-1e-17, 0.2), "0");
        assert_eq!(format_tick(3e6, 1e6), "3e6");
        assert_eq!(format_tick(2.5e6, 5e5), "2.5e6");
        assert_eq!(format_tick(2e-5, 1e-5), "2e-5");
        assert_eq!(format_tick(0.0012, 0.0002), "0.0012");
    }
}
