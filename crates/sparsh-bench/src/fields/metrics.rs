//! Scores of predicted fields against the simulator's: correlations and contact IoU for the
//! normal map, end-point and angular error for the flow, per frame pair.

use super::data::PairTruth;

/// Pearson's correlation of two equally long samples; `None` when either is constant.
pub fn pearson(a: &[f32], b: &[f32]) -> Option<f64> {
    let n = a.len() as f64;
    if a.is_empty() || a.len() != b.len() {
        return None;
    }
    let ma = a.iter().map(|&v| v as f64).sum::<f64>() / n;
    let mb = b.iter().map(|&v| v as f64).sum::<f64>() / n;
    let (mut sab, mut saa, mut sbb) = (0.0, 0.0, 0.0);
    for (&x, &y) in a.iter().zip(b) {
        let (dx, dy) = (x as f64 - ma, y as f64 - mb);
        sab += dx * dy;
        saa += dx * dx;
        sbb += dy * dy;
    }
    (saa > 1e-18 && sbb > 1e-18).then(|| sab / (saa * sbb).sqrt())
}

/// Ranks from 1, ties sharing their mean rank.
fn ranks(v: &[f32]) -> Vec<f32> {
    let mut idx: Vec<usize> = (0..v.len()).collect();
    idx.sort_by(|&i, &j| v[i].total_cmp(&v[j]));
    let mut out = vec![0.0f32; v.len()];
    let mut i = 0;
    while i < idx.len() {
        let mut j = i;
        while j + 1 < idx.len() && v[idx[j + 1]] == v[idx[i]] {
            j += 1;
        }
        let r = (i + j) as f32 / 2.0 + 1.0;
        for &k in &idx[i..=j] {
            out[k] = r;
        }
        i = j + 1;
    }
    out
}

/// Spearman's rank correlation (Pearson's on ranks, ties averaged).
pub fn spearman(a: &[f32], b: &[f32]) -> Option<f64> {
    pearson(&ranks(a), &ranks(b))
}

/// Intersection over union of `pred ≥ threshold` with `mask`; `None` when both are empty.
pub fn iou(pred: &[f32], threshold: f32, mask: &[bool]) -> Option<f64> {
    let (mut inter, mut union) = (0usize, 0usize);
    for (&p, &m) in pred.iter().zip(mask) {
        let on = p >= threshold;
        inter += (on && m) as usize;
        union += (on || m) as usize;
    }
    (union > 0).then(|| inter as f64 / union as f64)
}

/// The threshold, among 64 quantiles of the pooled predictions, with the best mean IoU over
/// the given frames (training frames in contact): chosen without the frames it is scored on.
pub fn best_threshold(preds: &[&[f32]], masks: &[&[bool]]) -> f32 {
    let mut pooled: Vec<f32> = preds.iter().flat_map(|p| p.iter().copied()).collect();
    if pooled.is_empty() {
        return 0.5;
    }
    pooled.sort_by(f32::total_cmp);
    let candidates: Vec<f32> = (0..64)
        .map(|k| {
            let q = 0.5 + 0.4995 * k as f64 / 63.0;
            pooled[((pooled.len() - 1) as f64 * q) as usize]
        })
        .collect();
    let mean_iou = |thr: f32| {
        let v: Vec<f64> = preds
            .iter()
            .zip(masks)
            .filter_map(|(p, m)| iou(p, thr, m))
            .collect();
        v.iter().sum::<f64>() / v.len().max(1) as f64
    };
    candidates
        .into_iter()
        .map(|t| (mean_iou(t), t))
        .max_by(|a, b| a.0.total_cmp(&b.0))
        .map_or(0.5, |(_, t)| t)
}

/// Mean end-point error `‖F − F*‖` over the pixels where `mask` holds (all when `None`).
pub fn endpoint_error(flow: &[[f32; 2]], truth: &[[f32; 2]], mask: Option<&[bool]>) -> Option<f64> {
    let (mut sum, mut n) = (0.0, 0usize);
    for (i, (f, t)) in flow.iter().zip(truth).enumerate() {
        if mask.is_none_or(|m| m[i]) {
            sum += ((f[0] - t[0]) as f64).hypot((f[1] - t[1]) as f64);
            n += 1;
        }
    }
    (n > 0).then(|| sum / n as f64)
}

/// Mean angular error (Barron, Fleet & Beauchemin 1994): the angle between `(u, v, 1)` and
/// `(u*, v*, 1)` in degrees, defined for zero flows too.
pub fn angular_error(flow: &[[f32; 2]], truth: &[[f32; 2]], mask: Option<&[bool]>) -> Option<f64> {
    let (mut sum, mut n) = (0.0, 0usize);
    for (i, (f, t)) in flow.iter().zip(truth).enumerate() {
        if mask.is_none_or(|m| m[i]) {
            let (u, v, a, b) = (f[0] as f64, f[1] as f64, t[0] as f64, t[1] as f64);
            let c = (u * a + v * b + 1.0) / ((u * u + v * v + 1.0) * (a * a + b * b + 1.0)).sqrt();
            sum += c.clamp(-1.0, 1.0).acos().to_degrees();
            n += 1;
        }
    }
    (n > 0).then(|| sum / n as f64)
}

/// The metrics of one frame pair, in table order; `None` where a metric does not apply (no
/// contact, a method without that branch).
pub const METRICS: [&str; 12] = [
    "pearson_p",
    "spearman_p",
    "pearson_uz",
    "spearman_uz",
    "contact_iou",
    "epe_contact_px",
    "epe_all_px",
    "angular_contact_deg",
    "angular_all_deg",
    "pearson_flow_q",
    "pearson_p_near",
    "flow_spread_px",
];

/// Radius (input pixels) by which the true contact is dilated for the correlation near it.
pub const NEAR_CONTACT_PX: usize = 3;

/// `mask` (`width` columns) dilated by a disc of `radius` pixels.
pub fn dilate(mask: &[bool], width: usize, radius: usize) -> Vec<bool> {
    let height = mask.len() / width;
    let r = radius as isize;
    let mut out = vec![false; mask.len()];
    for (i, _) in mask.iter().enumerate().filter(|(_, m)| **m) {
        let (y, x) = ((i / width) as isize, (i % width) as isize);
        for dy in -r..=r {
            for dx in -r..=r {
                let (yy, xx) = (y + dy, x + dx);
                let inside =
                    (0..height as isize).contains(&yy) && (0..width as isize).contains(&xx);
                if inside && dy * dy + dx * dx <= r * r {
                    out[yy as usize * width + xx as usize] = true;
                }
            }
        }
    }
    out
}

/// The spread of a flow over its frame: the root mean square of `F − F̄` (F̄ the frame's mean
/// flow), in pixels — 0 for a uniform flow, whatever the frame shows.
pub fn flow_spread(flow: &[[f32; 2]]) -> Option<f64> {
    let n = flow.len() as f64;
    if flow.is_empty() {
        return None;
    }
    let mean = [0, 1].map(|c| flow.iter().map(|v| v[c] as f64).sum::<f64>() / n);
    let ss: f64 = flow
        .iter()
        .map(|v| (v[0] as f64 - mean[0]).powi(2) + (v[1] as f64 - mean[1]).powi(2))
        .sum();
    Some((ss / n).sqrt())
}

/// Whether a larger value of metric `k` of [`METRICS`] is better (for the flow's spread, which
/// no value is better at: whether it is larger, i.e. varies more over the frame).
pub fn higher_is_better(k: usize) -> bool {
    !(5..=8).contains(&k)
}

/// Scores of one prediction (normal map and/or flow, `width` pixels a row) against its truth;
/// `threshold` is the normal map's contact threshold. The last, `pearson_p_near`, is r(p) over
/// the true contact dilated by [`NEAR_CONTACT_PX`]: how the map follows the pressure where there
/// is some, apart from how well it stays flat on the empty gel; the flow's spread over the frame
/// ([`flow_spread`]) shows a shear branch that outputs one uniform flow.
pub fn score_pair(
    normal: Option<&[f32]>,
    flow: Option<&[[f32; 2]]>,
    truth: &PairTruth,
    width: usize,
    threshold: f32,
) -> [Option<f64>; METRICS.len()] {
    let mut out = [None; METRICS.len()];
    let contact = truth.in_contact();
    if let Some(n) = normal.filter(|_| contact) {
        out[0] = pearson(n, &truth.pressure_kpa);
        out[1] = spearman(n, &truth.pressure_kpa);
        out[2] = pearson(n, &truth.indentation_mm);
        out[3] = spearman(n, &truth.indentation_mm);
        out[4] = iou(n, threshold, &truth.contact);
        let near = dilate(&truth.contact, width, NEAR_CONTACT_PX);
        let pick = |v: &[f32]| -> Vec<f32> {
            v.iter()
                .zip(&near)
                .filter(|(_, m)| **m)
                .map(|(x, _)| *x)
                .collect()
        };
        out[10] = pearson(&pick(n), &pick(&truth.pressure_kpa));
    }
    if let Some(f) = flow {
        if contact {
            out[5] = endpoint_error(f, &truth.flow_px, Some(&truth.contact));
            out[7] = angular_error(f, &truth.flow_px, Some(&truth.contact));
            let mag: Vec<f32> = f.iter().map(|v| v[0].hypot(v[1])).collect();
            out[9] = pearson(&mag, &truth.shear_traction_kpa);
        }
        out[6] = endpoint_error(f, &truth.flow_px, None);
        out[11] = flow_spread(f);
        out[8] = angular_error(f, &truth.flow_px, None);
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    fn truth(flow: Vec<[f32; 2]>, contact: Vec<bool>) -> PairTruth {
        let n = flow.len();
        let p: Vec<f32> = contact
            .iter()
            .map(|&c| if c { 10.0 } else { 0.0 })
            .collect();
        PairTruth {
            pressure_kpa: p.clone(),
            indentation_mm: p.iter().map(|v| v * 0.01).collect(),
            contact,
            shear_traction_kpa: vec![1.0; n],
            flow_px: flow,
        }
    }

    /// A uniform flow spreads by 0; a flow of +1 and −1 px along x on half the pixels each by
    /// exactly 1 px, whatever its mean.
    #[test]
    fn a_uniform_flow_has_no_spread() {
        assert_eq!(flow_spread(&[[0.3, -2.0]; 10]), Some(0.0));
        let split: Vec<[f32; 2]> = (0..10)
            .map(|i| [if i % 2 == 0 { 1.5 } else { -0.5 }, 4.0])
            .collect();
        assert!((flow_spread(&split).unwrap() - 1.0).abs() < 1e-12);
        assert_eq!(flow_spread(&[]), None);
    }

    /// Dilation by a disc: one pixel by radius 1 is the plus of five; by radius 2 the 13 pixels
    /// within distance 2, cut at the border.
    #[test]
    fn dilation_is_a_disc_cut_at_the_border() {
        let mut mask = vec![false; 25];
        mask[12] = true;
        let plus = dilate(&mask, 5, 1);
        let on: Vec<usize> = (0..25).filter(|&i| plus[i]).collect();
        assert_eq!(on, [7, 11, 12, 13, 17]);
        assert_eq!(dilate(&mask, 5, 2).iter().filter(|&&m| m).count(), 13);
        let mut corner = vec![false; 25];
        corner[0] = true;
        let on: Vec<usize> = (0..25).filter(|&i| dilate(&corner, 5, 1)[i]).collect();
        assert_eq!(on, [0, 1, 5]);
    }

    /// Near the contact the correlation reads only the dilated contact: a map equal to the
    /// pressure there (plus a constant) but with a bump far away scores 1 near the contact and
    /// less over the frame.
    #[test]
    fn the_correlation_near_the_contact_ignores_the_far_gel() {
        let (w, h) = (20usize, 20usize);
        let contact: Vec<bool> = (0..w * h)
            .map(|i| (i / w).abs_diff(5) <= 1 && (i % w).abs_diff(5) <= 1)
            .collect();
        let mut t = truth(vec![[0.0; 2]; w * h], contact);
        t.pressure_kpa[5 * w + 5] = 20.0;
        let mut map: Vec<f32> = t.pressure_kpa.iter().map(|p| p + 1.0).collect();
        map[18 * w + 18] = 30.0;
        let s = score_pair(Some(&map), None, &t, w, 5.0);
        assert!((s[10].unwrap() - 1.0).abs() < 1e-9, "{s:?}");
        assert!(s[0].unwrap() < 0.9, "{s:?}");
    }

    /// A flow equal to a known synthetic field scores EPE 0 and angular error 0; a flow off by
    /// (3, 4) everywhere scores EPE 5.
    #[test]
    fn a_known_flow_scores_zero_error() {
        let field: Vec<[f32; 2]> = (0..200)
            .map(|i| [((i % 20) as f32 * 0.3).sin(), (i / 20) as f32 * 0.1 - 0.5])
            .collect();
        let contact: Vec<bool> = (0..200).map(|i| (i % 20) > 5 && (i % 20) < 14).collect();
        let t = truth(field.clone(), contact);
        let s = score_pair(None, Some(&field), &t, 20, 0.5);
        assert_eq!(s[5], Some(0.0));
        assert_eq!(s[6], Some(0.0));
        assert!(s[7].unwrap().abs() < 1e-3 && s[8].unwrap().abs() < 1e-3);
        let off: Vec<[f32; 2]> = field.iter().map(|v| [v[0] + 3.0, v[1] + 4.0]).collect();
        let s = score_pair(None, Some(&off), &t, 20, 0.5);
        assert!((s[6].unwrap() - 5.0).abs() < 1e-5);
    }

    /// Angular error of (1, 0) against (0, 0) is atan(1) = 45°.
    #[test]
    fn angular_error_of_a_unit_flow_against_rest_is_45_degrees() {
        let a = angular_error(&[[1.0, 0.0]], &[[0.0, 0.0]], None).unwrap();
        assert!((a - 45.0).abs() < 1e-9);
    }

    #[test]
    fn correlations_match_hand_values() {
        let a = [1.0, 2.0, 3.0, 4.0];
        assert!((pearson(&a, &[2.0, 4.0, 6.0, 8.0]).unwrap() - 1.0).abs() < 1e-12);
        assert!((pearson(&a, &[4.0, 3.0, 2.0, 1.0]).unwrap() + 1.0).abs() < 1e-12);
        // monotone but not linear: Spearman 1, Pearson below 1
        let b = [1.0, 8.0, 27.0, 64.0];
        assert!((spearman(&a, &b).unwrap() - 1.0).abs() < 1e-12);
        assert!(pearson(&a, &b).unwrap() < 0.99);
        assert_eq!(pearson(&a, &[1.0; 4]), None);
        // ties share ranks: [1, 1, 2] → ranks [1.5, 1.5, 3]
        assert_eq!(ranks(&[1.0, 1.0, 2.0]), vec![1.5, 1.5, 3.0]);
    }

    #[test]
    fn threshold_is_chosen_for_the_best_iou() {
        let pred: Vec<f32> = (0..100).map(|i| i as f32 / 100.0).collect();
        let mask: Vec<bool> = (0..100).map(|i| i >= 70).collect();
        let t = best_threshold(&[&pred], &[&mask]);
        assert!((t - 0.70).abs() <= 0.011, "{t}");
        assert_eq!(iou(&pred, 0.70, &mask), Some(1.0));
    }
}
