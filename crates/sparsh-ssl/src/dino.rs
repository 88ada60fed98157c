//! DINO (Caron et al. 2021) as configured by Sparsh: views are token crops of one image, the
//! first register token stands in for `[cls]`, a 3-layer projection head ends in weight-normalized
//! prototypes, the teacher is an EMA of the student, its outputs are centred and sharpened.

use burn::module::Param;
use burn::nn::{Linear, LinearConfig};
use burn::prelude::*;
use burn::tensor::activation::{log_softmax, softmax};

use crate::ema::ema_update;
use crate::kernels::gelu;
use crate::masks::DinoViews;
use crate::vit::{Vit, VitConfig, VitOutput, batch_standardize, gather_tokens, index_tensor};

/// Configuration of [`Dino`] (official: hidden 2048, bottleneck 256, 65 536 prototypes,
/// student temperature 0.1, centre momentum 0.9).
#[derive(Config, Debug)]
pub struct DinoConfig {
    /// The encoder; needs at least one register token.
    pub encoder: VitConfig,
    /// Hidden width of the projection head.
    #[config(default = 2048)]
    pub head_hidden: usize,
    /// Bottleneck width before the prototypes.
    #[config(default = 256)]
    pub head_bottleneck: usize,
    /// Number of prototypes (output dimension).
    #[config(default = 65536)]
    pub num_prototypes: usize,
    /// Student softmax temperature.
    #[config(default = 0.1)]
    pub student_temp: f64,
    /// Momentum of the teacher-output centre.
    #[config(default = 0.9)]
    pub center_momentum: f64,
    /// Batch normalization after the two hidden layers of the head (DINO's `use_bn_in_head`).
    #[config(default = false)]
    pub head_batch_norm: bool,
    /// Weight of the KoLeo term on the student's `[cls]` features, summed over the global views
    /// (DINOv2: 0.1; DINO: 0).
    #[config(default = 0.0)]
    pub koleo_weight: f64,
    /// How the teacher's prototype scores become targets.
    #[config(default = "TeacherNorm::Center")]
    pub teacher_norm: TeacherNorm,
    /// Weight of the iBOT masked-patch term (DINOv2: 1; DINO: 0). Needs masked global views
    /// and `TeacherNorm::Batch`.
    #[config(default = 0.0)]
    pub ibot_weight: f64,
}

/// How the teacher's prototype scores are normalized before its sharpened softmax.
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum TeacherNorm {
    /// Minus a running centre of the teacher outputs (official DINO).
    Center,
    /// Each prototype's score standardized over the step's teacher batch (all global views):
    /// `(t − mean_b t) / std_b t`. The centre only removes the shared part, so when the samples
    /// differ by little (difference images: mostly flat background) the centred scores are
    /// nearly equal and the teacher's softmax nearly uniform, and the student follows it there;
    /// standardized scores keep the sample-specific part at unit scale, so the teacher stays
    /// sharp and every prototype is high for some samples. Use a temperature near 0.25.
    Batch,
}

/// Batch normalization of a head layer with the batch's own statistics (the head only runs in
/// training, so no running statistics are kept): `γ · (x − mean) / √(var + 1e-5) + β`, mean and
/// variance over the batch.
#[derive(Module, Debug)]
pub struct HeadNorm {
    /// Scale `[width]`.
    pub gamma: Param<Tensor<1>>,
    /// Shift `[width]`.
    pub beta: Param<Tensor<1>>,
}

impl HeadNorm {
    fn new(width: usize, device: &Device) -> Self {
        Self {
            gamma: Param::from_tensor(Tensor::ones([width], device)),
            beta: Param::from_tensor(Tensor::zeros([width], device)),
        }
    }

    /// # Shapes
    /// - `x`: `[batch, width]` → `[batch, width]`
    pub fn forward(&self, x: Tensor<2>) -> Tensor<2> {
        let c = x.clone() - x.mean_dim(0);
        let var = c.clone().powi_scalar(2).mean_dim(0);
        c / (var + 1e-5).sqrt() * self.gamma.val().unsqueeze() + self.beta.val().unsqueeze()
    }
}

/// `x / max(‖x‖₂, 1e-12)` along `dim` (`F.normalize`).
fn l2_normalize(x: Tensor<2>, dim: usize) -> Tensor<2> {
    let norm = x
        .clone()
        .powi_scalar(2)
        .sum_dim(dim)
        .sqrt()
        .clamp_min(1e-12);
    x / norm
}

/// The DINO projection head: `Linear → [BN] → GELU → Linear → [BN] → GELU → Linear`,
/// ℓ2-normalize, then prototypes with unit-norm columns (weight normalization with the gain
/// fixed to 1).
#[derive(Module, Debug)]
pub struct DinoHead {
    /// The three MLP layers.
    pub mlp: Vec<Linear>,
    /// Batch norms after the hidden layers (empty without `head_batch_norm`).
    pub norms: Vec<HeadNorm>,
    /// Prototype directions `[bottleneck, prototypes]`, normalized per column in the forward.
    pub last_layer: Param<Tensor<2>>,
}

impl DinoHead {
    /// Prototype scores.
    ///
    /// # Shapes
    /// - `x`: `[batch, dim]` → `[batch, prototypes]`
    pub fn forward(&self, x: Tensor<2>) -> Tensor<2> {
        let n = self.mlp.len();
        let mut x = x;
        for (i, layer) in self.mlp.iter().enumerate() {
            x = layer.forward(x);
            if let Some(norm) = self.norms.get(i) {
                x = norm.forward(x);
            }
            if i + 1 < n {
                x = gelu(x);
            }
        }
        l2_normalize(x, 1).matmul(l2_normalize(self.last_layer.val(), 0))
    }
}

/// DINO student and teacher.
#[derive(Module, Debug)]
pub struct Dino {
    /// The encoder being pretrained.
    pub encoder: Vit,
    /// Student head.
    pub head: DinoHead,
    /// Teacher encoder (EMA, no gradient).
    pub teacher_encoder: Vit,
    /// Teacher head (EMA, no gradient).
    pub teacher_head: DinoHead,
    /// Running centre of the teacher outputs `[1, prototypes]` (no gradient).
    pub center: Param<Tensor<2>>,
    /// Student temperature.
    #[module(skip)]
    pub student_temp: f64,
    /// Centre momentum.
    #[module(skip)]
    pub center_momentum: f64,
    /// Weight of the KoLeo term.
    #[module(skip)]
    pub koleo_weight: f64,
    /// Teacher score normalization.
    #[module(skip)]
    pub teacher_norm: TeacherNorm,
    /// Learned token `[1, 1, dim]` the student sees at masked positions (iBOT only).
    pub mask_token: Option<Param<Tensor<3>>>,
    /// Weight of the iBOT term.
    #[module(skip)]
    pub ibot_weight: f64,
}

impl DinoConfig {
    fn head(&self, device: &Device) -> DinoHead {
        let dims = [
            self.encoder.embed_dim,
            self.head_hidden,
            self.head_hidden,
            self.head_bottleneck,
        ];
        DinoHead {
            mlp: dims
                .windows(2)
                .map(|w| LinearConfig::new(w[0], w[1]).init(device))
                .collect(),
            norms: if self.head_batch_norm {
                (0..2)
                    .map(|_| HeadNorm::new(self.head_hidden, device))
                    .collect()
            } else {
                Vec::new()
            },
            last_layer: Param::from_tensor(Tensor::random(
                [self.head_bottleneck, self.num_prototypes],
                burn::tensor::Distribution::Normal(0.0, 0.02),
                device,
            )),
        }
    }

    /// Initialize a [`Dino`]; the teacher starts as a copy of the student.
    pub fn init(&self, device: &Device) -> Dino {
        let encoder = self.encoder.init(device);
        let head = self.head(device);
        let teacher_encoder = ema_update(self.encoder.init(device), &encoder, 0.0).no_grad();
        let teacher_head = ema_update(self.head(device), &head, 0.0).no_grad();
        Dino {
            encoder,
            head,
            teacher_encoder,
            teacher_head,
            center: Param::from_tensor(Tensor::zeros([1, self.num_prototypes], device))
                .set_require_grad(false),
            student_temp: self.student_temp,
            center_momentum: self.center_momentum,
            koleo_weight: self.koleo_weight,
            teacher_norm: self.teacher_norm,
            mask_token: (self.ibot_weight > 0.0).then(|| {
                Param::from_tensor(Tensor::random(
                    [1, 1, self.encoder.embed_dim],
                    burn::tensor::Distribution::Normal(0.0, 0.02),
                    device,
                ))
            }),
            ibot_weight: self.ibot_weight,
        }
    }
}

/// KoLeo regularizer (Sablayrolles et al. 2019, as in DINOv2's `KoLeoLoss`):
/// −mean_i ln(‖x̂_i − x̂_{n(i)} + 1e-8‖ + 1e-8) over the rows x̂ = x / max(‖x‖, 1e-8) of `x`, n(i)
/// the row of largest dot product with x̂_i other than itself; it grows without bound as rows
/// coincide, so it pushes a collapsing batch apart.
///
/// # Shapes
/// - `x`: `[batch, dim]` (batch ≥ 2) → `[1]`
pub fn koleo(x: Tensor<2>) -> Tensor<1> {
    let [n, _] = x.dims();
    let device = x.device();
    let norm = x.clone().powi_scalar(2).sum_dim(1).sqrt().clamp_min(1e-8);
    let unit = x / norm;
    // the nearest neighbour by the largest dot product (the diagonal lifted out of the way), then
    // its distance from the difference itself, as DINOv2's pdist does: 2 − 2·x̂_i·x̂_j cannot
    // resolve rows closer than ~1e-4 in f32, the case the term is there for
    let dots = unit.clone().matmul(unit.clone().transpose())
        - Tensor::<2>::eye(n, &device).mul_scalar(4.0);
    let nearest = unit.clone().select(0, dots.argmax(1).reshape([n]));
    let distance = (unit - nearest)
        .add_scalar(1e-8)
        .powi_scalar(2)
        .sum_dim(1)
        .sqrt();
    distance.add_scalar(1e-8).log().mean().neg()
}

/// The teacher's target distribution from its prototype scores `t` (`[rows, prototypes]`):
/// centred and sharpened, `softmax((t − centre) / τ)` (Caron et al. 2021, §3.1), or, under
/// [`TeacherNorm::Batch`], `softmax((t − mean_rows t) / √(var_rows t + 1e-8) / τ)` (variance
/// over the rows, biased).
pub fn teacher_targets(
    t: Tensor<2>,
    center: Tensor<2>,
    norm: TeacherNorm,
    temperature: f64,
) -> Tensor<2> {
    let scores = match norm {
        TeacherNorm::Center => t - center,
        TeacherNorm::Batch => {
            let [n, k] = t.dims();
            batch_standardize(t.reshape([n, 1, k])).reshape([n, k])
        }
    };
    softmax(scores.div_scalar(temperature), 1)
}

/// `−mean_rows Σ_k p_t · log p_s` for target distributions `t_prob` and student log-probabilities
/// `s_logp` (`[rows, prototypes]` both).
fn soft_cross_entropy(t_prob: Tensor<2>, s_logp: Tensor<2>) -> Tensor<1> {
    (t_prob * s_logp).sum_dim(1).mean().neg()
}

/// Cross-entropy of the student's sharpened scores `s` against the targets `t_prob`, averaged
/// over the rows (`[rows, prototypes]` both): `−mean_rows Σ_k p_t · log_softmax(s / τ_s)`. The
/// iBOT term of DINOv2 (Zhou et al. 2022, the masked-image-modelling loss L_MIM) on the masked
/// tokens; with the same number of masked tokens in every view, the mean over all of them is
/// DINOv2's per-image mean.
pub fn cross_entropy(t_prob: Tensor<2>, s: Tensor<2>, student_temp: f64) -> Tensor<1> {
    soft_cross_entropy(t_prob, log_softmax(s.div_scalar(student_temp), 1))
}

/// DINO's multi-view loss (Caron et al. 2021, eq. 3 and Algorithm 1, `DINOLoss` of the DINO
/// code): the teacher targets `t_prob` of the `g` global views (`[g · batch, prototypes]`, view
/// by view) against the student scores `s` of every view (`[views · batch, prototypes]`, the
/// global views first), over the pairs of different views:
///
/// ```text
/// loss = mean_{i < g, v ≠ i} mean_batch( −Σ_k P_t,i · log_softmax(s_v / τ_s) )
/// ```
pub fn dino_cross_entropy(
    t_prob: Tensor<2>,
    s: Tensor<2>,
    batch: usize,
    student_temp: f64,
) -> Tensor<1> {
    let g = t_prob.dims()[0] / batch;
    let s_logp = log_softmax(s.div_scalar(student_temp), 1);
    let n_views = s_logp.dims()[0] / batch;
    let mut total: Option<Tensor<1>> = None;
    let mut pairs = 0;
    for i in 0..g {
        let t = t_prob.clone().narrow(0, i * batch, batch);
        for v in (0..n_views).filter(|&v| v != i) {
            let ce = soft_cross_entropy(t.clone(), s_logp.clone().narrow(0, v * batch, batch));
            total = Some(match total {
                Some(acc) => acc + ce,
                None => ce,
            });
            pairs += 1;
        }
    }
    total.expect("at least two views").div_scalar(pairs as f64)
}

/// DINO's centre update (Caron et al. 2021, eq. 4): `c ← m · c + (1 − m) · mean_batch t`, with
/// `teacher_mean` the teacher scores' mean over the step's rows (`[1, prototypes]` both).
pub fn updated_center(center: Tensor<2>, teacher_mean: Tensor<2>, momentum: f64) -> Tensor<2> {
    (center.mul_scalar(momentum) + teacher_mean.mul_scalar(1.0 - momentum)).detach()
}

/// The tokens of each view of each sample, `[views × batch, k, dim]`.
fn view_tokens(tokens: Tensor<3>, views: &[Vec<Vec<usize>>]) -> Tensor<3> {
    let device = tokens.device();
    let rows: Vec<Vec<usize>> = views.iter().flatten().cloned().collect();
    let batch = tokens.repeat_dim(0, views.len());
    gather_tokens(batch, index_tensor(&rows, &device))
}

/// The `[cls]` (first register token) `[rows, dim]` of encoded views.
fn cls(out: &VitOutput) -> Tensor<2> {
    let reg = out
        .registers
        .clone()
        .expect("DINO encoder has a register token");
    let [b, _, d] = reg.dims();
    reg.narrow(1, 0, 1).reshape([b, d])
}

/// iBOT masking: the view tokens `tokens` (`[rows, k, dim]`, from positions `views`) with the
/// positions `masked` (`[rows, m]`, within each view) replaced by `mask_token` plus their
/// position embedding.
fn mask_view_tokens(
    tokens: Tensor<3>,
    pos_embed: Tensor<3>,
    views: &[Vec<Vec<usize>>],
    masked: &[Vec<usize>],
    mask_token: Tensor<3>,
) -> Tensor<3> {
    let [rows, k, d] = tokens.dims();
    let device = tokens.device();
    let mut keep = vec![1.0f32; rows * k];
    for (r, m) in masked.iter().enumerate() {
        for &i in m {
            keep[r * k + i] = 0.0;
        }
    }
    let keep = Tensor::<1>::from_floats(keep.as_slice(), &device).reshape([rows, k, 1]);
    let n = pos_embed.dims()[1];
    let pos = view_tokens(
        pos_embed
            .to_device(&device)
            .expand([rows / views.len(), n, d]),
        views,
    );
    let fill = mask_token.expand([rows, k, d]) + pos;
    tokens * keep.clone() + fill * keep.neg().add_scalar(1.0)
}

impl Dino {
    /// Cross-entropy between the sharpened, centred teacher distribution of each global view and
    /// the student distribution of every other view; also returns the teacher's mean output for
    /// the centre update.
    ///
    /// ```text
    /// P_t = softmax((t − c) / τ_t)  [TeacherNorm::Batch: softmax(standardize_batch(t) / τ_t)]
    /// log P_s = log_softmax(s / τ_s)
    /// loss = mean_{i ∈ global, v ≠ i} mean_batch( −Σ_k P_t,i · log P_s,v )
    ///        + koleo_weight · Σ_{i ∈ global} KoLeo(student [cls] of view i)   (as DINOv2)
    ///        + ibot_weight · mean_{masked tokens} ( −Σ_k P_t,patch · log P_s,patch )  (iBOT)
    /// ```
    /// iBOT (Zhou et al. 2022, in DINOv2): the student sees each global view with the positions
    /// `views.masked` replaced by a learned mask token; at those positions its patch outputs,
    /// through the shared head, match the teacher's on the unmasked view (patch scores
    /// standardized over the step's masked tokens).
    ///
    /// # Shapes
    /// - `x`: `[batch, frames, channels, height, width]`
    /// - output: loss `[1]`, teacher mean `[1, prototypes]`
    pub fn loss(
        &self,
        x: Tensor<5>,
        views: &DinoViews,
        teacher_temp: f64,
    ) -> (Tensor<1>, Tensor<2>) {
        let b = x.dims()[0];
        let device = x.device();
        let g = views.global.len();
        let student_tokens = self.encoder.embed(x.clone());
        let teacher_tokens = self.teacher_encoder.embed(x.detach()).detach();
        let t_views = self
            .teacher_encoder
            .forward_tokens(view_tokens(teacher_tokens, &views.global));
        let t_out = self.teacher_head.forward(cls(&t_views)).detach();
        let t_mean = t_out.clone().mean_dim(0);
        let t_prob = teacher_targets(t_out, self.center.val(), self.teacher_norm, teacher_temp);
        let masked: Vec<Vec<usize>> = views.masked.iter().flatten().cloned().collect();
        let mut s_tokens = view_tokens(student_tokens.clone(), &views.global);
        if let (Some(token), false) = (&self.mask_token, masked.is_empty()) {
            s_tokens = mask_view_tokens(
                s_tokens,
                self.encoder.pos_embed.clone(),
                &views.global,
                &masked,
                token.val(),
            );
        }
        let s_views = self.encoder.forward_tokens(s_tokens);
        let s_cls = cls(&s_views);
        let s_global = self.head.forward(s_cls.clone());
        let mut s_all = vec![s_global];
        if !views.local.is_empty() {
            let local = view_tokens(student_tokens, &views.local);
            s_all.push(self.head.forward(cls(&self.encoder.forward_tokens(local))));
        }
        let mut loss = dino_cross_entropy(t_prob, Tensor::cat(s_all, 0), b, self.student_temp);
        if self.ibot_weight > 0.0 && !masked.is_empty() {
            let idx = index_tensor(&masked, &device);
            let rows = |patches: Tensor<3>| {
                let picked = gather_tokens(patches, idx.clone());
                let [r, m, d] = picked.dims();
                picked.reshape([r * m, d])
            };
            let t_patch = self.teacher_head.forward(rows(t_views.patches)).detach();
            let t_patch =
                teacher_targets(t_patch, self.center.val(), TeacherNorm::Batch, teacher_temp);
            let s_patch = self.head.forward(rows(s_views.patches));
            let ce = cross_entropy(t_patch, s_patch, self.student_temp);
            loss = loss + ce.mul_scalar(self.ibot_weight);
        }
        if self.koleo_weight > 0.0 {
            for i in 0..g {
                let term = koleo(s_cls.clone().narrow(0, i * b, b));
                loss = loss + term.mul_scalar(self.koleo_weight);
            }
        }
        (loss, t_mean)
    }

    /// After an optimizer step: EMA of the teacher with `momentum`, centre update with the
    /// teacher mean of the step.
    pub fn after_step(mut self, momentum: f64, teacher_mean: Tensor<2>) -> Self {
        self.teacher_encoder = ema_update(self.teacher_encoder, &self.encoder, momentum);
        self.teacher_head = ema_update(self.teacher_head, &self.head, momentum);
        let m = self.center_momentum;
        self.center = self
            .center
            .map(|c| updated_center(c, teacher_mean.detach(), m));
        self
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::device::seeded;
    use crate::vit::VitConfig;

    /// KoLeo: −ln 2 for two antipodal unit vectors (distance 2); large for a nearly collapsed
    /// batch, and one gradient step on it lowers it (spreads the batch).
    #[test]
    fn koleo_is_the_log_nearest_distance_and_spreads_a_collapsed_batch() {
        let device = Device::flex();
        let apart = Tensor::<1>::from_floats([1.0, 0.0, -1.0, 0.0], &device).reshape([2, 2]);
        let k = koleo(apart).into_scalar::<f32>() as f64;
        assert!((k + 2f64.ln()).abs() < 1e-5, "{k}");
        let ad = Device::flex().autodiff();
        let close = Tensor::<1>::from_floats([1.0, 0.0, 1.0, 0.01, 1.0, -0.01, 1.0, 0.02], &ad)
            .reshape([4, 2])
            .require_grad();
        let before = koleo(close.clone());
        assert!(before.clone().into_scalar::<f32>() > 3.0);
        let start = koleo(close.clone().inner()).into_scalar::<f32>();
        let grad = before.backward();
        let g = close.grad(&grad).expect("gradient");
        let after = koleo(close.inner() - g.mul_scalar(1e-5)).into_scalar::<f32>();
        assert!(after < start, "{after} vs {start}");
        // rows closer than f32's 2 − 2·cos can resolve still get pushed apart
        let tight = Tensor::<1>::from_floats([1.0, 0.0, 1.0, 1e-5, 1.0, -1e-5], &ad)
            .reshape([3, 2])
            .require_grad();
        let grad = koleo(tight.clone()).backward();
        let g = tight.grad(&grad).expect("gradient");
        let size = g.abs().sum().into_scalar::<f32>();
        assert!(size.is_finite() && size > 1.0, "gradient {size}");
    }

    /// Mean entropy (nats) of the centred, sharpened teacher distribution of a batch.
    fn teacher_entropy(head: &DinoHead, x: Tensor<2>) -> f64 {
        let t = head.forward(x);
        let p = softmax((t.clone() - t.mean_dim(0)).div_scalar(0.04), 1);
        let plogp = p.clone() * p.add_scalar(1e-20).log();
        plogp.sum_dim(1).mean().neg().into_scalar::<f32>() as f64
    }

    #[test]
    fn batch_normalized_head_separates_nearly_identical_inputs() {
        // the [cls] tokens of a random encoder on tactile difference images differ by ~1e-3
        // across a batch; without batch norm the centred teacher output is then uniform
        // (entropy ln K: nothing for the student to learn), with it the samples stay apart
        let device = Device::flex();
        let k = 256;
        let cfg = |bn: bool| {
            DinoConfig::new(VitConfig::new([16, 16], 8).with_embed_dim(32))
                .with_head_hidden(64)
                .with_head_bottleneck(16)
                .with_num_prototypes(k)
                .with_head_batch_norm(bn)
        };
        let (plain, normed) = seeded(&device, 5, || {
            let common = Tensor::<2>::random(
                [1, 32],
                burn::tensor::Distribution::Normal(0.0, 1.0),
                &device,
            );
            let x = common.expand([16, 32])
                + Tensor::<2>::random(
                    [16, 32],
                    burn::tensor::Distribution::Normal(0.0, 1e-3),
                    &device,
                );
            (
                teacher_entropy(&cfg(false).head(&device), x.clone()),
                teacher_entropy(&cfg(true).head(&device), x),
            )
        });
        let uniform = (k as f64).ln();
        assert!(
            plain > uniform - 0.01,
            "plain head: entropy {plain} vs ln K {uniform}"
        );
        assert!(
            normed < uniform - 1.0,
            "batch-normed head: entropy {normed} vs ln K {uniform}"
        );
    }

    /// Teacher scores that differ across the batch by 1e-3: centring leaves a uniform target
    /// (entropy ln K), batch standardization a sharp one.
    #[test]
    fn batch_standardized_teacher_stays_sharp_on_nearly_identical_samples() {
        let device = Device::flex();
        let (n, k) = (32, 64);
        let t = seeded(&device, 8, || {
            Tensor::<2>::random(
                [1, k],
                burn::tensor::Distribution::Uniform(-1.0, 1.0),
                &device,
            )
            .expand([n, k])
                + Tensor::<2>::random(
                    [n, k],
                    burn::tensor::Distribution::Normal(0.0, 1e-3),
                    &device,
                )
        });
        let entropy = |p: Tensor<2>| {
            let plogp = p.clone() * p.add_scalar(1e-20).log();
            plogp.sum_dim(1).mean().neg().into_scalar::<f32>() as f64
        };
        let centre = t.clone().mean_dim(0);
        let centred = entropy(teacher_targets(
            t.clone(),
            centre.clone(),
            TeacherNorm::Center,
            0.04,
        ));
        let batch = entropy(teacher_targets(t, centre, TeacherNorm::Batch, 0.25));
        let uniform = (k as f64).ln();
        assert!(
            centred > uniform - 0.01,
            "centred: {centred} vs ln K {uniform}"
        );
        assert!(batch < uniform - 2.0, "batch: {batch} vs ln K {uniform}");
    }

    /// One loss and backward pass on random input, with or without iBOT masking: gradients
    /// reach the student (and the mask token) and not the teacher.
    fn gradients_reach_the_student(ibot: bool) {
        let device = Device::flex().autodiff();
        let (dino, x) = seeded(&device, 6, || {
            let dino = DinoConfig::new(
                VitConfig::new([16, 16], 8)
                    .with_embed_dim(32)
                    .with_depth(1)
                    .with_num_heads(4)
                    .with_num_registers(1),
            )
            .with_head_hidden(32)
            .with_head_bottleneck(16)
            .with_num_prototypes(64)
            .with_head_batch_norm(true)
            .with_teacher_norm(TeacherNorm::Batch)
            .with_ibot_weight(if ibot { 1.0 } else { 0.0 })
            .init(&device);
            crate::device::draw_parameters(&dino);
            let x = Tensor::<5>::random(
                [4, 1, 6, 16, 16],
                burn::tensor::Distribution::Default,
                &device,
            );
            (dino, x)
        });
        let all: Vec<usize> = (0..4).collect();
        let views = DinoViews {
            global: vec![vec![all.clone(); 4], vec![all.clone(); 4]],
            local: vec![vec![vec![0, 1]; 4]],
            masked: if ibot {
                vec![vec![vec![1, 3]; 4], vec![vec![0, 2]; 4]]
            } else {
                Vec::new()
            },
        };
        let (loss, _) = dino.loss(x, &views, 0.25);
        let grads = loss.backward();
        {
            let norm = |g: Option<Tensor<2>>| g.map(|g| g.abs().sum().into_scalar::<f32>());
            let student = norm(dino.encoder.patch_embed.weight.val().grad(&grads));
            assert!(
                student.is_some_and(|g| g > 0.0),
                "student patch embedding: {student:?}"
            );
            let head = norm(dino.head.mlp[0].weight.val().grad(&grads));
            assert!(head.is_some_and(|g| g > 0.0), "student head: {head:?}");
            assert_eq!(
                norm(dino.teacher_encoder.patch_embed.weight.val().grad(&grads)),
                None
            );
            assert_eq!(
                norm(dino.teacher_head.mlp[0].weight.val().grad(&grads)),
                None
            );
            let token = dino.mask_token.as_ref().map(|t| {
                t.val()
                    .grad(&grads)
                    .map(|g| g.abs().sum().into_scalar::<f32>())
            });
            match token {
                Some(g) => assert!(g.is_some_and(|g| g > 0.0), "mask token: {g:?}"),
                None => assert!(!ibot),
            }
        }
    }

    #[test]
    fn gradients_reach_the_student_and_not_the_teacher() {
        gradients_reach_the_student(false);
        gradients_reach_the_student(true);
    }

    #[test]
    fn ibot_masking_replaces_exactly_the_masked_positions() {
        let device = Device::flex();
        let (rows_per_view, k, d) = (2, 3, 4);
        let views = vec![vec![vec![0, 1, 2], vec![3, 4, 5]]];
        let tokens = Tensor::<3>::ones([rows_per_view, k, d], &device);
        let pos = Tensor::<1>::from_floats(
            (0..6 * d)
                .map(|i| (i / d) as f32 * 10.0)
                .collect::<Vec<_>>()
                .as_slice(),
            &device,
        )
        .reshape([1, 6, d]);
        let token = Tensor::<3>::full([1, 1, d], 0.5, &device);
        let out = mask_view_tokens(tokens, pos, &views, &[vec![1], vec![0, 2]], token);
        let v: Vec<f32> = out.into_data().try_to_vec::<f32>().unwrap();
        // per row and position, the first feature: 1 where kept, 0.5 + 10 · grid position where masked
        let first: Vec<f32> = v.iter().step_by(d).copied().collect();
        assert_eq!(first, vec![1.0, 10.5, 1.0, 30.5, 1.0, 50.5]);
    }
}
