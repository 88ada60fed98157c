//! The gel's material and its 8-node hexahedra.
//!
//! Nearly incompressible neo-Hookean solid, split into an isochoric and a volumetric part,
//! W = μ/2 (J^(−2/3) I₁ − 3) + κ/2 (θ − 1)², with the volumetric part evaluated on the element's
//! mean dilatation θ = v_e / V_e (deformed over reference volume) instead of the pointwise J: the
//! Q1/P0 mean-dilatation element of Simo, Taylor & Pister (CMAME 51, 1985), which does not lock
//! as ν → 0.5. Because the isochoric energy is invariant under F → λF, this is also the F-bar
//! element's energy (de Souza Neto et al. 1996) for a constant F-bar over the element, and it is
//! a potential: the element's stiffness is its exact, symmetric Hessian.
//!
//! Elements are axis-aligned boxes (the mesh is a graded tensor-product grid), integrated with
//! 2 × 2 × 2 Gauss points.

/// Shear and bulk modulus of the gel (kPa).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct NeoHookean {
    /// Shear modulus μ = E / (2(1 + ν)).
    pub shear_kpa: f64,
    /// Bulk modulus κ = E / (3(1 − 2ν)).
    pub bulk_kpa: f64,
}

impl NeoHookean {
    /// The small-strain moduli of Young's modulus `e_kpa` and Poisson ratio `nu` (ν < 0.5).
    pub fn from_young(e_kpa: f64, nu: f64) -> NeoHookean {
        NeoHookean {
            shear_kpa: e_kpa / (2.0 * (1.0 + nu)),
            bulk_kpa: e_kpa / (3.0 * (1.0 - 2.0 * nu)),
        }
    }
}

/// A 3 × 3 matrix, row-major.
pub type Mat3 = [[f64; 3]; 3];

fn det(f: &Mat3) -> f64 {
    f[0][0] * (f[1][1] * f[2][2] - f[1][2] * f[2][1])
        - f[0][1] * (f[1][0] * f[2][2] - f[1][2] * f[2][0])
        + f[0][2] * (f[1][0] * f[2][1] - f[1][1] * f[2][0])
}

/// F⁻ᵀ of a matrix with determinant `j`.
fn inverse_transpose(f: &Mat3, j: f64) -> Mat3 {
    // The cofactor matrix over the determinant.
    let c =
        |r0: usize, r1: usize, c0: usize, c1: usize| f[r0][c0] * f[r1][c1] - f[r0][c1] * f[r1][c0];
    [
        [c(1, 2, 1, 2) / j, -c(1, 2, 0, 2) / j, c(1, 2, 0, 1) / j],
        [-c(0, 2, 1, 2) / j, c(0, 2, 0, 2) / j, -c(0, 2, 0, 1) / j],
        [c(0, 1, 1, 2) / j, -c(0, 1, 0, 2) / j, c(0, 1, 0, 1) / j],
    ]
}

/// Gauss points of the element ([−1, 1]³ coordinates); weights are 1.
const GAUSS: f64 = 0.577_350_269_189_625_8;

/// An element's sizes (mm along x, y, z) and the shape-function gradients at its Gauss points.
#[derive(Debug, Clone, Copy)]
pub struct Box8 {
    /// Reference volume (mm³).
    pub volume_mm3: f64,
    /// ∂N_a/∂X_J at each Gauss point: `grad[g][a][J]`.
    grad: [[[f64; 3]; 8]; 8],
}

impl Box8 {
    /// The box of edge lengths `size` (mm). Local node a = ix + 2 iy + 4 iz, with ix, iy, iz ∈ {0, 1}
    /// the low or high face along each axis.
    pub fn new(size: [f64; 3]) -> Box8 {
        let mut grad = [[[0.0; 3]; 8]; 8];
        for (g, grad_g) in grad.iter_mut().enumerate() {
            let xi = [
                if g & 1 == 0 { -GAUSS } else { GAUSS },
                if g & 2 == 0 { -GAUSS } else { GAUSS },
                if g & 4 == 0 { -GAUSS } else { GAUSS },
            ];
            for (a, ga) in grad_g.iter_mut().enumerate() {
                let s = [
                    if a & 1 == 0 { -1.0 } else { 1.0 },
                    if a & 2 == 0 { -1.0 } else { 1.0 },
                    if a & 4 == 0 { -1.0 } else { 1.0 },
                ];
                let n = |d: usize| 0.5 * (1.0 + s[d] * xi[d]);
                // dN/dξ_d = s_d / 2 · Π_{e≠d} (1 + s_e ξ_e)/2, and dξ_d/dX_d = 2 / size_d.
                ga[0] = s[0] * n(1) * n(2) / size[0];
                ga[1] = s[1] * n(0) * n(2) / size[1];
                ga[2] = s[2] * n(0) * n(1) / size[2];
            }
        }
        Box8 {
            volume_mm3: size[0] * size[1] * size[2],
            grad,
        }
    }
}

/// The element's deformation is outside what the material can take (J ≤ 0 at a Gauss point).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Inverted;

/// Entries of a 24 × 24 symmetric matrix's lower triangle.
pub const PACKED: usize = 24 * 25 / 2;

/// Where entry (r, c) of a symmetric 24 × 24 matrix sits in its lower triangle packed by rows.
pub fn packed(r: usize, c: usize) -> usize {
    let (r, c) = if r >= c { (r, c) } else { (c, r) };
    r * (r + 1) / 2 + c
}

/// For each packed lower-triangle entry (a * 3 + i, b * 3 + k), where the entry
/// (a * 3 + k, b * 3 + i) of a symmetric matrix sits: its 3 × 3 blocks transposed.
const BLOCK_TRANSPOSED: [u16; PACKED] = {
    let mut table = [0u16; PACKED];
    let mut r = 0;
    while r < 24 {
        let mut c = 0;
        while c <= r {
            let (a, i, bb, k) = (r / 3, r % 3, c / 3, c % 3);
            let (r2, c2) = (a * 3 + k, bb * 3 + i);
            let (hi, lo) = if r2 >= c2 { (r2, c2) } else { (c2, r2) };
            table[r * (r + 1) / 2 + c] = (hi * (hi + 1) / 2 + lo) as u16;
            c += 1;
        }
        r += 1;
    }
    table
};

/// Energy (kPa·mm³ = μJ), gradient (mN) and Hessian (mN/mm) of one element.
#[derive(Debug, Clone)]
pub struct ElementState {
    /// Stored energy.
    pub energy: f64,
    /// ∂W/∂u, `[a * 3 + i]`.
    pub gradient: [f64; 24],
    /// ∂²W/∂u∂u, its lower triangle packed by rows (entry (a * 3 + i, b * 3 + k) at
    /// [`packed`]); left as it was when not asked for.
    pub hessian: [f64; PACKED],
}

impl Default for ElementState {
    fn default() -> Self {
        ElementState {
            energy: 0.0,
            gradient: [0.0; 24],
            hessian: [0.0; PACKED],
        }
    }
}

/// The lower triangle of Σ_q l[·][q] ⊗ rt[q] (two 24 × Q factors), packed by rows into `out`:
/// in three bands of eight rows, each row summed in registers over the columns its band needs.
#[inline(always)]
fn outer_lower<const Q: usize>(l: &[[f64; Q]; 24], rt: &[[f64; 24]; Q], out: &mut [f64; PACKED]) {
    outer_band::<Q, 8>(l, rt, 0, out);
    outer_band::<Q, 16>(l, rt, 8, out);
    outer_band::<Q, 24>(l, rt, 16, out);
}

/// Rows `first..first + 8` of [`outer_lower`], W = first + 8 columns wide.
#[inline(always)]
fn outer_band<const Q: usize, const W: usize>(
    l: &[[f64; Q]; 24],
    rt: &[[f64; 24]; Q],
    first: usize,
    out: &mut [f64; PACKED],
) {
    for (r, l_r) in l.iter().enumerate().skip(first).take(8) {
        let mut acc = [0.0; W];
        for (&x, row) in l_r.iter().zip(rt) {
            for (a, &y) in acc.iter_mut().zip(&row[..W]) {
                *a += x * y;
            }
        }
        // All W entries, a fixed-size copy: those past the row's r + 1 land on the next rows'
        // first entries, which those rows overwrite (the last row of each band is W wide).
        let start = r * (r + 1) / 2;
        out[start..start + W].copy_from_slice(&acc);
    }
}

/// Deformation gradients F = I + Σ_a u_a ⊗ ∇N_a at the Gauss points.
fn deformation(b: &Box8, u: &[[f64; 3]; 8]) -> [Mat3; 8] {
    let mut out = [[[0.0; 3]; 3]; 8];
    for (f, grad) in out.iter_mut().zip(&b.grad) {
        for i in 0..3 {
            for jj in 0..3 {
                let mut s = if i == jj { 1.0 } else { 0.0 };
                for a in 0..8 {
                    s += u[a][i] * grad[a][jj];
                }
                f[i][jj] = s;
            }
        }
    }
    out
}

/// The element's energy alone (line searches), or [`Inverted`].
pub fn energy(m: &NeoHookean, b: &Box8, u: &[[f64; 3]; 8]) -> Result<f64, Inverted> {
    let w = b.volume_mm3 / 8.0;
    let mut iso = 0.0;
    let mut dilatation = 0.0;
    for f in deformation(b, u) {
        let j = det(&f);
        if j <= 0.0 || !j.is_finite() {
            return Err(Inverted);
        }
        let [jm1, _, iso_invariant] = invariants_from_rest(&f)?;
        iso += w * 0.5 * m.shear_kpa * iso_invariant;
        dilatation += w * jm1;
    }
    let theta_m1 = dilatation / b.volume_mm3;
    Ok(iso + b.volume_mm3 * 0.5 * m.bulk_kpa * theta_m1 * theta_m1)
}

/// J − 1, J^(−2/3) − 1 and the isochoric invariant Ī₁ − 3 = J^(−2/3) I₁ − 3 of F = I + H,
/// from H = F − I (exact in floating point). All three are small near rest; formed from I₁ ≈ 3
/// and J ≈ 1 they keep only the absolute round-off of 3, about 1e-16 μ a Gauss point, which near
/// the solution swamps the energy decrease a line search looks for. Expanded instead:
/// J − 1 = tr H + ½((tr H)² − tr H²) + det H (exact for 3 × 3), I₁ − 3 = 2 tr H + |H|², and
/// Ī₁ − 3 = d + 3a + a d with d = I₁ − 3 and a = J^(−2/3) − 1 = expm1(−⅔ ln(1 + (J − 1))).
/// [`Inverted`] where round-off puts J − 1 at or below −1 (J ≈ 0, past the caller's J > 0).
fn invariants_from_rest(f: &Mat3) -> Result<[f64; 3], Inverted> {
    let mut h = *f;
    for (i, row) in h.iter_mut().enumerate() {
        row[i] -= 1.0;
    }
    let trace = h[0][0] + h[1][1] + h[2][2];
    let mut trace_h2 = 0.0;
    let mut norm2 = 0.0;
    for (i, row) in h.iter().enumerate() {
        for (k, &x) in row.iter().enumerate() {
            trace_h2 += x * h[k][i];
            norm2 += x * x;
        }
    }
    let jm1 = trace + 0.5 * (trace * trace - trace_h2) + det(&h);
    let d = 2.0 * trace + norm2;
    let a = (-2.0 / 3.0 * jm1.ln_1p()).exp_m1();
    let iso = d + 3.0 * a + a * d;
    if iso.is_finite() {
        Ok([jm1, a, iso])
    } else {
        Err(Inverted)
    }
}

/// Energy, gradient and (when `with_hessian`) Hessian of one element into `out`, or
/// [`Inverted`].
///
/// The Hessian is the sum over Gauss points of the isochoric tangent contracted with the
/// shape-function gradients, written as outer products of 24-vectors (see [`outer_lower`]),
/// with f_a = F ∇N_a, g_a = F⁻ᵀ ∇N_a:
/// K_ab = c (∇N_a·∇N_b) I − ⅔c (f_a g_bᵀ + g_a f_bᵀ) + ((2/9) c I₁ + U'J) g_a g_bᵀ
///        + (⅓ c I₁ − U'J) g_b g_aᵀ, c = μ J^(−2/3),
/// plus the mean dilatation's rank-one term U''(θ)/V_e ∂v_e/∂u ⊗ ∂v_e/∂u.
pub fn evaluate_into(
    m: &NeoHookean,
    b: &Box8,
    u: &[[f64; 3]; 8],
    with_hessian: bool,
    out: &mut ElementState,
) -> Result<(), Inverted> {
    #[cfg(target_arch = "x86_64")]
    if std::is_x86_feature_detected!("avx2") {
        // SAFETY: the CPU has just been found to have AVX2.
        return unsafe { evaluate_avx2(m, b, u, with_hessian, out) };
    }
    evaluate_portable(m, b, u, with_hessian, out)
}

/// [`evaluate_portable`] compiled for AVX2 (its outer products four lanes wide instead of two).
/// AVX2 without FMA: no multiply and add is fused, so the result is the portable one to the bit.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
fn evaluate_avx2(
    m: &NeoHookean,
    b: &Box8,
    u: &[[f64; 3]; 8],
    with_hessian: bool,
    out: &mut ElementState,
) -> Result<(), Inverted> {
    evaluate_portable(m, b, u, with_hessian, out)
}

/// [`evaluate_into`] for any CPU; inlined into [`evaluate_avx2`] to be compiled again there.
#[inline(always)]
fn evaluate_portable(
    m: &NeoHookean,
    b: &Box8,
    u: &[[f64; 3]; 8],
    with_hessian: bool,
    out: &mut ElementState,
) -> Result<(), Inverted> {
    let w = b.volume_mm3 / 8.0;
    let fs = deformation(b, u);
    let mut js = [0.0; 8];
    let mut gs = [[[0.0; 3]; 3]; 8];
    let mut dilatation = 0.0;
    let mut invariants = [[0.0; 3]; 8];
    for g in 0..8 {
        let j = det(&fs[g]);
        if j <= 0.0 || !j.is_finite() {
            return Err(Inverted);
        }
        js[g] = j;
        gs[g] = inverse_transpose(&fs[g], j);
        invariants[g] = invariants_from_rest(&fs[g])?;
        dilatation += w * invariants[g][0];
    }
    let theta_m1 = dilatation / b.volume_mm3;
    // U(θ) = κ/2 (θ − 1)²: U' and U''.
    let du = m.bulk_kpa * theta_m1;
    let ddu = m.bulk_kpa;
    let mut iso = 0.0;
    let mut gradient = [0.0; 24];
    // ∂v_e/∂u_ai = Σ_g w J G_iJ ∇N_aJ.
    let mut dv = [0.0; 24];
    // Per Gauss point, the 24-vectors the Hessian is made of (γ = −⅔c, α = (2/9) c I₁ + U'J,
    // β = ⅓ c I₁ − U'J): K's two outer products pair `left_k`'s w(γ f + α g) and wγ g with
    // `right_k`'s g and f, M's pairs `left_m`'s wβ g with `right_m`'s g; and the weight w c of
    // the ∇N_a·∇N_b term.
    let mut left_k = [[0.0; 16]; 24];
    let mut left_m = [[0.0; 8]; 24];
    let mut right_k = [[0.0; 24]; 16];
    let mut right_m = [[0.0; 24]; 8];
    let mut laplace_weight = [0.0; 8];
    for g in 0..8 {
        let (f, gi, j) = (&fs[g], &gs[g], js[g]);
        let grad = &b.grad[g];
        let i1: f64 = f.iter().flatten().map(|x| x * x).sum();
        let [_, jm23_m1, iso_invariant] = invariants[g];
        let jm23 = 1.0 + jm23_m1;
        let c = m.shear_kpa * jm23;
        // The same expressions, summed in the same order, as [`energy`]: the line search
        // compares the two, and near the solution their difference is the decrease it looks for.
        iso += w * 0.5 * m.shear_kpa * iso_invariant;
        let gamma = -2.0 / 3.0 * c;
        let alpha = 2.0 / 9.0 * c * i1 + du * j;
        let beta = c * i1 / 3.0 - du * j;
        laplace_weight[g] = w * c;
        // P_iso = μ J^(−2/3) (F − I₁/3 F⁻ᵀ).
        let mut p = [[0.0; 3]; 3];
        for i in 0..3 {
            for jj in 0..3 {
                p[i][jj] = c * (f[i][jj] - i1 / 3.0 * gi[i][jj]);
            }
        }
        for (a, grad_a) in grad.iter().enumerate() {
            for i in 0..3 {
                let (mut sf, mut sg, mut sp, mut sv) = (0.0, 0.0, 0.0, 0.0);
                for jj in 0..3 {
                    sf += f[i][jj] * grad_a[jj];
                    sg += gi[i][jj] * grad_a[jj];
                    sp += p[i][jj] * grad_a[jj];
                    sv += j * gi[i][jj] * grad_a[jj];
                }
                let r = a * 3 + i;
                gradient[r] += w * sp;
                dv[r] += w * sv;
                left_k[r][2 * g] = w * (gamma * sf + alpha * sg);
                left_k[r][2 * g + 1] = w * gamma * sg;
                left_m[r][g] = w * beta * sg;
                right_k[2 * g][r] = sg;
                right_k[2 * g + 1][r] = sf;
                right_m[g][r] = sg;
            }
        }
    }
    for (gr, d) in gradient.iter_mut().zip(&dv) {
        *gr += du * d;
    }
    out.energy = iso + b.volume_mm3 * 0.5 * m.bulk_kpa * theta_m1 * theta_m1;
    out.gradient = gradient;
    if !with_hessian {
        return Ok(());
    }
    let hessian = &mut out.hessian;
    // The first two outer products into K and the third into M = Σ wβ g gᵀ.
    let mut swapped = [0.0; PACKED];
    outer_lower(&left_k, &right_k, hessian);
    outer_lower(&left_m, &right_m, &mut swapped);
    // β g_b g_aᵀ is block (a, b) of M transposed: K[(a, i), (b, k)] += M[(a, k), (b, i)].
    for (k, &from) in hessian.iter_mut().zip(BLOCK_TRANSPOSED.iter()) {
        *k += swapped[from as usize];
    }
    // c (∇N_a·∇N_b) I.
    for a in 0..8 {
        for bb in 0..=a {
            let mut laplace = 0.0;
            for (grad, weight) in b.grad.iter().zip(&laplace_weight) {
                laplace += weight
                    * (grad[a][0] * grad[bb][0]
                        + grad[a][1] * grad[bb][1]
                        + grad[a][2] * grad[bb][2]);
            }
            for i in 0..3 {
                hessian[packed(a * 3 + i, bb * 3 + i)] += laplace;
            }
        }
    }
    // The mean dilatation's rank-one term.
    let s = ddu / b.volume_mm3;
    for r in 0..24 {
        let row = &mut hessian[r * (r + 1) / 2..r * (r + 1) / 2 + r + 1];
        let sr = s * dv[r];
        for (k, &dc) in row.iter_mut().zip(&dv[..=r]) {
            *k += sr * dc;
        }
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    fn evaluate(
        m: &NeoHookean,
        b: &Box8,
        u: &[[f64; 3]; 8],
        with_hessian: bool,
    ) -> Result<ElementState, Inverted> {
        let mut out = ElementState::default();
        evaluate_into(m, b, u, with_hessian, &mut out)?;
        Ok(out)
    }

    /// The line search compares [`energy`] at a trial state with the energy the assembly gave at
    /// the current one; near the solution the decrease it looks for is a few ulps, so the two
    /// must be the same expression, to the bit.
    #[test]
    fn the_assembly_energy_is_the_line_search_energy_to_the_bit() {
        let m = material();
        for (scale, size) in [
            (1.0, [1.0, 0.7, 0.5]),
            (0.01, [0.3, 0.3, 0.33]),
            (1e-6, [2.0, 1.0, 0.1]),
        ] {
            let b = Box8::new(size);
            let u = deformed(scale);
            let alone = energy(&m, &b, &u).unwrap();
            for with_hessian in [false, true] {
                let full = evaluate(&m, &b, &u, with_hessian).unwrap().energy;
                assert_eq!(
                    full.to_bits(),
                    alone.to_bits(),
                    "{scale}: {full} against {alone}"
                );
            }
        }
    }

    /// The AVX2 build of the element and the portable one must agree to the bit, or frames
    /// would depend on the CPU: neither contracts a multiply and an add, and both sum in the
    /// same order.
    #[cfg(target_arch = "x86_64")]
    #[test]
    fn the_avx2_element_equals_the_portable_one_to_the_bit() {
        if !std::is_x86_feature_detected!("avx2") {
            return;
        }
        let m = material();
        for (scale, size) in [(1.0, [1.0, 0.7, 0.5]), (0.1, [0.3, 0.3, 0.33])] {
            let b = Box8::new(size);
            let u = deformed(scale);
            let (mut fast, mut portable) = (ElementState::default(), ElementState::default());
            // SAFETY: the CPU has AVX2 (checked above).
            unsafe { evaluate_avx2(&m, &b, &u, true, &mut fast) }.unwrap();
            evaluate_portable(&m, &b, &u, true, &mut portable).unwrap();
            assert_eq!(fast.energy.to_bits(), portable.energy.to_bits());
            assert!(
                fast.gradient
                    .iter()
                    .zip(&portable.gradient)
                    .all(|(a, b)| a.to_bits() == b.to_bits())
            );
            assert!(
                fast.hessian
                    .iter()
                    .zip(&portable.hessian)
                    .all(|(a, b)| a.to_bits() == b.to_bits())
            );
        }
    }

    fn material() -> NeoHookean {
        NeoHookean::from_young(300.0, 0.45)
    }

    fn deformed(scale: f64) -> [[f64; 3]; 8] {
        // A smooth, non-affine displacement of the unit-ish box.
        let mut u = [[0.0; 3]; 8];
        for (a, ua) in u.iter_mut().enumerate() {
            let x = [(a & 1) as f64, ((a >> 1) & 1) as f64, ((a >> 2) & 1) as f64];
            ua[0] = scale * (0.3 * x[1] + 0.1 * x[0] * x[2]);
            ua[1] = scale * (-0.2 * x[2] + 0.15 * x[0]);
            ua[2] = scale * (-0.25 * x[2] + 0.05 * x[0] * x[1]);
        }
        u
    }

    #[test]
    fn gradient_and_hessian_match_finite_differences() {
        let m = material();
        let b = Box8::new([1.0, 0.7, 0.5]);
        let u = deformed(1.0);
        let s = evaluate(&m, &b, &u, true).unwrap();
        let h = 1e-6;
        for r in 0..24 {
            let mut up = u;
            let mut um = u;
            up[r / 3][r % 3] += h;
            um[r / 3][r % 3] -= h;
            let fd = (energy(&m, &b, &up).unwrap() - energy(&m, &b, &um).unwrap()) / (2.0 * h);
            assert!(
                (fd - s.gradient[r]).abs() < 1e-5 * (1.0 + fd.abs()),
                "gradient {r}"
            );
            let gp = evaluate(&m, &b, &up, false).unwrap().gradient;
            let gm = evaluate(&m, &b, &um, false).unwrap().gradient;
            for c in 0..24 {
                let fd = (gp[c] - gm[c]) / (2.0 * h);
                let an = s.hessian[packed(c, r)];
                assert!(
                    (fd - an).abs() < 1e-4 * (1.0 + an.abs()),
                    "hessian {c},{r}: {fd} vs {an}"
                );
            }
        }
    }

    /// Simple shear u_x = γ y keeps J = 1 and stores μγ²/2 a unit volume exactly (I₁ = 3 + γ²).
    /// At γ = 1e-7 the energy is 1e-14 of μ: formed as J^(−2/3) I₁ − 3 it would keep a few
    /// per cent of it (the round-off of 3); the line search needs it to the last digits.
    #[test]
    fn a_small_simple_shear_stores_its_closed_form_energy() {
        let m = material();
        let size = [1.0, 2.0, 0.5];
        let b = Box8::new(size);
        for gamma in [1e-3, 1e-7, 1e-10] {
            let mut u = [[0.0; 3]; 8];
            for (a, ua) in u.iter_mut().enumerate() {
                ua[0] = gamma * size[1] * ((a >> 1) & 1) as f64;
            }
            let exact = b.volume_mm3 * 0.5 * m.shear_kpa * gamma * gamma;
            let alone = energy(&m, &b, &u).unwrap();
            let full = evaluate(&m, &b, &u, true).unwrap().energy;
            for e in [alone, full] {
                assert!(
                    (e / exact - 1.0).abs() < 1e-12,
                    "γ {gamma}: {e} against {exact}"
                );
            }
        }
    }

    #[test]
    fn rigid_rotation_stores_no_energy() {
        let m = material();
        let b = Box8::new([1.0, 2.0, 0.5]);
        let (c, s) = (0.6f64.cos(), 0.6f64.sin());
        let mut u = [[0.0; 3]; 8];
        for (a, ua) in u.iter_mut().enumerate() {
            let x = [
                (a & 1) as f64,
                2.0 * ((a >> 1) & 1) as f64,
                0.5 * ((a >> 2) & 1) as f64,
            ];
            ua[0] = c * x[0] - s * x[1] - x[0] + 0.3;
            ua[1] = s * x[0] + c * x[1] - x[1];
            ua[2] = 0.1;
        }
        let st = evaluate(&m, &b, &u, false).unwrap();
        assert!(st.energy.abs() < 1e-9);
        assert!(st.gradient.iter().all(|g| g.abs() < 1e-9));
    }

    #[test]
    fn small_strain_uniaxial_stress_gives_youngs_modulus() {
        // Stretch ε along z with the lateral contraction ν ε: the stress along z is E ε, so the
        // nodal forces on the top face sum to E ε A.
        let (e, nu) = (300.0, 0.3);
        let m = NeoHookean::from_young(e, nu);
        let b = Box8::new([1.0, 1.0, 1.0]);
        let eps = 1e-6;
        let mut u = [[0.0; 3]; 8];
        for (a, ua) in u.iter_mut().enumerate() {
            let x = [(a & 1) as f64, ((a >> 1) & 1) as f64, ((a >> 2) & 1) as f64];
            *ua = [-nu * eps * x[0], -nu * eps * x[1], eps * x[2]];
        }
        let st = evaluate(&m, &b, &u, false).unwrap();
        let top: f64 = (4..8).map(|a| st.gradient[a * 3 + 2]).sum();
        assert!((top - e * eps).abs() < 1e-3 * e * eps, "{top}");
        let side: f64 = [1, 3, 5, 7].iter().map(|a| st.gradient[a * 3]).sum();
        assert!(side.abs() < 1e-3 * e * eps, "{side}");
    }

    /// Nodal forces of an element under F = diag(a, a, λ), summed over its face x = 1 and its
    /// face z = 1 (unit faces: the nominal stresses P₁₁ and P₃₃).
    fn face_stresses(m: &NeoHookean, a: f64, stretch: f64) -> (f64, f64) {
        let b = Box8::new([1.0, 1.0, 1.0]);
        let mut u = [[0.0; 3]; 8];
        for (n, un) in u.iter_mut().enumerate() {
            let x = [(n & 1) as f64, ((n >> 1) & 1) as f64, ((n >> 2) & 1) as f64];
            *un = [(a - 1.0) * x[0], (a - 1.0) * x[1], (stretch - 1.0) * x[2]];
        }
        let st = evaluate(m, &b, &u, false).unwrap();
        let side: f64 = [1, 3, 5, 7].iter().map(|n| st.gradient[n * 3]).sum();
        let top: f64 = (4..8).map(|n| st.gradient[n * 3 + 2]).sum();
        (side, top)
    }

    /// Uniaxial compression to λ = 0.6, homogeneous, against this energy's closed form written
    /// out here: for F = diag(a, a, λ), J = a²λ, I₁ = 2a² + λ², the nominal stress is
    /// P = μ J^(−2/3) (F − I₁/3 F⁻ᵀ) + κ (J − 1) J F⁻ᵀ; the lateral stretch a makes P₁₁ = 0
    /// (found by bisection), and P₃₃ is then the axial stress. Nearly incompressible, it tends to
    /// the incompressible neo-Hookean μ (λ − λ⁻²).
    #[test]
    fn large_strain_uniaxial_compression_follows_the_closed_form() {
        let stretch = 0.6;
        for nu in [0.45, 0.499, 0.4999] {
            let m = NeoHookean::from_young(300.0, nu);
            let (mu, kappa) = (m.shear_kpa, m.bulk_kpa);
            let stress = |a: f64, k: usize| {
                let f = [a, a, stretch];
                let j = a * a * stretch;
                let i1 = 2.0 * a * a + stretch * stretch;
                mu * j.powf(-2.0 / 3.0) * (f[k] - i1 / (3.0 * f[k])) + kappa * (j - 1.0) * j / f[k]
            };
            // P₁₁ < 0 at a = 1 (compressed axially, the sides pull in), > 0 at a = 2
            let (mut lo, mut hi) = (1.0, 2.0);
            for _ in 0..200 {
                let mid = 0.5 * (lo + hi);
                if stress(mid, 0) < 0.0 {
                    lo = mid;
                } else {
                    hi = mid;
                }
            }
            let a = 0.5 * (lo + hi);
            let axial = stress(a, 2);
            let (side, top) = face_stresses(&m, a, stretch);
            assert!(side.abs() < 1e-8 * axial.abs(), "ν {nu}: lateral {side}");
            assert!(
                (top - axial).abs() < 1e-9 * axial.abs(),
                "ν {nu}: element {top} kPa, closed form {axial} kPa"
            );
            let incompressible = mu * (stretch - stretch.powi(-2));
            let gap = (axial / incompressible - 1.0).abs();
            let bound = [(0.45, 0.1), (0.499, 0.01), (0.4999, 0.001)]
                .iter()
                .find(|(n, _)| *n == nu)
                .unwrap()
                .1;
            assert!(
                gap < bound,
                "ν {nu}: {axial} against μ(λ − λ⁻²) = {incompressible}"
            );
        }
    }

    #[test]
    fn inversion_is_reported() {
        let m = material();
        let b = Box8::new([1.0, 1.0, 1.0]);
        let mut u = [[0.0; 3]; 8];
        for ua in u.iter_mut().skip(4) {
            ua[2] = -1.5;
        }
        assert_eq!(energy(&m, &b, &u).err(), Some(Inverted));
        assert!(evaluate(&m, &b, &u, true).is_err());
    }
}
