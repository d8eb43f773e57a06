//! PNG encoding of every image nerflabel writes (FORMATS.md): 8-bit RGB
//! colour, 16-bit single-channel depth in integer units (millimetres unless
//! a layout says otherwise, 0 = no surface) and instance-id masks (8-bit
//! when every id fits, else 16-bit). Labels, synth blobs, fixture files and
//! plots share it, so one encoder setting decides all their bytes.

use image::codecs::png::{CompressionType, FilterType, PngEncoder};
use image::{ExtendedColorType, ImageEncoder, ImageError};

/// Depth unit of millimetre PNGs, in metres.
pub const MILLIMETRE: f64 = 0.001;

/// Encode raw samples; fast compression, since the PNGs are mostly noise-free
/// renders and encoding sits on the per-view critical path. Named explicitly
/// rather than taken from the encoder's defaults, which may change.
fn encode(bytes: &[u8], width: u32, height: u32, colour: ExtendedColorType) -> Result<Vec<u8>, ImageError> {
    let mut png = Vec::with_capacity(bytes.len() / 2);
    PngEncoder::new_with_quality(&mut png, CompressionType::Fast, FilterType::Adaptive)
        .write_image(bytes, width, height, colour)?;
    Ok(png)
}

/// 16-bit samples as the encoder takes them: native-endian (it writes PNG's
/// big-endian itself).
fn native_bytes(values: &[u16]) -> Vec<u8> {
    values.iter().flat_map(|v| v.to_ne_bytes()).collect()
}

/// 8-bit RGB PNG of row-major RGB8 pixels.
pub fn encode_rgb(rgb: &[u8], width: u32, height: u32) -> Result<Vec<u8>, ImageError> {
    encode(rgb, width, height, ExtendedColorType::Rgb8)
}

/// 16-bit single-channel PNG of depth in integer units (see
/// [`quantise_depth`] and [`depth_mm_saturating`]).
pub fn encode_depth(units: &[u16], width: u32, height: u32) -> Result<Vec<u8>, ImageError> {
    encode(&native_bytes(units), width, height, ExtendedColorType::L16)
}

/// Instance-id PNG: 8-bit when `max_id` (the largest id the mask may hold,
/// the box count) is at most 255, else 16-bit.
pub fn encode_mask(ids: &[u16], max_id: usize, width: u32, height: u32) -> Result<Vec<u8>, ImageError> {
    if max_id <= 255 {
        let bytes: Vec<u8> = ids.iter().map(|&id| id.min(255) as u8).collect();
        encode(&bytes, width, height, ExtendedColorType::L8)
    } else {
        encode(&native_bytes(ids), width, height, ExtendedColorType::L16)
    }
}

/// Depths in metres to integer units of `unit_m` metres (rounded): 0 for no
/// surface (not positive, or NaN); a depth beyond 65535 units (infinite
/// included) is also written as 0 and counted. Returns the values and that
/// count, which labels and fixture report as a warning.
pub fn quantise_depth(depth_m: &[f32], unit_m: f64) -> (Vec<u16>, usize) {
    let mut overflow = 0;
    let values = depth_m
        .iter()
        .map(|&z| {
            let q = (z as f64 / unit_m).round();
            if q.is_nan() || q <= 0.0 {
                0
            } else if q > u16::MAX as f64 {
                overflow += 1;
                0
            } else {
                q as u16
            }
        })
        .collect();
    (values, overflow)
}

/// Millimetres of z-depths in metres for the synth blobs, which keep every
/// surface a surface: 0 for none (not positive or not finite), at least 1
/// for any surface, 65535 for anything farther. Rounds in f32, so a depth
/// near a half millimetre may land 1 mm off [`quantise_depth`]; the synth
/// output is defined by this rounding.
pub fn depth_mm_saturating(depth_m: &[f32]) -> Vec<u16> {
    let mm = |z: f32| {
        if z > 0.0 && z.is_finite() {
            (z * 1000.0).round().clamp(1.0, 65_535.0) as u16
        } else {
            0
        }
    };
    depth_m.iter().map(|&z| mm(z)).collect()
}

#[cfg(test)]
mod tests {
    use super::*;
    use image::{DynamicImage, ImageFormat};

    fn decode(png: &[u8]) -> DynamicImage {
        image::load_from_memory_with_format(png, ImageFormat::Png).unwrap()
    }

    #[test]
    fn rgb_round_trips_exactly() {
        let (w, h) = (7, 5);
        let rgb: Vec<u8> = (0..w * h * 3).map(|i| (i * 37 % 256) as u8).collect();
        let img = decode(&encode_rgb(&rgb, w, h).unwrap());
        let DynamicImage::ImageRgb8(img) = img else {
            panic!("not RGB8")
        };
        assert_eq!(img.dimensions(), (w, h));
        assert_eq!(img.into_raw(), rgb);
    }

    #[test]
    fn quantised_depth_rounds_and_counts_what_does_not_fit() {
        let depth = [0.0, 1.2344, 0.0001, 70.0, f32::NAN, -1.0, f32::INFINITY, 65.535];
        let (mm, overflow) = quantise_depth(&depth, MILLIMETRE);
        assert_eq!(mm, vec![0, 1234, 0, 0, 0, 0, 0, 65_535]);
        assert_eq!(overflow, 2);
        let (q, overflow) = quantise_depth(&[0.0, 1.0004, 1.0006, 70.0, -1.0], 0.001);
        assert_eq!(q, vec![0, 1000, 1001, 0, 0]);
        assert_eq!(overflow, 1);
        let DynamicImage::ImageLuma16(img) = decode(&encode_depth(&mm, 4, 2).unwrap()) else {
            panic!("not 16-bit grey")
        };
        assert_eq!(img.into_raw(), mm);
    }

    #[test]
    fn saturating_millimetres_keep_every_surface() {
        let depth = [0.0, 1.2344, 0.0001, 70.0, f32::NAN, -1.0, f32::INFINITY, 65.535];
        assert_eq!(depth_mm_saturating(&depth), vec![0, 1234, 1, 65_535, 0, 0, 0, 65_535]);
    }

    #[test]
    fn masks_are_8_bit_up_to_255_boxes_and_16_bit_beyond() {
        let ids = [0, 1, 255, 7, 0, 3];
        let DynamicImage::ImageLuma8(small) = decode(&encode_mask(&ids, 255, 3, 2).unwrap()) else {
            panic!("not 8-bit grey")
        };
        assert_eq!(small.into_raw(), vec![0, 1, 255, 7, 0, 3]);
        let ids = [0, 256, 300, 1, 65_535, 2];
        let DynamicImage::ImageLuma16(big) = decode(&encode_mask(&ids, 300, 3, 2).unwrap()) else {
            panic!("not 16-bit grey")
        };
        assert_eq!(big.into_raw(), vec![0, 256, 300, 1, 65_535, 2]);
    }
}
