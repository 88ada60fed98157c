//! Vectorised CPU kernels for the encoder's element-wise layers: the exact GELU and layer norm,
//! forward and backward, on burn `flex` tensors (with or without autodiff); every other device
//! (wgpu, CUDA) takes burn's own ops.
//!
//! burn `flex` evaluates GELU and its derivative one element at a time through a scalar `erf`
//! (libm's `erff`) on the calling thread (28 % of the encoder's forward pass in a `perf` profile of
//! `benches/embed.rs`, 6 % of the reference training step), and under autodiff it runs layer norm as burn's generic composition (two means, a
//! subtraction, a square, a square root, a division, a scale and a shift), each a pass over the
//! activations that is recorded for the backward pass. Here both are one pass each way, split over
//! the rayon pool.
//!
//! **GELU** is the exact form `x Φ(x) = ½ x (1 + erf(x / √2))` (Hendrycks & Gimpel 2016, PyTorch's
//! `nn.GELU()` default, the official encoder's MLP activation), not the tanh approximation. Φ
//! comes from the complementary error function of Numerical Recipes (`erfcc`: Press, Teukolsky,
//! Vetterling & Flannery, *Numerical Recipes in C*, 2nd ed., §6.2, a Chebyshev fit of fractional
//! error below 1.2e-7 everywhere) and `exp` from Cephes' `expf` (S. L. Moshier, Cephes Math
//! Library), written without branches so that the compiler vectorises them. Against the exact GELU
//! in f64 the kernel's absolute error is below 4e-7 (and 1.2e-7 · |x| beyond |x| = 1) and the
//! derivative's below 3e-7, tested; Φ(x) for x < 0 is ½ erfc(|x| / √2), so the left tail keeps its
//! relative accuracy instead of cancelling in 1 + erf.
//!
//! **Layer norm** is `(x − μ) / √(σ² + ε) · γ + β` over the last axis, σ² the biased variance
//! (PyTorch's `nn.LayerNorm`), with the textbook backward pass (x̂ the normalised input, g the
//! upstream gradient): `∂x = (ĝ − mean ĝ − x̂ · mean(ĝ x̂)) / √(σ² + ε)` with `ĝ = g γ`,
//! `∂γ = Σ g x̂`, `∂β = Σ g` over the rows. The row sums are taken in a fixed order whatever the
//! number of threads, so results do not depend on the pool size.

use burn::backend::autodiff::checkpoint::base::Checkpointer;
use burn::backend::autodiff::checkpoint::strategy::{
    BalancedCheckpointing, CheckpointStrategy, NoCheckpointing,
};
use burn::backend::autodiff::grads::Gradients;
use burn::backend::autodiff::ops::{Backward, Ops, OpsKind, unary};
use burn::backend::flex::FlexTensor;
use burn::backend::ops::ActivationOps;
use burn::backend::tensor::FloatTensor;
use burn::backend::{
    Autodiff, BackendTensor, DispatchAutodiffContext, DispatchTensor, DispatchTensorKind, Flex,
    GradientCheckpointingStrategy,
};
use burn::nn::LayerNorm;
use burn::prelude::*;
use burn::tensor::DType;
use multiversion::multiversion;
use rayon::prelude::*;

/// Elements per rayon task of the element-wise kernels (64 KiB of f32).
const CHUNK: usize = 1 << 14;
/// Rows per rayon task of the layer-norm kernels.
const ROWS: usize = 64;

/// A tensor as the kernels see it.
enum Flexed {
    /// A `flex` tensor without autodiff.
    Plain(FlexTensor),
    /// A `flex` tensor under autodiff, and its checkpointing strategy.
    Tracked(FloatTensor<Autodiff<Flex>>, GradientCheckpointingStrategy),
    /// Anything else (another device), untouched (boxed: a dispatch tensor is large).
    Other(Box<DispatchTensor>),
}

impl Flexed {
    fn of<const D: usize>(t: Tensor<D>) -> Self {
        match t.into_dispatch() {
            DispatchTensor {
                kind: DispatchTensorKind::Flex(BackendTensor::Float(t)),
                autodiff: DispatchAutodiffContext::Disabled,
            } => Flexed::Plain(t),
            DispatchTensor {
                kind: DispatchTensorKind::Autodiff(inner),
                autodiff: DispatchAutodiffContext::Enabled(strategy),
            } => match *inner {
                DispatchTensorKind::Flex(BackendTensor::Autodiff(t)) => {
                    Flexed::Tracked(t, strategy)
                }
                other => Flexed::Other(Box::new(DispatchTensor {
                    kind: DispatchTensorKind::Autodiff(Box::new(other)),
                    autodiff: DispatchAutodiffContext::Enabled(strategy),
                })),
            },
            other => Flexed::Other(Box::new(other)),
        }
    }

    fn tensor<const D: usize>(self) -> Tensor<D> {
        Tensor::from_dispatch(match self {
            Flexed::Plain(t) => DispatchTensor {
                kind: DispatchTensorKind::Flex(BackendTensor::Float(t)),
                autodiff: DispatchAutodiffContext::Disabled,
            },
            Flexed::Tracked(t, strategy) => DispatchTensor {
                kind: DispatchTensorKind::Autodiff(Box::new(DispatchTensorKind::Flex(
                    BackendTensor::Autodiff(t),
                ))),
                autodiff: DispatchAutodiffContext::Enabled(strategy),
            },
            Flexed::Other(t) => *t,
        })
    }
}

/// The exact GELU of every element of `x`, differentiable; vectorised on `flex` tensors.
pub fn gelu<const D: usize>(x: Tensor<D>) -> Tensor<D> {
    match Flexed::of(x) {
        Flexed::Plain(x) => Flexed::Plain(gelu_flex(x)).tensor(),
        Flexed::Tracked(x, strategy) => {
            let y = match strategy {
                GradientCheckpointingStrategy::Balanced => gelu_tracked::<BalancedCheckpointing>(x),
                GradientCheckpointingStrategy::Disabled => gelu_tracked::<NoCheckpointing>(x),
            };
            Flexed::Tracked(y, strategy).tensor()
        }
        other => burn::tensor::activation::gelu(other.tensor()),
    }
}

/// `norm` (its γ and β, `epsilon` its ε) applied to the last axis of `x`, differentiable; one
/// pass each way on `flex` tensors, burn's layer norm elsewhere.
pub fn layer_norm<const D: usize>(x: Tensor<D>, norm: &LayerNorm, epsilon: f64) -> Tensor<D> {
    let Some(beta) = &norm.beta else {
        return burn::tensor::module::layer_norm(x, norm.gamma.val(), None, epsilon);
    };
    let parts = (
        Flexed::of(x),
        Flexed::of(norm.gamma.val()),
        Flexed::of(beta.val()),
    );
    match parts {
        (Flexed::Plain(x), Flexed::Plain(g), Flexed::Plain(b)) => {
            Flexed::Plain(layer_norm_forward(x, &g, &b, epsilon as f32).0).tensor()
        }
        (Flexed::Tracked(x, s), Flexed::Tracked(g, sg), Flexed::Tracked(b, sb))
            if s == sg && s == sb =>
        {
            let y = match s {
                GradientCheckpointingStrategy::Balanced => {
                    layer_norm_tracked::<BalancedCheckpointing>(x, g, b, epsilon as f32)
                }
                GradientCheckpointingStrategy::Disabled => {
                    layer_norm_tracked::<NoCheckpointing>(x, g, b, epsilon as f32)
                }
            };
            Flexed::Tracked(y, s).tensor()
        }
        (x, g, b) => burn::tensor::module::layer_norm(
            x.tensor(),
            g.tensor::<1>(),
            Some(b.tensor::<1>()),
            epsilon,
        ),
    }
}

/// The backward step of [`gelu`] on `flex`: `grad · GELU'(x)`, `x` kept from the forward pass.
#[derive(Debug)]
struct GeluBackward;

impl Backward<Flex, 1> for GeluBackward {
    type State = FlexTensor;

    fn backward(
        self,
        ops: Ops<Self::State, 1>,
        grads: &mut Gradients,
        _checkpointer: &mut Checkpointer,
    ) {
        let x = ops.state;
        unary::<Flex, _>(ops.parents, ops.node, grads, |grad| {
            gelu_backward_flex(x, grad)
        });
    }
}

/// [`gelu`] on a `flex` autodiff tensor, recorded with [`GeluBackward`] when tracked.
fn gelu_tracked<C: CheckpointStrategy>(
    x: FloatTensor<Autodiff<Flex>>,
) -> FloatTensor<Autodiff<Flex>> {
    match GeluBackward
        .prepare::<C>([x.node()])
        .compute_bound()
        .stateful()
    {
        OpsKind::Tracked(prep) => {
            let input = dense(x.into_primitive());
            prep.finish(input.clone(), gelu_flex(input))
        }
        OpsKind::UnTracked(prep) => prep.finish(gelu_flex(x.into_primitive())),
    }
}

/// The backward step of [`layer_norm`] on `flex`; the state is the dense input, γ and the rows'
/// `[mean, 1 / √(σ² + ε)]`.
#[derive(Debug)]
struct LayerNormBackward;

impl Backward<Flex, 3> for LayerNormBackward {
    type State = (FlexTensor, FlexTensor, FlexTensor);

    fn backward(
        self,
        ops: Ops<Self::State, 3>,
        grads: &mut Gradients,
        _checkpointer: &mut Checkpointer,
    ) {
        let (x, gamma, stats) = ops.state;
        let grad = grads.consume::<Flex>(&ops.node);
        let (dx, dgamma, dbeta) = layer_norm_backward(&x, &gamma, &stats, grad);
        let [px, pg, pb] = ops.parents;
        for (parent, g) in [(px, dx), (pg, dgamma), (pb, dbeta)] {
            if let Some(node) = parent {
                grads.register::<Flex>(node.id, g);
            }
        }
    }
}

/// [`layer_norm`] on `flex` autodiff tensors, recorded with [`LayerNormBackward`] when tracked.
fn layer_norm_tracked<C: CheckpointStrategy>(
    x: FloatTensor<Autodiff<Flex>>,
    gamma: FloatTensor<Autodiff<Flex>>,
    beta: FloatTensor<Autodiff<Flex>>,
    epsilon: f32,
) -> FloatTensor<Autodiff<Flex>> {
    let nodes = [x.node(), gamma.node(), beta.node()];
    let (x, gamma, beta) = (
        dense(x.into_primitive()),
        dense(gamma.into_primitive()),
        dense(beta.into_primitive()),
    );
    match LayerNormBackward
        .prepare::<C>(nodes)
        .compute_bound()
        .stateful()
    {
        OpsKind::Tracked(prep) => {
            let (y, stats) = layer_norm_forward(x.clone(), &gamma, &beta, epsilon);
            prep.finish((x, gamma, stats), y)
        }
        OpsKind::UnTracked(prep) => prep.finish(layer_norm_forward(x, &gamma, &beta, epsilon).0),
    }
}

/// `t` with its f32 elements packed from offset 0 (a copy only when they are not).
fn dense(t: FlexTensor) -> FlexTensor {
    let n = t.layout().num_elements();
    if t.layout().contiguous_offsets() == Some((0, n)) && t.bytes().len() == 4 * n {
        t
    } else {
        t.to_contiguous()
    }
}

/// A new f32 `flex` tensor of `shape`.
fn flex_tensor(values: Vec<f32>, shape: impl Into<burn::tensor::Shape>) -> FlexTensor {
    FlexTensor::from_data(TensorData::new(values, shape))
}

/// `f` applied to every element of `x`, in place when `x` owns its buffer.
fn map_flex(x: FlexTensor, f: impl Fn(f32) -> f32 + Sync) -> FlexTensor {
    let mut x = dense(x);
    if x.is_unique() {
        x.storage_mut::<f32>()
            .par_chunks_mut(CHUNK)
            .for_each(|c| map_into(c, None, &f));
        return x;
    }
    let mut out = vec![0.0f32; x.layout().num_elements()];
    out.par_chunks_mut(CHUNK)
        .zip(x.storage::<f32>().par_chunks(CHUNK))
        .for_each(|(o, i)| map_into(o, Some(i), &f));
    flex_tensor(out, x.layout().shape().clone())
}

// The element loops below are compiled for AVX-512 and for AVX2 as well as for the baseline
// (SSE2), the best one the CPU has chosen at run time: 16 or 8 lanes instead of 4. Each version
// does the same IEEE operations in the same order (Rust fuses no multiply with an add), so the
// results do not depend on the CPU.

/// `out[k] = f(input[k])`, or `f(out[k])` in place without `input`.
#[multiversion(targets("x86_64+avx512f+avx512vl+avx512bw+avx512dq", "x86_64+avx2+fma"))]
fn map_into<F: Fn(f32) -> f32>(out: &mut [f32], input: Option<&[f32]>, f: &F) {
    match input {
        Some(input) => out.iter_mut().zip(input).for_each(|(o, &v)| *o = f(v)),
        None => out.iter_mut().for_each(|v| *v = f(*v)),
    }
}

/// `a[k] = f(a[k], b[k])`.
#[multiversion(targets("x86_64+avx512f+avx512vl+avx512bw+avx512dq", "x86_64+avx2+fma"))]
fn zip_into<F: Fn(f32, f32) -> f32>(a: &mut [f32], b: &[f32], f: &F) {
    a.iter_mut().zip(b).for_each(|(a, &b)| *a = f(*a, b));
}

/// The exact GELU of every element of `x`, in place.
pub(crate) fn gelu_in_place(x: &mut [f32]) {
    map_into(x, None, &gelu_f32);
}

/// `x ← softmax(x)`: `e^{x − max x}` over its sum (taken in eight partial sums, fixed order).
#[multiversion(targets("x86_64+avx512f+avx512vl+avx512bw+avx512dq", "x86_64+avx2+fma"))]
pub(crate) fn softmax_in_place(x: &mut [f32]) {
    let max = x.iter().fold(f32::NEG_INFINITY, |m, &v| m.max(v));
    x.iter_mut().for_each(|v| *v = exp_f32(*v - max));
    let mut acc = [0.0f32; 8];
    let chunks = x.chunks_exact(8);
    let tail: f32 = chunks.remainder().iter().sum();
    for c in chunks {
        for k in 0..8 {
            acc[k] += c[k];
        }
    }
    let inv = 1.0 / (lanes_sum(acc) + tail);
    x.iter_mut().for_each(|v| *v *= inv);
}

/// GELU of an f32 `flex` tensor (other dtypes: burn's).
fn gelu_flex(x: FlexTensor) -> FlexTensor {
    if x.dtype() != DType::F32 {
        return Flex::gelu(x);
    }
    map_flex(x, gelu_f32)
}

/// `grad · GELU'(x)` on f32 `flex` tensors of one shape (other dtypes: burn's).
fn gelu_backward_flex(x: FlexTensor, grad: FlexTensor) -> FlexTensor {
    if x.dtype() != DType::F32 || grad.dtype() != DType::F32 {
        return Flex::gelu_backward(x, grad);
    }
    let x = dense(x);
    let mut grad = dense(grad);
    // `storage_mut` copies a shared buffer first, so no other holder's gradient is overwritten
    grad.storage_mut::<f32>()
        .par_chunks_mut(CHUNK)
        .zip(x.storage::<f32>().par_chunks(CHUNK))
        .for_each(|(g, x)| zip_into(g, x, &|g, x| g * gelu_derivative_f32(x)));
    grad
}

/// Σ a·b in eight interleaved partial sums (one vector register; the compiler vectorises this
/// shape of loop), added in a fixed order.
#[inline(always)]
fn dot(a: &[f32], b: &[f32]) -> f32 {
    let mut acc = [0.0f32; 8];
    let (ca, cb) = (a.chunks_exact(8), b.chunks_exact(8));
    let tail: f32 = ca
        .remainder()
        .iter()
        .zip(cb.remainder())
        .map(|(x, y)| x * y)
        .sum();
    for (x, y) in ca.zip(cb) {
        for k in 0..8 {
            acc[k] += x[k] * y[k];
        }
    }
    lanes_sum(acc) + tail
}

/// The eight partial sums of one vector register added in a fixed order.
#[inline(always)]
fn lanes_sum(acc: [f32; 8]) -> f32 {
    ((acc[0] + acc[4]) + (acc[1] + acc[5])) + ((acc[2] + acc[6]) + (acc[3] + acc[7]))
}

/// Layer norm of the dense f32 `x` over its last axis: the output and the rows' `[mean,
/// 1 / √(σ² + ε)]` as a `[rows, 2]` tensor.
fn layer_norm_forward(
    x: FlexTensor,
    gamma: &FlexTensor,
    beta: &FlexTensor,
    epsilon: f32,
) -> (FlexTensor, FlexTensor) {
    let x = dense(x);
    let (gamma, beta) = (dense(gamma.clone()), dense(beta.clone()));
    let shape = x.layout().shape().clone();
    let d = gamma.layout().num_elements();
    let rows = x.layout().num_elements() / d;
    let (xs, gs, bs) = (
        x.storage::<f32>(),
        gamma.storage::<f32>(),
        beta.storage::<f32>(),
    );
    let mut out = vec![0.0f32; rows * d];
    let mut stats = vec![0.0f32; rows * 2];
    let ones = vec![1.0f32; d];
    out.par_chunks_mut(ROWS * d)
        .zip(stats.par_chunks_mut(ROWS * 2))
        .zip(xs.par_chunks(ROWS * d))
        .for_each(|((o, st), xs)| layer_norm_rows(o, st, xs, [gs, bs, &ones], epsilon));
    (flex_tensor(out, shape), flex_tensor(stats, [rows, 2]))
}

/// The rows of one task of [`layer_norm_forward`]: `o` from `xs`, `[mean, 1 / √(σ² + ε)]` per
/// row into `st`.
#[multiversion(targets("x86_64+avx512f+avx512vl+avx512bw+avx512dq", "x86_64+avx2+fma"))]
pub(crate) fn layer_norm_rows(
    o: &mut [f32],
    st: &mut [f32],
    xs: &[f32],
    [gs, bs, ones]: [&[f32]; 3],
    epsilon: f32,
) {
    let d = gs.len();
    for ((o, st), x) in o.chunks_mut(d).zip(st.chunks_mut(2)).zip(xs.chunks(d)) {
        let mean = dot(x, ones) / d as f32;
        // the centred row first, in the output, then its variance
        o.iter_mut().zip(x).for_each(|(o, &x)| *o = x - mean);
        let rstd = 1.0 / (dot(o, o) / d as f32 + epsilon).sqrt();
        for ((o, &g), &b) in o.iter_mut().zip(gs).zip(bs) {
            *o = *o * rstd * g + b;
        }
        st[0] = mean;
        st[1] = rstd;
    }
}

/// The gradients of layer norm with respect to `x`, γ and β, from the upstream `grad`.
fn layer_norm_backward(
    x: &FlexTensor,
    gamma: &FlexTensor,
    stats: &FlexTensor,
    grad: FlexTensor,
) -> (FlexTensor, FlexTensor, FlexTensor) {
    let d = gamma.layout().num_elements();
    let mut grad = dense(grad);
    let (xs, gs, st) = (
        x.storage::<f32>(),
        gamma.storage::<f32>(),
        stats.storage::<f32>(),
    );
    // ∂x overwrites the upstream gradient row by row; each task also returns its Σ g x̂ and Σ g
    let partial: Vec<(Vec<f32>, Vec<f32>)> = grad
        .storage_mut::<f32>()
        .par_chunks_mut(ROWS * d)
        .zip(xs.par_chunks(ROWS * d))
        .zip(st.par_chunks(ROWS * 2))
        .map(|((g, xs), st)| {
            let (mut dgamma, mut dbeta) = (vec![0.0f32; d], vec![0.0f32; d]);
            layer_norm_backward_rows(g, xs, st, gs, [&mut dgamma, &mut dbeta]);
            (dgamma, dbeta)
        })
        .collect();
    let (mut dgamma, mut dbeta) = (vec![0.0f32; d], vec![0.0f32; d]);
    for (pg, pb) in &partial {
        dgamma.iter_mut().zip(pg).for_each(|(a, b)| *a += b);
        dbeta.iter_mut().zip(pb).for_each(|(a, b)| *a += b);
    }
    (grad, flex_tensor(dgamma, [d]), flex_tensor(dbeta, [d]))
}

/// The rows of one task of [`layer_norm_backward`]: ∂x over the upstream gradient `g`, and this
/// task's Σ g x̂ and Σ g added into `dgamma` and `dbeta`.
#[multiversion(targets("x86_64+avx512f+avx512vl+avx512bw+avx512dq", "x86_64+avx2+fma"))]
fn layer_norm_backward_rows(
    g: &mut [f32],
    xs: &[f32],
    st: &[f32],
    gs: &[f32],
    [dgamma, dbeta]: [&mut [f32]; 2],
) {
    let d = gs.len();
    // per row: x̂, then ĝ = g γ, with the partial sums of ∂γ and ∂β on the way
    let (mut xhat, mut ghat) = (vec![0.0f32; d], vec![0.0f32; d]);
    let ones = vec![1.0f32; d];
    for ((g, x), st) in g.chunks_mut(d).zip(xs.chunks(d)).zip(st.chunks(2)) {
        let (mean, rstd) = (st[0], st[1]);
        xhat.iter_mut()
            .zip(x)
            .for_each(|(h, &x)| *h = (x - mean) * rstd);
        for (((((gh, &g), &gm), &h), dg), db) in ghat
            .iter_mut()
            .zip(g.iter())
            .zip(gs)
            .zip(&xhat)
            .zip(dgamma.iter_mut())
            .zip(dbeta.iter_mut())
        {
            *gh = g * gm;
            *dg += g * h;
            *db += g;
        }
        let a = dot(&ghat, &ones) / d as f32;
        let b = dot(&ghat, &xhat) / d as f32;
        for ((g, &gh), &h) in g.iter_mut().zip(&ghat).zip(&xhat) {
            *g = (gh - a - h * b) * rstd;
        }
    }
}

/// `e^x` for `x` in [−87, 88] (clamped outside), within about 1 ulp: Cephes `expf` (round
/// `x / ln 2` to `n`, reduce with a two-part `ln 2`, degree-6 polynomial, scale by `2ⁿ`), with
/// the rounding done by adding and subtracting 1.5 · 2²³ so that it vectorises without SSE4.1.
#[inline(always)]
fn exp_f32(x: f32) -> f32 {
    const ROUND: f32 = 12_582_912.0;
    let x = x.clamp(-87.0, 88.0);
    let n = (x * std::f32::consts::LOG2_E + ROUND) - ROUND;
    let r = x - n * 0.693_359_4;
    let r = r + n * 2.121_944_4e-4;
    let p = 1.987_569_1e-4;
    let p = p * r + 1.398_199_9e-3;
    let p = p * r + 8.333_452e-3;
    let p = p * r + 4.166_579_6e-2;
    let p = p * r + 0.166_666_65;
    let p = p * r + 0.5;
    let y = p * r * r + r + 1.0;
    // 2ⁿ: n + 127 (in 1..=254) sits in the low mantissa bits of n + 127 + 1.5 · 2²³; shifted up
    // by 23 it is the exponent field (an integer conversion would not vectorise on SSE2)
    y * f32::from_bits((n + (127.0 + ROUND)).to_bits() << 23)
}

/// `erfc(z)` for `z ≥ 0`: Numerical Recipes' `erfcc`, fractional error below 1.2e-7.
#[inline(always)]
fn erfc_nonneg(z: f32) -> f32 {
    let t = 1.0 / (1.0 + 0.5 * z);
    let p = 0.170_872_77;
    let p = p * t - 0.822_152_23;
    let p = p * t + 1.488_515_9;
    let p = p * t - 1.135_204;
    let p = p * t + 0.278_868_07;
    let p = p * t - 0.186_288_06;
    let p = p * t + 0.096_784_18;
    let p = p * t + 0.374_091_96;
    let p = p * t + 1.000_023_7;
    let p = p * t - 1.265_512_2;
    t * exp_f32(p - z * z)
}

/// The standard normal CDF Φ(x), from `erfc` on both sides (no cancellation in the left tail).
#[inline(always)]
fn normal_cdf(x: f32) -> f32 {
    let half = 0.5 * erfc_nonneg(x.abs() * std::f32::consts::FRAC_1_SQRT_2);
    if x >= 0.0 { 1.0 - half } else { half }
}

/// `x Φ(x)`.
#[inline(always)]
fn gelu_f32(x: f32) -> f32 {
    x * normal_cdf(x)
}

/// `d/dx x Φ(x) = Φ(x) + x φ(x)`, `φ(x) = e^{−x²/2} / √(2π)`.
#[inline(always)]
fn gelu_derivative_f32(x: f32) -> f32 {
    const INV_SQRT_2PI: f32 = 0.398_942_3;
    normal_cdf(x) + x * INV_SQRT_2PI * exp_f32(-0.5 * x * x)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Φ in f64 through libm's `erfc` (fdlibm's, accurate to about 1 f64 ulp).
    fn cdf64(x: f64) -> f64 {
        0.5 * libm::erfc(-x / std::f64::consts::SQRT_2)
    }

    /// Over [−14, 14] in steps of 1e-4: GELU within 4e-7 absolute and 1.2e-7 · |x| beyond
    /// |x| = 1, its derivative within 3e-7 absolute.
    #[test]
    fn kernel_matches_the_exact_gelu_in_f64() {
        let (mut worst, mut worst_scaled, mut worst_grad) = (0.0f64, 0.0f64, 0.0f64);
        for i in -140_000..=140_000 {
            let x = i as f32 * 1e-4;
            let xd = x as f64;
            let cdf = cdf64(xd);
            let err = (gelu_f32(x) as f64 - xd * cdf).abs();
            worst = worst.max(err);
            worst_scaled = worst_scaled.max(err / xd.abs().max(1.0));
            let pdf = (-0.5 * xd * xd).exp() / (2.0 * std::f64::consts::PI).sqrt();
            worst_grad = worst_grad.max((gelu_derivative_f32(x) as f64 - (cdf + xd * pdf)).abs());
        }
        assert!(worst < 4e-7, "GELU absolute error {worst:.3e}");
        assert!(
            worst_scaled < 1.2e-7,
            "GELU error / max(1, |x|) {worst_scaled:.3e}"
        );
        assert!(worst_grad < 3e-7, "GELU' absolute error {worst_grad:.3e}");
    }

    /// The left tail keeps its relative accuracy (1 + erf would cancel to 0 or to noise).
    #[test]
    fn left_tail_is_relatively_accurate() {
        for x in [-4.0f32, -6.0, -8.0, -10.0] {
            let want = x as f64 * cdf64(x as f64);
            let rel = (gelu_f32(x) as f64 / want - 1.0).abs();
            assert!(rel < 2e-5, "x = {x}: relative error {rel:.3e}");
        }
    }

    /// On `flex`, with and without autodiff and on a transposed (strided) input, the values and
    /// the gradient equal burn's own GELU to f32 rounding.
    #[test]
    fn flex_tensors_match_burns_gelu_and_its_gradient() {
        let device = Device::flex();
        let x = crate::device::seeded_random(
            &device,
            1,
            [64, 96],
            burn::tensor::Distribution::Normal(0.0, 3.0),
        );
        let close = |a: Tensor<2>, b: Tensor<2>, tol: f32| {
            let a: Vec<f32> = a.into_data().try_to_vec().unwrap();
            let b: Vec<f32> = b.into_data().try_to_vec().unwrap();
            let worst = a
                .iter()
                .zip(&b)
                .map(|(a, b)| (a - b).abs() / b.abs().max(1.0))
                .fold(0.0f32, f32::max);
            assert!(worst < tol, "worst difference {worst:.3e}");
        };
        close(
            gelu(x.clone()),
            burn::tensor::activation::gelu(x.clone()),
            1e-6,
        );
        close(
            gelu(x.clone().transpose()),
            burn::tensor::activation::gelu(x.clone().transpose()),
            1e-6,
        );
        // a left-tail value that only this kernel gets right (burn's 1 + erf cancels to 0): the
        // tensor path runs it, with and without autodiff
        for dev in [device.clone(), device.clone().autodiff()] {
            let y: Vec<f32> = gelu(Tensor::<1>::from_floats([-8.0f32], &dev))
                .into_data()
                .try_to_vec()
                .unwrap();
            let want = -8.0 * cdf64(-8.0);
            assert!(
                (y[0] as f64 / want - 1.0).abs() < 2e-5,
                "{} against {want}",
                y[0]
            );
        }
        let ad = device.clone().autodiff();
        let upstream =
            crate::device::seeded_random(&ad, 2, [96, 64], burn::tensor::Distribution::Default);
        let grad_of = |f: fn(Tensor<2>) -> Tensor<2>| {
            let leaf = Tensor::<2>::from_data(x.to_data(), &ad).require_grad();
            let y = f(leaf.clone().transpose());
            let grads = (y.clone() * upstream.clone()).sum().backward();
            (y.inner(), leaf.grad(&grads).expect("gradient of the leaf"))
        };
        let (ours, ours_grad) = grad_of(gelu);
        let (burns, burns_grad) = grad_of(burn::tensor::activation::gelu);
        close(ours, burns, 1e-6);
        close(ours_grad, burns_grad, 1e-6);
    }

    /// Layer norm on `flex`, with and without autodiff and on a transposed input, against burn's:
    /// the output, and the gradients of the input, γ and β.
    #[test]
    fn flex_layer_norm_matches_burns_and_its_gradients() {
        use burn::module::Param;
        use burn::nn::LayerNormConfig;
        let ad = Device::flex().autodiff();
        let d = 48;
        let mut norm = LayerNormConfig::new(d).with_epsilon(1e-6).init(&ad);
        let random = |shape: [usize; 2], sd: f64| {
            let seed = (shape[0] * 1000 + shape[1]) as u64;
            crate::device::seeded_random(
                &ad,
                seed,
                shape,
                burn::tensor::Distribution::Normal(0.5, sd),
            )
        };
        norm.gamma = Param::from_tensor(random([1, d], 1.0).reshape([d]));
        norm.beta = Some(Param::from_tensor(random([1, d], 1.0).reshape([d])));
        let x = random([d, 100], 3.0);
        let upstream = random([100, d], 1.0);
        let run = |ours: bool| {
            let leaf = Tensor::<2>::from_data(x.to_data(), &ad).require_grad();
            let input = leaf.clone().transpose();
            let y = if ours {
                layer_norm(input, &norm, 1e-6)
            } else {
                norm.forward(input)
            };
            let grads = (y.clone() * upstream.clone()).sum().backward();
            let beta = norm.beta.as_ref().unwrap();
            let flat = |t: Tensor<2>| -> Vec<f32> { t.into_data().try_to_vec().unwrap() };
            let flat1 = |t: Tensor<1>| -> Vec<f32> { t.into_data().try_to_vec().unwrap() };
            [
                flat(y.inner()),
                flat(leaf.grad(&grads).unwrap()),
                flat1(norm.gamma.val().grad(&grads).unwrap()),
                flat1(beta.val().grad(&grads).unwrap()),
            ]
        };
        let (ours, burns) = (run(true), run(false));
        for (what, (a, b)) in ["output", "∂x", "∂γ", "∂β"]
            .iter()
            .zip(ours.iter().zip(&burns))
        {
            let scale = b.iter().fold(1.0f32, |m, v| m.max(v.abs()));
            let worst = a
                .iter()
                .zip(b)
                .map(|(a, b)| (a - b).abs())
                .fold(0.0f32, f32::max);
            assert!(worst / scale < 1e-5, "{what}: {worst:.3e} of {scale:.3e}");
        }
        // without autodiff
        let plain = Device::flex();
        let on_plain =
            |t: Tensor<1>| Param::from_tensor(Tensor::<1>::from_data(t.to_data(), &plain));
        let mut plain_norm = LayerNormConfig::new(d).with_epsilon(1e-6).init(&plain);
        plain_norm.gamma = on_plain(norm.gamma.val());
        plain_norm.beta = norm.beta.as_ref().map(|b| on_plain(b.val()));
        let norm = plain_norm;
        let x = Tensor::<2>::from_data(x.to_data(), &plain).transpose();
        let a: Vec<f32> = layer_norm(x.clone(), &norm, 1e-6)
            .into_data()
            .try_to_vec()
            .unwrap();
        let b: Vec<f32> = norm.forward(x).into_data().try_to_vec().unwrap();
        let worst = a
            .iter()
            .zip(&b)
            .map(|(a, b)| (a - b).abs())
            .fold(0.0f32, f32::max);
        assert!(worst < 1e-5, "without autodiff: {worst:.3e}");
    }
}
