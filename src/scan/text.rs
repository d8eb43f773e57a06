//! Parsers for the small text files of scan layouts: whitespace or comma
//! separated number matrices, CSV tables with an optional header, and TUM's
//! `timestamp value...` lists. They never panic, whatever the input.

use super::{Bounds, Intrinsics, ScanError};
use nalgebra::{Matrix4, Point3};
use std::path::Path;

/// Largest text file read (TUM groundtruth files of hour-long runs are ~20 MB).
pub const MAX_TEXT_BYTES: u64 = 128 << 20;

/// A parse failure; `line` is 1-based, 0 when it concerns the whole text.
#[derive(Clone, Debug, PartialEq)]
pub struct TextError {
    pub line: usize,
    pub reason: String,
}

impl TextError {
    fn new(line: usize, reason: impl Into<String>) -> TextError {
        TextError {
            line,
            reason: reason.into(),
        }
    }
}

/// Read a text file (size-capped; invalid UTF-8 replaced).
pub(crate) fn read_text(path: &Path) -> Result<String, ScanError> {
    let meta = std::fs::metadata(path).map_err(|e| ScanError::io(path, e))?;
    if meta.len() > MAX_TEXT_BYTES {
        return Err(ScanError::Invalid(
            path.to_path_buf(),
            format!("file too large ({} bytes, at most {MAX_TEXT_BYTES})", meta.len()),
        ));
    }
    let bytes = std::fs::read(path).map_err(|e| ScanError::io(path, e))?;
    Ok(String::from_utf8_lossy(&bytes).into_owned())
}

/// Lines that carry content: 1-based line number and the line without a
/// `#` comment, skipping blank lines.
pub fn content_lines(text: &str) -> impl Iterator<Item = (usize, &str)> {
    text.lines().enumerate().filter_map(|(i, line)| {
        let body = match line.find('#') {
            Some(at) => line.get(..at).unwrap_or(""),
            None => line,
        };
        let body = body.trim();
        (!body.is_empty()).then_some((i + 1, body))
    })
}

/// Split a line on whitespace and commas.
fn tokens(line: &str) -> impl Iterator<Item = &str> {
    line.split(|c: char| c.is_whitespace() || c == ',')
        .filter(|t| !t.is_empty())
}

/// Parse one number token (accepts `inf`/`nan`, which validation rejects later).
pub fn number(token: &str, line: usize) -> Result<f64, TextError> {
    token
        .trim()
        .parse::<f64>()
        .map_err(|_| TextError::new(line, format!("expected a number, found '{}'", shorten(token))))
}

/// Keep messages one short line even for binary garbage.
fn shorten(token: &str) -> String {
    let clean: String = token.chars().filter(|c| !c.is_control()).take(24).collect();
    if token.chars().count() > 24 {
        format!("{clean}...")
    } else {
        clean
    }
}

/// Rows of numbers separated by whitespace and/or commas, with line numbers.
pub fn number_rows(text: &str) -> Result<Vec<(usize, Vec<f64>)>, TextError> {
    content_lines(text)
        .map(|(line, body)| {
            let row = tokens(body).map(|t| number(t, line)).collect::<Result<Vec<_>, _>>()?;
            Ok((line, row))
        })
        .collect()
}

/// A rectangular matrix: every row must have the same number of columns.
pub fn matrix(text: &str) -> Result<Vec<Vec<f64>>, TextError> {
    let rows = number_rows(text)?;
    let Some((_, first)) = rows.first() else {
        return Err(TextError::new(0, "empty file, expected a matrix"));
    };
    let cols = first.len();
    for (line, row) in &rows {
        if row.len() != cols {
            return Err(TextError::new(
                *line,
                format!("expected {cols} numbers like the first row, found {}", row.len()),
            ));
        }
    }
    Ok(rows.into_iter().map(|(_, r)| r).collect())
}

/// All numbers of a matrix in row-major order with its shape.
fn flat(text: &str) -> Result<(usize, usize, Vec<f64>), TextError> {
    let m = matrix(text)?;
    let rows = m.len();
    let cols = m.first().map_or(0, |r| r.len());
    Ok((rows, cols, m.into_iter().flatten().collect()))
}

/// A 4x4 transform: 4x4, 3x4 (bottom row 0 0 0 1 implied) or 16/12 numbers on one line.
pub fn matrix4(text: &str) -> Result<Matrix4<f64>, TextError> {
    let (rows, cols, v) = flat(text)?;
    let shape_ok = matches!((rows, cols), (4, 4) | (3, 4) | (1, 16) | (1, 12));
    if !shape_ok {
        return Err(TextError::new(0, format!("expected a 4x4 matrix, found {rows}x{cols}")));
    }
    let at = |i: usize| v.get(i).copied().unwrap_or(0.0);
    let bottom = if v.len() == 16 {
        [at(12), at(13), at(14), at(15)]
    } else {
        [0.0, 0.0, 0.0, 1.0]
    };
    // Rows in the file, as `Matrix4::new` takes them.
    #[rustfmt::skip]
    let m = Matrix4::new(
        at(0), at(1), at(2), at(3),
        at(4), at(5), at(6), at(7),
        at(8), at(9), at(10), at(11),
        bottom[0], bottom[1], bottom[2], bottom[3],
    );
    Ok(m)
}

/// Pinhole intrinsics from a 3x3 K, a 4x4 or 3x4 with K top-left, or one
/// row `fx fy cx cy`.
/// Largest skew accepted, as a fraction of fx.
const MAX_SKEW: f64 = 1e-4;

pub fn intrinsics(text: &str) -> Result<Intrinsics, TextError> {
    let m = matrix(text)?;
    let rows = m.len();
    let cols = m.first().map_or(0, |r| r.len());
    let get = |r: usize, c: usize| m.get(r).and_then(|row| row.get(c)).copied().unwrap_or(0.0);
    match (rows, cols) {
        (1, 4) => Ok(Intrinsics {
            fx: get(0, 0),
            fy: get(0, 1),
            cx: get(0, 2),
            cy: get(0, 3),
        }),
        (3, 3) | (3, 4) | (4, 4) => {
            let (k20, k21, k22, k10) = (get(2, 0), get(2, 1), get(2, 2), get(1, 0));
            if k20 != 0.0 || k21 != 0.0 || k10 != 0.0 || !(k22.is_finite() && k22 != 0.0) {
                return Err(TextError::new(
                    0,
                    "not a camera matrix: expected rows 'fx s cx', '0 fy cy', '0 0 1'",
                ));
            }
            // The camera model has no skew: refuse one that would move pixels
            // (over 1e-4 fx, i.e. under 0.05 px across a 640-pixel image).
            let (fx, skew) = (get(0, 0), get(0, 1));
            if skew.abs() > MAX_SKEW * fx.abs() {
                return Err(TextError::new(
                    0,
                    format!("skew {skew} (K[0][1]) is not supported: the camera model has none; set it to 0 if it is negligible, or undistort the images"),
                ));
            }
            Ok(Intrinsics {
                fx: fx / k22,
                fy: get(1, 1) / k22,
                cx: get(0, 2) / k22,
                cy: get(1, 2) / k22,
            })
        }
        _ => Err(TextError::new(
            0,
            format!("expected a 3x3 or 4x4 camera matrix, found {rows}x{cols}"),
        )),
    }
}

/// Scene bounds: the first six numbers `min_x min_y min_z max_x max_y max_z`.
pub fn bounds(text: &str) -> Result<Bounds, TextError> {
    let rows = number_rows(text)?;
    let v: Vec<f64> = rows.into_iter().flat_map(|(_, r)| r).take(6).collect();
    let [x0, y0, z0, x1, y1, z1] = v[..] else {
        return Err(TextError::new(
            0,
            format!("expected 6 numbers (min xyz, max xyz), found {}", v.len()),
        ));
    };
    let (min, max) = (Point3::new(x0, y0, z0), Point3::new(x1, y1, z1));
    if !v.iter().all(|x| x.is_finite()) || (0..3).any(|i| min[i] >= max[i]) {
        return Err(TextError::new(0, "bounds must be finite with min < max on every axis"));
    }
    Ok(Bounds { min, max })
}

/// A CSV table: optional header names and rows of trimmed fields.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Table {
    pub header: Option<Vec<String>>,
    pub rows: Vec<(usize, Vec<String>)>,
}

impl Table {
    /// Index of a header column, matched case-insensitively.
    pub fn column(&self, name: &str) -> Option<usize> {
        self.header.as_ref()?.iter().position(|h| h.eq_ignore_ascii_case(name))
    }
}

/// Parse comma-separated values; the first line is a header when any of its
/// fields is not a number.
pub fn csv(text: &str) -> Table {
    let mut table = Table::default();
    for (line, body) in content_lines(text) {
        let fields: Vec<String> = body.split(',').map(|f| f.trim().to_string()).collect();
        if table.header.is_none() && table.rows.is_empty() && fields.iter().any(|f| f.parse::<f64>().is_err()) {
            table.header = Some(fields);
        } else {
            table.rows.push((line, fields));
        }
    }
    table
}

/// One TUM list line: line number, timestamp and the other tokens.
pub type TimedLine<'a> = (usize, f64, Vec<&'a str>);

/// TUM list lines `timestamp token [token...]`.
pub fn timestamped(text: &str) -> Result<Vec<TimedLine<'_>>, TextError> {
    content_lines(text)
        .map(|(line, body)| {
            let mut parts = body.split_whitespace();
            let ts = number(parts.next().unwrap_or(""), line)?;
            if !ts.is_finite() {
                return Err(TextError::new(line, "timestamp is not finite"));
            }
            Ok((line, ts, parts.collect()))
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::rng::Rng;
    use nalgebra::Vector4;

    #[test]
    fn matrix4_reads_rows_and_comments() {
        let m = matrix4("# T_CW\n1 0 0 5\n0 1 0 6\n\n0 0 1 7 # z\n0 0 0 1\n").unwrap();
        assert_eq!(m.column(3), Vector4::new(5.0, 6.0, 7.0, 1.0));
        assert_eq!(m[(0, 0)], 1.0);
        let m3 = matrix4("1,0,0,1\n0,1,0,2\n0,0,1,3\n").unwrap();
        assert_eq!(m3.column(3), Vector4::new(1.0, 2.0, 3.0, 1.0));
        let one = matrix4("0 -1 0 1 1 0 0 2 0 0 1 3 0 0 0 1").unwrap();
        // Row 0 is (0, -1, 0, 1): first column's x is 0, second column's x is -1.
        assert_eq!(one[(0, 1)], -1.0);
        assert_eq!(one[(1, 0)], 1.0);
    }

    #[test]
    fn matrix4_rejects_bad_shapes_and_tokens() {
        assert_eq!(
            matrix4("1 2 3\n4 5 6\n").unwrap_err().reason,
            "expected a 4x4 matrix, found 2x3"
        );
        let e = matrix4("1 0 0 0\n0 1 x 0\n").unwrap_err();
        assert_eq!(e.line, 2);
        assert!(e.reason.contains("'x'"));
        let e = matrix4("1 0 0 0\n0 1 0\n0 0 1 0\n0 0 0 1").unwrap_err();
        assert_eq!(e.line, 2);
        assert_eq!(matrix4("").unwrap_err().line, 0);
        // ScanNet marks lost tracking with -inf: parsed, rejected later by validation.
        assert!(matrix4(&"-inf ".repeat(16)).unwrap()[(0, 0)].is_infinite());
    }

    #[test]
    fn intrinsics_accepts_3x3_4x4_and_row() {
        let k = intrinsics("500 0 320\n0 510 240\n0 0 1\n").unwrap();
        assert_eq!((k.fx, k.fy, k.cx, k.cy), (500.0, 510.0, 320.0, 240.0));
        let k4 = intrinsics("500 0 320 0\n0 510 240 0\n0 0 1 0\n0 0 0 1\n").unwrap();
        assert_eq!(k, k4);
        assert_eq!(intrinsics("500 510 320 240").unwrap(), k);
        assert!(intrinsics("500 0 320\n0 510 240\n1 0 1\n").is_err());
        assert!(intrinsics("1 2\n3 4\n").is_err());
    }

    #[test]
    fn skew_is_refused_not_dropped_unless_negligible() {
        // Regression: K[0][1] was dropped silently.
        let err = intrinsics("500 2.5 320\n0 510 240\n0 0 1\n").unwrap_err().reason;
        assert!(err.contains("skew 2.5"), "{err}");
        assert!(
            intrinsics("500 0.00001 320\n0 510 240\n0 0 1\n").is_ok(),
            "rounding noise is accepted"
        );
    }

    #[test]
    fn bounds_take_first_six_and_check_order() {
        let b = bounds("-1 -2 -3 1 2 3 0.01\n").unwrap();
        assert_eq!(b.min, Point3::new(-1.0, -2.0, -3.0));
        assert_eq!(b.max, Point3::new(1.0, 2.0, 3.0));
        assert!(bounds("1 1 1 0 2 2").is_err());
        assert!(bounds("1 2 3").is_err());
    }

    #[test]
    fn csv_detects_header() {
        let t = csv("timestamp, frame, x\n0.5, 0, 1.25\n0.6, 1, 2\n");
        assert_eq!(t.column("FRAME"), Some(1));
        assert_eq!(t.rows.len(), 2);
        assert_eq!(
            t.rows[1],
            (3, vec!["0.6".to_string(), "1".to_string(), "2".to_string()])
        );
        let plain = csv("1,2,3\n4,5,6\n");
        assert!(plain.header.is_none());
        assert_eq!(plain.rows.len(), 2);
    }

    #[test]
    fn timestamped_lines() {
        let v = timestamped("# c\n1.5 rgb/1.5.png\n2.0 1 2 3\n").unwrap();
        assert_eq!(v.len(), 2);
        assert_eq!(v[0].1, 1.5);
        assert_eq!(v[1].2, vec!["1", "2", "3"]);
        assert_eq!(timestamped("abc x").unwrap_err().line, 1);
        assert!(timestamped("inf x").is_err());
    }

    #[test]
    fn parsers_never_panic_on_garbage() {
        let mut rng = Rng::new(7, 0);
        let alphabet = b"0123456789 .,-+eE#\n\r\tinfaNx\xff\x00";
        for _ in 0..3000 {
            let len = rng.below(120) as usize;
            let bytes: Vec<u8> = (0..len)
                .map(|_| alphabet[rng.below(alphabet.len() as u64) as usize])
                .collect();
            let text = String::from_utf8_lossy(&bytes);
            let _ = matrix4(&text);
            let _ = intrinsics(&text);
            let _ = bounds(&text);
            let _ = csv(&text);
            let _ = timestamped(&text);
        }
    }
}
