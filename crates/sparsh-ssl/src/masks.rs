//! Masking and view samplers of the four objectives, on the patch grid.
//!
//! Tokens are numbered row-major over `(frame, row, column)` of the patch grid, as in
//! [`crate::vit::patchify`]. Every sampler returns plain index lists of equal length per batch
//! (JEPA context and target sets are truncated to the batch minimum, as the official collators do),
//! so they batch into one integer tensor.

use std::ops::Range;

use crate::rng::Rng;

/// MAE random masking of one batch.
#[derive(Debug, Clone)]
pub struct MaeMask {
    /// Visible tokens per sample, `[batch][keep]`, in shuffled order.
    pub keep: Vec<Vec<usize>>,
    /// Position of each token in the shuffled order, `[batch][tokens]`: gathering
    /// `cat(visible, mask tokens)` with it restores the grid order.
    pub restore: Vec<Vec<usize>>,
    /// `true` where the token is masked (predicted), `[batch][tokens]`.
    pub masked: Vec<Vec<bool>>,
}

impl MaeMask {
    /// The masks of the batch rows `rows` (a micro-batch).
    pub fn rows(&self, rows: Range<usize>) -> Self {
        Self {
            keep: self.keep[rows.clone()].to_vec(),
            restore: self.restore[rows.clone()].to_vec(),
            masked: self.masked[rows].to_vec(),
        }
    }
}

/// Per-sample uniform random masking of `ratio` of `tokens` (official: 0.75); keeps
/// `⌊tokens · (1 − ratio)⌋` tokens, at least one.
pub fn mae_mask(rng: &mut Rng, batch: usize, tokens: usize, ratio: f64) -> MaeMask {
    let k = (((tokens as f64) * (1.0 - ratio)) as usize).clamp(1, tokens);
    let mut out = MaeMask {
        keep: Vec::with_capacity(batch),
        restore: Vec::with_capacity(batch),
        masked: Vec::with_capacity(batch),
    };
    for _ in 0..batch {
        let perm = rng.permutation(tokens);
        let mut restore = vec![0; tokens];
        let mut masked = vec![true; tokens];
        for (pos, &tok) in perm.iter().enumerate() {
            restore[tok] = pos;
        }
        for &tok in &perm[..k] {
            masked[tok] = false;
        }
        out.keep.push(perm[..k].to_vec());
        out.restore.push(restore);
        out.masked.push(masked);
    }
    out
}

/// Context and target token sets of a JEPA step.
#[derive(Debug, Clone)]
pub struct JepaMasks {
    /// Context tokens `[batch][k_context]`, sorted.
    pub context: Vec<Vec<usize>>,
    /// Target sets `[set][batch][k_target]`, sorted (I-JEPA: one per target block;
    /// V-JEPA: one, the union of the tube blocks).
    pub targets: Vec<Vec<Vec<usize>>>,
}

impl JepaMasks {
    /// The masks of the batch rows `rows` (a micro-batch).
    pub fn rows(&self, rows: Range<usize>) -> Self {
        Self {
            context: self.context[rows.clone()].to_vec(),
            targets: self
                .targets
                .iter()
                .map(|t| t[rows.clone()].to_vec())
                .collect(),
        }
    }
}

/// Block geometry on a `rows × cols` grid.
fn block_size(
    rng: &mut Rng,
    rows: usize,
    cols: usize,
    scale: [f64; 2],
    aspect: [f64; 2],
) -> (usize, usize) {
    let area = rng.range_f64(scale[0], scale[1]) * (rows * cols) as f64;
    let ar = rng.range_f64(aspect[0], aspect[1]);
    let h = ((area * ar).sqrt().round() as usize).clamp(1, rows);
    let w = ((area / ar).sqrt().round() as usize).clamp(1, cols);
    (h, w)
}

/// Tokens of an `h × w` block at a random position, `(row, column)` pairs.
fn place_block(rng: &mut Rng, rows: usize, cols: usize, h: usize, w: usize) -> Vec<(usize, usize)> {
    let top = rng.below(rows - h + 1);
    let left = rng.below(cols - w + 1);
    (top..top + h)
        .flat_map(|r| (left..left + w).map(move |c| (r, c)))
        .collect()
}

fn truncate_to_min(sets: &mut [Vec<usize>]) {
    let k = sets.iter().map(Vec::len).min().unwrap_or(0);
    for s in sets {
        s.truncate(k);
    }
}

/// I-JEPA multi-block sampler settings (official defaults).
#[derive(Debug, Clone, serde::Serialize, serde::Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct IjepaMaskConfig {
    /// Target blocks (official 4).
    pub num_targets: usize,
    /// Target block area fraction range (official 0.15–0.2).
    pub target_scale: [f64; 2],
    /// Target aspect ratio range (official 0.75–1.5).
    pub target_aspect: [f64; 2],
    /// Context block area fraction range (official 0.85–1.0), aspect 1.
    pub context_scale: [f64; 2],
    /// Fewest context tokens accepted before retrying the placement (official 4).
    pub min_keep: usize,
}

impl Default for IjepaMaskConfig {
    fn default() -> Self {
        Self {
            num_targets: 4,
            target_scale: [0.15, 0.2],
            target_aspect: [0.75, 1.5],
            context_scale: [0.85, 1.0],
            min_keep: 4,
        }
    }
}

/// I-JEPA masks on a `rows × cols` grid: block sizes drawn once per batch, positions per sample;
/// the context is the context block minus every target block (no overlap).
pub fn ijepa_masks(
    rng: &mut Rng,
    batch: usize,
    rows: usize,
    cols: usize,
    cfg: &IjepaMaskConfig,
) -> JepaMasks {
    let (th, tw) = block_size(rng, rows, cols, cfg.target_scale, cfg.target_aspect);
    let (ch, cw) = block_size(rng, rows, cols, cfg.context_scale, [1.0, 1.0]);
    let mut targets = vec![Vec::with_capacity(batch); cfg.num_targets];
    let mut context = Vec::with_capacity(batch);
    for _ in 0..batch {
        let mut best: Option<(Vec<Vec<usize>>, Vec<usize>)> = None;
        for _attempt in 0..20 {
            let mut covered = vec![false; rows * cols];
            let tset: Vec<Vec<usize>> = (0..cfg.num_targets)
                .map(|_| {
                    let mut t: Vec<usize> = place_block(rng, rows, cols, th, tw)
                        .into_iter()
                        .map(|(r, c)| r * cols + c)
                        .collect();
                    t.sort_unstable();
                    t.iter().for_each(|&i| covered[i] = true);
                    t
                })
                .collect();
            let ctx: Vec<usize> = {
                let mut v: Vec<usize> = place_block(rng, rows, cols, ch, cw)
                    .into_iter()
                    .map(|(r, c)| r * cols + c)
                    .filter(|&i| !covered[i])
                    .collect();
                v.sort_unstable();
                v
            };
            let better = best.as_ref().is_none_or(|(_, b)| ctx.len() > b.len());
            let enough = ctx.len() >= cfg.min_keep;
            if better {
                best = Some((tset, ctx));
            }
            if enough {
                break;
            }
        }
        let (tset, ctx) = best.expect("at least one attempt");
        for (m, t) in tset.into_iter().enumerate() {
            targets[m].push(t);
        }
        context.push(ctx);
    }
    truncate_to_min(&mut context);
    JepaMasks { context, targets }
}

/// One V-JEPA tube-mask generator (official: 8 blocks at 0.15 and 2 blocks at 0.7).
#[derive(Debug, Clone, serde::Serialize, serde::Deserialize)]
#[serde(deny_unknown_fields)]
pub struct TubeMaskConfig {
    /// Blocks whose union is masked.
    pub num_blocks: usize,
    /// Spatial area fraction of each block.
    pub spatial_scale: f64,
    /// Aspect ratio range.
    #[serde(default = "default_tube_aspect")]
    pub aspect: [f64; 2],
}

fn default_tube_aspect() -> [f64; 2] {
    [0.75, 1.5]
}

/// The official pair of V-JEPA generators.
pub fn default_tube_masks() -> Vec<TubeMaskConfig> {
    vec![
        TubeMaskConfig {
            num_blocks: 8,
            spatial_scale: 0.15,
            aspect: default_tube_aspect(),
        },
        TubeMaskConfig {
            num_blocks: 2,
            spatial_scale: 0.7,
            aspect: default_tube_aspect(),
        },
    ]
}

/// V-JEPA tube masks on a `frames × rows × cols` grid: the union of the blocks, extended over
/// every frame, is the target; its complement the context. Block size per batch, positions per
/// sample; a placement leaving no context is redrawn.
pub fn tube_masks(
    rng: &mut Rng,
    batch: usize,
    grid: [usize; 3],
    cfg: &TubeMaskConfig,
) -> JepaMasks {
    let [gt, rows, cols] = grid;
    let s = cfg.spatial_scale;
    let (h, w) = block_size(rng, rows, cols, [s, s], cfg.aspect);
    let n2 = rows * cols;
    let mut targets = Vec::with_capacity(batch);
    let mut context = Vec::with_capacity(batch);
    for _ in 0..batch {
        let mut covered = vec![false; n2];
        for _attempt in 0..50 {
            covered = vec![false; n2];
            for _ in 0..cfg.num_blocks {
                for (r, c) in place_block(rng, rows, cols, h, w) {
                    covered[r * cols + c] = true;
                }
            }
            if covered.iter().any(|&m| !m) {
                break;
            }
        }
        if covered.iter().all(|&m| m) {
            // every placement covered the grid: free one corner token so a context exists
            covered[0] = false;
        }
        let (mut tgt, mut ctx) = (Vec::new(), Vec::new());
        for t in 0..gt {
            for (i, &m) in covered.iter().enumerate() {
                if m {
                    tgt.push(t * n2 + i)
                } else {
                    ctx.push(t * n2 + i)
                }
            }
        }
        targets.push(tgt);
        context.push(ctx);
    }
    truncate_to_min(&mut targets);
    truncate_to_min(&mut context);
    JepaMasks {
        context,
        targets: vec![targets],
    }
}

/// DINO view settings (official: 2 global views at 0.48–1, 8 local views at 0.1–0.48).
#[derive(Debug, Clone, serde::Serialize, serde::Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct DinoViewConfig {
    /// Global views (seen by student and teacher).
    pub num_global: usize,
    /// Global view area fraction range.
    pub global_scale: [f64; 2],
    /// Local views (student only).
    pub num_local: usize,
    /// Local view area fraction range.
    pub local_scale: [f64; 2],
    /// Fraction of each global view's tokens the student sees masked (iBOT; 0 = none).
    pub mask_ratio: f64,
}

impl Default for DinoViewConfig {
    fn default() -> Self {
        Self {
            num_global: 2,
            global_scale: [0.48, 1.0],
            num_local: 8,
            local_scale: [0.1, 0.48],
            mask_ratio: 0.0,
        }
    }
}

/// DINO views of one batch: token crops of the patch grid.
#[derive(Debug, Clone)]
pub struct DinoViews {
    /// Global views `[view][batch][k_global]`.
    pub global: Vec<Vec<Vec<usize>>>,
    /// Local views `[view][batch][k_local]`.
    pub local: Vec<Vec<Vec<usize>>>,
    /// Positions within each global view that the student sees masked, `[view][batch][m]`
    /// (iBOT; empty without masking).
    pub masked: Vec<Vec<Vec<usize>>>,
}

impl DinoViews {
    /// The views of the batch rows `rows` (a micro-batch).
    pub fn rows(&self, rows: Range<usize>) -> Self {
        let cut =
            |views: &[Vec<Vec<usize>>]| views.iter().map(|v| v[rows.clone()].to_vec()).collect();
        Self {
            global: cut(&self.global),
            local: cut(&self.local),
            masked: cut(&self.masked),
        }
    }
}

/// DINO token-crop views: each view keeps a rectangle of the patch grid whose area fraction is
/// drawn in its scale range and aspect ratio in 3/4–4/3 (one size per kind per batch, positions
/// per view and sample); with `mask_ratio > 0`, that fraction of each global view's positions
/// (at least one, never all) drawn at random per view and sample for iBOT.
pub fn dino_views(
    rng: &mut Rng,
    batch: usize,
    rows: usize,
    cols: usize,
    cfg: &DinoViewConfig,
) -> DinoViews {
    let aspect = [0.75, 4.0 / 3.0];
    let kind = |n: usize, scale: [f64; 2], rng: &mut Rng| {
        let (h, w) = block_size(rng, rows, cols, scale, aspect);
        (0..n)
            .map(|_| {
                (0..batch)
                    .map(|_| {
                        place_block(rng, rows, cols, h, w)
                            .into_iter()
                            .map(|(r, c)| r * cols + c)
                            .collect()
                    })
                    .collect()
            })
            .collect()
    };
    let global: Vec<Vec<Vec<usize>>> = kind(cfg.num_global, cfg.global_scale, rng);
    let local = kind(cfg.num_local, cfg.local_scale, rng);
    let masked = if cfg.mask_ratio > 0.0 {
        let k = global.first().and_then(|v| v.first()).map_or(0, Vec::len);
        let m = ((cfg.mask_ratio * k as f64).round() as usize).clamp(1, k.max(2) - 1);
        global
            .iter()
            .map(|view| {
                view.iter()
                    .map(|_| {
                        let mut picks = rng.permutation(k);
                        picks.truncate(m);
                        picks.sort_unstable();
                        picks
                    })
                    .collect()
            })
            .collect()
    } else {
        Vec::new()
    };
    DinoViews {
        global,
        local,
        masked,
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::collections::HashSet;

    /// Whether `set` is exactly a filled rectangle of the `cols`-wide grid.
    fn is_rectangle(set: &[usize], cols: usize) -> bool {
        let rs: Vec<usize> = set.iter().map(|i| i / cols).collect();
        let cs: Vec<usize> = set.iter().map(|i| i % cols).collect();
        let (r0, r1) = (*rs.iter().min().unwrap(), *rs.iter().max().unwrap());
        let (c0, c1) = (*cs.iter().min().unwrap(), *cs.iter().max().unwrap());
        let uniq: HashSet<_> = set.iter().collect();
        uniq.len() == set.len() && set.len() == (r1 - r0 + 1) * (c1 - c0 + 1)
    }

    #[test]
    fn mae_mask_counts_disjoint_and_inverse() {
        let mut rng = Rng::new(3);
        let m = mae_mask(&mut rng, 5, 108, 0.75);
        for b in 0..5 {
            assert_eq!(m.keep[b].len(), 27);
            assert_eq!(m.masked[b].iter().filter(|&&x| x).count(), 81);
            assert!(m.keep[b].iter().all(|&t| !m.masked[b][t]));
            let uniq: HashSet<_> = m.keep[b].iter().collect();
            assert_eq!(uniq.len(), 27);
            for (pos, &tok) in m.keep[b].iter().enumerate() {
                assert_eq!(m.restore[b][tok], pos);
            }
            let mut r = m.restore[b].clone();
            r.sort_unstable();
            assert_eq!(r, (0..108).collect::<Vec<_>>());
        }
        assert_ne!(m.keep[0], m.keep[1]);
    }

    #[test]
    fn ijepa_masks_blocks_sizes_and_no_overlap() {
        let (rows, cols) = (12, 9);
        let cfg = IjepaMaskConfig::default();
        for seed in 0..20 {
            let mut rng = Rng::new(seed);
            let m = ijepa_masks(&mut rng, 6, rows, cols, &cfg);
            assert_eq!(m.targets.len(), 4);
            let kt = m.targets[0][0].len();
            let frac = kt as f64 / (rows * cols) as f64;
            assert!((0.08..=0.3).contains(&frac), "target fraction {frac}");
            let kc = m.context[0].len();
            assert!(kc >= 1);
            for b in 0..6 {
                assert_eq!(m.context[b].len(), kc);
                let ctx: HashSet<_> = m.context[b].iter().collect();
                for t in &m.targets {
                    assert_eq!(t[b].len(), kt);
                    assert!(is_rectangle(&t[b], cols));
                    assert!(
                        t[b].iter().all(|i| !ctx.contains(i)),
                        "context overlaps a target"
                    );
                }
            }
        }
    }

    #[test]
    fn tube_masks_span_all_frames_and_partition() {
        let grid = [2, 12, 9];
        let n2 = 108;
        for cfg in default_tube_masks() {
            for seed in 0..10 {
                let mut rng = Rng::new(seed);
                let m = tube_masks(&mut rng, 4, grid, &cfg);
                let tg = &m.targets[0];
                for b in 0..4 {
                    assert_eq!(tg[b].len(), tg[0].len());
                    assert_eq!(m.context[b].len(), m.context[0].len());
                    assert!(!m.context[b].is_empty());
                    let t: HashSet<_> = tg[b].iter().copied().collect();
                    assert!(m.context[b].iter().all(|i| !t.contains(i)));
                    // a tube: before truncation each masked spatial cell is masked in every
                    // frame; after it, all frame-0 targets precede frame-1 ones
                    let f0: Vec<usize> = tg[b].iter().filter(|&&i| i < n2).copied().collect();
                    let f1: HashSet<usize> =
                        tg[b].iter().filter(|&&i| i >= n2).map(|i| i - n2).collect();
                    assert!(f1.iter().all(|i| f0.contains(i)));
                }
                let frac = tg[0].len() as f64 / (2 * n2) as f64;
                assert!(frac >= cfg.spatial_scale * 0.5, "{frac}");
            }
        }
    }

    #[test]
    fn dino_views_are_rectangles_in_scale() {
        let (rows, cols) = (12, 9);
        let cfg = DinoViewConfig::default();
        for seed in 0..20 {
            let v = dino_views(&mut Rng::new(seed), 3, rows, cols, &cfg);
            assert_eq!((v.global.len(), v.local.len()), (2, 8));
            for (views, [lo, hi]) in [(&v.global, cfg.global_scale), (&v.local, cfg.local_scale)] {
                let k = views[0][0].len();
                let frac = k as f64 / (rows * cols) as f64;
                assert!(
                    frac >= lo * 0.6 && frac <= hi * 1.4,
                    "fraction {frac} not near [{lo}, {hi}]"
                );
                for view in views.iter() {
                    for s in view {
                        assert_eq!(s.len(), k);
                        assert!(is_rectangle(s, cols));
                    }
                }
            }
            assert!(v.masked.is_empty());
        }
    }

    #[test]
    fn ibot_masks_take_the_ratio_of_each_global_view_and_leave_the_rest() {
        let (rows, cols) = (12, 9);
        let cfg = DinoViewConfig {
            mask_ratio: 0.3,
            ..DinoViewConfig::default()
        };
        let unmasked = dino_views(&mut Rng::new(4), 5, rows, cols, &DinoViewConfig::default());
        let v = dino_views(&mut Rng::new(4), 5, rows, cols, &cfg);
        // the masks are drawn after the views, which stay as they were
        assert_eq!((&v.global, &v.local), (&unmasked.global, &unmasked.local));
        assert_eq!(v.masked.len(), 2);
        let k = v.global[0][0].len();
        let m = (0.3 * k as f64).round() as usize;
        let mut distinct = HashSet::new();
        for view in &v.masked {
            assert_eq!(view.len(), 5);
            for s in view {
                assert_eq!(s.len(), m);
                assert!(s.windows(2).all(|w| w[0] < w[1]) && s[m - 1] < k);
                distinct.insert(s.clone());
            }
        }
        assert!(distinct.len() > 5, "masks repeat across samples and views");
    }
}
