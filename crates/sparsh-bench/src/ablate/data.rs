//! The contact-circle task's frames: a frame's difference from its no-contact frame, box-filtered
//! to the models' input size, and the contact circle in the real pack's pixels. Synthetic frames
//! come from a generated dataset (centre from the ball's position, radius from the solved contact
//! area: a = √(A/π)), real ones from a Taxim pack (its marked `touch_center`, `touch_radius`).

use std::path::Path;

use image::RgbImage;

use crate::Error;

/// A contact circle in the real pack's pixels (x = column, y = row, pixel centres at integers).
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct Circle {
    /// Centre column.
    pub cx_px: f64,
    /// Centre row.
    pub cy_px: f64,
    /// Radius.
    pub r_px: f64,
}

impl From<sparsh_optics::Circle> for Circle {
    fn from(c: sparsh_optics::Circle) -> Self {
        Circle {
            cx_px: c.centre_px[0],
            cy_px: c.centre_px[1],
            r_px: c.radius_px,
        }
    }
}

/// The real pack's image: size and pixel pitch; synthetic labels are mapped onto it.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PackGeometry {
    /// Width (pixels).
    pub width_px: usize,
    /// Height (pixels).
    pub height_px: usize,
    /// Pixel pitch on the gel (mm).
    pub mm_per_px: f64,
}

impl PackGeometry {
    /// The circle of a contact centred at (`x_mm`, `y_mm`) on the gel (the optical axis at the
    /// image centre) with radius `a_mm`: pixel i's centre lies at x = (i + ½ − W/2)·pitch.
    pub fn circle(&self, x_mm: f64, y_mm: f64, a_mm: f64) -> Circle {
        Circle {
            cx_px: x_mm / self.mm_per_px + self.width_px as f64 / 2.0 - 0.5,
            cy_px: y_mm / self.mm_per_px + self.height_px as f64 / 2.0 - 0.5,
            r_px: a_mm / self.mm_per_px,
        }
    }
}

/// Frames of the task at the input size, with their circles.
#[derive(Debug, Clone, Default)]
pub struct CircleFrames {
    /// Input `[height, width]`.
    pub size: [usize; 2],
    /// Difference images `[n, 3, h, w]` row-major, in 8-bit levels (frame − background).
    pub images: Vec<f32>,
    /// The contact circle of each frame.
    pub circles: Vec<Circle>,
    /// Group of each frame (its sequence, or its pack index): splits never cut a group.
    pub groups: Vec<usize>,
}

impl CircleFrames {
    /// Number of frames.
    pub fn len(&self) -> usize {
        self.circles.len()
    }

    /// Whether there is no frame.
    pub fn is_empty(&self) -> bool {
        self.circles.is_empty()
    }

    /// The difference image of frame `k`, `[3, h, w]`.
    pub fn image(&self, k: usize) -> &[f32] {
        let n = 3 * self.size[0] * self.size[1];
        &self.images[k * n..(k + 1) * n]
    }

    fn push(&mut self, frame: &RgbImage, background: &RgbImage, circle: Circle, group: usize) {
        self.images
            .extend(box_difference(frame, background, self.size));
        self.circles.push(circle);
        self.groups.push(group);
    }

    /// The frames `rows` as a new set.
    pub fn select(&self, rows: &[usize]) -> CircleFrames {
        let mut out = CircleFrames {
            size: self.size,
            ..Default::default()
        };
        for &k in rows {
            out.images.extend_from_slice(self.image(k));
            out.circles.push(self.circles[k]);
            out.groups.push(self.groups[k]);
        }
        out
    }
}

/// `frame − background` per channel, averaged over the blocks of pixels that make one input
/// pixel (the frame's size must be a whole multiple of `size`), channel-major `[3, h, w]`.
pub fn box_difference(frame: &RgbImage, background: &RgbImage, size: [usize; 2]) -> Vec<f32> {
    let (fw, fh) = (frame.width() as usize, frame.height() as usize);
    let [h, w] = size;
    let (bx, by) = (fw / w, fh / h);
    let norm = 1.0 / (bx * by) as f32;
    let (f, b) = (frame.as_raw(), background.as_raw());
    let mut out = vec![0.0f32; 3 * h * w];
    for y in 0..h * by {
        for x in 0..w * bx {
            let p = (y * fw + x) * 3;
            let o = (y / by) * w + x / bx;
            for c in 0..3 {
                out[c * h * w + o] += (f[p + c] as f32 - b[p + c] as f32) * norm;
            }
        }
    }
    out
}

/// Checks that `frame` is `size` times a whole factor.
fn check_size(path: &Path, frame: &RgbImage, size: [usize; 2]) -> Result<(), Error> {
    let (w, h) = (frame.width() as usize, frame.height() as usize);
    if w % size[1] != 0 || h % size[0] != 0 || w / size[1] != h / size[0] {
        return Err(Error::file(
            path,
            format!(
                "frames are {w}×{h}: the input size {}×{} must divide them by one whole factor",
                size[1], size[0]
            ),
        ));
    }
    Ok(())
}

/// The frames of a generated dataset in contact (contact area above zero), each against its
/// sequence's background, labelled with its circle on `pack`; `also` sees each kept frame and
/// its background.
pub fn synthetic(
    dir: &Path,
    pack: PackGeometry,
    size: [usize; 2],
    mut also: impl FnMut(&RgbImage, &RgbImage) -> Result<(), Error>,
) -> Result<CircleFrames, Error> {
    let rows = crate::labels::read_label_rows(dir)?;
    let mut out = CircleFrames {
        size,
        ..Default::default()
    };
    let open = |rel: &str| -> Result<RgbImage, Error> {
        let p = dir.join(rel);
        Ok(image::open(&p).map_err(|e| Error::file(&p, e))?.to_rgb8())
    };
    for seq in rows {
        let Some(first) = seq.first() else { continue };
        let background = open(&first.background)?;
        for row in &seq {
            if row.contact_area_mm2 <= 0.0 {
                continue;
            }
            let frame = open(&format!("frames/{:06}.png", row.frame))?;
            check_size(&dir.join("frames"), &frame, size)?;
            if frame.dimensions() != background.dimensions() {
                return Err(Error::file(
                    dir.join(&first.background),
                    "background and frames differ in size",
                ));
            }
            let [x, y, _] = row.pose.position_mm;
            let a_mm = (row.contact_area_mm2 / std::f64::consts::PI).sqrt();
            also(&frame, &background)?;
            out.push(&frame, &background, pack.circle(x, y, a_mm), row.sequence);
        }
    }
    if out.is_empty() {
        return Err(Error::file(
            dir.join("labels.jsonl"),
            "no frame in contact (contact_area_mm2 > 0)",
        ));
    }
    Ok(out)
}

/// The pack's frames `frames`, each against the pack's no-contact frame, with the marked circles;
/// `also` sees each frame and the no-contact frame.
pub fn real(
    path: &Path,
    pack: &sparsh_optics::pack::CalibrationPack,
    frames: &[usize],
    size: [usize; 2],
    mut also: impl FnMut(&RgbImage, &RgbImage) -> Result<(), Error>,
) -> Result<CircleFrames, Error> {
    check_size(path, &pack.background, size)?;
    let mut out = CircleFrames {
        size,
        ..Default::default()
    };
    for &k in frames {
        also(&pack.frames[k], &pack.background)?;
        out.push(
            &pack.frames[k],
            &pack.background,
            pack.marked_circle(k).into(),
            k,
        );
    }
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_box_difference_averages_each_block_per_channel() {
        let bg = RgbImage::from_pixel(4, 2, image::Rgb([10, 20, 30]));
        let mut f = bg.clone();
        f.put_pixel(0, 0, image::Rgb([14, 20, 30]));
        f.put_pixel(3, 1, image::Rgb([10, 28, 22]));
        let d = box_difference(&f, &bg, [1, 2]);
        // blocks of 2×2: left gets +4 red in one of four pixels, right +8 green and −8 blue
        assert_eq!(d, vec![1.0, 0.0, 0.0, 2.0, 0.0, -2.0]);
    }

    #[test]
    fn a_contact_at_the_optical_axis_lands_between_the_two_central_pixels() {
        let g = PackGeometry {
            width_px: 640,
            height_px: 480,
            mm_per_px: 0.0295,
        };
        let c = g.circle(0.0, 0.0, 1.77);
        assert_eq!((c.cx_px, c.cy_px), (319.5, 239.5));
        assert!((c.r_px - 60.0).abs() < 1e-9);
        // one pixel to the right is one pitch along +x
        assert!((g.circle(0.0295, 0.0, 1.0).cx_px - 320.5).abs() < 1e-9);
    }
}
