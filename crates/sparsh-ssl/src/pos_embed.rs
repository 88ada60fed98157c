//! Position embeddings of the Sparsh encoder: the official fixed sinusoidal table, and the
//! resampling of a stored table to another patch grid.
//!
//! A position grid lists the official axes of the embedding: `[rows, columns]` for images and
//! `[frames / tubelet, rows, columns]` for clips (the official `SinusoidalEmbed` is 2-D when
//! `num_frames == 1` and 3-D otherwise). Tokens are row-major over the grid (`"ij"` indexing,
//! the first axis slowest), the order of the patch embedding's output.

use burn::prelude::*;

/// Frequency bands of the official `SinusoidalEmbed` (`tactile_ssl/model/layers/patch_embed.py`,
/// `logspace = False`): for each of the `axes` axes the same `B = ⌈dim / (2·axes)⌉` bands
/// `ω_k = 10000^(−k/B)`, `k = 0..B` (`10000 ** -linspace(0, 1, B + 1)[:-1]`). Shape `[axes][B]`,
/// the layout of the checkpoint buffer `pos_embed.frequency_bands`.
pub fn sincos_bands(dim: usize, axes: usize) -> Vec<Vec<f64>> {
    let bands = dim.div_ceil(2 * axes);
    let row: Vec<f64> = (0..bands)
        .map(|k| 10000f64.powf(-(k as f64) / bands as f64))
        .collect();
    vec![row; axes]
}

/// The official `SinusoidalEmbed.forward` with the given frequency bands `[axes][B]`: at the grid
/// point with integer coordinates `(c_0, .., c_{A−1})` (`create_ndgrid`, `normalized_coords =
/// False`), the features are, axis after axis, `[sin(c_a·ω_a0 ..), cos(c_a·ω_a0 ..)]`, cut to the
/// first `dim` values. Row-major over `grid`, `grid.len() · dim` values.
///
/// ```text
/// 2-D, dim 384: B = 96: [sin(row·ω) 96, cos(row·ω) 96, sin(col·ω) 96, cos(col·ω) 96]
/// 3-D, dim 384: B = 64: [sin/cos(frame·ω) 128, sin/cos(row·ω) 128, sin/cos(col·ω) 128]
/// ```
pub fn sincos_from_bands(dim: usize, grid: &[usize], bands: &[Vec<f64>]) -> Vec<f32> {
    let n: usize = grid.iter().product();
    let mut out = Vec::with_capacity(n * dim);
    let mut coords = vec![0usize; grid.len()];
    for token in 0..n {
        let mut rest = token;
        for a in (0..grid.len()).rev() {
            coords[a] = rest % grid[a];
            rest /= grid[a];
        }
        let start = out.len();
        for (a, omega) in bands.iter().enumerate() {
            let c = coords[a] as f64;
            out.extend(omega.iter().map(|w| (c * w).sin() as f32));
            out.extend(omega.iter().map(|w| (c * w).cos() as f32));
        }
        out.truncate(start + dim);
    }
    out
}

/// The official fixed sinusoidal embedding (default bands, [`sincos_bands`]) over `grid`.
pub fn sincos_embedding(dim: usize, grid: &[usize]) -> Vec<f32> {
    sincos_from_bands(dim, grid, &sincos_bands(dim, grid.len()))
}

/// [`sincos_embedding`] as a `[1, tokens, dim]` tensor.
pub fn sincos_tensor(dim: usize, grid: &[usize], device: &Device) -> Tensor<3> {
    let n = grid.iter().product::<usize>();
    Tensor::<1>::from_floats(sincos_embedding(dim, grid).as_slice(), device).reshape([1, n, dim])
}

/// How a stored table is resampled to another grid: PyTorch's `F.interpolate` modes used by the
/// official `VisionTransformer.interpolate_pos_encoding` (`tactile_ssl/model/vision_transformer.py`)
/// — bicubic for images, trilinear for clips — with `align_corners = False` and no antialiasing
/// (`interpolate_antialias = False`).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Resample {
    /// Separable cubic convolution, `A = −0.75` (`upsample_bicubic2d`).
    Bicubic,
    /// Separable linear (`upsample_trilinear3d`).
    Trilinear,
}

/// `(source index, weight)` pairs of each output index along one axis, as PyTorch computes them
/// (`aten/src/ATen/native/UpSample.h`: `area_pixel_compute_source_index` with scale `src / dst`,
/// `get_cubic_upsample_coefficients`, `upsample_get_value_bounded` clamping the four cubic taps to
/// the edge; the linear source index is clamped at 0 and its upper tap at the last index).
fn axis_weights(src: usize, dst: usize, mode: Resample) -> Vec<Vec<(usize, f64)>> {
    let scale = src as f64 / dst as f64;
    let last = src as i64 - 1;
    (0..dst)
        .map(|i| {
            let real = scale * (i as f64 + 0.5) - 0.5;
            match mode {
                Resample::Bicubic => {
                    const A: f64 = -0.75;
                    let near = |x: f64| ((A + 2.0) * x - (A + 3.0)) * x * x + 1.0;
                    let far = |x: f64| ((A * x - 5.0 * A) * x + 8.0 * A) * x - 4.0 * A;
                    let base = real.floor();
                    let t = real - base;
                    let w = [far(t + 1.0), near(t), near(1.0 - t), far(2.0 - t)];
                    (0..4)
                        .map(|k| ((base as i64 - 1 + k as i64).clamp(0, last) as usize, w[k]))
                        .collect()
                }
                Resample::Trilinear => {
                    let real = real.max(0.0);
                    let i0 = real as usize;
                    let i1 = if (i0 as i64) < last { i0 + 1 } else { i0 };
                    let l1 = real - i0 as f64;
                    vec![(i0, 1.0 - l1), (i1, l1)]
                }
            }
        })
        .collect()
}

/// Resamples a row-major table `[src grid…, dim]` to `dst` (same number of axes), one axis at a
/// time (both PyTorch modes are separable products of per-axis weights).
pub fn resample(
    table: &[f32],
    dim: usize,
    src: &[usize],
    dst: &[usize],
    mode: Resample,
) -> Vec<f32> {
    let mut cur: Vec<f64> = table.iter().map(|&v| v as f64).collect();
    let mut shape = src.to_vec();
    for axis in 0..src.len() {
        let weights = axis_weights(src[axis], dst[axis], mode);
        let outer: usize = shape[..axis].iter().product();
        let inner: usize = shape[axis + 1..].iter().product::<usize>() * dim;
        let mut next = vec![0.0; outer * dst[axis] * inner];
        for o in 0..outer {
            for (j, taps) in weights.iter().enumerate() {
                let out = &mut next[(o * dst[axis] + j) * inner..][..inner];
                for &(s, w) in taps {
                    let row = &cur[(o * shape[axis] + s) * inner..][..inner];
                    for (y, x) in out.iter_mut().zip(row) {
                        *y += w * x;
                    }
                }
            }
        }
        shape[axis] = dst[axis];
        cur = next;
    }
    cur.into_iter().map(|v| v as f32).collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn sincos_starts_with_zero_sines_and_unit_cosines_and_keeps_dim() {
        // 2-D dim 30: 8 bands per axis, 32 values cut to 30
        let e = sincos_embedding(30, &[4, 3]);
        assert_eq!(e.len(), 12 * 30);
        assert_eq!(&e[0..8], &[0.0; 8]);
        assert_eq!(&e[8..16], &[1.0; 8]);
        // token 1 is row 0, column 1: the row block is unchanged, the column block is not
        assert_eq!(&e[30..46], &e[0..16]);
        assert!((e[30 + 16] - 1f32.sin()).abs() < 1e-7);
    }

    #[test]
    fn resampling_to_the_same_grid_is_the_identity() {
        let table: Vec<f32> = (0..2 * 4 * 3 * 5)
            .map(|i| (i as f32 * 0.37).sin())
            .collect();
        for mode in [Resample::Bicubic, Resample::Trilinear] {
            let same = resample(&table, 5, &[2, 4, 3], &[2, 4, 3], mode);
            assert!(table.iter().zip(&same).all(|(a, b)| (a - b).abs() < 1e-6));
        }
    }
}
