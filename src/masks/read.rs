//! Read the given 2D instance masks of some frames, in the layouts SAM 2 and
//! DAVIS write:
//! - per frame: `DIR/<stem>.png`, 8-bit palette or grayscale (or 16-bit
//!   grayscale for ids above 255), pixel value = object id, 0 = background;
//! - per object: `DIR/<id>/<stem>.png`, one binary PNG per frame (any
//!   non-zero value is the object).
//!
//! An optional `DIR/labels.json` (`{"1": "mug", ...}`) names the objects.
//! A mask at another resolution than its frame is scaled to it (nearest
//! pixel) with a warning.

use crate::scan::Scan;
use std::collections::BTreeMap;
use std::fs;
use std::io::BufReader;
use std::path::{Path, PathBuf};

/// Largest mask file read (a 16-bit 8K mask is far smaller).
const MAX_MASK_BYTES: u64 = 256 << 20;
/// Largest side of a mask image.
const MAX_MASK_SIDE: u32 = 16384;
/// Largest labels.json read.
const MAX_LABELS_BYTES: u64 = 4 << 20;

/// Why a masks folder was rejected.
#[derive(Debug, thiserror::Error)]
pub enum MaskError {
    #[error("{path}: cannot read: {source}")]
    Io { path: PathBuf, source: std::io::Error },
    #[error("{path}: {problem}")]
    Format { path: PathBuf, problem: String },
}

fn format_err(path: &Path, problem: impl Into<String>) -> MaskError {
    MaskError::Format {
        path: path.to_path_buf(),
        problem: problem.into(),
    }
}

/// How the folder is laid out.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum MaskLayout {
    /// `DIR/<stem>.png`, value = object id.
    PerFrame,
    /// `DIR/<id>/<stem>.png`, binary.
    PerObject,
}

/// The masks given for some frames of a scan.
#[derive(Clone, Debug)]
pub struct GivenMasks {
    pub layout: MaskLayout,
    /// Per frame (index into `scan.frames`): object id per pixel at the
    /// frame's size, row-major, 0 = background.
    pub frames: BTreeMap<usize, Vec<u16>>,
    /// Every object id used in a given mask, with its name (from
    /// labels.json, else `object <id>`).
    pub objects: BTreeMap<u16, String>,
    /// Non-fatal findings (scaled masks, names of unused ids).
    pub warnings: Vec<String>,
}

/// A decoded mask image: one value per pixel.
struct RawMask {
    width: u32,
    height: u32,
    values: Vec<u32>,
}

/// Read the masks folder `dir` for `scan`.
pub fn read_masks(dir: &Path, scan: &Scan) -> Result<GivenMasks, MaskError> {
    let entries = list_dir(dir)?;
    let pngs: Vec<&PathBuf> = entries.iter().filter(|p| is_png(p)).collect();
    let object_dirs: Vec<(u16, &PathBuf)> = entries
        .iter()
        .filter(|p| p.is_dir())
        .filter_map(|p| Some((object_id_of_dir(p)?, p)))
        .collect();
    let layout = match (pngs.is_empty(), object_dirs.is_empty()) {
        (false, true) => MaskLayout::PerFrame,
        (true, false) => MaskLayout::PerObject,
        (false, false) => return Err(format_err(
            dir,
            "holds both PNG files (one mask per frame) and numbered folders (one folder per object): use one layout",
        )),
        (true, true) => {
            return Err(format_err(
                dir,
                "holds no masks: expected <stem>.png per frame (value = object id) or <id>/<stem>.png per object",
            ))
        }
    };
    let stems = FrameStems::of(scan);
    let mut warnings = Vec::new();
    let mut frames: BTreeMap<usize, Vec<u16>> = BTreeMap::new();
    match layout {
        MaskLayout::PerFrame => {
            for path in pngs {
                let frame = stems.frame_of(path)?;
                let raw = decode_png(path)?;
                let ids = raw
                    .values
                    .iter()
                    .map(|&v| u16::try_from(v).map_err(|_| format_err(path, format!("object id {v} is above 65535"))))
                    .collect::<Result<Vec<u16>, _>>()?;
                let (w, h) = scan.frames[frame].size();
                let ids = fit_to_frame(path, ids, raw.width, raw.height, w, h, &mut warnings);
                frames.insert(frame, ids);
            }
        }
        MaskLayout::PerObject => {
            for (id, folder) in object_dirs {
                let files: Vec<PathBuf> = list_dir(folder)?.into_iter().filter(|p| is_png(p)).collect();
                if files.is_empty() {
                    return Err(format_err(folder, format!("object {id}'s folder holds no PNG masks")));
                }
                for path in files {
                    let frame = stems.frame_of(&path)?;
                    let raw = decode_png(&path)?;
                    let binary: Vec<u16> = raw.values.iter().map(|&v| if v > 0 { id } else { 0 }).collect();
                    let (w, h) = scan.frames[frame].size();
                    let binary = fit_to_frame(&path, binary, raw.width, raw.height, w, h, &mut warnings);
                    let mask = frames.entry(frame).or_insert_with(|| vec![0; binary.len()]);
                    // Overlapping object masks: the lower id keeps the pixel.
                    for (m, &b) in mask.iter_mut().zip(&binary) {
                        if *m == 0 {
                            *m = b;
                        }
                    }
                }
            }
        }
    }
    let mut objects: BTreeMap<u16, String> = BTreeMap::new();
    for mask in frames.values() {
        for &id in mask {
            if id > 0 {
                objects.entry(id).or_insert_with(|| format!("object {id}"));
            }
        }
    }
    let labels_path = dir.join("labels.json");
    if labels_path.is_file() {
        for (id, name) in read_labels(&labels_path)? {
            match objects.get_mut(&id) {
                Some(slot) => *slot = name,
                None => warnings.push(format!(
                    "{}: object {id} (`{name}`) appears in no given mask",
                    labels_path.display()
                )),
            }
        }
    }
    if objects.is_empty() {
        return Err(format_err(
            dir,
            "every given mask is empty (all pixels 0): there is no object to carry",
        ));
    }
    Ok(GivenMasks {
        layout,
        frames,
        objects,
        warnings,
    })
}

fn list_dir(dir: &Path) -> Result<Vec<PathBuf>, MaskError> {
    let io = |source| MaskError::Io {
        path: dir.to_path_buf(),
        source,
    };
    let mut entries: Vec<PathBuf> = fs::read_dir(dir)
        .map_err(io)?
        .map(|e| e.map(|e| e.path()))
        .collect::<Result<_, _>>()
        .map_err(|source| MaskError::Io {
            path: dir.to_path_buf(),
            source,
        })?;
    entries.sort();
    Ok(entries)
}

fn is_png(path: &Path) -> bool {
    path.is_file()
        && path
            .extension()
            .and_then(|e| e.to_str())
            .is_some_and(|e| e.eq_ignore_ascii_case("png"))
}

/// A folder named by a positive object id (`1`, `007`).
fn object_id_of_dir(path: &Path) -> Option<u16> {
    let name = path.file_name()?.to_str()?;
    name.parse::<u16>()
        .ok()
        .filter(|&id| id > 0 && name.bytes().all(|b| b.is_ascii_digit()))
}

/// The scan's frame stems, to find the frame a mask file names.
struct FrameStems {
    exact: BTreeMap<String, usize>,
    /// Numeric stems by value (`00012` names frame `000012`).
    numeric: BTreeMap<u64, usize>,
    example: String,
}

impl FrameStems {
    fn of(scan: &Scan) -> FrameStems {
        let mut exact = BTreeMap::new();
        let mut numeric = BTreeMap::new();
        for (i, f) in scan.frames.iter().enumerate() {
            exact.insert(f.name.clone(), i);
            if let Ok(n) = f.name.parse::<u64>() {
                numeric.insert(n, i);
            }
        }
        let example = scan.frames.first().map_or_else(String::new, |f| f.name.clone());
        FrameStems {
            exact,
            numeric,
            example,
        }
    }

    fn frame_of(&self, path: &Path) -> Result<usize, MaskError> {
        let stem = path.file_stem().and_then(|s| s.to_str()).unwrap_or_default();
        self.exact
            .get(stem)
            .or_else(|| stem.parse::<u64>().ok().and_then(|n| self.numeric.get(&n)))
            .copied()
            .ok_or_else(|| {
                format_err(
                    path,
                    format!(
                        "`{stem}` is not a frame of the scan (frames are named by their colour image's stem, e.g. `{}`)",
                        self.example
                    ),
                )
            })
    }
}

/// Decode a PNG without expanding palettes: palette indices, gray values
/// (8 or 16 bit); colour images count any non-black pixel as 1 (binary masks
/// saved as RGB).
fn decode_png(path: &Path) -> Result<RawMask, MaskError> {
    let io = |source| MaskError::Io {
        path: path.to_path_buf(),
        source,
    };
    let bytes = fs::metadata(path).map_err(io)?.len();
    if bytes > MAX_MASK_BYTES {
        return Err(format_err(
            path,
            format!("{bytes} bytes is larger than any mask (at most {MAX_MASK_BYTES})"),
        ));
    }
    let file = fs::File::open(path).map_err(io)?;
    let bad = |e: png::DecodingError| format_err(path, format!("not a readable PNG ({e})"));
    let mut decoder = png::Decoder::new(BufReader::new(file));
    decoder.set_transformations(png::Transformations::IDENTITY);
    let mut reader = decoder.read_info().map_err(bad)?;
    let (width, height) = (reader.info().width, reader.info().height);
    if width == 0 || height == 0 || width > MAX_MASK_SIDE || height > MAX_MASK_SIDE {
        return Err(format_err(path, format!("absurd mask dimensions {width}x{height}")));
    }
    let size = reader
        .output_buffer_size()
        .ok_or_else(|| format_err(path, "mask too large to decode"))?;
    let mut buf = vec![0u8; size];
    let out = reader.next_frame(&mut buf).map_err(bad)?;
    let (color, depth) = (out.color_type, out.bit_depth);
    let line = out.line_size;
    let bits = depth as usize;
    let channels = color.samples();
    let mut values = Vec::with_capacity(width as usize * height as usize);
    for y in 0..height as usize {
        let row = &buf[y * line..(y + 1) * line];
        for x in 0..width as usize {
            let sample = |c: usize| -> u32 {
                let index = x * channels + c;
                match bits {
                    16 => u16::from_be_bytes([row[2 * index], row[2 * index + 1]]) as u32,
                    8 => row[index] as u32,
                    _ => {
                        let bit = index * bits;
                        let byte = row[bit / 8];
                        ((byte >> (8 - bits - bit % 8)) & ((1u8 << bits) - 1)) as u32
                    }
                }
            };
            let value = match color {
                png::ColorType::Grayscale | png::ColorType::Indexed => sample(0),
                png::ColorType::GrayscaleAlpha => sample(0),
                png::ColorType::Rgb | png::ColorType::Rgba => (sample(0) | sample(1) | sample(2) > 0) as u32,
            };
            values.push(value);
        }
    }
    Ok(RawMask { width, height, values })
}

/// Scale a mask to the frame's size (nearest pixel), warning when it differs.
fn fit_to_frame(path: &Path, ids: Vec<u16>, w: u32, h: u32, fw: u32, fh: u32, warnings: &mut Vec<String>) -> Vec<u16> {
    if (w, h) == (fw, fh) {
        return ids;
    }
    warnings.push(format!(
        "{}: {w}x{h} mask scaled to its frame's {fw}x{fh} (nearest pixel)",
        path.display()
    ));
    let mut out = Vec::with_capacity(fw as usize * fh as usize);
    for y in 0..fh as u64 {
        let sy = ((2 * y + 1) * h as u64 / (2 * fh as u64)).min(h as u64 - 1);
        for x in 0..fw as u64 {
            let sx = ((2 * x + 1) * w as u64 / (2 * fw as u64)).min(w as u64 - 1);
            out.push(ids[(sy * w as u64 + sx) as usize]);
        }
    }
    out
}

/// `labels.json`: `{"1": "mug", ...}`.
fn read_labels(path: &Path) -> Result<Vec<(u16, String)>, MaskError> {
    let io = |source| MaskError::Io {
        path: path.to_path_buf(),
        source,
    };
    if fs::metadata(path).map_err(io)?.len() > MAX_LABELS_BYTES {
        return Err(format_err(path, "larger than any labels file"));
    }
    let text = fs::read_to_string(path).map_err(io)?;
    let json: serde_json::Value =
        serde_json::from_str(&text).map_err(|e| format_err(path, format!("not valid JSON ({e})")))?;
    let map = json
        .as_object()
        .ok_or_else(|| format_err(path, "expected an object mapping ids to names, e.g. {\"1\": \"mug\"}"))?;
    map.iter()
        .map(|(key, value)| {
            let id = key
                .parse::<u16>()
                .ok()
                .filter(|&id| id > 0)
                .ok_or_else(|| format_err(path, format!("key `{key}`: expected an object id 1..=65535")))?;
            let name = value
                .as_str()
                .filter(|s| !s.trim().is_empty())
                .ok_or_else(|| format_err(path, format!("object `{key}`: expected a non-empty name string")))?;
            Ok((id, name.to_string()))
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::scan::{load, LoadOptions};
    use std::sync::OnceLock;

    /// The committed small fixture: 24 frames of 160x120, stems 000000...
    fn scan() -> &'static Scan {
        static SCAN: OnceLock<Scan> = OnceLock::new();
        SCAN.get_or_init(|| {
            let dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("fixtures/small");
            load(&dir, &LoadOptions::default()).unwrap()
        })
    }

    fn write_png(path: &Path, w: u32, h: u32, color: png::ColorType, depth: png::BitDepth, data: &[u8]) {
        let file = fs::File::create(path).unwrap();
        let mut encoder = png::Encoder::new(std::io::BufWriter::new(file), w, h);
        encoder.set_color(color);
        encoder.set_depth(depth);
        if color == png::ColorType::Indexed {
            encoder.set_palette((0..=255u8).flat_map(|i| [i, 255 - i, i / 2]).collect::<Vec<u8>>());
        }
        let mut writer = encoder.write_header().unwrap();
        writer.write_image_data(data).unwrap();
    }

    /// A 160x120 mask with `id` in the rectangle x 10..30, y 20..40.
    fn rect(id: u16) -> Vec<u16> {
        (0..120u32)
            .flat_map(|y| {
                (0..160u32).map(move |x| {
                    if (10..30).contains(&x) && (20..40).contains(&y) {
                        id
                    } else {
                        0
                    }
                })
            })
            .collect()
    }

    #[test]
    fn palette_masks_give_their_indices_not_colours() {
        let dir = tempfile::tempdir().unwrap();
        let ids = rect(3);
        let bytes: Vec<u8> = ids.iter().map(|&v| v as u8).collect();
        write_png(
            &dir.path().join("000004.png"),
            160,
            120,
            png::ColorType::Indexed,
            png::BitDepth::Eight,
            &bytes,
        );
        fs::write(dir.path().join("labels.json"), r#"{"3": "mug", "9": "lamp"}"#).unwrap();
        let given = read_masks(dir.path(), scan()).unwrap();
        assert_eq!(given.layout, MaskLayout::PerFrame);
        assert_eq!(given.frames[&4], ids);
        assert_eq!(given.objects.get(&3).map(String::as_str), Some("mug"));
        assert!(given
            .warnings
            .iter()
            .any(|w| w.contains("object 9 (`lamp`) appears in no given mask")));
    }

    #[test]
    fn sixteen_bit_masks_carry_ids_above_255() {
        let dir = tempfile::tempdir().unwrap();
        let ids = rect(1000);
        let bytes: Vec<u8> = ids.iter().flat_map(|v| v.to_be_bytes()).collect();
        write_png(
            &dir.path().join("000002.png"),
            160,
            120,
            png::ColorType::Grayscale,
            png::BitDepth::Sixteen,
            &bytes,
        );
        let given = read_masks(dir.path(), scan()).unwrap();
        assert_eq!(given.frames[&2], ids);
        assert_eq!(given.objects.get(&1000).map(String::as_str), Some("object 1000"));
    }

    #[test]
    fn per_object_folders_of_binary_masks_combine_into_one_mask_per_frame() {
        let dir = tempfile::tempdir().unwrap();
        for (id, x0) in [(2u16, 10u32), (5, 100)] {
            let folder = dir.path().join(id.to_string());
            fs::create_dir(&folder).unwrap();
            let bytes: Vec<u8> = (0..120u32)
                .flat_map(|y| (0..160u32).map(move |x| if (x0..x0 + 20).contains(&x) && y < 10 { 255 } else { 0 }))
                .collect();
            write_png(
                &folder.join("000007.png"),
                160,
                120,
                png::ColorType::Grayscale,
                png::BitDepth::Eight,
                &bytes,
            );
        }
        let given = read_masks(dir.path(), scan()).unwrap();
        assert_eq!(given.layout, MaskLayout::PerObject);
        let mask = &given.frames[&7];
        assert_eq!((mask[15], mask[105], mask[50], mask[160 * 20 + 15]), (2, 5, 0, 0));
        assert_eq!(given.objects.keys().copied().collect::<Vec<_>>(), vec![2, 5]);
    }

    #[test]
    fn a_mask_at_another_resolution_is_scaled_with_a_warning() {
        let dir = tempfile::tempdir().unwrap();
        // 80x60: half the frame's size; object in x 5..15, y 10..20 -> 10..30, 20..40.
        let bytes: Vec<u8> = (0..60u32)
            .flat_map(|y| (0..80u32).map(move |x| ((5..15).contains(&x) && (10..20).contains(&y)) as u8 * 3))
            .collect();
        write_png(
            &dir.path().join("000001.png"),
            80,
            60,
            png::ColorType::Grayscale,
            png::BitDepth::Eight,
            &bytes,
        );
        let given = read_masks(dir.path(), scan()).unwrap();
        assert_eq!(given.frames[&1], rect(3));
        assert!(given
            .warnings
            .iter()
            .any(|w| w.contains("80x60 mask scaled to its frame's 160x120")));
    }

    #[test]
    fn bad_folders_and_files_are_named_in_clear_errors() {
        let message = |dir: &Path| read_masks(dir, scan()).unwrap_err().to_string();
        let empty = tempfile::tempdir().unwrap();
        assert!(
            message(empty.path()).contains("holds no masks"),
            "{}",
            message(empty.path())
        );

        let stranger = tempfile::tempdir().unwrap();
        let bytes = vec![1u8; 160 * 120];
        write_png(
            &stranger.path().join("frame_x.png"),
            160,
            120,
            png::ColorType::Grayscale,
            png::BitDepth::Eight,
            &bytes,
        );
        let m = message(stranger.path());
        assert!(
            m.contains("frame_x.png") && m.contains("is not a frame of the scan") && m.contains("000000"),
            "{m}"
        );

        let broken = tempfile::tempdir().unwrap();
        fs::write(broken.path().join("000003.png"), b"not a png").unwrap();
        let m = message(broken.path());
        assert!(m.contains("000003.png") && m.contains("not a readable PNG"), "{m}");

        let both = tempfile::tempdir().unwrap();
        write_png(
            &both.path().join("000003.png"),
            160,
            120,
            png::ColorType::Grayscale,
            png::BitDepth::Eight,
            &bytes,
        );
        fs::create_dir(both.path().join("1")).unwrap();
        assert!(message(both.path()).contains("use one layout"));

        let empty_object = tempfile::tempdir().unwrap();
        fs::create_dir(empty_object.path().join("4")).unwrap();
        assert!(message(empty_object.path()).contains("object 4's folder holds no PNG masks"));

        let blank = tempfile::tempdir().unwrap();
        write_png(
            &blank.path().join("000003.png"),
            160,
            120,
            png::ColorType::Grayscale,
            png::BitDepth::Eight,
            &vec![0; 160 * 120],
        );
        assert!(message(blank.path()).contains("every given mask is empty"));

        let bad_labels = tempfile::tempdir().unwrap();
        write_png(
            &bad_labels.path().join("000003.png"),
            160,
            120,
            png::ColorType::Grayscale,
            png::BitDepth::Eight,
            &bytes,
        );
        fs::write(bad_labels.path().join("labels.json"), r#"{"mug": 1}"#).unwrap();
        let m = message(bad_labels.path());
        assert!(m.contains("labels.json") && m.contains("key `mug`"), "{m}");
    }

    #[test]
    fn numeric_stems_match_frames_by_value() {
        let dir = tempfile::tempdir().unwrap();
        let bytes: Vec<u8> = rect(1).iter().map(|&v| v as u8).collect();
        // DAVIS names frames 00000.png; the scan's stems have six digits.
        write_png(
            &dir.path().join("00012.png"),
            160,
            120,
            png::ColorType::Grayscale,
            png::BitDepth::Eight,
            &bytes,
        );
        let given = read_masks(dir.path(), scan()).unwrap();
        assert!(given.frames.contains_key(&12));
    }
}
