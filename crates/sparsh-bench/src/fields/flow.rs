//! Farnebäck dense optical flow (G. Farnebäck, "Two-frame motion estimation based on polynomial
//! expansion", SCIA 2003): the classical, learning-free baseline that learned shear-field
//! decoders are compared against.
//!
//! Every neighbourhood of both images is fitted by a quadratic f(x) ≈ xᵀAx + bᵀx + c (the
//! paper's *polynomial expansion*). A translation f₂(x) = f₁(x − d) leaves A unchanged and moves
//! the linear term to b₂ = b₁ − 2A₁d, so d solves A d = Δb with A = (A₁ + A₂)/2 and
//! Δb = −½(b₂ − b₁) (*displacement estimation*). The pointwise constraints are pooled over a
//! Gaussian window, (Σ w AᵀA) d = Σ w AᵀΔb, re-linearised around the current estimate d̃
//! (A₂ and b₂ read at x + d̃, Δb = −½(b₂(x + d̃) − b₁(x)) + A d̃; *a priori displacement*), and run
//! coarse to fine over an image pyramid (*iterative and multi-scale estimation*).
//!
//! Images are `f32`, row-major, values typically in [0, 1]; the work is done in `f64`. Borders
//! are handled by clamping coordinates (replicated edge pixels); constraints whose fit reaches
//! past the image edge get a reduced certainty and those whose displaced point leaves the image
//! get none (the paper's certainty weighting; OpenCV down-weights its 5-pixel border likewise).

/// Parameters of Farnebäck's method. The defaults follow OpenCV's `calcOpticalFlowFarneback`
/// usage (`pyr_scale` 0.5, `levels` 3, `winsize` 15 with its Gaussian window — σ = 0.3 · 7 =
/// 2.1 —, `iterations` 3, `poly_n` 5, `poly_sigma` 1.1).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct FarnebackParams {
    /// Size ratio between successive pyramid levels, in (0, 1).
    pub pyramid_scale: f64,
    /// Number of pyramid levels including the full-resolution image, at least 1 (1 = no
    /// pyramid). Levels whose shorter side would fall below 16 px are dropped.
    pub levels: usize,
    /// Standard deviation (px) of the Gaussian window w over which the displacement constraints
    /// are pooled, positive and finite; the window spans ±⌈3σ⌉ px.
    pub window_sigma: f64,
    /// Displacement updates per pyramid level (0 leaves the flow at zero).
    pub iterations: usize,
    /// Side (px) of the square neighbourhood of the polynomial fit, at least 3: a poly_n × poly_n
    /// window, radius ⌊poly_n/2⌋. OpenCV's implementation uses a wider (2·poly_n+1) support.
    pub poly_n: usize,
    /// Standard deviation (px) of the Gaussian applicability of the polynomial fit, positive and
    /// finite (values below 0.25 px are raised to 0.25 px).
    pub poly_sigma: f64,
}

/// A [`FarnebackParams`] field outside its range: which one, and what is wrong.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
#[error("Farnebäck flow: {field} {msg}")]
pub struct InvalidParameter {
    /// The field.
    pub field: &'static str,
    /// What is wrong with its value.
    pub msg: String,
}

impl FarnebackParams {
    /// Every field inside its documented range, or the first that is not.
    pub fn validate(&self) -> Result<(), InvalidParameter> {
        let bad = |field, msg: String| Err(InvalidParameter { field, msg });
        if !(self.pyramid_scale > 0.0 && self.pyramid_scale < 1.0) {
            return bad(
                "pyramid_scale",
                format!("{} is not in (0, 1)", self.pyramid_scale),
            );
        }
        if self.levels == 0 {
            return bad("levels", "0: at least 1 (the full-resolution image)".into());
        }
        for (field, value) in [
            ("window_sigma", self.window_sigma),
            ("poly_sigma", self.poly_sigma),
        ] {
            if !(value.is_finite() && value > 0.0) {
                return bad(
                    field,
                    format!("{value} is not a positive finite number of px"),
                );
            }
        }
        if self.poly_n < 3 {
            return bad("poly_n", format!("{}: at least 3 px", self.poly_n));
        }
        Ok(())
    }
}

impl Default for FarnebackParams {
    fn default() -> Self {
        Self {
            pyramid_scale: 0.5,
            levels: 3,
            window_sigma: 2.1,
            iterations: 3,
            poly_n: 5,
            poly_sigma: 1.1,
        }
    }
}

/// Shortest side (px) a pyramid level may have.
const MIN_LEVEL_SIDE_PX: usize = 16;
/// Tikhonov weight, relative to the mean trace of the pooled normal matrix, that pulls each
/// update towards the current estimate d̃ where the image has no structure.
const RELATIVE_REGULARISER: f64 = 1e-3;
/// Absolute floor of that weight, so a flat image still gives a well-posed 2×2 solve.
const REGULARISER_FLOOR: f64 = 1e-12;
/// Floor of the polynomial applicability's σ (px), keeping the fit's Gram matrix invertible.
const MIN_POLY_SIGMA_PX: f64 = 0.25;

/// Dense flow from `prev` to `next` (both `height × width`, row-major): for each pixel x of `prev`,
/// the displacement d(x) = [dx (columns), dy (rows)] in pixels with prev(x) ≈ next(x + d(x)).
///
/// The returned vector is row-major like the inputs. Non-finite input values are read as 0 and
/// every returned component is finite. Parameters outside their ranges are refused
/// ([`FarnebackParams::validate`]). Panics only if a slice length differs from `height * width`
/// (callers own the shapes); an empty image gives an empty flow.
pub fn farneback_flow(
    prev: &[f32],
    next: &[f32],
    height: usize,
    width: usize,
    params: &FarnebackParams,
) -> Result<Vec<[f32; 2]>, InvalidParameter> {
    params.validate()?;
    let pixel_count = height * width;
    assert_eq!(
        prev.len(),
        pixel_count,
        "prev must hold height * width pixels"
    );
    assert_eq!(
        next.len(),
        pixel_count,
        "next must hold height * width pixels"
    );
    if pixel_count == 0 {
        return Ok(Vec::new());
    }
    let prev = Image::from_f32(prev, height, width);
    let next = Image::from_f32(next, height, width);

    let poly_radius = params.poly_n / 2;
    let poly_sigma = params.poly_sigma.max(MIN_POLY_SIGMA_PX);
    let applicability = PolyApplicability::new(poly_sigma, poly_radius);
    let window = gaussian_kernel(params.window_sigma, height.max(width));

    let scales = pyramid_scales(height, width, params);
    let mut flow = FlowField::zeros(scaled_len(height, scales[0]), scaled_len(width, scales[0]));
    for scale in scales {
        let prev_level = prev.pyramid_level(scale);
        let next_level = next.pyramid_level(scale);
        // The coarser level's estimate (the zero field at the coarsest level) as the prior d̃.
        flow = flow.upsampled(prev_level.height, prev_level.width);
        let mut solver = DisplacementSolver {
            prev: applicability.expand(&prev_level),
            next: applicability.expand(&next_level),
            window: &window,
            poly_radius,
            normal_terms: vec![[0.0; 5]; flow.vectors.len()],
            blur_scratch: Vec::new(),
        };
        for _ in 0..params.iterations {
            solver.update(&mut flow);
        }
    }
    Ok(flow
        .vectors
        .iter()
        .map(|&[dx_px, dy_px]| [finite_or_zero(dx_px), finite_or_zero(dy_px)])
        .collect())
}

/// The scale factors of the pyramid levels, coarsest first, ending with 1 (full resolution);
/// never empty.
fn pyramid_scales(height: usize, width: usize, params: &FarnebackParams) -> Vec<f64> {
    let ratio = params.pyramid_scale;
    let mut scales = vec![1.0];
    while scales.len() < params.levels {
        let scale = ratio * scales[scales.len() - 1];
        if scaled_len(height, scale).min(scaled_len(width, scale)) < MIN_LEVEL_SIDE_PX {
            break;
        }
        scales.push(scale);
    }
    scales.reverse();
    scales
}

/// The side of a pyramid level: `len · scale` rounded, at least 1.
fn scaled_len(len: usize, scale: f64) -> usize {
    ((len as f64 * scale).round() as usize).max(1)
}

/// `value` as `f32`, or 0 if it is not finite (after the cast).
fn finite_or_zero(value: f64) -> f32 {
    let value = value as f32;
    if value.is_finite() { value } else { 0.0 }
}

/// A single-channel `f64` image, row-major.
struct Image {
    height: usize,
    width: usize,
    pixels: Vec<f64>,
}

impl Image {
    /// The image of `pixels`, non-finite values read as 0.
    fn from_f32(pixels: &[f32], height: usize, width: usize) -> Self {
        let pixels = pixels
            .iter()
            .map(|&v| if v.is_finite() { f64::from(v) } else { 0.0 })
            .collect();
        Self {
            height,
            width,
            pixels,
        }
    }

    /// The pyramid level at `scale` ≤ 1, built directly from full resolution as OpenCV does:
    /// Gaussian blur with σ = (1/scale − 1)/2 against aliasing, then bilinear resampling on the
    /// pixel-centre-aligned grid of size `round(side · scale)`.
    fn pyramid_level(&self, scale: f64) -> Self {
        let (height, width) = (
            scaled_len(self.height, scale),
            scaled_len(self.width, scale),
        );
        if height == self.height && width == self.width {
            return Self {
                height,
                width,
                pixels: self.pixels.clone(),
            };
        }
        let kernel = gaussian_kernel((1.0 / scale - 1.0) / 2.0, self.height.max(self.width));
        let mut blurred: Vec<[f64; 1]> = self.pixels.iter().map(|&v| [v]).collect();
        blur(&mut blurred, &mut Vec::new(), self.width, &kernel);
        let pixels = resample_bilinear(&blurred, self.height, self.width, height, width)
            .into_iter()
            .map(|[v]| v)
            .collect();
        Self {
            height,
            width,
            pixels,
        }
    }
}

/// A displacement field [dx, dy] (px) on a `height × width` grid, row-major.
struct FlowField {
    height: usize,
    width: usize,
    vectors: Vec<[f64; 2]>,
}

impl FlowField {
    /// The zero field.
    fn zeros(height: usize, width: usize) -> Self {
        Self {
            height,
            width,
            vectors: vec![[0.0; 2]; height * width],
        }
    }

    /// The field bilinearly resampled to `height × width`, each component multiplied by the size
    /// ratio of its axis (≈ 1/pyramid_scale) so displacements are in the finer level's pixels;
    /// the same size gives the field unchanged.
    fn upsampled(&self, height: usize, width: usize) -> Self {
        let x_ratio = width as f64 / self.width as f64;
        let y_ratio = height as f64 / self.height as f64;
        let vectors = resample_bilinear(&self.vectors, self.height, self.width, height, width)
            .into_iter()
            .map(|[dx_px, dy_px]| [dx_px * x_ratio, dy_px * y_ratio])
            .collect();
        Self {
            height,
            width,
            vectors,
        }
    }
}

/// Coefficients of the local quadratic f(x) ≈ xᵀAx + bᵀx + c around a pixel (x = column offset,
/// y = row offset), stored as [a_xx, a_xy, a_yy, b_x, b_y] with A = [[a_xx, a_xy], [a_xy, a_yy]]
/// (so the xy monomial's coefficient is 2·a_xy); c is not needed.
type Quadratic = [f64; 5];

/// A polynomial expansion of one image: one [`Quadratic`] per pixel.
struct Expansion {
    height: usize,
    width: usize,
    quadratics: Vec<Quadratic>,
}

/// The Gaussian applicability of the polynomial fit and the moments that turn its projections
/// into least-squares coefficients.
struct PolyApplicability {
    /// Normalised 1-D Gaussian g(k), k = −radius..=radius; the 2-D weight is g(x)·g(y).
    weights: Vec<f64>,
    /// Σ g(k)·k².
    second_moment: f64,
    /// Σ g(k)·k⁴.
    fourth_moment: f64,
}

impl PolyApplicability {
    /// The applicability of σ = `sigma_px` over a (2·radius + 1)² neighbourhood.
    fn new(sigma_px: f64, radius: usize) -> Self {
        let weights = gaussian_kernel_of_radius(sigma_px, radius);
        let moment = |power: i32| {
            weights
                .iter()
                .enumerate()
                .map(|(i, g)| g * (i as f64 - radius as f64).powi(power))
                .sum::<f64>()
        };
        Self {
            second_moment: moment(2),
            fourth_moment: moment(4),
            weights,
        }
    }

    /// Polynomial expansion of `image` by weighted least squares with weights w = g(x)g(y), as
    /// separable correlations (the paper's and OpenCV's formulation). With the basis
    /// {1, x, y, x², y², xy}, Σw = 1, m₂ = Σ g k² and m₄ = Σ g k⁴, the normal equations decouple
    /// into b_x = ⟨x f⟩/m₂, b_y = ⟨y f⟩/m₂, a_xx = (⟨x² f⟩ − m₂⟨f⟩)/(m₄ − m₂²) (a_yy alike) and
    /// 2·a_xy = ⟨xy f⟩/m₂², where ⟨·⟩ = Σ w(·) over the neighbourhood (edge pixels replicated).
    fn expand(&self, image: &Image) -> Expansion {
        let (height, width) = (image.height, image.width);
        let radius = (self.weights.len() / 2) as isize;
        // Vertical pass: Σ g(k)·kᵖ·f(row + k, col) for p = 0, 1, 2.
        let mut column_moments = vec![[0.0; 3]; height * width];
        for row in 0..height {
            for col in 0..width {
                let mut sums = [0.0; 3];
                for (tap, g) in self.weights.iter().enumerate() {
                    let k = tap as isize - radius;
                    let value = image.pixels[clamp_index(row as isize + k, height) * width + col];
                    let k = k as f64;
                    sums[0] += g * value;
                    sums[1] += g * k * value;
                    sums[2] += g * k * k * value;
                }
                column_moments[row * width + col] = sums;
            }
        }
        // Horizontal pass and the closed-form least-squares solution.
        let (m2, m4) = (self.second_moment, self.fourth_moment);
        let mut quadratics = vec![[0.0; 5]; height * width];
        for row in 0..height {
            for col in 0..width {
                let (mut f, mut xf, mut xxf, mut yf, mut xyf, mut yyf) =
                    (0.0, 0.0, 0.0, 0.0, 0.0, 0.0);
                for (tap, g) in self.weights.iter().enumerate() {
                    let k = tap as isize - radius;
                    let [v0, v1, v2] =
                        column_moments[row * width + clamp_index(col as isize + k, width)];
                    let k = k as f64;
                    f += g * v0;
                    xf += g * k * v0;
                    xxf += g * k * k * v0;
                    yf += g * v1;
                    xyf += g * k * v1;
                    yyf += g * v2;
                }
                let quadratic_scale = 1.0 / (m4 - m2 * m2);
                quadratics[row * width + col] = [
                    (xxf - m2 * f) * quadratic_scale,
                    0.5 * xyf / (m2 * m2),
                    (yyf - m2 * f) * quadratic_scale,
                    xf / m2,
                    yf / m2,
                ];
            }
        }
        Expansion {
            height,
            width,
            quadratics,
        }
    }
}

/// The displacement estimation at one pyramid level: both expansions, the pooling window and
/// buffers reused across iterations.
struct DisplacementSolver<'a> {
    /// Expansion of the previous image.
    prev: Expansion,
    /// Expansion of the next image.
    next: Expansion,
    /// Normalised Gaussian window w.
    window: &'a [f64],
    /// Radius of the polynomial fit, for the edge certainty.
    poly_radius: usize,
    /// Per pixel c·[(AᵀA)₁₁, (AᵀA)₁₂, (AᵀA)₂₂, (AᵀΔb)ₓ, (AᵀΔb)ᵧ], then their pooled sums.
    normal_terms: Vec<[f64; 5]>,
    /// Scratch of the separable blur.
    blur_scratch: Vec<[f64; 5]>,
}

impl DisplacementSolver<'_> {
    /// One displacement update of `flow` in place. For every pixel x, with d̃ = `flow`(x),
    /// A = (A₁(x) + A₂(x + d̃))/2 and Δb = −½(b₂(x + d̃) − b₁(x)) + A d̃ (`next` read
    /// bilinearly), the products c·AᵀA and c·AᵀΔb (c: certainty) are pooled with the Gaussian
    /// window and the 2×2 system (Σ w c AᵀA + λI) d = Σ w c AᵀΔb + λ d̃ is solved. The small λ
    /// pulls d towards d̃ only where the image has no structure; at convergence (d = d̃) it
    /// cancels, so it adds no bias.
    fn update(&mut self, flow: &mut FlowField) {
        let (height, width) = (self.prev.height, self.prev.width);
        for (index, terms) in self.normal_terms.iter_mut().enumerate() {
            let (row, col) = (index / width, index % width);
            let [dx_px, dy_px] = flow.vectors[index];
            let (target_col, target_row) = (col as f64 + dx_px, row as f64 + dy_px);
            let certainty = edge_certainty(col as f64, width, self.poly_radius)
                * edge_certainty(row as f64, height, self.poly_radius)
                * edge_certainty(target_col, width, self.poly_radius)
                * edge_certainty(target_row, height, self.poly_radius);
            if certainty == 0.0 {
                *terms = [0.0; 5];
                continue;
            }
            let [a1_xx, a1_xy, a1_yy, b1_x, b1_y] = self.prev.quadratics[index];
            let [a2_xx, a2_xy, a2_yy, b2_x, b2_y] =
                sample_bilinear(&self.next.quadratics, height, width, target_row, target_col);
            let (a_xx, a_xy, a_yy) = (
                (a1_xx + a2_xx) / 2.0,
                (a1_xy + a2_xy) / 2.0,
                (a1_yy + a2_yy) / 2.0,
            );
            let delta_b_x = -0.5 * (b2_x - b1_x) + a_xx * dx_px + a_xy * dy_px;
            let delta_b_y = -0.5 * (b2_y - b1_y) + a_xy * dx_px + a_yy * dy_px;
            *terms = [
                certainty * (a_xx * a_xx + a_xy * a_xy),
                certainty * a_xy * (a_xx + a_yy),
                certainty * (a_xy * a_xy + a_yy * a_yy),
                certainty * (a_xx * delta_b_x + a_xy * delta_b_y),
                certainty * (a_xy * delta_b_x + a_yy * delta_b_y),
            ];
        }
        blur(
            &mut self.normal_terms,
            &mut self.blur_scratch,
            width,
            self.window,
        );
        let pooled = &self.normal_terms;
        let mean_trace =
            pooled.iter().map(|m| m[0] + m[2]).sum::<f64>() / (2 * pooled.len()) as f64;
        let lambda = RELATIVE_REGULARISER * mean_trace + REGULARISER_FLOOR;
        for (&[g_xx, g_xy, g_yy, h_x, h_y], vector) in pooled.iter().zip(&mut flow.vectors) {
            let [prior_dx_px, prior_dy_px] = *vector;
            let (g_xx, g_yy) = (g_xx + lambda, g_yy + lambda);
            let (h_x, h_y) = (h_x + lambda * prior_dx_px, h_y + lambda * prior_dy_px);
            let det = g_xx * g_yy - g_xy * g_xy;
            *vector = [
                (g_yy * h_x - g_xy * h_y) / det,
                (g_xx * h_y - g_xy * h_x) / det,
            ];
        }
    }
}

/// Certainty of a constraint along one axis at coordinate `pos` (px) of an axis of `len` pixels:
/// 0 outside [0, len − 1], rising linearly to 1 over the `poly_radius` pixels next to the edge,
/// whose polynomial fits reach into replicated border pixels.
fn edge_certainty(pos: f64, len: usize, poly_radius: usize) -> f64 {
    let last = (len - 1) as f64;
    if !(0.0..=last).contains(&pos) {
        return 0.0;
    }
    let distance_px = pos.min(last - pos);
    ((distance_px + 1.0) / (poly_radius as f64 + 1.0)).min(1.0)
}

/// `index` clamped into `0..len` (replicated border).
fn clamp_index(index: isize, len: usize) -> usize {
    index.clamp(0, len as isize - 1) as usize
}

/// The field `values` (`height × width`, row-major) read at (`row`, `col`) by bilinear
/// interpolation, coordinates clamped into the image.
fn sample_bilinear<const C: usize>(
    values: &[[f64; C]],
    height: usize,
    width: usize,
    row: f64,
    col: f64,
) -> [f64; C] {
    let row = row.clamp(0.0, (height - 1) as f64);
    let col = col.clamp(0.0, (width - 1) as f64);
    let (row0, col0) = (row.floor() as usize, col.floor() as usize);
    let (row1, col1) = ((row0 + 1).min(height - 1), (col0 + 1).min(width - 1));
    let (fy, fx) = (row - row0 as f64, col - col0 as f64);
    let corners = [
        (row0, col0, (1.0 - fy) * (1.0 - fx)),
        (row0, col1, (1.0 - fy) * fx),
        (row1, col0, fy * (1.0 - fx)),
        (row1, col1, fy * fx),
    ];
    let mut sample = [0.0; C];
    for (r, c, weight) in corners {
        for (s, v) in sample.iter_mut().zip(&values[r * width + c]) {
            *s += weight * v;
        }
    }
    sample
}

/// The field `values` (`height × width`) bilinearly resampled to `new_height × new_width` with
/// pixel centres aligned (source = (target + ½)·old/new − ½), as OpenCV's `INTER_LINEAR`.
fn resample_bilinear<const C: usize>(
    values: &[[f64; C]],
    height: usize,
    width: usize,
    new_height: usize,
    new_width: usize,
) -> Vec<[f64; C]> {
    let y_step = height as f64 / new_height as f64;
    let x_step = width as f64 / new_width as f64;
    let mut resampled = Vec::with_capacity(new_height * new_width);
    for row in 0..new_height {
        let source_row = (row as f64 + 0.5) * y_step - 0.5;
        for col in 0..new_width {
            let source_col = (col as f64 + 0.5) * x_step - 0.5;
            resampled.push(sample_bilinear(
                values, height, width, source_row, source_col,
            ));
        }
    }
    resampled
}

/// A normalised Gaussian kernel of σ = `sigma_px` over ±⌈3σ⌉ taps, the radius capped at
/// `max_radius`; a non-positive or NaN σ gives the identity kernel.
fn gaussian_kernel(sigma_px: f64, max_radius: usize) -> Vec<f64> {
    if sigma_px.is_nan() || sigma_px <= 0.0 {
        return vec![1.0];
    }
    let radius = (3.0 * sigma_px).ceil().min(max_radius as f64) as usize;
    gaussian_kernel_of_radius(sigma_px, radius)
}

/// A normalised Gaussian kernel of σ = `sigma_px` (> 0) with taps −radius..=radius.
fn gaussian_kernel_of_radius(sigma_px: f64, radius: usize) -> Vec<f64> {
    let taps: Vec<f64> = (0..=2 * radius)
        .map(|i| {
            let k = i as f64 - radius as f64;
            (-k * k / (2.0 * sigma_px * sigma_px)).exp()
        })
        .collect();
    let total: f64 = taps.iter().sum();
    taps.into_iter().map(|t| t / total).collect()
}

/// Separable correlation, in place, of every channel of `values` (rows of `width`) with the
/// symmetric `kernel` along rows and columns, edge pixels replicated; `scratch` is resized to
/// hold the row pass.
fn blur<const C: usize>(
    values: &mut [[f64; C]],
    scratch: &mut Vec<[f64; C]>,
    width: usize,
    kernel: &[f64],
) {
    let height = values.len() / width;
    let radius = kernel.len() / 2;
    scratch.clear();
    scratch.resize(values.len(), [0.0; C]);
    let mut padded_row = Vec::with_capacity(width + 2 * radius);
    for (source_row, out_row) in values
        .chunks_exact(width)
        .zip(scratch.chunks_exact_mut(width))
    {
        padded_row.clear();
        padded_row.extend(
            (0..width + 2 * radius)
                .map(|i| source_row[clamp_index(i as isize - radius as isize, width)]),
        );
        let out_row = out_row.as_flattened_mut();
        for (tap, weight) in kernel.iter().enumerate() {
            let shifted = padded_row[tap..tap + width].as_flattened();
            for (o, v) in out_row.iter_mut().zip(shifted) {
                *o += weight * v;
            }
        }
    }
    for (row, out_row) in values.chunks_exact_mut(width).enumerate() {
        let out_row = out_row.as_flattened_mut();
        out_row.fill(0.0);
        for (tap, weight) in kernel.iter().enumerate() {
            let source_row = clamp_index((row + tap) as isize - radius as isize, height);
            let source_row = scratch[source_row * width..(source_row + 1) * width].as_flattened();
            for (o, v) in out_row.iter_mut().zip(source_row) {
                *o += weight * v;
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A seeded linear congruential generator (Knuth's MMIX constants) giving uniforms in [0, 1).
    struct Lcg(u64);

    impl Lcg {
        fn uniform(&mut self) -> f64 {
            self.0 = self
                .0
                .wrapping_mul(6_364_136_223_846_793_005)
                .wrapping_add(1_442_695_040_888_963_407);
            (self.0 >> 11) as f64 / (1u64 << 53) as f64
        }
    }

    /// A smooth analytic texture: 0.5 plus six plane waves of random direction, wavelength
    /// 7–16 px and phase, total amplitude 0.45.
    struct Texture {
        waves: Vec<(f64, f64, f64)>,
    }

    impl Texture {
        fn new(seed: u64) -> Self {
            let mut rng = Lcg(seed);
            let waves = (0..6)
                .map(|_| {
                    let angle = std::f64::consts::TAU * rng.uniform();
                    let wavenumber = std::f64::consts::TAU / (7.0 + 9.0 * rng.uniform());
                    let phase = std::f64::consts::TAU * rng.uniform();
                    (wavenumber * angle.cos(), wavenumber * angle.sin(), phase)
                })
                .collect();
            Self { waves }
        }

        fn value(&self, x: f64, y: f64) -> f64 {
            let waves: f64 = self
                .waves
                .iter()
                .map(|&(kx, ky, phase)| (kx * x + ky * y + phase).sin())
                .sum();
            0.5 + 0.075 * waves
        }

        /// The texture rendered through `warp`: pixel (col, row) shows value(warp(col, row)).
        fn render(
            &self,
            height: usize,
            width: usize,
            warp: impl Fn(f64, f64) -> (f64, f64),
        ) -> Vec<f32> {
            (0..height * width)
                .map(|i| {
                    let (x, y) = warp((i % width) as f64, (i / width) as f64);
                    self.value(x, y) as f32
                })
                .collect()
        }
    }

    /// Flow vectors of the pixels at least `margin` px from every edge.
    fn interior(flow: &[[f32; 2]], height: usize, width: usize, margin: usize) -> Vec<[f64; 2]> {
        (margin..height - margin)
            .flat_map(|row| (margin..width - margin).map(move |col| row * width + col))
            .map(|i| [f64::from(flow[i][0]), f64::from(flow[i][1])])
            .collect()
    }

    /// The `q` quantile (nearest rank) of `values`.
    fn quantile(mut values: Vec<f64>, q: f64) -> f64 {
        values.sort_by(f64::total_cmp);
        values[((values.len() - 1) as f64 * q).round() as usize]
    }

    /// Renders the texture translated by (`dx_px`, `dy_px`) and returns the interior flow.
    fn translated_interior_flow(
        height: usize,
        width: usize,
        dx_px: f64,
        dy_px: f64,
    ) -> Vec<[f64; 2]> {
        let texture = Texture::new(7);
        let prev = texture.render(height, width, |x, y| (x, y));
        let next = texture.render(height, width, |x, y| (x - dx_px, y - dy_px));
        let flow =
            farneback_flow(&prev, &next, height, width, &FarnebackParams::default()).unwrap();
        interior(&flow, height, width, 10)
    }

    #[test]
    fn expansion_of_a_quadratic_is_exact() {
        // f = 0.3 + 0.02x − 0.01y + 0.004x² − 0.003xy + 0.002y²: A = [[0.004, −0.0015],
        // [−0.0015, 0.002]], and around pixel p the linear term is b = b₀ + 2A·p.
        let (height, width) = (12, 15);
        let pixels: Vec<f32> = (0..height * width)
            .map(|i| {
                let (x, y) = ((i % width) as f64, (i / width) as f64);
                (0.3 + 0.02 * x - 0.01 * y + 0.004 * x * x - 0.003 * x * y + 0.002 * y * y) as f32
            })
            .collect();
        let image = Image::from_f32(&pixels, height, width);
        let expansion = PolyApplicability::new(1.1, 2).expand(&image);
        let (a_xx, a_xy, a_yy) = (0.004, -0.0015, 0.002);
        for row in 2..height - 2 {
            for col in 2..width - 2 {
                let (x, y) = (col as f64, row as f64);
                let expected = [
                    a_xx,
                    a_xy,
                    a_yy,
                    0.02 + 2.0 * (a_xx * x + a_xy * y),
                    -0.01 + 2.0 * (a_xy * x + a_yy * y),
                ];
                for (got, want) in expansion.quadratics[row * width + col].iter().zip(expected) {
                    assert!((got - want).abs() < 1e-5, "({row}, {col}): {got} vs {want}");
                }
            }
        }
    }

    #[test]
    fn identical_images_give_zero_flow() {
        let (height, width) = (72, 96);
        let image = Texture::new(1).render(height, width, |x, y| (x, y));
        let flow =
            farneback_flow(&image, &image, height, width, &FarnebackParams::default()).unwrap();
        assert_eq!(flow.len(), height * width);
        for [dx_px, dy_px] in flow {
            assert!(dx_px.hypot(dy_px) < 1e-3, "({dx_px}, {dy_px})");
        }
    }

    #[test]
    fn subpixel_translation_is_recovered() {
        let (dx_px, dy_px) = (1.5, -0.7);
        let flow = translated_interior_flow(72, 96, dx_px, dy_px);
        let median_dx = quantile(flow.iter().map(|d| d[0]).collect(), 0.5);
        let median_dy = quantile(flow.iter().map(|d| d[1]).collect(), 0.5);
        let p90_error = quantile(
            flow.iter()
                .map(|d| (d[0] - dx_px).hypot(d[1] - dy_px))
                .collect(),
            0.9,
        );
        assert!((median_dx - dx_px).abs() < 0.1, "median dx {median_dx}");
        assert!((median_dy - dy_px).abs() < 0.1, "median dy {median_dy}");
        assert!(p90_error < 0.3, "90th-percentile error {p90_error}");
    }

    #[test]
    fn large_translation_is_recovered_through_the_pyramid() {
        let (dx_px, dy_px) = (4.0, 2.5);
        let flow = translated_interior_flow(120, 160, dx_px, dy_px);
        let median_dx = quantile(flow.iter().map(|d| d[0]).collect(), 0.5);
        let median_dy = quantile(flow.iter().map(|d| d[1]).collect(), 0.5);
        assert!((median_dx - dx_px).abs() < 0.25, "median dx {median_dx}");
        assert!((median_dy - dy_px).abs() < 0.25, "median dy {median_dy}");
    }

    #[test]
    fn expansion_gives_outward_flow() {
        let (height, width) = (72, 96);
        let (cx, cy) = ((width - 1) as f64 / 2.0, (height - 1) as f64 / 2.0);
        let zoom = 1.03;
        let texture = Texture::new(3);
        let prev = texture.render(height, width, |x, y| (x, y));
        let next = texture.render(height, width, |x, y| {
            (cx + (x - cx) / zoom, cy + (y - cy) / zoom)
        });
        let flow =
            farneback_flow(&prev, &next, height, width, &FarnebackParams::default()).unwrap();
        // True flow: d(x) = (zoom − 1)(x − c). Regress the flow on x − c over the interior.
        let margin = 10;
        let (mut flow_dot_radial, mut radial_squared) = (0.0, 0.0);
        for row in margin..height - margin {
            for col in margin..width - margin {
                let [dx_px, dy_px] = flow[row * width + col];
                let (rx, ry) = (col as f64 - cx, row as f64 - cy);
                flow_dot_radial += f64::from(dx_px) * rx + f64::from(dy_px) * ry;
                radial_squared += rx * rx + ry * ry;
            }
        }
        let slope = flow_dot_radial / radial_squared;
        assert!(slope > 0.0, "flow points inward: slope {slope}");
        assert!(
            (slope - (zoom - 1.0)).abs() < 0.01,
            "slope {slope}, expected {}",
            zoom - 1.0
        );
    }

    #[test]
    fn flat_image_gives_finite_near_zero_flow() {
        let (height, width) = (72, 96);
        let prev = vec![0.4; height * width];
        let next = vec![0.6; height * width];
        for [dx_px, dy_px] in
            farneback_flow(&prev, &next, height, width, &FarnebackParams::default()).unwrap()
        {
            assert!(dx_px.is_finite() && dy_px.is_finite());
            assert!(dx_px.hypot(dy_px) < 1e-3, "({dx_px}, {dy_px})");
        }
    }

    #[test]
    fn degenerate_shapes_and_content_stay_finite() {
        let params = FarnebackParams::default();
        assert!(farneback_flow(&[], &[], 0, 5, &params).unwrap().is_empty());
        let [[dx_px, dy_px]] = farneback_flow(&[0.3], &[0.7], 1, 1, &params).unwrap()[..] else {
            panic!("one pixel in, one vector out");
        };
        assert!(dx_px.hypot(dy_px) < 1e-3, "({dx_px}, {dy_px})");
        let (height, width) = (3, 40);
        let texture = Texture::new(5);
        let mut prev = texture.render(height, width, |x, y| (x, y));
        let next = texture.render(height, width, |x, y| (x - 1.0, y));
        prev[7] = f32::NAN;
        prev[8] = f32::INFINITY;
        let wide = FarnebackParams {
            levels: 50,
            iterations: 1,
            poly_n: 40,
            poly_sigma: 0.01,
            ..params
        };
        for params in [params, wide] {
            let flow = farneback_flow(&prev, &next, height, width, &params).unwrap();
            assert_eq!(flow.len(), height * width);
            assert!(flow.iter().flatten().all(|v| v.is_finite()), "{params:?}");
        }
    }

    #[test]
    fn parameters_outside_their_ranges_are_refused_by_name() {
        let ok = FarnebackParams::default();
        let image = vec![0.5f32; 16 * 16];
        let cases = [
            (
                FarnebackParams {
                    pyramid_scale: f64::NAN,
                    ..ok
                },
                "pyramid_scale",
            ),
            (
                FarnebackParams {
                    pyramid_scale: 1.0,
                    ..ok
                },
                "pyramid_scale",
            ),
            (
                FarnebackParams {
                    pyramid_scale: -0.5,
                    ..ok
                },
                "pyramid_scale",
            ),
            (FarnebackParams { levels: 0, ..ok }, "levels"),
            (
                FarnebackParams {
                    window_sigma: -1.0,
                    ..ok
                },
                "window_sigma",
            ),
            (
                FarnebackParams {
                    window_sigma: f64::INFINITY,
                    ..ok
                },
                "window_sigma",
            ),
            (
                FarnebackParams {
                    window_sigma: f64::NAN,
                    ..ok
                },
                "window_sigma",
            ),
            (
                FarnebackParams {
                    poly_sigma: 0.0,
                    ..ok
                },
                "poly_sigma",
            ),
            (
                FarnebackParams {
                    poly_sigma: f64::NAN,
                    ..ok
                },
                "poly_sigma",
            ),
            (FarnebackParams { poly_n: 2, ..ok }, "poly_n"),
        ];
        for (params, field) in cases {
            let err = farneback_flow(&image, &image, 16, 16, &params).unwrap_err();
            assert_eq!(err.field, field, "{params:?}: {err}");
            assert!(
                err.to_string()
                    .starts_with(&format!("Farnebäck flow: {field} ")),
                "{err}"
            );
        }
        assert!(farneback_flow(&image, &image, 16, 16, &ok).is_ok());
    }
}
