//! The supervised ceiling of T1A at the input's resolution: a small U-Net (Ronneberger et al.,
//! "U-Net", MICCAI 2015) from the pair `I_t ⊕ I_{t−k}` to the normal map and the flow, trained on
//! the ground-truth fields and early-stopped on held-out training sequences. It reads no
//! encoder: it says how well the task can be learned from these frames at all, which the
//! decoders on a frozen encoder's 12 × 9 token grid are then judged against.

use burn::module::Module;
use burn::nn::PaddingConfig2d;
use burn::nn::conv::{Conv2d, Conv2dConfig};
use burn::optim::{AdamWConfig, GradientsParams};
use burn::prelude::*;
use burn::tensor::activation::{relu, sigmoid};
use serde::{Deserialize, Serialize};
use sparsh_ssl::device::seeded_module;
use sparsh_ssl::rng::Rng;

use super::dpt::{PAIR_CHANNELS, resize};
use super::train::{Prediction, Targets};

/// Two 3 × 3 convolutions with ReLU, the first of stride `stride`.
#[derive(Module, Debug)]
pub struct ConvPair {
    /// First convolution.
    pub first: Conv2d,
    /// Second convolution.
    pub second: Conv2d,
}

impl ConvPair {
    fn new(cin: usize, cout: usize, stride: usize, device: &Device) -> Self {
        let conv = |cin: usize, stride: usize| {
            Conv2dConfig::new([cin, cout], [3, 3])
                .with_stride([stride, stride])
                .with_padding(PaddingConfig2d::Explicit(1, 1, 1, 1))
                .init(device)
        };
        Self {
            first: conv(cin, stride),
            second: conv(cout, 1),
        }
    }

    fn forward(&self, x: Tensor<4>) -> Tensor<4> {
        relu(self.second.forward(relu(self.first.forward(x))))
    }
}

/// The U-Net: four levels of `[c, 2c, 4c, 4c]` channels (each below the first at half the
/// resolution, by a stride-2 convolution), the way up by bilinear resize to the level above,
/// concatenation with its features and two convolutions; a 1 × 1 head to the normal map
/// (sigmoid) and one to the flow (`tanh · max_flow_px`), as the DPT decoder's outputs. The
/// receptive field of the deepest level is about 60 input pixels, more than a gel thickness at
/// 96 × 72.
#[derive(Module, Debug)]
pub struct FieldCnn {
    /// The way down, finest level first.
    pub down: Vec<ConvPair>,
    /// The way up, from the second-deepest level to the finest.
    pub up: Vec<ConvPair>,
    /// Head of the normal map.
    pub normal: Conv2d,
    /// Head of the flow.
    pub flow: Conv2d,
    /// Flow bound (input pixels).
    pub max_flow_px: f64,
}

impl FieldCnn {
    /// A fresh network of base width `channels`.
    pub fn new(channels: usize, max_flow_px: f64, device: &Device) -> Self {
        let widths = [channels, 2 * channels, 4 * channels, 4 * channels];
        let mut down = Vec::new();
        let mut cin = PAIR_CHANNELS;
        for (level, &c) in widths.iter().enumerate() {
            down.push(ConvPair::new(
                cin,
                c,
                if level == 0 { 1 } else { 2 },
                device,
            ));
            cin = c;
        }
        let mut up = Vec::new();
        for level in (0..widths.len() - 1).rev() {
            up.push(ConvPair::new(cin + widths[level], widths[level], 1, device));
            cin = widths[level];
        }
        let head = |cout: usize| Conv2dConfig::new([cin, cout], [1, 1]).init(device);
        Self {
            down,
            up,
            normal: head(1),
            flow: head(2),
            max_flow_px,
        }
    }

    /// `[batch, PAIR_CHANNELS, h, w]` (frames stored as `½ + I − bg`) → normal map
    /// `[batch, 1, h, w]` and flow `[batch, 2, h, w]`.
    pub fn forward(&self, input: Tensor<4>) -> (Tensor<4>, Tensor<4>) {
        let mut x = (input - 0.5) * 4.0;
        let mut skips = Vec::with_capacity(self.down.len());
        for stage in &self.down {
            x = stage.forward(x);
            skips.push(x.clone());
        }
        skips.pop();
        for stage in &self.up {
            let skip = skips.pop().expect("one skip per level up");
            let [_, _, h, w] = skip.dims();
            x = stage.forward(Tensor::cat(vec![resize(x, [h, w]), skip], 1));
        }
        (
            sigmoid(self.normal.forward(x.clone())),
            self.flow.forward(x).tanh() * self.max_flow_px,
        )
    }
}

/// `[ceiling]` of a field-probe config: the U-Net's size and schedule.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct CeilingSection {
    /// Train the U-Net ceiling.
    pub cnn: bool,
    /// Base width of the U-Net.
    pub channels: usize,
    /// Optimizer steps (AdamW, weight decay 1e-4, half-cosine to 0).
    pub steps: usize,
    /// Pairs per step.
    pub batch_size: usize,
    /// Peak learning rate.
    pub lr: f64,
    /// Steps between validations; the step of the lowest validation loss is kept.
    pub validate_every: usize,
    /// Every `validation_period`-th training sequence is held out for the validation.
    pub validation_period: usize,
}

impl Default for CeilingSection {
    fn default() -> Self {
        Self {
            cnn: false,
            channels: 16,
            steps: 3000,
            batch_size: 8,
            lr: 2e-3,
            validate_every: 150,
            validation_period: 5,
        }
    }
}

/// How the U-Net's training went.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct CeilingRecord {
    /// File under `RUN/decoders/`.
    pub file: String,
    /// Training and validation pairs.
    pub pairs: [usize; 2],
    /// `(step, validation loss, its normal term, its flow term)` at every validation.
    pub validation: Vec<(usize, f64, f64, f64)>,
    /// The step kept (lowest validation loss).
    pub best_step: usize,
    /// Wall time (s).
    pub seconds: f64,
}

fn tensor(values: Vec<f32>, rows: usize, size: [usize; 2], device: &Device) -> Tensor<4> {
    Tensor::<1>::from_floats(values.as_slice(), device).reshape([
        rows,
        PAIR_CHANNELS,
        size[0],
        size[1],
    ])
}

/// Trains the U-Net on samples of `size` (`[height, width]`) whose inputs `input` gives for
/// rows, `sequence[i]` naming row i's sequence, with their `targets` (one per row), holding out
/// every `validation_period`-th sequence (at least one); drawn on the CPU under `seed`, trained
/// on `device`. Returns the network at the step of the lowest validation loss (without autodiff,
/// on `device`) and the record (its file name left empty); an error with fewer than two
/// sequences.
#[allow(clippy::too_many_arguments)]
pub fn train_ceiling(
    input: &dyn Fn(&[usize]) -> Vec<f32>,
    size: [usize; 2],
    sequence: &[usize],
    targets: &Targets,
    section: &CeilingSection,
    max_flow_px: f64,
    seed: u64,
    device: &Device,
    log: &dyn Fn(&str),
) -> Result<(FieldCnn, CeilingRecord), String> {
    let t0 = std::time::Instant::now();
    let mut sequences = sequence.to_vec();
    sequences.sort_unstable();
    sequences.dedup();
    if sequences.len() < 2 {
        return Err(format!(
            "the ceiling CNN validates on held-out training sequences; the training split has {}",
            sequences.len()
        ));
    }
    let period = section.validation_period.min(sequences.len());
    let held: Vec<usize> = sequences
        .iter()
        .copied()
        .skip(period - 1)
        .step_by(period)
        .collect();
    let (val, train): (Vec<usize>, Vec<usize>) =
        (0..sequence.len()).partition(|&i| held.contains(&sequence[i]));
    let cpu = Device::flex().autodiff();
    let model = seeded_module(&cpu, seed, || {
        FieldCnn::new(section.channels, max_flow_px, &cpu)
    });
    let device = device.clone().inner().autodiff();
    let mut model = sparsh_ssl::device::on_device(model, &device);
    let mut optim = AdamWConfig::new().with_weight_decay(1e-4).init();
    let validate = |m: &FieldCnn| {
        let valid_device = device.clone().inner();
        let (mut sum, mut normal, mut flow) = (0.0, 0.0, 0.0);
        for chunk in val.chunks(16) {
            let x = tensor(input(chunk), chunk.len(), size, &valid_device);
            let (n, f) = m.forward(x);
            let (ln, lf) = targets.loss(n, f, chunk, &valid_device);
            let share = chunk.len() as f64 / val.len() as f64;
            let (ln, lf) = (
                ln.into_scalar::<f32>() as f64,
                lf.into_scalar::<f32>() as f64,
            );
            normal += share * ln;
            flow += share * lf;
            sum += share * (ln + lf);
        }
        (sum, normal, flow)
    };
    let mut order: Vec<usize> = Vec::new();
    let (mut cursor, mut epoch) = (0, 0u64);
    let mut validation = Vec::new();
    let mut best: Option<(f64, usize, FieldCnn)> = None;
    for step in 0..section.steps {
        let mut rows = Vec::with_capacity(section.batch_size);
        while rows.len() < section.batch_size.min(train.len()) {
            if cursor == order.len() {
                order = Rng::for_step(seed, epoch, 13)
                    .permutation(train.len())
                    .into_iter()
                    .map(|k| train[k])
                    .collect();
                epoch += 1;
                cursor = 0;
            }
            rows.push(order[cursor]);
            cursor += 1;
        }
        let (n, f) = model.forward(tensor(input(&rows), rows.len(), size, &device));
        let (ln, lf) = targets.loss(n, f, &rows, &device);
        let grads = GradientsParams::from_grads((ln + lf).backward(), &model);
        let lr = 0.5
            * section.lr
            * (1.0 + (std::f64::consts::PI * step as f64 / section.steps as f64).cos());
        model = optim.step(lr, model, grads);
        let done = step + 1;
        if done % section.validate_every == 0 || done == section.steps {
            let valid = model.valid();
            let (loss, normal, flow) = validate(&valid);
            log(&format!(
                "  ceiling CNN: step {done}/{}, validation loss {loss:.5} (normal {normal:.5}, \
                 flow {flow:.5})",
                section.steps
            ));
            validation.push((done, loss, normal, flow));
            if best.as_ref().is_none_or(|(b, _, _)| loss < *b) {
                best = Some((loss, done, valid));
            }
        }
    }
    let (_, best_step, model) = best.expect("at least one validation");
    let record = CeilingRecord {
        file: String::new(),
        pairs: [train.len(), val.len()],
        validation,
        best_step,
        seconds: t0.elapsed().as_secs_f64(),
    };
    Ok((model, record))
}

/// The U-Net's predictions for `n` samples of `size` whose inputs `input` gives, on the device
/// `model` lives on.
pub fn predict_ceiling(
    model: &FieldCnn,
    input: &dyn Fn(&[usize]) -> Vec<f32>,
    size: [usize; 2],
    n: usize,
) -> Vec<Prediction> {
    let device = sparsh_ssl::device::device_of(model).inner();
    let rows: Vec<usize> = (0..n).collect();
    let mut out = Vec::with_capacity(n);
    for chunk in rows.chunks(16) {
        let (normal, flow) = model.forward(tensor(input(chunk), chunk.len(), size, &device));
        out.extend(Prediction::of_batch(normal, flow));
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The U-Net reads a contact from the image alone: the input's first channel shows a disc
    /// at a random place, the target normal map is that disc and the flow a known shift inside
    /// it. On samples it never trained on, its map is high on the disc and low off it, its flow
    /// points the right way; the kept step is the one of the lowest validation loss.
    #[test]
    fn the_ceiling_cnn_finds_a_contact_it_has_not_seen() {
        let [h, w] = [16usize, 24usize];
        let mut rng = Rng::new(4);
        let mut samples = |n: usize| {
            let (mut inputs, mut truths) = (Vec::new(), Vec::new());
            for _ in 0..n {
                let (cy, cx, r) = (
                    rng.range_f64(4.0, 12.0),
                    rng.range_f64(4.0, 20.0),
                    rng.range_f64(2.0, 4.0),
                );
                let disc: Vec<bool> = (0..h * w)
                    .map(|i| {
                        let (y, x) = ((i / w) as f64 + 0.5, (i % w) as f64 + 0.5);
                        (y - cy).hypot(x - cx) < r
                    })
                    .collect();
                inputs.extend(disc.iter().map(|&c| if c { 0.8 } else { 0.5 }));
                inputs.extend(std::iter::repeat_n(0.5, (PAIR_CHANNELS - 1) * h * w));
                truths.push(super::super::data::PairTruth {
                    pressure_kpa: disc.iter().map(|&c| if c { 10.0 } else { 0.0 }).collect(),
                    indentation_mm: vec![0.0; h * w],
                    contact: disc.clone(),
                    shear_traction_kpa: vec![0.0; h * w],
                    flow_px: disc
                        .iter()
                        .map(|&c| if c { [1.0, -0.5] } else { [0.0; 2] })
                        .collect(),
                });
            }
            (inputs, truths)
        };
        let (train_inputs, train_truths) = samples(40);
        let (test_inputs, test_truths) = samples(12);
        let targets = Targets::new(&train_truths, 2.0);
        let sequence: Vec<usize> = (0..40).map(|i| i / 4).collect();
        let section = CeilingSection {
            cnn: true,
            channels: 8,
            steps: 400,
            batch_size: 8,
            lr: 2e-3,
            validate_every: 100,
            validation_period: 5,
        };
        let per = PAIR_CHANNELS * h * w;
        let rows_of = |values: &[f32]| {
            let values = values.to_vec();
            move |rows: &[usize]| -> Vec<f32> {
                rows.iter()
                    .flat_map(|&i| values[i * per..(i + 1) * per].to_vec())
                    .collect()
            }
        };
        let (model, record) = train_ceiling(
            &rows_of(&train_inputs),
            [h, w],
            &sequence,
            &targets,
            &section,
            2.0,
            0,
            &Device::flex(),
            &|_| {},
        )
        .unwrap();
        assert_eq!(record.pairs, [32, 8]);
        assert_eq!(record.validation.len(), 4);
        let lowest = record
            .validation
            .iter()
            .min_by(|a, b| a.1.total_cmp(&b.1))
            .unwrap();
        assert_eq!(record.best_step, lowest.0);
        let preds = predict_ceiling(&model, &rows_of(&test_inputs), [h, w], 12);
        let (mut on, mut off, mut flow_x) = ((0.0, 0usize), (0.0, 0usize), 0.0);
        for (p, t) in preds.iter().zip(&test_truths) {
            for (i, &c) in t.contact.iter().enumerate() {
                if c {
                    on = (on.0 + p.normal[i] as f64, on.1 + 1);
                    flow_x += p.flow[i][0] as f64;
                } else {
                    off = (off.0 + p.normal[i] as f64, off.1 + 1);
                }
            }
        }
        let (on, off) = (on.0 / on.1 as f64, off.0 / off.1 as f64);
        assert!(
            on - off > 0.5,
            "on the disc {on:.3}, off it {off:.3}; {:?}",
            record.validation
        );
        assert!(flow_x > 0.0, "{flow_x}");
        // a single training sequence leaves nothing to validate on
        let one = vec![0; 40];
        let err = train_ceiling(
            &rows_of(&train_inputs),
            [h, w],
            &one,
            &targets,
            &section,
            2.0,
            0,
            &Device::flex(),
            &|_| {},
        )
        .err()
        .unwrap();
        assert!(err.contains("held-out training sequences"), "{err}");
    }
}
