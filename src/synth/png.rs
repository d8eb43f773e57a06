//! PNG blobs of a synthetic view: 8-bit RGB colour, 16-bit millimetre
//! depth (0 = nothing hit) and instance-id masks (8-bit when every id fits).

use image::codecs::png::{CompressionType, FilterType, PngEncoder};
use image::{ExtendedColorType, ImageEncoder, ImageError};

/// Encode raw samples; fast compression, since the PNGs are mostly noise-free
/// renders and encoding sits on the per-view critical path.
fn encode(bytes: &[u8], width: u32, height: u32, colour: ExtendedColorType) -> Result<Vec<u8>, ImageError> {
    let mut png = Vec::with_capacity(bytes.len() / 2);
    PngEncoder::new_with_quality(&mut png, CompressionType::Fast, FilterType::Adaptive)
        .write_image(bytes, width, height, colour)?;
    Ok(png)
}

/// 8-bit RGB PNG of row-major RGB8 pixels.
pub fn encode_rgb(rgb: &[u8], width: u32, height: u32) -> Result<Vec<u8>, ImageError> {
    encode(rgb, width, height, ExtendedColorType::Rgb8)
}

/// Millimetres of a z-depth in metres: 0 for no surface, at least 1 for any
/// surface, saturating at 65535.
#[inline]
pub fn depth_to_mm(z_m: f32) -> u16 {
    if z_m > 0.0 && z_m.is_finite() {
        (z_m * 1000.0).round().clamp(1.0, 65_535.0) as u16
    } else {
        0
    }
}

/// 16-bit single-channel PNG of z-depth in millimetres (0 = nothing hit).
pub fn encode_depth_mm(depth_m: &[f32], width: u32, height: u32) -> Result<Vec<u8>, ImageError> {
    // The encoder takes native-endian samples and writes PNG's big-endian itself.
    let bytes: Vec<u8> = depth_m.iter().flat_map(|&z| depth_to_mm(z).to_ne_bytes()).collect();
    encode(&bytes, width, height, ExtendedColorType::L16)
}

/// Instance-id PNG: 8-bit when `max_id` <= 255, else 16-bit (ids above
/// 65535 saturate; boxes files hold far fewer boxes).
pub fn encode_mask(ids: &[u32], max_id: u32, width: u32, height: u32) -> Result<Vec<u8>, ImageError> {
    if max_id <= 255 {
        let bytes: Vec<u8> = ids.iter().map(|&id| id.min(255) as u8).collect();
        encode(&bytes, width, height, ExtendedColorType::L8)
    } else {
        let bytes: Vec<u8> = ids.iter().flat_map(|&id| (id.min(65_535) as u16).to_ne_bytes()).collect();
        encode(&bytes, width, height, ExtendedColorType::L16)
    }
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
        let DynamicImage::ImageRgb8(img) = img else { panic!("not RGB8") };
        assert_eq!(img.dimensions(), (w, h));
        assert_eq!(img.into_raw(), rgb);
    }

    #[test]
    fn depth_round_trips_in_millimetres_with_zero_for_no_surface() {
        let depth = [0.0, 1.2344, 0.0001, 70.0, f32::NAN, -1.0, f32::INFINITY, 65.535];
        let img = decode(&encode_depth_mm(&depth, 4, 2).unwrap());
        let DynamicImage::ImageLuma16(img) = img else { panic!("not 16-bit grey") };
        assert_eq!(img.into_raw(), vec![0, 1234, 1, 65_535, 0, 0, 0, 65_535]);
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
