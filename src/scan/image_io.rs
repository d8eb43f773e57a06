//! Decode colour images (PNG/JPEG, any channel layout, to 8-bit RGB) and
//! 16-bit single-channel depth PNGs. The header is read first so absurd
//! dimensions are refused before any pixel buffer is allocated.

use super::{DepthMap, RgbImage, ScanError, MAX_IMAGE_SIDE};
use image::{ColorType, DynamicImage, ImageDecoder, ImageFormat, ImageReader};
use std::io::{BufReader, Cursor};
use std::path::Path;

/// Largest image file read into memory.
const MAX_IMAGE_BYTES: u64 = 512 << 20;

/// Image file extensions accepted for colour frames (lower case).
pub const RGB_EXTENSIONS: [&str; 3] = ["png", "jpg", "jpeg"];

/// Whether `path`'s extension is one of `exts` (case-insensitive).
pub fn has_extension(path: &Path, exts: &[&str]) -> bool {
    path.extension()
        .and_then(|e| e.to_str())
        .is_some_and(|e| exts.iter().any(|x| x.eq_ignore_ascii_case(e)))
}

fn image_error(path: &Path, reason: impl Into<String>) -> ScanError {
    ScanError::Image {
        path: path.to_path_buf(),
        reason: reason.into(),
    }
}

fn check_dimensions(path: &Path, (w, h): (u32, u32)) -> Result<(), ScanError> {
    if w == 0 || h == 0 || w > MAX_IMAGE_SIDE || h > MAX_IMAGE_SIDE {
        return Err(image_error(
            path,
            format!("absurd image dimensions {w}x{h} (each side must be 1..={MAX_IMAGE_SIDE})"),
        ));
    }
    Ok(())
}

/// Width and height from the image header only.
pub fn dimensions(path: &Path) -> Result<(u32, u32), ScanError> {
    let file = std::fs::File::open(path).map_err(|e| ScanError::io(path, e))?;
    let reader = ImageReader::new(BufReader::new(file))
        .with_guessed_format()
        .map_err(|e| ScanError::io(path, e))?;
    if reader.format().is_none() {
        return Err(image_error(path, "not a PNG or JPEG image"));
    }
    let dims = reader
        .into_dimensions()
        .map_err(|e| image_error(path, format!("cannot read image header: {e}")))?;
    check_dimensions(path, dims)?;
    Ok(dims)
}

fn read_bytes(path: &Path) -> Result<Vec<u8>, ScanError> {
    let meta = std::fs::metadata(path).map_err(|e| ScanError::io(path, e))?;
    if meta.len() > MAX_IMAGE_BYTES {
        return Err(image_error(path, format!("file too large ({} bytes)", meta.len())));
    }
    std::fs::read(path).map_err(|e| ScanError::io(path, e))
}

/// Open a decoder on in-memory bytes after checking format and header size.
fn decoder<'a>(path: &Path, bytes: &'a [u8]) -> Result<(ImageFormat, impl ImageDecoder + 'a), ScanError> {
    let reader = ImageReader::new(Cursor::new(bytes))
        .with_guessed_format()
        .map_err(|e| ScanError::io(path, e))?;
    let format = match reader.format() {
        Some(f @ (ImageFormat::Png | ImageFormat::Jpeg)) => f,
        Some(other) => {
            return Err(image_error(
                path,
                format!("unsupported image format {other:?}, expected PNG or JPEG"),
            ))
        }
        None if bytes.is_empty() => return Err(image_error(path, "cannot decode image: empty file")),
        None => return Err(image_error(path, "cannot decode image: not a PNG or JPEG file")),
    };
    if format == ImageFormat::Jpeg && !jpeg_is_complete(bytes) {
        return Err(image_error(
            path,
            "cannot decode image: truncated JPEG (no end-of-image marker)",
        ));
    }
    let decoder = reader
        .into_decoder()
        .map_err(|e| image_error(path, format!("cannot decode image header: {e}")))?;
    check_dimensions(path, decoder.dimensions())?;
    Ok((format, decoder))
}

fn decode_all(path: &Path, decoder: impl ImageDecoder) -> Result<DynamicImage, ScanError> {
    DynamicImage::from_decoder(decoder).map_err(|e| image_error(path, format!("cannot decode image: {e}")))
}

/// Decode a colour image to 8-bit RGB (gray, alpha and 16-bit are converted).
pub fn decode_rgb(path: &Path) -> Result<RgbImage, ScanError> {
    let bytes = read_bytes(path)?;
    let (_, decoder) = decoder(path, &bytes)?;
    Ok(decode_all(path, decoder)?.into_rgb8())
}

/// Decode a 16-bit single-channel depth PNG to metres (`value * metres_per_unit`).
pub fn decode_depth(path: &Path, metres_per_unit: f32) -> Result<DepthMap, ScanError> {
    let bytes = read_bytes(path)?;
    let (format, decoder) = decoder(path, &bytes)?;
    let color = decoder.color_type();
    if format != ImageFormat::Png || color != ColorType::L16 {
        let kind = if format == ImageFormat::Png { "" } else { " JPEG" };
        return Err(ScanError::DepthFormat {
            path: path.to_path_buf(),
            found: format!("{}{kind}", describe(color)),
        });
    }
    let (width, height) = decoder.dimensions();
    let DynamicImage::ImageLuma16(raw) = decode_all(path, decoder)? else {
        return Err(ScanError::DepthFormat {
            path: path.to_path_buf(),
            found: "a different pixel type".into(),
        });
    };
    let metres = raw.into_raw().into_iter().map(|v| v as f32 * metres_per_unit).collect();
    Ok(DepthMap { width, height, metres })
}

/// Human wording of a pixel type, e.g. `8-bit RGB`.
fn describe(color: ColorType) -> &'static str {
    match color {
        ColorType::L8 => "8-bit gray",
        ColorType::La8 => "8-bit gray+alpha",
        ColorType::Rgb8 => "8-bit RGB",
        ColorType::Rgba8 => "8-bit RGBA",
        ColorType::L16 => "16-bit gray",
        ColorType::La16 => "16-bit gray+alpha",
        ColorType::Rgb16 => "16-bit RGB",
        ColorType::Rgba16 => "16-bit RGBA",
        ColorType::Rgb32F => "32-bit float RGB",
        ColorType::Rgba32F => "32-bit float RGBA",
        _ => "an unsupported pixel type",
    }
}

/// Whether a JPEG stream reaches its end-of-image marker after the first
/// start-of-scan. The JPEG decoder is lenient and would grey-fill a
/// truncated file, so the check is made here.
fn jpeg_is_complete(bytes: &[u8]) -> bool {
    // Walk the marker segments up to the first SOS (FF DA).
    let mut i = 2usize;
    let sos_end = loop {
        let (Some(&ff), Some(&marker)) = (bytes.get(i), bytes.get(i + 1)) else {
            return false;
        };
        if ff != 0xFF {
            return false;
        }
        if marker == 0xFF {
            i += 1; // fill byte
            continue;
        }
        let (Some(&hi), Some(&lo)) = (bytes.get(i + 2), bytes.get(i + 3)) else {
            return false;
        };
        let len = usize::from(hi) << 8 | usize::from(lo);
        let next = i + 2 + len;
        if marker == 0xDA {
            break next;
        }
        if marker == 0xD9 || len < 2 {
            return false;
        }
        i = next;
    };
    // Entropy-coded data stuffs FF as FF 00, so FF D9 after SOS is the real end.
    bytes
        .get(sos_end..)
        .is_some_and(|rest| rest.windows(2).any(|w| w == [0xFF, 0xD9]))
}

#[cfg(test)]
mod tests {
    use super::*;
    use image::codecs::jpeg::JpegEncoder;
    use image::{ImageBuffer, Luma};

    fn jpeg_bytes() -> Vec<u8> {
        let img = RgbImage::from_fn(16, 8, |x, y| image::Rgb([x as u8 * 10, y as u8 * 20, 100]));
        let mut out = Vec::new();
        JpegEncoder::new_with_quality(&mut out, 90).encode_image(&img).unwrap();
        out
    }

    #[test]
    fn jpeg_completeness() {
        let full = jpeg_bytes();
        assert!(jpeg_is_complete(&full));
        assert!(!jpeg_is_complete(&full[..full.len() - 2]));
        assert!(!jpeg_is_complete(&full[..full.len() / 2]));
        assert!(!jpeg_is_complete(&full[..3]));
        assert!(!jpeg_is_complete(&[]));
    }

    #[test]
    fn decodes_gray_and_rgba_to_rgb_and_depth_to_metres() {
        let dir = tempfile::tempdir().unwrap();
        let gray = dir.path().join("g.png");
        image::GrayImage::from_pixel(4, 3, Luma([77])).save(&gray).unwrap();
        let rgb = decode_rgb(&gray).unwrap();
        assert_eq!(rgb.dimensions(), (4, 3));
        assert_eq!(rgb.get_pixel(1, 1).0, [77, 77, 77]);

        let depth = dir.path().join("d.png");
        ImageBuffer::<Luma<u16>, _>::from_fn(4, 3, |x, _| Luma([1000 + x as u16]))
            .save(&depth)
            .unwrap();
        let d = decode_depth(&depth, 0.001).unwrap();
        assert_eq!((d.width, d.height), (4, 3));
        assert!((d.get(3, 2) - 1.003).abs() < 1e-6);

        let err = decode_depth(&gray, 0.001).unwrap_err().to_string();
        assert!(
            err.ends_with("g.png: expected a 16-bit single-channel PNG, found 8-bit gray"),
            "{err}"
        );
        let jpg = dir.path().join("c.jpg");
        std::fs::write(&jpg, jpeg_bytes()).unwrap();
        assert!(decode_depth(&jpg, 0.001)
            .unwrap_err()
            .to_string()
            .contains("8-bit RGB JPEG"));
        assert_eq!(dimensions(&jpg).unwrap(), (16, 8));
    }
}
