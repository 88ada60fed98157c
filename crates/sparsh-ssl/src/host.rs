//! The frozen encoder's forward pass on the host CPU, for features one frame at a time at the
//! sensor's rate.
//!
//! burn `flex` runs one ViT-tiny frame (108 tokens at the CPU recipes' 96×72) as some two hundred
//! small ops, each its own trip through the rayon pool, and its matrix products pack every weight
//! matrix again at every call (a `perf` profile of one frame on two threads: 46 % GEMM
//! micro-kernel, 13 % operand packing, 12 % the pool's workers waking and waiting). Here the
//! weights are copied out of the [`Vit`] once, in `[in, out]` row-major order, which the `gemm`
//! crate reads as it is when the product is taken transposed (`Yᵀ = Wᵀ Xᵀ`: column-major `Wᵀ`,
//! at most 8 micro-tiles of tokens per call), with the layer scale folded into the
//! projections it scales (`γ ⊙ (x W + b) = x (W diag γ) + γ ⊙ b`). Each block is then two
//! parallel regions over chunks of token rows, every product in a chunk single-threaded:
//! 1. layer norm and the `qkv` projection of the chunk's tokens;
//! 2. attention of the chunk's queries over every key, the output projection and residual, layer
//!    norm, the GELU MLP and its residual.
//!
//! Layer norm, GELU and the softmax's `exp` are [`crate::kernels`]' (layer norm and GELU as in
//! training; burn's attention takes the standard library's `exp`, with a running maximum), and
//! the folded layer scale and the bias added after the product round differently: the features agree
//! with [`Vit::forward`] to float rounding (tested), and a token's features do not depend on how
//! the rows are chunked, so neither on the thread count (tested bit for bit; see `chunk_rows`).

use burn::nn::{LayerNorm, Linear};
use burn::prelude::*;
use rayon::prelude::*;

use crate::kernels::{gelu_in_place, layer_norm_rows, softmax_in_place};
use crate::vit::{Block, LN_EPS, Vit};

/// How the tokens of one sample become its features.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Pool {
    /// The mean over the patch tokens: `[dim]` per sample.
    Mean,
    /// Every patch token: `[tokens, dim]` per sample.
    None,
}

/// Token rows in one product, about at most. The GEMM reads the weights where they are when a
/// product has at most 8 micro-tiles of 6 token columns (`gemm-common`'s packing threshold, f32
/// with AVX2 or AVX-512) and packs them again at every call otherwise.
const MAX_ROWS: usize = 48;

/// Rows a chunk of `n` token rows for `tasks` parallel tasks: about [`MAX_ROWS`] at most, as
/// many chunks as a multiple of the tasks where that divides evenly enough, and never a chunk of
/// one row (unless `n` is 1).
///
/// What keeps a token's features independent of the chunking: (1) no product of one row (the
/// GEMM takes a matrix-vector kernel there, its sums in another order); (2) no product whose
/// operands are both contiguous along the summed axis (the GEMM's dot-product kernels for small
/// products; hence the transposed queries); (3) at most 64 rows a chunk: the GEMM cuts a long
/// sum into blocks of one length when both sides of its output are at most 64 and of another
/// otherwise, so a chunk of more rows could move a cut. The rest (packing, tiling) does not
/// change a sum.
fn chunk_rows(n: usize, tasks: usize) -> usize {
    let tasks = tasks.max(1);
    let mut rows = n.div_ceil(tasks * n.div_ceil(tasks * MAX_ROWS)).max(2);
    while n > 1 && n % rows == 1 {
        rows += 1;
    }
    debug_assert!(rows <= 64, "{rows} rows a chunk");
    rows
}

/// The values of a tensor on the host, row-major.
fn host<const D: usize>(t: Tensor<D>) -> Vec<f32> {
    t.into_data()
        .convert::<f32>()
        .try_to_vec::<f32>()
        .expect("f32 weights")
}

/// Layer norm's `[γ, β]` (β zero when the norm has none).
fn norm_of(norm: &LayerNorm) -> [Vec<f32>; 2] {
    let gamma = host(norm.gamma.val());
    let beta = norm
        .beta
        .as_ref()
        .map_or_else(|| vec![0.0; gamma.len()], |b| host(b.val()));
    [gamma, beta]
}

/// A linear layer's weight `[in, out]` and bias `[out]`, each output column scaled by `scale`.
fn linear_of(linear: &Linear, scale: Option<&[f32]>) -> Linear32 {
    let mut weight = host(linear.weight.val());
    let mut bias = linear
        .bias
        .as_ref()
        .map_or_else(|| vec![0.0; linear.weight.dims()[1]], |b| host(b.val()));
    if let Some(gamma) = scale {
        for row in weight.chunks_mut(gamma.len()) {
            row.iter_mut().zip(gamma).for_each(|(w, g)| *w *= g);
        }
        bias.iter_mut().zip(gamma).for_each(|(b, g)| *b *= g);
    }
    Linear32 { weight, bias }
}

/// A linear layer on the host: `weight` `[in, out]` row-major, `bias` `[out]`.
#[derive(Debug, Clone)]
struct Linear32 {
    weight: Vec<f32>,
    bias: Vec<f32>,
}

impl Linear32 {
    fn outputs(&self) -> usize {
        self.bias.len()
    }

    /// `y = x W + b` for the rows of `x` (`y` is overwritten).
    fn forward(&self, x: &[f32], y: &mut [f32]) {
        let out = self.outputs();
        y.chunks_mut(out)
            .for_each(|r| r.copy_from_slice(&self.bias));
        self.accumulate(x, y);
    }

    /// `y += x W`, then `y += b`.
    fn add_forward(&self, x: &[f32], y: &mut [f32]) {
        self.accumulate(x, y);
        y.chunks_mut(self.outputs())
            .for_each(|r| r.iter_mut().zip(&self.bias).for_each(|(y, b)| *y += b));
    }

    /// `y += x W` over the rows of `x` and `y`.
    fn accumulate(&self, x: &[f32], y: &mut [f32]) {
        let out = self.outputs();
        let inp = self.weight.len() / out;
        let rows = y.len() / out;
        assert!(x.len() == rows * inp && y.len() == rows * out);
        // SAFETY: the three row-major matrices are in bounds by the assertion above
        // (rows × inp, inp × out, rows × out), and `y` does not alias `x` or the weight.
        unsafe {
            product(
                [rows, out, inp],
                (y.as_mut_ptr(), [out, 1]),
                (x.as_ptr(), [inp, 1]),
                (self.weight.as_ptr(), [out, 1]),
                1.0,
                true,
            )
        }
    }
}

/// `dst (+)= scale · lhs · rhs` for `[m, n, k]` matrices given as (pointer, `[row stride, column
/// stride]`), single-threaded; `dst` is read when `accumulate`.
///
/// # Safety
/// Every element the strides reach is in bounds, and `dst` aliases neither operand.
unsafe fn product(
    [m, n, k]: [usize; 3],
    (dst, [dst_rs, dst_cs]): (*mut f32, [usize; 2]),
    (lhs, [lhs_rs, lhs_cs]): (*const f32, [usize; 2]),
    (rhs, [rhs_rs, rhs_cs]): (*const f32, [usize; 2]),
    scale: f32,
    accumulate: bool,
) {
    // SAFETY: forwarded from the caller.
    unsafe {
        gemm::gemm(
            m,
            n,
            k,
            dst,
            dst_cs as isize,
            dst_rs as isize,
            accumulate,
            lhs,
            lhs_cs as isize,
            lhs_rs as isize,
            rhs,
            rhs_cs as isize,
            rhs_rs as isize,
            1.0,
            scale,
            false,
            false,
            false,
            gemm::Parallelism::None,
        )
    }
}

/// One transformer block on the host (layer scale folded into `proj` and `fc2`).
#[derive(Debug, Clone)]
struct Block32 {
    norm1: [Vec<f32>; 2],
    qkv: Linear32,
    proj: Linear32,
    norm2: [Vec<f32>; 2],
    fc1: Linear32,
    fc2: Linear32,
    heads: usize,
}

impl Block32 {
    fn of(block: &Block) -> Self {
        let gamma = |g: &Option<burn::module::Param<Tensor<1>>>| g.as_ref().map(|g| host(g.val()));
        let (ls1, ls2) = (gamma(&block.ls1), gamma(&block.ls2));
        Self {
            norm1: norm_of(&block.norm1),
            qkv: linear_of(&block.attn.qkv, None),
            proj: linear_of(&block.attn.proj, ls1.as_deref()),
            norm2: norm_of(&block.norm2),
            fc1: linear_of(&block.mlp.fc1, None),
            fc2: linear_of(&block.mlp.fc2, ls2.as_deref()),
            heads: block.attn.num_heads,
        }
    }

    /// Step (2) of a block for the rows `first..` of `x` (`xs`), from every token's `qkv`.
    fn rest(&self, qkv: &[f32], first: usize, xs: &mut [f32], s: &mut Scratch, n: usize) {
        let dim = self.norm1[0].len();
        let rows = xs.len() / dim;
        let dh = dim / self.heads;
        let scale = 1.0 / (dh as f32).sqrt();
        let attended = &mut s.attended[..rows * dim];
        let weights = &mut s.weights[..rows * n];
        let queries = &mut s.queries[..rows * dh];
        for h in 0..self.heads {
            // the chunk's queries of head h transposed, `[dh, rows]`: with both operands
            // contiguous along d, a small product would take the GEMM's dot-product kernels,
            // whose sums run in another order than the chunk of another size would get
            for (q, row) in qkv[first * 3 * dim..]
                .chunks(3 * dim)
                .take(rows)
                .enumerate()
            {
                for (d, &v) in row[h * dh..(h + 1) * dh].iter().enumerate() {
                    queries[d * rows + q] = v;
                }
            }
            let k = &qkv[dim + h * dh..];
            let v = &qkv[2 * dim + h * dh..];
            assert!(v.len() >= (n - 1) * 3 * dim + dh);
            // SAFETY: queries is rows × dh (column-major), kᵀ dh × n and v n × dh at row stride
            // 3·dim, all in `qkv` by the assertion (k starts before v); weights is rows × n;
            // attended rows × dim.
            unsafe {
                // scores = q kᵀ / √d_head
                product(
                    [rows, n, dh],
                    (weights.as_mut_ptr(), [n, 1]),
                    (queries.as_ptr(), [1, rows]),
                    (k.as_ptr(), [1, 3 * dim]),
                    scale,
                    false,
                );
            }
            weights.chunks_mut(n).for_each(softmax_in_place);
            // SAFETY: as above.
            unsafe {
                product(
                    [rows, dh, n],
                    (attended.as_mut_ptr().add(h * dh), [dim, 1]),
                    (weights.as_ptr(), [n, 1]),
                    (v.as_ptr(), [3 * dim, 1]),
                    1.0,
                    false,
                );
            }
        }
        self.proj.add_forward(attended, xs);
        let normed = &mut s.normed[..rows * dim];
        norm_rows(xs, &self.norm2, normed, &mut s.stats, &s.ones);
        let hidden = &mut s.hidden[..rows * self.fc1.outputs()];
        self.fc1.forward(normed, hidden);
        gelu_in_place(hidden);
        self.fc2.add_forward(hidden, xs);
    }
}

/// A [`Vit`]'s weights on the host, laid out for [`HostVit::embed`].
#[derive(Debug, Clone)]
pub struct HostVit {
    patch_embed: Linear32,
    /// Position embedding `[tokens, dim]`.
    pos_embed: Vec<f32>,
    /// Register tokens `[registers, dim]`.
    registers: Vec<f32>,
    blocks: Vec<Block32>,
    norm: [Vec<f32>; 2],
    /// Patch-token grid `[frames / tubelet, rows, columns]`.
    grid: [usize; 3],
    patch_size: usize,
    tubelet_size: usize,
}

/// Work buffers of one chunk of token rows.
struct Scratch {
    /// Layer-normalized rows `[rows, dim]`.
    normed: Vec<f32>,
    /// Attention output `[rows, dim]`, all heads.
    attended: Vec<f32>,
    /// Attention weights of one head `[rows, tokens]`.
    weights: Vec<f32>,
    /// One head's queries `[d_head, rows]`.
    queries: Vec<f32>,
    /// MLP hidden layer `[rows, hidden]`.
    hidden: Vec<f32>,
    /// Layer norm's per-row statistics `[rows, 2]`.
    stats: Vec<f32>,
    /// `[dim]` ones (layer norm's row sums are dot products with them).
    ones: Vec<f32>,
}

impl HostVit {
    /// The weights of `vit` copied to the host.
    pub fn new(vit: &Vit) -> Self {
        let tokens = vit.pos_embed.dims()[1];
        let grid = match vit.pos_grid[..] {
            [gh, gw] => [1, gh, gw],
            [gt, gh, gw] => [gt, gh, gw],
            _ => unreachable!("position grids have 2 or 3 axes"),
        };
        debug_assert_eq!(grid.iter().product::<usize>(), tokens);
        Self {
            patch_embed: linear_of(&vit.patch_embed, None),
            pos_embed: host(vit.pos_embed.clone()),
            registers: vit
                .register_tokens
                .as_ref()
                .map_or_else(Vec::new, |r| host(r.val())),
            blocks: vit.blocks.iter().map(Block32::of).collect(),
            norm: norm_of(&vit.norm),
            grid,
            patch_size: vit.patch_size,
            tubelet_size: vit.tubelet_size,
        }
    }

    /// Token width.
    pub fn dim(&self) -> usize {
        self.norm[0].len()
    }

    /// Patch tokens per sample.
    pub fn tokens(&self) -> usize {
        self.grid.iter().product()
    }

    fn patch_dim(&self) -> usize {
        self.patch_embed.weight.len() / self.dim()
    }

    /// Features of `samples` clips `[frames, channels, height, width]` concatenated in `inputs`
    /// (the input of [`Vit::forward`]), concatenated in the same order: `[dim]` per sample
    /// pooled, else `[tokens, dim]`. Fewer samples than threads split each sample's tokens over
    /// the pool; at least as many run one sample per task.
    ///
    /// # Panics
    /// When `inputs` is not a whole number of samples of `sample_shape`, or that shape is not the
    /// encoder's input.
    pub fn embed(&self, inputs: &[f32], sample_shape: [usize; 4], pool: Pool) -> Vec<f32> {
        let len: usize = sample_shape.iter().product();
        assert!(len > 0, "empty sample shape {sample_shape:?}");
        let samples = inputs.len() / len;
        assert_eq!(samples * len, inputs.len(), "whole samples");
        let threads = rayon::current_num_threads();
        let per = match pool {
            Pool::Mean => self.dim(),
            Pool::None => self.tokens() * self.dim(),
        };
        let mut out = vec![0.0; samples * per];
        if samples >= threads {
            out.par_chunks_mut(per)
                .zip(inputs.par_chunks(len))
                .for_each(|(o, x)| self.sample(x, sample_shape, 1, pool, o));
        } else {
            for (o, x) in out.chunks_mut(per).zip(inputs.chunks(len)) {
                self.sample(x, sample_shape, threads, pool, o);
            }
        }
        out
    }

    /// One sample's features into `out`, its token rows split into chunks for `tasks` parallel
    /// tasks.
    fn sample(
        &self,
        input: &[f32],
        [frames, channels, height, width]: [usize; 4],
        tasks: usize,
        pool: Pool,
        out: &mut [f32],
    ) {
        let (dim, r, tokens) = (self.dim(), self.registers.len() / self.dim(), self.tokens());
        let [gt, gh, gw] = self.grid;
        let (p, tube) = (self.patch_size, self.tubelet_size);
        let pd = self.patch_dim();
        assert_eq!(
            [frames, height, width, channels * tube * p * p],
            [gt * tube, gh * p, gw * p, pd],
            "input shape"
        );
        let n = r + tokens;
        let rows = chunk_rows(n, tasks);
        let hidden = self.blocks.first().map_or(0, |b| b.fc1.outputs());
        let mut scratch: Vec<Scratch> = (0..n.div_ceil(rows))
            .map(|_| Scratch {
                normed: vec![0.0; rows * dim],
                attended: vec![0.0; rows * dim],
                weights: vec![0.0; rows * n],
                queries: vec![0.0; rows * dim],
                hidden: vec![0.0; rows * hidden],
                stats: vec![0.0; rows * 2],
                ones: vec![1.0; dim],
            })
            .collect();

        // patch embedding: flattened patches (channel, frame, row, column) → tokens + positions,
        // in chunks of the patch tokens' own (registers would leave a chunk of one token)
        let mut patches = vec![0.0f32; tokens * pd];
        patches.par_chunks_mut(pd).enumerate().for_each(|(t, dst)| {
            let (ft, y, xg) = (t / (gh * gw), t / gw % gh, t % gw);
            let mut k = 0;
            for ch in 0..channels {
                for f in ft * tube..(ft + 1) * tube {
                    for py in 0..p {
                        let at = ((f * channels + ch) * height + y * p + py) * width + xg * p;
                        dst[k..k + p].copy_from_slice(&input[at..at + p]);
                        k += p;
                    }
                }
            }
        });
        let mut x = vec![0.0f32; n * dim];
        x[..r * dim].copy_from_slice(&self.registers);
        let token_rows = chunk_rows(tokens, tasks);
        x[r * dim..]
            .par_chunks_mut(token_rows * dim)
            .zip(patches.par_chunks(token_rows * pd))
            .zip(self.pos_embed.par_chunks(token_rows * dim))
            .for_each(|((ys, patches), pos)| {
                self.patch_embed.forward(patches, ys);
                ys.iter_mut().zip(pos).for_each(|(y, e)| *y += e);
            });

        let mut qkv = vec![0.0f32; n * 3 * dim];
        for block in &self.blocks {
            // (1) norm and qkv of each chunk's rows
            qkv.par_chunks_mut(rows * 3 * dim)
                .zip(x.par_chunks(rows * dim))
                .zip(scratch.par_iter_mut())
                .for_each(|((q, xs), s)| {
                    let normed = &mut s.normed[..xs.len()];
                    norm_rows(xs, &block.norm1, normed, &mut s.stats, &s.ones);
                    block.qkv.forward(normed, q);
                });
            // (2) attention of the chunk's queries, projection, MLP, both residuals
            x.par_chunks_mut(rows * dim)
                .zip(scratch.par_iter_mut())
                .enumerate()
                .for_each(|(c, (xs, s))| block.rest(&qkv, c * rows, xs, s, n));
        }

        // final norm of the patch tokens (registers dropped), pooled or not
        let (_, patches) = x.split_at(r * dim);
        let mut normed = vec![0.0f32; tokens * dim];
        let mut stats = vec![0.0f32; tokens * 2];
        norm_rows(
            patches,
            &self.norm,
            &mut normed,
            &mut stats,
            &vec![1.0; dim],
        );
        match pool {
            Pool::None => out.copy_from_slice(&normed),
            Pool::Mean => {
                out.fill(0.0);
                for row in normed.chunks(dim) {
                    out.iter_mut().zip(row).for_each(|(o, v)| *o += v);
                }
                out.iter_mut().for_each(|o| *o /= tokens as f32);
            }
        }
    }
}

/// Layer norm (ε [`LN_EPS`]) of the rows of `x` into `out`; `stats` takes each row's mean and
/// inverse deviation, `ones` is `[dim]` ones.
fn norm_rows(
    x: &[f32],
    [gamma, beta]: &[Vec<f32>; 2],
    out: &mut [f32],
    stats: &mut [f32],
    ones: &[f32],
) {
    let rows = x.len() / gamma.len();
    layer_norm_rows(
        out,
        &mut stats[..rows * 2],
        x,
        [gamma, beta, ones],
        LN_EPS as f32,
    );
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::embed::encode;
    use crate::vit::VitConfig;

    fn pool(threads: usize) -> rayon::ThreadPool {
        rayon::ThreadPoolBuilder::new()
            .num_threads(threads)
            .build()
            .unwrap()
    }

    /// Random weights, then layer scales, norms' β and registers drawn away from their
    /// initial values (ones, zeros, near-zeros) so that a term dropped in the host pass shows.
    fn encoder(cfg: &VitConfig) -> Vit {
        use burn::module::Param;
        use burn::tensor::Distribution;
        let device = Device::flex();
        crate::device::seeded_module(&device, 4, || {
            let mut vit = cfg.init(&device);
            let draw =
                |dims: usize| Tensor::<1>::random([dims], Distribution::Uniform(0.5, 1.5), &device);
            let d = cfg.embed_dim;
            for b in &mut vit.blocks {
                if b.ls1.is_some() {
                    b.ls1 = Some(Param::from_tensor(draw(d)));
                    b.ls2 = Some(Param::from_tensor(draw(d)));
                }
                b.norm2.beta = Some(Param::from_tensor(draw(d) - 1.0));
            }
            vit.norm.gamma = Param::from_tensor(draw(d));
            if let Some(r) = &vit.register_tokens {
                let dims = r.dims();
                vit.register_tokens = Some(Param::from_tensor(Tensor::random(
                    dims,
                    Distribution::Normal(0.0, 1.0),
                    &device,
                )));
            }
            vit
        })
    }

    /// The host pass against burn's graph ([`Vit::forward`] through [`encode`]) for an image
    /// encoder with registers and layer scale, a V-JEPA clip encoder (tubelets of 2 frames) and
    /// an encoder of one token, pooled and not, at batch 1 and 3; and bit for bit the same on
    /// pools of 1, 2, 3, 16 and 40 threads (chunks of 2 to 49 rows, the registers filling whole
    /// chunks on the largest pools).
    #[test]
    fn host_features_match_burns_graph_and_not_the_thread_count() {
        // 96 tokens and 4 registers; a hidden layer of 576 (a sum over k = 576 in the second MLP
        // layer, longer than one of the GEMM's blocks)
        let image = VitConfig::new([48, 32], 4)
            .with_mlp_ratio(12.0)
            .with_embed_dim(48)
            .with_depth(2)
            .with_num_heads(3)
            .with_num_registers(4)
            .with_layer_scale(Some(1.0));
        let clip = VitConfig::new([16, 12], 4)
            .with_in_chans(3)
            .with_num_frames(4)
            .with_tubelet_size(2)
            .with_embed_dim(32)
            .with_depth(2)
            .with_num_heads(4);
        let one_token = VitConfig::new([4, 4], 4)
            .with_embed_dim(16)
            .with_depth(1)
            .with_num_heads(2);
        for cfg in [image, clip, one_token] {
            let vit = encoder(&cfg);
            let frozen = HostVit::new(&vit);
            let shape = [
                cfg.num_frames,
                cfg.in_chans,
                cfg.img_size[0],
                cfg.img_size[1],
            ];
            let len: usize = shape.iter().product();
            for batch in [1, 3] {
                let x = crate::device::seeded_random(
                    &Device::flex(),
                    batch as u64,
                    [batch, shape[0], shape[1], shape[2], shape[3]],
                    burn::tensor::Distribution::Normal(0.0, 1.0),
                );
                let inputs = host(x.clone().reshape([batch * len]));
                for p in [Pool::None, Pool::Mean] {
                    let want = pool(1).install(|| encode(&vit, x.clone(), p));
                    let got = pool(1).install(|| frozen.embed(&inputs, shape, p));
                    assert_eq!(got.len(), want.len());
                    let diff = got
                        .iter()
                        .zip(&want)
                        .fold(0f32, |m, (a, b)| m.max((a - b).abs()));
                    let scale = want.iter().fold(0f32, |m, v| m.max(v.abs()));
                    assert!(
                        diff <= 2e-5 * scale,
                        "{p:?}, batch {batch}: off by {diff:e} (scale {scale})"
                    );
                    for threads in [2, 3, 16, 40] {
                        let again = pool(threads).install(|| frozen.embed(&inputs, shape, p));
                        assert!(
                            again
                                .iter()
                                .zip(&got)
                                .all(|(a, b)| a.to_bits() == b.to_bits()),
                            "{p:?}, batch {batch}: {threads} threads change the bits"
                        );
                    }
                }
            }
        }
    }
}
