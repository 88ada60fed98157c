//! A trained encoder as a frozen feature extractor: tactile frames in, token features out, as the
//! encoder's recipe feeds it while training.
//!
//! One sample is the recipe's frame stacking at frame `t` (I_t ⊕ I_{t−5} for the image
//! objectives, four frames for V-JEPA), each frame preprocessed against the sequence's no-contact
//! background ([`crate::data::preprocess`]). An offset reaching before the first frame reads the
//! no-contact frame (the background against itself), so every frame of a sequence has features.
//! Inference runs without autodiff: on the CPU as the host pass of [`crate::host`] (weights laid
//! out once for the GEMM, two parallel regions a block), on any other device as burn ops on the
//! device the encoder was moved to ([`FrozenEncoder::to_device`]).

use std::path::Path;

use burn::prelude::*;
use image::RgbImage;
use rayon::prelude::*;

use crate::Error;
use crate::data::{GeneratedSequence, preprocess, read_image};
use crate::host::HostVit;
pub use crate::host::Pool;
use crate::recipe::Recipe;
use crate::vit::Vit;

/// A trained encoder with its recipe's input: image size and frame stacking.
#[derive(Debug, Clone)]
pub struct FrozenEncoder {
    vit: Vit,
    /// The host pass's copy of the weights while the encoder is on the CPU.
    host: Option<HostVit>,
    offsets: Vec<usize>,
    /// `[frames, channels, height, width]` of one sample.
    sample_shape: [usize; 4],
    tokens: usize,
}

impl FrozenEncoder {
    /// Loads the recipe's encoder from `weights` (safetensors, official key names) on the CPU; an
    /// error names the file when its tensors do not fit the recipe's encoder.
    pub fn load(recipe: &Recipe, weights: &Path) -> Result<Self, Error> {
        let cfg = recipe.encoder_config()?;
        let vit = crate::weights::load_encoder(cfg.init(&Device::flex()), weights, None)?;
        Ok(Self {
            host: Some(HostVit::new(&vit)),
            vit,
            offsets: recipe.frame_offsets(),
            sample_shape: [
                cfg.num_frames,
                cfg.in_chans,
                cfg.img_size[0],
                cfg.img_size[1],
            ],
            tokens: cfg.num_patches(),
        })
    }

    /// The encoder on `device` (loaded on the CPU, then moved): returned as it is when it lives
    /// there already, so on the CPU it computes exactly as it did before the move existed.
    pub fn to_device(mut self, device: &Device) -> Self {
        self.vit = crate::device::on_device(self.vit, device);
        if self.device() != Device::flex() {
            self.host = None;
        }
        self
    }

    /// The device the encoder computes on.
    pub fn device(&self) -> Device {
        crate::device::device_of(&self.vit)
    }

    /// Frame offsets back in time of one sample, in input order (`[0, 5]`: I_t, then I_{t−5}).
    pub fn frame_offsets(&self) -> &[usize] {
        &self.offsets
    }

    /// Shape of one sample's features: `[dim]` pooled, else `[tokens, dim]`.
    pub fn feature_shape(&self, pool: Pool) -> Vec<usize> {
        match pool {
            Pool::Mean => vec![self.vit.dim()],
            Pool::None => vec![self.tokens, self.vit.dim()],
        }
    }

    /// The encoder input of one sample: `frames` (one image per offset of
    /// [`frame_offsets`](Self::frame_offsets), newest first) preprocessed against `background`
    /// and concatenated, `[frames, channels, height, width]` flattened.
    pub fn input(&self, frames: &[&RgbImage], background: &RgbImage) -> Result<Vec<f32>, Error> {
        if frames.len() != self.offsets.len() {
            return Err(Error::Data(format!(
                "the recipe stacks {} frames (offsets {:?}), got {}",
                self.offsets.len(),
                self.offsets,
                frames.len()
            )));
        }
        let [_, _, h, w] = self.sample_shape;
        let mut out = Vec::with_capacity(self.sample_len());
        for f in frames {
            out.extend(preprocess(f, background, [h, w]).map_err(Error::Data)?);
        }
        Ok(out)
    }

    /// Features of one sample (see [`input`](Self::input)): the call a robot makes per frame.
    pub fn embed_frames(
        &self,
        frames: &[&RgbImage],
        background: &RgbImage,
        pool: Pool,
    ) -> Result<Vec<f32>, Error> {
        Ok(self.embed_inputs(&self.input(frames, background)?, pool))
    }

    /// Features of samples whose inputs are concatenated in `inputs` (a whole number of
    /// samples), concatenated in the same order.
    pub fn embed_inputs(&self, inputs: &[f32], pool: Pool) -> Vec<f32> {
        let n = inputs.len() / self.sample_len();
        assert_eq!(n * self.sample_len(), inputs.len(), "whole samples");
        if let Some(host) = &self.host {
            return host.embed(inputs, self.sample_shape, pool);
        }
        let [f, c, h, w] = self.sample_shape;
        let x = Tensor::<1>::from_floats(inputs, &self.device()).reshape([n, f, c, h, w]);
        encode(&self.vit, x, pool)
    }

    fn sample_len(&self) -> usize {
        self.sample_shape.iter().product()
    }

    /// Features of every frame of `sequences` (a dataset written by `sparsh generate`, see
    /// [`crate::data::generated_sequences`]), `batch` samples per forward pass, rows in
    /// ascending frame number; `done(n)` after each pass of `n` samples.
    pub fn embed_sequences(
        &self,
        sequences: &[GeneratedSequence],
        pool: Pool,
        batch: usize,
        done: &dyn Fn(usize),
    ) -> Result<Embeddings, Error> {
        let batch = batch.max(1);
        let per = self.feature_shape(pool).iter().product::<usize>();
        let [_, _, h, w] = self.sample_shape;
        let mut rows: Vec<(usize, Vec<f32>)> = Vec::new();
        let (mut pending, mut pending_ids) = (Vec::new(), Vec::new());
        let mut flush = |pending: &mut Vec<f32>, ids: &mut Vec<usize>| {
            if ids.is_empty() {
                return;
            }
            let features = self.embed_inputs(pending, pool);
            done(ids.len());
            rows.extend(ids.drain(..).zip(features.chunks(per).map(<[f32]>::to_vec)));
            pending.clear();
        };
        for seq in sequences {
            let bg = read_image(&seq.background)?;
            let rest = preprocess(&bg, &bg, [h, w]).map_err(|e| Error::file(&seq.background, e))?;
            let frames = seq
                .frames
                .par_iter()
                .map(|p| preprocess(&read_image(p)?, &bg, [h, w]).map_err(|e| Error::file(p, e)))
                .collect::<Result<Vec<_>, _>>()?;
            for (t, &id) in seq.frame_ids.iter().enumerate() {
                for &off in &self.offsets {
                    pending.extend_from_slice(t.checked_sub(off).map_or(&rest, |i| &frames[i]));
                }
                pending_ids.push(id);
                if pending_ids.len() == batch {
                    flush(&mut pending, &mut pending_ids);
                }
            }
        }
        flush(&mut pending, &mut pending_ids);
        rows.sort_by_key(|(id, _)| *id);
        let mut shape = vec![rows.len()];
        shape.extend(self.feature_shape(pool));
        Ok(Embeddings {
            frame_ids: rows.iter().map(|(id, _)| *id).collect(),
            values: rows.into_iter().flat_map(|(_, v)| v).collect(),
            shape,
        })
    }
}

/// Features of a batch of clips `[batch, frames, channels, height, width]` on the host,
/// row-major `[batch, dim]` pooled, else `[batch, tokens, dim]`, as burn ops. `vit` and `x` are
/// on one device. (On the CPU a [`FrozenEncoder`] runs the faster [`HostVit`] instead.)
///
/// On the CPU the batch is split into one part per thread of the rayon pool, encoded in parallel: burn's
/// CPU backend runs element-wise ops (residual adds, softmax, copies) on the calling thread, so
/// this is what puts every core to work outside the matrix products and this crate's own
/// GELU and layer-norm kernels ([`crate::kernels`]). A sample's features do not depend on the
/// split beyond float rounding. On any other device the batch is one forward pass.
pub fn encode(vit: &Vit, x: Tensor<5>, pool: Pool) -> Vec<f32> {
    if x.device() != Device::flex() {
        return encode_part(vit, x, pool);
    }
    let b = x.dims()[0];
    let size = b.div_ceil(rayon::current_num_threads().clamp(1, b.max(1)));
    if size >= b {
        return encode_part(vit, x, pool);
    }
    (0..b)
        .step_by(size)
        .collect::<Vec<_>>()
        .into_par_iter()
        .map(|start| encode_part(vit, x.clone().narrow(0, start, size.min(b - start)), pool))
        .collect::<Vec<_>>()
        .concat()
}

fn encode_part(vit: &Vit, x: Tensor<5>, pool: Pool) -> Vec<f32> {
    let tokens = vit.forward(x, None).patches;
    let features = match pool {
        Pool::Mean => tokens.mean_dim(1),
        Pool::None => tokens,
    };
    features
        .into_data()
        .convert::<f32>()
        .try_to_vec::<f32>()
        .expect("f32 features")
}

/// Features of the frames of a dataset.
#[derive(Debug, Clone)]
pub struct Embeddings {
    /// Frame number of each row (`frames/NNNNNN.png`), ascending.
    pub frame_ids: Vec<usize>,
    /// Row-major values of [`shape`](Self::shape).
    pub values: Vec<f32>,
    /// `[frames, dim]` pooled, else `[frames, tokens, dim]`.
    pub shape: Vec<usize>,
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::vit::VitConfig;

    /// A batch split over two threads gives each sample the features it has alone on one
    /// thread, and the mean pool is the mean of the tokens.
    #[test]
    fn split_batches_and_pooling_match_single_samples() {
        let device = Device::flex();
        let vit = crate::device::seeded_module(&device, 1, || {
            VitConfig::new([16, 12], 4)
                .with_embed_dim(32)
                .with_depth(2)
                .with_num_heads(4)
                .init(&device)
        });
        let x = crate::device::seeded_random(
            &device,
            2,
            [3, 1, 6, 16, 12],
            burn::tensor::Distribution::Default,
        );
        let pool = |n| {
            rayon::ThreadPoolBuilder::new()
                .num_threads(n)
                .build()
                .unwrap()
        };
        let pooled = pool(2).install(|| encode(&vit, x.clone(), Pool::Mean));
        let tokens = pool(2).install(|| encode(&vit, x.clone(), Pool::None));
        assert_eq!((pooled.len(), tokens.len()), (3 * 32, 3 * 12 * 32));
        for i in 0..3 {
            let alone = pool(1).install(|| encode(&vit, x.clone().narrow(0, i, 1), Pool::Mean));
            for d in 0..32 {
                let mean = (0..12).map(|t| tokens[(i * 12 + t) * 32 + d]).sum::<f32>() / 12.0;
                assert!((alone[d] - pooled[i * 32 + d]).abs() < 1e-5, "sample {i}");
                assert!((mean - pooled[i * 32 + d]).abs() < 1e-5, "sample {i}");
            }
        }
    }
}
