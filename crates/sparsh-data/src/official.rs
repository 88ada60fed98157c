//! The official Sparsh input preprocessing (`data/digit/utils.py` of facebookresearch/sparsh):
//! 1. background subtraction `diff = clip((img − bg)/255 + 0.5, 0, 1)`, stored as 8-bit;
//! 2. landscape frames rotated to portrait clockwise (`cv2.ROTATE_90_CLOCKWISE`), and a frame
//!    whose height is not 4/3 of its width cut to its centre `int(3h/4)` rows ([`official_crop`]);
//! 3. resized (triangle filter) and scaled to `[0, 1]`; no mean/std normalization.

use image::{RgbImage, imageops};

/// The official crop of a portrait frame `w × h` (`load_sample_from_buf` in
/// `data/digit/utils.py`): where `h / w` is not 4/3, keep the width and the centre
/// `int(h / (4/3))` rows, rows `int((h − h₂)/2) .. int((h + h₂)/2)` in Python's float arithmetic;
/// else the whole frame. Returns `[left, top, width, height]`.
pub fn official_crop(w: u32, h: u32) -> [u32; 4] {
    let r = 4.0 / 3.0;
    if h as f64 / w as f64 == r {
        return [0, 0, w, h];
    }
    let h2 = (h as f64 / r) as u32;
    let top = ((h - h2) as f64 / 2.0) as u32;
    let bottom = ((h + h2) as f64 / 2.0) as u32;
    [0, top, w, bottom - top]
}

/// Official preprocessing of one frame against its background (see the module docs):
/// [`subtract_background`], then [`official_resize`] to `size` = `[height, width]`.
pub fn preprocess(img: &RgbImage, bg: &RgbImage, size: [usize; 2]) -> Result<Vec<f32>, String> {
    Ok(official_resize(&subtract_background(img, bg)?, size))
}

/// Step 1 of the official preprocessing: `clip((img − bg)/255 + 0.5, 0, 1)` as 8-bit
/// (truncated, as `(diff * 255).astype(np.uint8)`).
pub fn subtract_background(img: &RgbImage, bg: &RgbImage) -> Result<RgbImage, String> {
    if img.dimensions() != bg.dimensions() {
        return Err(format!(
            "frame is {:?} but background is {:?}",
            img.dimensions(),
            bg.dimensions()
        ));
    }
    Ok(RgbImage::from_fn(img.width(), img.height(), |x, y| {
        let (a, b) = (img.get_pixel(x, y).0, bg.get_pixel(x, y).0);
        image::Rgb(std::array::from_fn(|c| {
            let v = (a[c] as f32 - b[c] as f32) / 255.0 + 0.5;
            (v.clamp(0.0, 1.0) * 255.0) as u8
        }))
    }))
}

/// Steps 2–3 of the official preprocessing: a landscape frame turned clockwise to portrait,
/// the [`official_crop`], resized (triangle filter) to `size` = `[height, width]` and scaled to
/// `[0, 1]`; channel-major (`3 × height × width`).
pub fn official_resize(img: &RgbImage, size: [usize; 2]) -> Vec<f32> {
    let portrait = if img.width() > img.height() {
        imageops::rotate90(img)
    } else {
        img.clone()
    };
    let [x0, y0, cw, ch] = official_crop(portrait.width(), portrait.height());
    let cropped = imageops::crop_imm(&portrait, x0, y0, cw, ch).to_image();
    let resized = imageops::resize(
        &cropped,
        size[1] as u32,
        size[0] as u32,
        imageops::FilterType::Triangle,
    );
    let (hh, ww) = (size[0], size[1]);
    let mut out = vec![0.0; 3 * hh * ww];
    for (x, y, p) in resized.enumerate_pixels() {
        for c in 0..3 {
            out[(c * hh + y as usize) * ww + x as usize] = p.0[c] as f32 / 255.0;
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn background_subtraction_rotation_crop_resize() {
        // landscape 8×6 frame: background 100, frame 100 except a bright top-left pixel block
        let bg = RgbImage::from_pixel(8, 6, image::Rgb([100, 100, 100]));
        let mut img = bg.clone();
        for x in 0..2 {
            for y in 0..2 {
                img.put_pixel(x, y, image::Rgb([255, 0, 100]));
            }
        }
        let out = preprocess(&img, &bg, [8, 6]).unwrap();
        assert_eq!(out.len(), 3 * 8 * 6);
        // unchanged pixels become 0.5 (127/255 after the official 8-bit rounding)
        let grey = 127.0 / 255.0;
        let blue = &out[2 * 48..];
        assert!(blue.iter().all(|v| (v - grey).abs() < 1e-6));
        // red: (255 − 100)/255 + 0.5 clipped to 1; green: 0.5 − 100/255
        let red = &out[..48];
        assert!(red.iter().any(|&v| v > 0.9));
        assert!(red.iter().all(|&v| v >= grey - 1e-6));
        // clockwise rotation takes the top-left corner of a landscape frame to the top-right
        // of the portrait one
        let at = |y: usize, x: usize| red[y * 6 + x];
        assert!(at(0, 5) > 0.9, "{}", at(0, 5));
        assert!((at(7, 0) - grey).abs() < 1e-6);
    }

    /// The crop against the official slice computed by Python
    /// (`h2 = int(h/r); img[int((h-h2)/2):int((h+h2)/2)]`, r = 4/3).
    #[test]
    fn crop_is_the_official_slice() {
        for (w, h, want) in [
            (240, 320, [0, 0, 240, 320]),
            (240, 240, [0, 30, 240, 180]),
            (240, 241, [0, 30, 240, 180]),
            (100, 200, [0, 25, 100, 150]),
            (77, 101, [0, 13, 77, 75]),
            (90, 120, [0, 0, 90, 120]),
        ] {
            assert_eq!(official_crop(w, h), want, "{w}×{h}");
        }
    }

    #[test]
    fn mismatched_background_is_an_error() {
        let a = RgbImage::new(8, 6);
        let b = RgbImage::new(6, 8);
        assert!(
            preprocess(&a, &b, [4, 3])
                .unwrap_err()
                .contains("background")
        );
    }
}
