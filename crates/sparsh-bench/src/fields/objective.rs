//! Whether the shear branch's self-supervised objective prefers the true motion: a decoder
//! trained on a loss can only learn the flow that scores lowest under it. On the training
//! pairs in contact, [`shear_objective`] scores the loss of [`super::loss::shear_loss`] (the
//! Charbonnier photometric term of the backward warp, plus its smoothness) for the true lateral
//! displacement change u(t) − u(t − k) of the gel, for zero flow, and for the uniform flow of
//! the true one's mean over the contact — per family, since only a gel with printed markers
//! carries texture that moves with the material.

use std::collections::BTreeMap;

use burn::prelude::*;

use super::data::{FramePairs, GroundTruth, Pair};
use super::loss::{LossWeights, shear_loss, shear_photometric};
use crate::Error;

/// The candidate flows scored, in table order.
pub const FLOWS: [&str; 3] = ["true", "zero", "uniform"];

/// The objective on one family's pairs.
#[derive(Debug, Clone, PartialEq)]
pub struct ObjectiveRow {
    /// Family name.
    pub family: String,
    /// Pairs in contact scored.
    pub pairs: usize,
    /// Mean loss (photometric + smoothness) per flow of [`FLOWS`].
    pub loss: [f64; 3],
    /// Mean photometric term alone (Charbonnier of the warp's residual) per flow.
    pub photometric: [f64; 3],
    /// Share of pairs whose true flow scores a lower loss than zero flow.
    pub true_below_zero: f64,
    /// Share of pairs whose true flow scores a lower photometric term than zero flow.
    pub photometric_true_below_zero: f64,
    /// Mean magnitude of the true flow over the contact (input pixels).
    pub contact_flow_px: f64,
}

/// Scores the three flows of [`FLOWS`] on `pairs` (those in contact at frame t), grouped by
/// family in name order.
pub fn shear_objective(
    data: &FramePairs,
    pairs: &[Pair],
    weights: &LossWeights,
) -> Result<Vec<ObjectiveRow>, Error> {
    let device = Device::flex();
    let [h, w] = data.size();
    let truth = GroundTruth::new(data);
    let image = |f: &[f32]| Tensor::<1>::from_floats(f, &device).reshape([1, 3, h, w]);
    let field = |f: &[[f32; 2]]| {
        let planar: Vec<f32> = (0..2).flat_map(|c| f.iter().map(move |v| v[c])).collect();
        Tensor::<1>::from_floats(planar.as_slice(), &device).reshape([1, 2, h, w])
    };
    // per family: sums of loss, photometric, wins (loss, photometric), flow magnitude, pairs
    type Sums = ([f64; 3], [f64; 3], [f64; 2], f64, usize);
    let mut sums: BTreeMap<String, Sums> = BTreeMap::new();
    for &p in pairs {
        let t = truth.pair(p)?;
        let inside: Vec<[f32; 2]> = t
            .flow_px
            .iter()
            .zip(&t.contact)
            .filter(|(_, c)| **c)
            .map(|(f, _)| *f)
            .collect();
        if inside.is_empty() {
            continue;
        }
        let n = inside.len() as f32;
        let mean = inside
            .iter()
            .fold([0.0f32; 2], |m, f| [m[0] + f[0] / n, m[1] + f[1] / n]);
        let magnitude = inside.iter().map(|f| f[0].hypot(f[1]) as f64).sum::<f64>() / n as f64;
        let (now, before) = data.frames(p);
        let (now, before) = (image(now), image(before));
        let flows = [t.flow_px.clone(), vec![[0.0; 2]; h * w], vec![mean; h * w]];
        let entry = sums
            .entry(data.sequences[p.sequence].family.clone())
            .or_default();
        let (mut loss, mut photometric) = ([0.0; 3], [0.0; 3]);
        for (k, f) in flows.iter().enumerate() {
            (loss[k], photometric[k]) = score(field(f), now.clone(), before.clone(), weights);
            entry.0[k] += loss[k];
            entry.1[k] += photometric[k];
        }
        entry.2[0] += f64::from(loss[0] < loss[1]);
        entry.2[1] += f64::from(photometric[0] < photometric[1]);
        entry.3 += magnitude;
        entry.4 += 1;
    }
    Ok(sums
        .into_iter()
        .map(|(family, (loss, photometric, wins, flow, n))| {
            let m = n as f64;
            ObjectiveRow {
                family,
                pairs: n,
                loss: loss.map(|v| v / m),
                photometric: photometric.map(|v| v / m),
                true_below_zero: wins[0] / m,
                photometric_true_below_zero: wins[1] / m,
                contact_flow_px: flow / m,
            }
        })
        .collect())
}

/// The shear loss of `flow` on the pair (`[1, 2, h, w]`, `[1, 3, h, w]` twice), and its
/// photometric term alone.
fn score(flow: Tensor<4>, now: Tensor<4>, before: Tensor<4>, weights: &LossWeights) -> (f64, f64) {
    let scalar = |t: Tensor<1>| t.into_scalar::<f32>() as f64;
    let photometric = shear_photometric(flow.clone(), now.clone(), before.clone());
    (
        scalar(shear_loss(flow, now, before, weights)),
        scalar(photometric),
    )
}

/// The rows as a Markdown table.
pub fn markdown(rows: &[ObjectiveRow]) -> String {
    let mut s = String::from(
        "| family | pairs in contact | true flow in contact (px) | loss: true | zero | uniform | \
         photometric: true | zero | uniform | true below zero: loss | photometric |\n\
         |---|---|---|---|---|---|---|---|---|---|---|\n",
    );
    for r in rows {
        s += &format!(
            "| {} | {} | {:.3} | {:.5} | {:.5} | {:.5} | {:.5} | {:.5} | {:.5} | {:.0} % | {:.0} % |\n",
            r.family,
            r.pairs,
            r.contact_flow_px,
            r.loss[0],
            r.loss[1],
            r.loss[2],
            r.photometric[0],
            r.photometric[1],
            r.photometric[2],
            100.0 * r.true_below_zero,
            100.0 * r.photometric_true_below_zero
        );
    }
    s
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_shift_scores_its_own_flow_lowest_and_smoothness_only_where_the_flow_varies() {
        // A smooth texture and the same texture moved right by 1.25 px: the backward warp by
        // the true (uniform) flow undoes it, so its photometric term sits near the Charbonnier
        // floor ε = 1e-3, below zero flow's and the opposite flow's; a uniform flow has no
        // smoothness cost, so its loss is its photometric term.
        let (h, w, shift) = (24usize, 32usize, 1.25f32);
        let texture = |x: f32, y: f32| 0.5 + 0.2 * (0.7 * x).sin() * (0.5 * y).cos();
        let image = |dx: f32| {
            let v: Vec<f32> = (0..3)
                .flat_map(|_| (0..h * w).map(move |i| texture((i % w) as f32 - dx, (i / w) as f32)))
                .collect();
            Tensor::<1>::from_floats(v.as_slice(), &Device::flex()).reshape([1, 3, h, w])
        };
        let (before, now) = (image(0.0), image(shift));
        let uniform = |fx: f32| {
            let v: Vec<f32> = (0..h * w)
                .map(|_| fx)
                .chain((0..h * w).map(|_| 0.0))
                .collect();
            Tensor::<1>::from_floats(v.as_slice(), &Device::flex()).reshape([1, 2, h, w])
        };
        let w8 = LossWeights::default();
        let (loss_true, photo_true) = score(uniform(shift), now.clone(), before.clone(), &w8);
        let (_, photo_zero) = score(uniform(0.0), now.clone(), before.clone(), &w8);
        let (_, photo_back) = score(uniform(-shift), now.clone(), before.clone(), &w8);
        assert!(
            (loss_true - photo_true).abs() < 1e-7,
            "{loss_true} {photo_true}"
        );
        // the clamped border columns and bilinear blur leave a little residual
        assert!(photo_true < 0.2 * photo_zero, "{photo_true} {photo_zero}");
        assert!(photo_zero < photo_back, "{photo_zero} {photo_back}");
        // a flow that varies pays its smoothness on top
        let ramp: Vec<f32> = (0..h * w)
            .map(|i| shift * (i % w) as f32 / w as f32)
            .chain((0..h * w).map(|_| 0.0))
            .collect();
        let ramp = Tensor::<1>::from_floats(ramp.as_slice(), &Device::flex()).reshape([1, 2, h, w]);
        let (loss_ramp, photo_ramp) = score(ramp, now, before, &w8);
        assert!(loss_ramp > photo_ramp + 1e-4, "{loss_ramp} {photo_ramp}");
    }
}
