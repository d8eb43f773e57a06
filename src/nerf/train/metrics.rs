//! Image metrics for held-out evaluation: PSNR, SSIM and depth error.

/// PSNR in dB of two RGB8 images of equal size (99 dB when identical).
pub fn psnr(a: &[u8], b: &[u8]) -> f64 {
    let mse = a
        .iter()
        .zip(b)
        .map(|(&x, &y)| (x as f64 - y as f64).powi(2))
        .sum::<f64>()
        / a.len().max(1) as f64;
    if mse <= 0.0 {
        return 99.0;
    }
    10.0 * (255.0f64 * 255.0 / mse).log10()
}

/// Mean SSIM over the RGB channels (Gaussian window sigma 1.5, 11 taps).
pub fn ssim(a: &[u8], b: &[u8], width: usize, height: usize) -> f64 {
    if width == 0 || height == 0 || a.len() != width * height * 3 || b.len() != a.len() {
        return 0.0;
    }
    let mut total = 0.0;
    for c in 0..3 {
        let x: Vec<f32> = a.iter().skip(c).step_by(3).map(|&v| v as f32 / 255.0).collect();
        let y: Vec<f32> = b.iter().skip(c).step_by(3).map(|&v| v as f32 / 255.0).collect();
        total += ssim_channel(&x, &y, width, height);
    }
    total / 3.0
}

fn ssim_channel(x: &[f32], y: &[f32], w: usize, h: usize) -> f64 {
    let (c1, c2) = (0.01f32 * 0.01, 0.03f32 * 0.03);
    let xx: Vec<f32> = x.iter().map(|v| v * v).collect();
    let yy: Vec<f32> = y.iter().map(|v| v * v).collect();
    let xy: Vec<f32> = x.iter().zip(y).map(|(a, b)| a * b).collect();
    let [mx, my, sxx, syy, sxy] = [x, y, &xx[..], &yy[..], &xy[..]].map(|img| blur(img, w, h));
    let mut sum = 0.0f64;
    for i in 0..w * h {
        let (ux, uy) = (mx[i], my[i]);
        let vx = sxx[i] - ux * ux;
        let vy = syy[i] - uy * uy;
        let cov = sxy[i] - ux * uy;
        let s = ((2.0 * ux * uy + c1) * (2.0 * cov + c2)) / ((ux * ux + uy * uy + c1) * (vx + vy + c2));
        sum += s as f64;
    }
    sum / (w * h) as f64
}

/// Separable Gaussian blur with clamped borders.
fn blur(img: &[f32], w: usize, h: usize) -> Vec<f32> {
    const R: i64 = 5;
    let kernel: Vec<f32> = (-R..=R).map(|k| (-(k * k) as f32 / (2.0 * 1.5 * 1.5)).exp()).collect();
    let norm: f32 = kernel.iter().sum();
    let mut tmp = vec![0.0f32; w * h];
    let mut out = vec![0.0f32; w * h];
    for yy in 0..h {
        for xx in 0..w {
            let mut s = 0.0;
            for (k, kv) in kernel.iter().enumerate() {
                let sx = (xx as i64 + k as i64 - R).clamp(0, w as i64 - 1) as usize;
                s += kv * img[yy * w + sx];
            }
            tmp[yy * w + xx] = s / norm;
        }
    }
    for yy in 0..h {
        for xx in 0..w {
            let mut s = 0.0;
            for (k, kv) in kernel.iter().enumerate() {
                let sy = (yy as i64 + k as i64 - R).clamp(0, h as i64 - 1) as usize;
                s += kv * tmp[sy * w + xx];
            }
            out[yy * w + xx] = s / norm;
        }
    }
    out
}

/// Mean absolute depth error over pixels valid in both maps (0 = invalid);
/// `None` when no pixel is valid in both.
pub fn depth_mae(predicted: &[f32], truth: &[f32]) -> Option<f64> {
    let (mut sum, mut n) = (0.0f64, 0usize);
    for (&p, &t) in predicted.iter().zip(truth) {
        if p > 0.0 && t > 0.0 && p.is_finite() && t.is_finite() {
            sum += (p - t).abs() as f64;
            n += 1;
        }
    }
    (n > 0).then(|| sum / n as f64)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn psnr_and_ssim_rank_degradations() {
        let (w, h) = (32, 24);
        let img: Vec<u8> = (0..w * h * 3).map(|i| ((i * 37) % 251) as u8).collect();
        assert_eq!(psnr(&img, &img), 99.0);
        assert!((ssim(&img, &img, w, h) - 1.0).abs() < 1e-6);
        let slight: Vec<u8> = img.iter().map(|&v| v.saturating_add(4)).collect();
        let heavy: Vec<u8> = img
            .iter()
            .enumerate()
            .map(|(i, &v)| if i % 2 == 0 { 255 - v } else { v })
            .collect();
        assert!((psnr(&img, &slight) - 20.0 * (255.0f64 / 4.0).log10()).abs() < 0.5);
        assert!(psnr(&img, &slight) > psnr(&img, &heavy) + 10.0);
        assert!(ssim(&img, &slight, w, h) > 0.9);
        assert!(ssim(&img, &heavy, w, h) < 0.5);
    }

    #[test]
    fn depth_mae_ignores_invalid_pixels() {
        assert_eq!(depth_mae(&[1.0, 2.0, 0.0], &[1.5, 0.0, 3.0]), Some(0.5));
        assert_eq!(depth_mae(&[0.0], &[1.0]), None);
    }
}
