//! The self-supervised losses of the field decoder, and the supervised one of its ceiling.
//!
//! - Normal: the frame is rebuilt from its background through the predicted map `D`:
//!   `Î_t = ½ + S(γ ∂D/∂x, γ ∂D/∂y)` (the background-subtracted frame is ½ where nothing
//!   touches), with `S` a learned per-pixel shading (two 1 × 1 convolutions) — the gel's colour
//!   change is a function of its surface slope, the premise of the photometric and calibrated
//!   optics alike. Loss: `α (1 − SSIM)/2 + (1 − α) |Î − I|` with α = 0.85 (monodepth2's mix; the
//!   official code's inverted branch leaves only the L1 term), plus an edge-aware smoothness of
//!   `D` and a small L1 pull of `D` towards 0 (at rest the gel is flat: without it the sign of
//!   `D` is free, as only its slope is seen).
//! - Shear: the frame `I_t` is warped back by the flow `F` (`Î_{t−k}(x) = I_t(x + F(x))`,
//!   bilinear) and compared with `I_{t−k}` by the Charbonnier penalty `√(r² + ε²)`, plus an
//!   edge-aware smoothness of `F` (weight 0.05 as the official decoder).

use burn::nn::conv::{Conv2d, Conv2dConfig};
use burn::prelude::*;
use burn::tensor::module::avg_pool2d;
use burn::tensor::ops::AvgPoolOptions;

/// Weights of the loss terms.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct LossWeights {
    /// SSIM share α of the photometric mix.
    pub ssim: f64,
    /// Edge-aware smoothness of the normal map.
    pub normal_smoothness: f64,
    /// L1 pull of the normal map towards 0.
    pub normal_sparsity: f64,
    /// Edge-aware smoothness of the flow (official: 0.05).
    pub shear_smoothness: f64,
    /// Slope gain γ of the shading input.
    pub slope_gain: f64,
}

impl Default for LossWeights {
    fn default() -> Self {
        Self {
            ssim: 0.85,
            normal_smoothness: 0.01,
            normal_sparsity: 0.01,
            shear_smoothness: 0.05,
            slope_gain: 10.0,
        }
    }
}

/// The learned shading `S`: surface slope → colour change.
#[derive(Module, Debug)]
pub struct Shading {
    /// Slope (2) → hidden (16).
    pub fc1: Conv2d,
    /// Hidden → colour (3).
    pub fc2: Conv2d,
}

impl Shading {
    /// A fresh shading model.
    pub fn new(device: &Device) -> Self {
        Self {
            fc1: Conv2dConfig::new([2, 16], [1, 1]).init(device),
            fc2: Conv2dConfig::new([16, 3], [1, 1]).init(device),
        }
    }

    /// `Î = ½ + S(γ ∇D)` for maps `[batch, 1, h, w]` → `[batch, 3, h, w]`.
    pub fn render(&self, normal: Tensor<4>, slope_gain: f64) -> Tensor<4> {
        let (gx, gy) = gradients(normal);
        let slope = Tensor::cat(vec![gx, gy], 1) * slope_gain;
        self.fc2.forward(self.fc1.forward(slope).tanh()) + 0.5
    }
}

/// Forward differences along x and y, zero in the last column / row (same size as `x`).
pub fn gradients(x: Tensor<4>) -> (Tensor<4>, Tensor<4>) {
    let [b, c, h, w] = x.dims();
    let device = x.device();
    let gx = x.clone().narrow(3, 1, w - 1) - x.clone().narrow(3, 0, w - 1);
    let gy = x.clone().narrow(2, 1, h - 1) - x.narrow(2, 0, h - 1);
    (
        Tensor::cat(vec![gx, Tensor::zeros([b, c, h, 1], &device)], 3),
        Tensor::cat(vec![gy, Tensor::zeros([b, c, 1, w], &device)], 2),
    )
}

/// Edge-aware smoothness (monodepth2): `mean |∂x m| e^{−mean_c |∂x I|} + mean |∂y m| e^{−mean_c |∂y I|}`.
pub fn edge_aware_smoothness(map: Tensor<4>, image: Tensor<4>) -> Tensor<1> {
    let (mx, my) = gradients(map);
    let (ix, iy) = gradients(image);
    let wx = (ix.abs().mean_dim(1) * -1.0).exp();
    let wy = (iy.abs().mean_dim(1) * -1.0).exp();
    (mx.abs() * wx).mean() + (my.abs() * wy).mean()
}

/// Per-pixel structural dissimilarity `(1 − SSIM)/2` over 3 × 3 windows (monodepth2),
/// `[batch, c, h, w]`.
pub fn dssim(x: Tensor<4>, y: Tensor<4>) -> Tensor<4> {
    let pool = |t: Tensor<4>| {
        avg_pool2d(
            t,
            AvgPoolOptions::new([3, 3])
                .with_stride([1, 1])
                .with_padding([1, 1])
                .with_count_include_pad(false),
        )
    };
    let (c1, c2) = (0.01f64.powi(2), 0.03f64.powi(2));
    let (mx, my) = (pool(x.clone()), pool(y.clone()));
    let sx = pool(x.clone() * x.clone()) - mx.clone() * mx.clone();
    let sy = pool(y.clone() * y.clone()) - my.clone() * my.clone();
    let sxy = pool(x * y) - mx.clone() * my.clone();
    let num = (mx.clone() * my.clone() * 2.0 + c1) * (sxy * 2.0 + c2);
    let den = (mx.clone() * mx + my.clone() * my + c1) * (sx + sy + c2);
    ((num / den) * -1.0 + 1.0).clamp(0.0, 2.0) * 0.5
}

/// The photometric error `α·DSSIM + (1 − α)·|x − y|`, mean over everything.
pub fn photometric(x: Tensor<4>, y: Tensor<4>, alpha: f64) -> Tensor<1> {
    let l1 = (x.clone() - y.clone()).abs();
    if alpha <= 0.0 {
        return l1.mean();
    }
    (dssim(x, y) * alpha + l1 * (1.0 - alpha)).mean()
}

/// Bilinear backward warp: `out(x) = image(x + flow(x))`, coordinates clamped to the image;
/// differentiable in the flow through the interpolation weights.
///
/// # Shapes
/// - `image`: `[batch, c, h, w]`, `flow`: `[batch, 2, h, w]` (pixels; x then y) → `[batch, c, h, w]`
pub fn warp(image: Tensor<4>, flow: Tensor<4>) -> Tensor<4> {
    let [b, c, h, w] = image.dims();
    let device = image.device();
    let xs = Tensor::<1, Int>::arange(0..w as i64, &device)
        .float()
        .reshape([1, 1, 1, w])
        .expand([b, 1, h, w]);
    let ys = Tensor::<1, Int>::arange(0..h as i64, &device)
        .float()
        .reshape([1, 1, h, 1])
        .expand([b, 1, h, w]);
    let x = (xs + flow.clone().narrow(1, 0, 1)).clamp(0.0, (w - 1) as f64);
    let y = (ys + flow.narrow(1, 1, 1)).clamp(0.0, (h - 1) as f64);
    let x0 = x.clone().detach().floor();
    let y0 = y.clone().detach().floor();
    let (ax, ay) = (x - x0.clone(), y - y0.clone());
    let x1 = (x0.clone() + 1.0).clamp_max((w - 1) as f64);
    let y1 = (y0.clone() + 1.0).clamp_max((h - 1) as f64);
    let flat = image.reshape([b, c, h * w]);
    let pick = |xi: Tensor<4>, yi: Tensor<4>| {
        let idx = (yi * w as f64 + xi)
            .int()
            .reshape([b, 1, h * w])
            .repeat_dim(1, c);
        flat.clone().gather(2, idx).reshape([b, c, h, w])
    };
    let (i00, i10) = (pick(x0.clone(), y0.clone()), pick(x1.clone(), y0));
    let (i01, i11) = (pick(x0, y1.clone()), pick(x1, y1));
    let one = |a: Tensor<4>| a * -1.0 + 1.0;
    let top = i00 * one(ax.clone()) + i10 * ax.clone();
    let bottom = i01 * one(ax.clone()) + i11 * ax;
    top * one(ay.clone()) + bottom * ay
}

/// The normal branch's self-supervised loss (module docs).
pub fn normal_loss(
    normal: Tensor<4>,
    frame: Tensor<4>,
    shading: &Shading,
    w: &LossWeights,
) -> Tensor<1> {
    let rebuilt = shading.render(normal.clone(), w.slope_gain);
    photometric(rebuilt, frame.clone(), w.ssim)
        + edge_aware_smoothness(normal.clone(), frame) * w.normal_smoothness
        + normal.mean() * w.normal_sparsity
}

/// The shear loss's photometric term: the Charbonnier penalty √(r² + ε²), ε = 10⁻³, of the
/// residual r between `current` warped back by `flow` and `previous`, averaged.
pub fn shear_photometric(flow: Tensor<4>, current: Tensor<4>, previous: Tensor<4>) -> Tensor<1> {
    let r = warp(current, flow) - previous;
    (r.clone() * r + 1e-6).sqrt().mean()
}

/// The shear branch's self-supervised loss (module docs).
pub fn shear_loss(
    flow: Tensor<4>,
    current: Tensor<4>,
    previous: Tensor<4>,
    w: &LossWeights,
) -> Tensor<1> {
    shear_photometric(flow.clone(), current, previous.clone())
        + edge_aware_smoothness(flow, previous) * w.shear_smoothness
}

#[cfg(test)]
mod tests {
    use super::*;

    fn tensor(v: Vec<f32>, shape: [usize; 4]) -> Tensor<4> {
        Tensor::<1>::from_floats(v.as_slice(), &Device::flex()).reshape(shape)
    }

    /// A smooth pattern and the same pattern moved by (1.5, −0.75) px.
    fn moved_pair(h: usize, w: usize, shift: [f64; 2]) -> (Vec<f32>, Vec<f32>) {
        let f = |x: f64, y: f64| (0.5 + 0.2 * (0.45 * x).sin() * (0.3 * y).cos()) as f32;
        let mut a = Vec::new();
        let mut b = Vec::new();
        for y in 0..h {
            for x in 0..w {
                a.push(f(x as f64, y as f64));
                b.push(f(x as f64 - shift[0], y as f64 - shift[1]));
            }
        }
        (a, b)
    }

    /// Warping the moved frame by the true motion gives the first frame back (inside), and the
    /// shear loss is lower with the true flow than with zero flow: the loss points the right way.
    #[test]
    fn warping_with_the_true_flow_undoes_the_motion() {
        let (h, w) = (24, 20);
        let shift = [1.5, -0.75];
        let (prev, now) = moved_pair(h, w, shift);
        let prev_t = tensor(prev.clone(), [1, 1, h, w]);
        let now_t = tensor(now, [1, 1, h, w]);
        let mut fv = vec![shift[0] as f32; h * w];
        fv.extend(vec![shift[1] as f32; h * w]);
        let flow = tensor(fv, [1, 2, h, w]);
        let back: Vec<f32> = warp(now_t.clone(), flow.clone())
            .into_data()
            .try_to_vec()
            .unwrap();
        for y in 2..h - 2 {
            for x in 2..w - 3 {
                let err = (back[y * w + x] - prev[y * w + x]).abs();
                assert!(err < 0.02, "({x}, {y}): {err}");
            }
        }
        let weights = LossWeights::default();
        let zero = Tensor::zeros([1, 2, h, w], &Device::flex());
        let with_truth: f32 =
            shear_loss(flow, now_t.clone(), prev_t.clone(), &weights).into_scalar();
        let with_zero: f32 = shear_loss(zero, now_t, prev_t, &weights).into_scalar();
        assert!(with_truth < 0.5 * with_zero, "{with_truth} vs {with_zero}");
    }

    /// SSIM of an image with itself is 1 (DSSIM 0); against a different one it is positive.
    #[test]
    fn dssim_is_zero_on_identical_images() {
        let (a, b) = moved_pair(12, 10, [2.0, 1.0]);
        let x = tensor(a.clone(), [1, 1, 12, 10]);
        let same: f32 = dssim(x.clone(), tensor(a, [1, 1, 12, 10]))
            .mean()
            .into_scalar();
        let other: f32 = dssim(x, tensor(b, [1, 1, 12, 10])).mean().into_scalar();
        assert!(same.abs() < 1e-5, "{same}");
        assert!(other > 0.01, "{other}");
    }

    /// The flow's gradient from the photometric term points toward the true motion.
    #[test]
    fn the_shear_gradient_points_to_the_true_motion() {
        let (h, w) = (24, 20);
        let (prev, now) = moved_pair(h, w, [1.0, 0.0]);
        let device = Device::flex().autodiff();
        let prev_t = Tensor::<1>::from_floats(prev.as_slice(), &device).reshape([1, 1, h, w]);
        let now_t = Tensor::<1>::from_floats(now.as_slice(), &device).reshape([1, 1, h, w]);
        let flow = Tensor::<4>::zeros([1, 2, h, w], &device).require_grad();
        let weights = LossWeights {
            shear_smoothness: 0.0,
            ..LossWeights::default()
        };
        let loss = shear_loss(flow.clone(), now_t, prev_t, &weights);
        let grads = loss.backward();
        let g: Vec<f32> = flow.grad(&grads).unwrap().into_data().try_to_vec().unwrap();
        let gx: f32 = g[..h * w].iter().sum();
        assert!(
            gx < 0.0,
            "descent should raise the x flow: gradient sum {gx}"
        );
    }
}
