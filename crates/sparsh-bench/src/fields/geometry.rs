//! Where the ground truth lands in the encoder's input: the same rotation to portrait, centre
//! crop to 4:3 and resize that `sparsh_ssl::data::preprocess` applies to a frame, applied to
//! points, vectors and fields given on the frame's pixels or its contact grid.

/// The map from a frame's pixels (`x` = column, `y` = row, pixel centres at integers) to the
/// encoder input's.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct InputGeometry {
    /// Frame width (pixels).
    pub frame_width: usize,
    /// Frame height (pixels).
    pub frame_height: usize,
    /// Landscape frames are turned clockwise to portrait.
    pub rotated: bool,
    /// Left and top of the official crop in the (rotated) frame.
    pub crop_origin: [usize; 2],
    /// Width and height of the crop.
    pub crop_size: [usize; 2],
    /// Input `[height, width]`.
    pub size: [usize; 2],
}

impl InputGeometry {
    /// The geometry of a `frame_width × frame_height` frame preprocessed to `size`
    /// (`[height, width]`), with the arithmetic of `preprocess`.
    pub fn new(frame_width: usize, frame_height: usize, size: [usize; 2]) -> Self {
        let rotated = frame_width > frame_height;
        let (w, h) = if rotated {
            (frame_height, frame_width)
        } else {
            (frame_width, frame_height)
        };
        let [x0, y0, cw, ch] = sparsh_ssl::data::official_crop(w as u32, h as u32);
        Self {
            frame_width,
            frame_height,
            rotated,
            crop_origin: [x0 as usize, y0 as usize],
            crop_size: [cw as usize, ch as usize],
            size,
        }
    }

    /// Input pixels per crop pixel along x and y.
    fn scale(&self) -> [f64; 2] {
        [
            self.size[1] as f64 / self.crop_size[0] as f64,
            self.size[0] as f64 / self.crop_size[1] as f64,
        ]
    }

    /// Input pixels per frame pixel (the mean of the two axes; they differ by rounding only).
    pub fn pixels_per_frame_pixel(&self) -> f64 {
        let [sx, sy] = self.scale();
        0.5 * (sx + sy)
    }

    /// A frame point in input coordinates: `rotate90` (clockwise) takes `(x, y)` to
    /// `(H − 1 − y, x)`, the crop shifts it, the resize maps pixel centres `(c + ½)·s − ½`.
    pub fn point_to_input(&self, p: [f64; 2]) -> [f64; 2] {
        let [x, y] = p;
        let (xr, yr) = if self.rotated {
            (self.frame_height as f64 - 1.0 - y, x)
        } else {
            (x, y)
        };
        let [sx, sy] = self.scale();
        [
            (xr - self.crop_origin[0] as f64 + 0.5) * sx - 0.5,
            (yr - self.crop_origin[1] as f64 + 0.5) * sy - 0.5,
        ]
    }

    /// The inverse of [`Self::point_to_input`].
    pub fn point_to_frame(&self, q: [f64; 2]) -> [f64; 2] {
        let [sx, sy] = self.scale();
        let xr = (q[0] + 0.5) / sx - 0.5 + self.crop_origin[0] as f64;
        let yr = (q[1] + 0.5) / sy - 0.5 + self.crop_origin[1] as f64;
        if self.rotated {
            [yr, self.frame_height as f64 - 1.0 - xr]
        } else {
            [xr, yr]
        }
    }

    /// A displacement in frame pixels as input pixels: turned with the frame, then scaled.
    pub fn vector_to_input(&self, v: [f64; 2]) -> [f64; 2] {
        let [vx, vy] = if self.rotated { [-v[1], v[0]] } else { v };
        let [sx, sy] = self.scale();
        [vx * sx, vy * sy]
    }

    /// Samples a field given on an `nx × ny` grid of equal cells covering the frame
    /// (row-major) at every input pixel: bilinear at 3 × 3 points spread over the pixel's
    /// footprint, averaged, so a downscale averages as the frame's resize does.
    pub fn resample(&self, values: &[f32], nx: usize, ny: usize) -> Vec<f32> {
        let [h, w] = self.size;
        let cell = [
            self.frame_width as f64 / nx as f64,
            self.frame_height as f64 / ny as f64,
        ];
        let at = |fx: f64, fy: f64| -> f64 {
            // frame pixel → grid coordinates with cell centres at integers
            let gx = ((fx + 0.5) / cell[0] - 0.5).clamp(0.0, nx as f64 - 1.0);
            let gy = ((fy + 0.5) / cell[1] - 0.5).clamp(0.0, ny as f64 - 1.0);
            let (x0, y0) = (gx.floor() as usize, gy.floor() as usize);
            let (x1, y1) = ((x0 + 1).min(nx - 1), (y0 + 1).min(ny - 1));
            let (ax, ay) = (gx - x0 as f64, gy - y0 as f64);
            let v = |x: usize, y: usize| values[y * nx + x] as f64;
            (1.0 - ay) * ((1.0 - ax) * v(x0, y0) + ax * v(x1, y0))
                + ay * ((1.0 - ax) * v(x0, y1) + ax * v(x1, y1))
        };
        let mut out = vec![0.0f32; h * w];
        for yi in 0..h {
            for xi in 0..w {
                let mut sum = 0.0;
                for sy in [-1.0 / 3.0, 0.0, 1.0 / 3.0] {
                    for sx in [-1.0 / 3.0, 0.0, 1.0 / 3.0] {
                        let [fx, fy] = self.point_to_frame([xi as f64 + sx, yi as f64 + sy]);
                        sum += at(fx, fy);
                    }
                }
                out[yi * w + xi] = (sum / 9.0) as f32;
            }
        }
        out
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use image::{Rgb, RgbImage};

    /// A frame with one bright pixel, preprocessed by the encoder's own pipeline, has its
    /// brightest input pixel where the geometry maps that pixel.
    #[test]
    fn points_land_where_preprocess_puts_them() {
        let (w, h) = (320u32, 240u32);
        let bg = RgbImage::from_pixel(w, h, Rgb([100, 100, 100]));
        for &(px, py) in &[(40u32, 30u32), (250, 200), (160, 120), (300, 20)] {
            let mut img = bg.clone();
            for dy in 0..4 {
                for dx in 0..4 {
                    img.put_pixel(px + dx, py + dy, Rgb([250, 250, 250]));
                }
            }
            let size = [96, 72];
            let pre = sparsh_ssl::data::preprocess(&img, &bg, size).unwrap();
            let (mut best, mut at) = (0.0f32, 0usize);
            for (i, &v) in pre[..96 * 72].iter().enumerate() {
                if v > best {
                    (best, at) = (v, i);
                }
            }
            let g = InputGeometry::new(w as usize, h as usize, size);
            let q = g.point_to_input([px as f64 + 1.5, py as f64 + 1.5]);
            let (qx, qy) = ((at % 72) as f64, (at / 72) as f64);
            assert!(
                (q[0] - qx).abs() <= 1.0 && (q[1] - qy).abs() <= 1.0,
                "pixel ({px}, {py}): mapped to {q:?}, preprocess put it at ({qx}, {qy})"
            );
            let back = g.point_to_frame(q);
            assert!(
                (back[0] - px as f64 - 1.5).abs() < 1e-9
                    && (back[1] - py as f64 - 1.5).abs() < 1e-9
            );
        }
    }

    /// A displacement along the frame's +x (columns) points down the portrait input (+y), and
    /// one along +y points left; lengths scale with the resize.
    #[test]
    fn vectors_turn_with_the_frame() {
        let g = InputGeometry::new(320, 240, [96, 72]);
        let s = g.pixels_per_frame_pixel();
        assert!((s - 0.3).abs() < 1e-12);
        let a = g.point_to_input([100.0, 100.0]);
        let b = g.point_to_input([110.0, 100.0]);
        let v = g.vector_to_input([10.0, 0.0]);
        assert!((b[0] - a[0] - v[0]).abs() < 1e-9 && (b[1] - a[1] - v[1]).abs() < 1e-9);
        assert!(v[0].abs() < 1e-12 && (v[1] - 3.0).abs() < 1e-9);
        let v = g.vector_to_input([0.0, 10.0]);
        assert!((v[0] + 3.0).abs() < 1e-9 && v[1].abs() < 1e-12);
    }

    /// A field linear in frame x, given on a half-resolution grid, is resampled to the linear
    /// function of the mapped coordinate (away from the clamped borders).
    #[test]
    fn resampled_linear_field_is_linear_in_the_input() {
        let (nx, ny) = (160, 120);
        let values: Vec<f32> = (0..nx * ny)
            .map(|i| {
                let gx = (i % nx) as f64;
                // grid cell centre in frame pixels: (gx + ½)·2 − ½
                ((gx + 0.5) * 2.0 - 0.5) as f32
            })
            .collect();
        let g = InputGeometry::new(320, 240, [96, 72]);
        let out = g.resample(&values, nx, ny);
        for yi in 5..91 {
            for xi in 5..67 {
                let fx = g.point_to_frame([xi as f64, yi as f64])[0];
                assert!((out[yi * 72 + xi] as f64 - fx).abs() < 1e-3, "{xi} {yi}");
            }
        }
    }
}
