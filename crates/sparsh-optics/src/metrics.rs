//! Image similarity on 8-bit RGB images, in the conventions of scikit-image 0.2x so the scores
//! compare with published ones: PSNR with a data range of 255, SSIM of Wang et al. (IEEE TIP
//! 2004) with a 7×7 uniform window, sample covariances (N/(N−1)), K1 = 0.01, K2 = 0.03, the mean
//! over windows lying fully inside the image, averaged over the three channels; MAE in 0–255 units.

use image::RgbImage;
use serde::Serialize;

/// PSNR, SSIM and MAE of one image pair.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct Scores {
    /// Peak signal-to-noise ratio (dB, peak 255); infinite for identical images.
    pub psnr_db: f64,
    /// Structural similarity (1 = identical).
    pub ssim: f64,
    /// Mean absolute error (0–255 units).
    pub mae: f64,
}

/// Scores of `test` against `reference` (same size, at least 7×7).
pub fn scores(reference: &RgbImage, test: &RgbImage) -> Scores {
    assert_eq!(
        reference.dimensions(),
        test.dimensions(),
        "images differ in size"
    );
    let (a, b) = (reference.as_raw(), test.as_raw());
    let n = a.len() as f64;
    let (mut se, mut ae) = (0.0f64, 0.0f64);
    for (&x, &y) in a.iter().zip(b) {
        let d = x as f64 - y as f64;
        se += d * d;
        ae += d.abs();
    }
    let mse = se / n;
    Scores {
        psnr_db: 10.0 * (255.0f64 * 255.0 / mse).log10(),
        ssim: ssim(reference, test),
        mae: ae / n,
    }
}

/// Mean SSIM over channels (see the module doc for the convention).
pub fn ssim(reference: &RgbImage, test: &RgbImage) -> f64 {
    const WIN: usize = 7;
    let (w, h) = (reference.width() as usize, reference.height() as usize);
    assert!(w >= WIN && h >= WIN, "SSIM needs images of at least 7×7");
    let c1 = (0.01f64 * 255.0).powi(2);
    let c2 = (0.03f64 * 255.0).powi(2);
    let np = (WIN * WIN) as f64;
    let cov_norm = np / (np - 1.0);
    let (a, b) = (reference.as_raw(), test.as_raw());
    let mut total = 0.0;
    for ch in 0..3 {
        // Summed-area tables of x, y, x², y², xy.
        let sat = |f: &dyn Fn(f64, f64) -> f64| {
            let mut t = vec![0.0f64; (w + 1) * (h + 1)];
            for j in 0..h {
                let mut row = 0.0;
                for i in 0..w {
                    let k = (j * w + i) * 3 + ch;
                    row += f(a[k] as f64, b[k] as f64);
                    t[(j + 1) * (w + 1) + i + 1] = t[j * (w + 1) + i + 1] + row;
                }
            }
            t
        };
        let tables = [
            sat(&|x, _| x),
            sat(&|_, y| y),
            sat(&|x, _| x * x),
            sat(&|_, y| y * y),
            sat(&|x, y| x * y),
        ];
        let window = |t: &[f64], i: usize, j: usize| {
            (t[(j + WIN) * (w + 1) + i + WIN]
                - t[j * (w + 1) + i + WIN]
                - t[(j + WIN) * (w + 1) + i]
                + t[j * (w + 1) + i])
                / np
        };
        let mut sum = 0.0;
        for j in 0..=h - WIN {
            for i in 0..=w - WIN {
                let [mx, my, mxx, myy, mxy] = std::array::from_fn(|q| window(&tables[q], i, j));
                let vx = cov_norm * (mxx - mx * mx);
                let vy = cov_norm * (myy - my * my);
                let vxy = cov_norm * (mxy - mx * my);
                sum += ((2.0 * mx * my + c1) * (2.0 * vxy + c2))
                    / ((mx * mx + my * my + c1) * (vx + vy + c2));
            }
        }
        total += sum / ((w - WIN + 1) * (h - WIN + 1)) as f64;
    }
    total / 3.0
}

/// The square of half-width `half_width_px` around `centre_px` (x = column, y = row), clipped to
/// the image: columns round(x − hw) ..= round(x + hw), and likewise rows.
pub fn crop(img: &RgbImage, centre_px: [f64; 2], half_width_px: f64) -> RgbImage {
    let (w, h) = (img.width() as i64, img.height() as i64);
    let x0 = ((centre_px[0] - half_width_px).round() as i64).clamp(0, w - 1);
    let x1 = ((centre_px[0] + half_width_px).round() as i64).clamp(0, w - 1);
    let y0 = ((centre_px[1] - half_width_px).round() as i64).clamp(0, h - 1);
    let y1 = ((centre_px[1] + half_width_px).round() as i64).clamp(0, h - 1);
    image::imageops::crop_imm(
        img,
        x0 as u32,
        y0 as u32,
        (x1 - x0 + 1) as u32,
        (y1 - y0 + 1) as u32,
    )
    .to_image()
}

#[cfg(test)]
mod tests {
    use super::*;

    fn noise_image(w: u32, h: u32, seed: u64) -> RgbImage {
        let mut s = seed;
        RgbImage::from_fn(w, h, |_, _| {
            image::Rgb(std::array::from_fn(|_| {
                s = s
                    .wrapping_mul(6364136223846793005)
                    .wrapping_add(1442695040888963407);
                (s >> 56) as u8
            }))
        })
    }

    #[test]
    fn identical_images_score_perfectly() {
        let a = noise_image(20, 15, 1);
        let s = scores(&a, &a);
        assert!(s.psnr_db.is_infinite() && (s.ssim - 1.0).abs() < 1e-12 && s.mae == 0.0);
    }

    #[test]
    fn a_constant_offset_matches_closed_forms() {
        // y = x + 10 everywhere: MAE 10, PSNR 20·log10(255/10); SSIM's structure and contrast
        // terms are 1, its luminance term is (2μx μy + C1)/(μx² + μy² + C1) per window.
        let a = RgbImage::from_pixel(12, 9, image::Rgb([100, 100, 100]));
        let b = RgbImage::from_pixel(12, 9, image::Rgb([110, 110, 110]));
        let s = scores(&a, &b);
        assert!((s.mae - 10.0).abs() < 1e-12);
        assert!((s.psnr_db - 20.0 * (25.5f64).log10()).abs() < 1e-9);
        let c1 = (0.01f64 * 255.0).powi(2);
        let lum = (2.0 * 100.0 * 110.0 + c1) / (100.0f64 * 100.0 + 110.0 * 110.0 + c1);
        assert!((s.ssim - lum).abs() < 1e-12);
    }

    #[test]
    fn ssim_is_symmetric_and_falls_with_noise() {
        let a = noise_image(30, 30, 2);
        let b = noise_image(30, 30, 3);
        assert!((ssim(&a, &b) - ssim(&b, &a)).abs() < 1e-12);
        assert!(ssim(&a, &b) < 0.2);
    }

    #[test]
    fn crop_is_clipped_to_the_image() {
        let a = noise_image(40, 30, 4);
        assert_eq!(crop(&a, [20.0, 15.0], 5.0).dimensions(), (11, 11));
        assert_eq!(crop(&a, [1.0, 1.0], 5.0).dimensions(), (7, 7));
    }
}
