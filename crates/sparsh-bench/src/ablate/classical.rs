//! The classical contact-circle detector, which learns nothing from data but its three settings:
//! the difference image's magnitude |I − I₀| (Euclidean over channels), a box blur, a threshold,
//! the largest 4-connected region above it, its centroid as the centre and √(area/π) times a
//! scale as the radius. The settings are tuned by grid search on synthetic frames only.

use super::data::{Circle, CircleFrames};

/// The detector's settings.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct Detector {
    /// Half-width of the box blur (input pixels; 0 = none).
    pub blur_px: usize,
    /// Threshold on the blurred magnitude (8-bit levels).
    pub threshold: f32,
    /// Radius = scale · √(area/π).
    pub radius_scale: f64,
}

/// Box blur of half-width `r` (edge-clamped window means), separable.
fn blur(v: &[f32], h: usize, w: usize, r: usize) -> Vec<f32> {
    if r == 0 {
        return v.to_vec();
    }
    let pass = |src: &[f32], along_x: bool| -> Vec<f32> {
        let mut out = vec![0.0f32; h * w];
        for y in 0..h {
            for x in 0..w {
                let (pos, len) = if along_x { (x, w) } else { (y, h) };
                let (lo, hi) = (pos.saturating_sub(r), (pos + r).min(len - 1));
                let mut s = 0.0;
                for q in lo..=hi {
                    s += if along_x {
                        src[y * w + q]
                    } else {
                        src[q * w + x]
                    };
                }
                out[y * w + x] = s / (hi - lo + 1) as f32;
            }
        }
        out
    };
    pass(&pass(v, true), false)
}

/// The blurred magnitude of frame `k`'s difference image.
fn magnitude(frames: &CircleFrames, k: usize, blur_px: usize) -> Vec<f32> {
    let [h, w] = frames.size;
    let img = frames.image(k);
    let m: Vec<f32> = (0..h * w)
        .map(|p| {
            (0..3)
                .map(|c| img[c * h * w + p].powi(2))
                .sum::<f32>()
                .sqrt()
        })
        .collect();
    blur(&m, h, w, blur_px)
}

/// The largest 4-connected region of `mask`: (pixel count, centroid x, centroid y).
fn largest_region(mask: &[bool], h: usize, w: usize) -> Option<(usize, f64, f64)> {
    let mut seen = vec![false; h * w];
    let mut best: Option<(usize, f64, f64)> = None;
    let mut stack = Vec::new();
    for start in 0..h * w {
        if !mask[start] || seen[start] {
            continue;
        }
        seen[start] = true;
        stack.push(start);
        let (mut n, mut sx, mut sy) = (0usize, 0.0f64, 0.0f64);
        while let Some(p) = stack.pop() {
            let (x, y) = (p % w, p / w);
            n += 1;
            sx += x as f64;
            sy += y as f64;
            let mut visit = |q: usize| {
                if mask[q] && !seen[q] {
                    seen[q] = true;
                    stack.push(q);
                }
            };
            if x > 0 {
                visit(p - 1);
            }
            if x + 1 < w {
                visit(p + 1);
            }
            if y > 0 {
                visit(p - w);
            }
            if y + 1 < h {
                visit(p + w);
            }
        }
        if best.is_none_or(|b| n > b.0) {
            best = Some((n, sx / n as f64, sy / n as f64));
        }
    }
    best
}

/// Centroid and equivalent radius of the region, in input pixels, before the radius scale.
fn region(frames: &CircleFrames, k: usize, blur_px: usize, threshold: f32) -> Option<[f64; 3]> {
    let [h, w] = frames.size;
    let m = magnitude(frames, k, blur_px);
    let mask: Vec<bool> = m.iter().map(|&v| v > threshold).collect();
    largest_region(&mask, h, w)
        .map(|(n, cx, cy)| [cx, cy, (n as f64 / std::f64::consts::PI).sqrt()])
}

/// An input pixel's centre in the pack's pixels (`factor` pack pixels per input pixel).
fn to_pack(v: f64, factor: f64) -> f64 {
    (v + 0.5) * factor - 0.5
}

impl Detector {
    /// The circle of frame `k` (`pack_width` px wide in the pack); `None` when nothing exceeds
    /// the threshold.
    pub fn detect(&self, frames: &CircleFrames, k: usize, pack_width: usize) -> Option<Circle> {
        let f = pack_width as f64 / frames.size[1] as f64;
        region(frames, k, self.blur_px, self.threshold).map(|[cx, cy, r]| Circle {
            cx_px: to_pack(cx, f),
            cy_px: to_pack(cy, f),
            r_px: self.radius_scale * r * f,
        })
    }

    /// The settings best on `frames` (synthetic): for each blur and threshold of the grid, the
    /// radius scale is the median ratio of true to equivalent radius, and the setting kept is
    /// the one of least median (centre error + radius error) in pack pixels; a frame without a
    /// region counts as missing by its true radius twice.
    pub fn tune(frames: &CircleFrames, pack_width: usize) -> Detector {
        let f = pack_width as f64 / frames.size[1] as f64;
        let mut best: Option<(f64, Detector)> = None;
        for blur_px in [0, 1, 2] {
            for step in 1..=40 {
                let threshold = step as f32;
                let found: Vec<Option<[f64; 3]>> = (0..frames.len())
                    .map(|k| region(frames, k, blur_px, threshold))
                    .collect();
                let mut ratios: Vec<f64> = found
                    .iter()
                    .zip(&frames.circles)
                    .filter_map(|(r, c)| r.filter(|r| r[2] > 0.0).map(|r| c.r_px / (r[2] * f)))
                    .collect();
                if ratios.is_empty() {
                    continue;
                }
                ratios.sort_by(f64::total_cmp);
                let radius_scale = crate::stats::quantile(&ratios, 0.5);
                let mut cost: Vec<f64> = found
                    .iter()
                    .zip(&frames.circles)
                    .map(|(r, c)| match r {
                        Some([x, y, rr]) => {
                            (to_pack(*x, f) - c.cx_px).hypot(to_pack(*y, f) - c.cy_px)
                                + (radius_scale * rr * f - c.r_px).abs()
                        }
                        None => 2.0 * c.r_px,
                    })
                    .collect();
                cost.sort_by(f64::total_cmp);
                let median = crate::stats::quantile(&cost, 0.5);
                if best.is_none_or(|b| median < b.0) {
                    best = Some((
                        median,
                        Detector {
                            blur_px,
                            threshold,
                            radius_scale,
                        },
                    ));
                }
            }
        }
        best.map_or(
            Detector {
                blur_px: 1,
                threshold: 8.0,
                radius_scale: 1.0,
            },
            |b| b.1,
        )
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Discs of a soft-edged bump: the tuned detector finds each centre to a fraction of a pixel
    /// and its radius to a few per cent.
    #[test]
    fn tuning_recovers_discs_of_a_known_profile() {
        let (h, w) = (60usize, 80usize);
        let mut frames = CircleFrames {
            size: [h, w],
            ..Default::default()
        };
        for k in 0..12 {
            let c = Circle {
                cx_px: 20.0 + 3.7 * k as f64,
                cy_px: 15.0 + 2.3 * k as f64,
                r_px: 5.0 + 0.5 * k as f64,
            };
            let mut img = vec![0.0f32; 3 * h * w];
            for y in 0..h {
                for x in 0..w {
                    let d = (x as f64 - c.cx_px).hypot(y as f64 - c.cy_px) / c.r_px;
                    // 30 levels inside, falling off smoothly outside
                    let v = if d <= 1.0 {
                        30.0
                    } else {
                        30.0 * (-(d - 1.0) * 4.0).exp()
                    };
                    img[y * w + x] = v as f32;
                    img[h * w + y * w + x] = -0.5 * v as f32;
                }
            }
            frames.images.extend(img);
            frames.circles.push(c);
            frames.groups.push(k);
        }
        let d = Detector::tune(&frames, w);
        for (k, c) in frames.circles.iter().enumerate() {
            let p = d.detect(&frames, k, w).expect("a region");
            assert!(
                (p.cx_px - c.cx_px).hypot(p.cy_px - c.cy_px) < 0.5,
                "{p:?} vs {c:?}"
            );
            assert!((p.r_px - c.r_px).abs() / c.r_px < 0.08, "{p:?} vs {c:?}");
        }
    }

    #[test]
    fn the_largest_region_wins() {
        let mut mask = vec![false; 5 * 5];
        for p in [0, 1, 5] {
            mask[p] = true;
        }
        for p in [18, 19, 23, 24] {
            mask[p] = true;
        }
        assert_eq!(largest_region(&mask, 5, 5), Some((4, 3.5, 3.5)));
        assert_eq!(largest_region(&[false; 4], 2, 2), None);
    }
}
