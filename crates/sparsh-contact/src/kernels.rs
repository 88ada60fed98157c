//! Influence coefficients: the surface displacement at a cell centre caused by a uniform unit
//! traction (1 kPa) on a square cell, for the elastic half-space and for a layer bonded to a
//! rigid base.
//!
//! Half-space, point forces on the surface (Johnson 1985, eqs. 3.19 and 3.86 at z = 0, shear
//! modulus G = E/(2(1+ν)), E* = E/(1−ν²)):
//! - normal force P (Boussinesq): u_z = P/(π E* r) (positive into the gel);
//! - tangential force Q along x (Cerruti): u_x = Q/(2πG) [(1−ν)/r + ν x²/r³],
//!   u_y = Q/(2πG) ν x y/r³.
//!
//! Integrating over a cell [X−a, X+a] × [Y−b, Y+b] needs antiderivatives A with ∂²A/∂x∂y equal
//! to the kernel (Love 1929 for 1/r; the same steps for the Cerruti terms):
//! ∬ 1/r = x asinh(y/|x|) + y asinh(x/|y|), ∬ x²/r³ = y asinh(x/|y|), ∬ y²/r³ = x asinh(y/|x|),
//! ∬ x y/r³ = −r, evaluated at the four corners. Writing Love's logarithms as asinh drops terms
//! that depend on one coordinate only (they cancel between corners) and avoids the cancellation
//! of ln(y + r) for y < 0.
//!
//! Normal–tangential coupling (Johnson eqs. 3.19a and 3.86c): a normal force P moves the surface
//! radially, u_r = −(1−2ν)P/(4πG r), and a tangential force Q along x moves it into the gel by
//! u_z = (1−2ν)Q x/(4πG r²); ∬ x/r² = x atan(y/x) + (y/2) ln(x² + y²). The half-space rung drops
//! these terms (Goodman's approximation, Johnson §7.2; they vanish at ν = 0.5); a bonded layer has
//! coupling at every ν ([`LayerCorrection`]), which the layered rung keeps.

/// Which displacement–traction pair a coefficient couples.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) enum Component {
    /// u_z from p.
    Zz,
    /// u_x from q_x.
    Xx,
    /// u_y from q_y.
    Yy,
    /// u_x from q_y (= u_y from q_x).
    Xy,
    /// u_z from q_x (= −u_x from p): odd in x.
    Zx,
    /// u_z from q_y (= −u_y from p): odd in y.
    Zy,
}

/// x asinh(y/|x|), continuous at x = 0.
fn xash(x: f64, y: f64) -> f64 {
    if x == 0.0 {
        0.0
    } else {
        x * (y / x.abs()).asinh()
    }
}

/// Σ over the corners of the cell of half-width `half_mm` centred (−x, −y) from the field point.
fn corners(x: f64, y: f64, half_mm: f64, f: impl Fn(f64, f64) -> f64) -> f64 {
    let (a, b) = (half_mm, half_mm);
    f(x + a, y + b) - f(x + a, y - b) - f(x - a, y + b) + f(x - a, y - b)
}

/// Half-space displacement (mm, u_z positive into the gel) at offset (x, y) mm from the centre of
/// a square cell of edge `cell_mm` carrying a uniform unit traction (1 kPa); `youngs_kpa` and
/// `poisson` are the gel's E and ν.
pub(crate) fn halfspace_cell(
    component: Component,
    x: f64,
    y: f64,
    cell_mm: f64,
    youngs_kpa: f64,
    poisson: f64,
) -> f64 {
    let half = 0.5 * cell_mm;
    let nu = poisson;
    let shear_kpa = youngs_kpa / (2.0 * (1.0 + nu));
    let e_star = youngs_kpa / (1.0 - nu * nu);
    let one_over_r = |x: f64, y: f64| xash(x, y) + xash(y, x);
    let pi = std::f64::consts::PI;
    match component {
        Component::Zz => corners(x, y, half, one_over_r) / (pi * e_star),
        Component::Xx => {
            corners(x, y, half, |x, y| {
                (1.0 - nu) * one_over_r(x, y) + nu * xash(y, x)
            }) / (2.0 * pi * shear_kpa)
        }
        Component::Yy => {
            corners(x, y, half, |x, y| {
                (1.0 - nu) * one_over_r(x, y) + nu * xash(x, y)
            }) / (2.0 * pi * shear_kpa)
        }
        Component::Xy => corners(x, y, half, |x, y| -nu * x.hypot(y)) / (2.0 * pi * shear_kpa),
        Component::Zx => (1.0 - 2.0 * nu) * corners(x, y, half, x_over_r2) / (4.0 * pi * shear_kpa),
        Component::Zy => (1.0 - 2.0 * nu) * corners(y, x, half, x_over_r2) / (4.0 * pi * shear_kpa),
    }
}

/// x atan(y/x) + (y/2) ln(x² + y²), whose mixed derivative is x/r² (0 where a term's factor is 0).
fn x_over_r2(x: f64, y: f64) -> f64 {
    let angle = if x == 0.0 { 0.0 } else { x * (y / x).atan() };
    let log = if y == 0.0 {
        0.0
    } else {
        0.5 * y * (x * x + y * y).ln()
    };
    angle + log
}

/// Ratio N/D of the bonded-layer compliance to the half-space one at s = 2|q|h (Carbone &
/// Mangialardi 2008, eq. A.30, numerator and denominator divided by cosh s so that nothing
/// overflows): C_layer(q) = (2/(E*|q|)) · N/D with
/// N = [(3−4ν) sinh s − s]/cosh s, D = (3−4ν) + (s²/2 + 5 − 12ν + 8ν²)/cosh s.
/// (3−4ν) sinh s − s is written (2−4ν) sinh s + (sinh s − s), with the series of sinh s − s for
/// small s, so ν = 0.5 (where N ~ s³/6) loses no digits.
pub(crate) fn layer_ratio(s: f64, poisson: f64) -> f64 {
    let nu = poisson;
    let sinh_minus_s = if s < 0.1 {
        let s2 = s * s;
        s * s2 / 6.0 * (1.0 + s2 / 20.0 * (1.0 + s2 / 42.0))
    } else {
        s.sinh() - s
    };
    if s > 700.0 {
        // cosh s overflows; the ratio is 1 to within e^(−700).
        return 1.0;
    }
    let sech = 1.0 / s.cosh();
    let numerator = (2.0 - 4.0 * nu) * s.tanh() + sinh_minus_s * sech;
    let denominator = (3.0 - 4.0 * nu) + (0.5 * s * s + 5.0 - 12.0 * nu + 8.0 * nu * nu) * sech;
    numerator / denominator
}

/// Bessel function J₀ (rational and asymptotic approximations of Numerical Recipes §6.5,
/// absolute error below 1e-8).
pub(crate) fn bessel_j0(x: f64) -> f64 {
    let ax = x.abs();
    if ax < 8.0 {
        let y = x * x;
        let n = 57568490574.0
            + y * (-13362590354.0
                + y * (651619640.7 + y * (-11214424.18 + y * (77392.33017 + y * (-184.9052456)))));
        let d = 57568490411.0
            + y * (1029532985.0 + y * (9494680.718 + y * (59272.64853 + y * (267.8532712 + y))));
        n / d
    } else {
        let z = 8.0 / ax;
        let y = z * z;
        let xx = ax - std::f64::consts::FRAC_PI_4;
        let p = 1.0
            + y * (-0.1098628627e-2
                + y * (0.2734510407e-4 + y * (-0.2073370639e-5 + y * 0.2093887211e-6)));
        let q = -0.1562499995e-1
            + y * (0.1430488765e-3
                + y * (-0.6911147651e-5 + y * (0.7621095161e-6 - y * 0.934935152e-7)));
        (std::f64::consts::FRAC_2_PI / ax).sqrt() * (xx.cos() * p - z * xx.sin() * q)
    }
}

/// Bessel function J₁ (Numerical Recipes §6.5, absolute error below 1e-8).
pub(crate) fn bessel_j1(x: f64) -> f64 {
    let ax = x.abs();
    if ax < 8.0 {
        let y = x * x;
        let n = x
            * (72362614232.0
                + y * (-7895059235.0
                    + y * (242396853.1
                        + y * (-2972611.439 + y * (15704.48260 + y * (-30.16036606))))));
        let d = 144725228442.0
            + y * (2300535178.0 + y * (18583304.74 + y * (99447.43394 + y * (376.9991397 + y))));
        n / d
    } else {
        let z = 8.0 / ax;
        let y = z * z;
        let xx = ax - 3.0 * std::f64::consts::FRAC_PI_4;
        let p = 1.0
            + y * (0.183105e-2
                + y * (-0.3516396496e-4 + y * (0.2457520174e-5 + y * (-0.240337019e-6))));
        let q = 0.04687499995
            + y * (-0.2002690873e-3
                + y * (0.8449199096e-5 + y * (-0.88228987e-6 + y * 0.105787412e-6)));
        let j = (std::f64::consts::FRAC_2_PI / ax).sqrt() * (xx.cos() * p - z * xx.sin() * q);
        if x < 0.0 { -j } else { j }
    }
}

/// Bessel function J₂ = 2J₁(x)/x − J₀(x), by its series below x = 1 (where the recurrence
/// cancels).
pub(crate) fn bessel_j2(x: f64) -> f64 {
    if x.abs() < 1.0 {
        let y = x * x;
        y / 8.0 * (1.0 - y / 12.0 * (1.0 - y / 32.0 * (1.0 - y / 60.0)))
    } else {
        2.0 * bessel_j1(x) / x - bessel_j0(x)
    }
}

/// Surface compliances of a layer of thickness h bonded to a rigid base, times G|k|, at
/// t = |k|h (G the shear modulus): a surface traction of wavevector k moves the surface by
/// C/(G|k|) times it. From the general solution u = (A + Bz)e^(kz) + (C + Dz)e^(−kz) of Navier's
/// equations in the plane of k (Johnson 1985, §2.2; the same steps as Carbone & Mangialardi 2008,
/// App. A), with the base held and the surface loaded; with w = e^(−2t) (nothing overflows) and
/// D = (3−4ν)(1 + w²) + (10 − 24ν + 16ν² + 4t²) w:
/// - longitudinal (along k, from a traction along k): (1−ν)[(3−4ν)(1 − w²) + 4tw]/D;
/// - transverse (across k): tanh t;
/// - coupling: a pressure p̂ moves the surface along k by i X p̂/(G|k|), and a traction q̂ along
///   k moves it into the gel by −i X q̂/(G|k|), X = [(1−2ν)(3−4ν)(1 − w)² − 4t²w]/(2D).
///
/// (The normal one is [`layer_ratio`]·(1−ν).) As t → ∞ they tend to the half-space's 1−ν, 1 and
/// (1−2ν)/2; as t → 0 to a sheared slab's t, t, and for ν = 0.5 to −t²/2 (squeeze flow).
#[derive(Debug, Clone, Copy, PartialEq)]
pub(crate) struct LayerCompliance {
    pub(crate) longitudinal: f64,
    pub(crate) transverse: f64,
    pub(crate) coupling: f64,
}

impl LayerCompliance {
    pub(crate) fn at(t: f64, poisson: f64) -> LayerCompliance {
        let nu = poisson;
        let w = (-2.0 * t).exp();
        let kappa = 3.0 - 4.0 * nu;
        let d = kappa * (1.0 + w * w) + (10.0 - 24.0 * nu + 16.0 * nu * nu + 4.0 * t * t) * w;
        LayerCompliance {
            longitudinal: (1.0 - nu) * (kappa * (1.0 - w * w) + 4.0 * t * w) / d,
            transverse: t.tanh(),
            coupling: ((1.0 - 2.0 * nu) * kappa * (1.0 - w) * (1.0 - w) - 4.0 * t * t * w)
                / (2.0 * d),
        }
    }
}

/// The bonded layer's point-force responses minus the half-space's, in real space, tabulated in r
/// (per unit force, mm per kPa·mm²). Each is a Hankel transform of the compliance difference
/// ([`layer_ratio`], [`LayerCompliance`]); with ρ = r/h and G the shear modulus:
/// - normal: (1/2πGh) ∫ (C_zz − (1−ν)) J₀(tρ) dt, written as Φ(r/2h)/(2πE*h) with
///   Φ(ρ) = ∫ (N/D − 1)(s) J₀(sρ) ds, s = 2t;
/// - tangential: u_x from a force along x is a(r) + b(r) cos 2θ, u_y from it b(r) sin 2θ, with
///   a = (1/4πGh) ∫ (C_L + C_T − (2−ν)) J₀(tρ) dt and b = −(1/4πGh) ∫ (C_L − C_T + ν) J₂(tρ) dt
///   (the half-space's Cerruti terms are a = (2−ν)/(4πGr), b = ν/(4πGr));
/// - coupling: a force along x moves the surface into the gel by (x/r) f(r), and a normal force
///   moves it by −(x/r) f(r) along x, f = (1/2πGh) ∫ (X − (1−2ν)/2) J₁(tρ) dt.
///
/// The integrands are bounded at t = 0 and decay like t² e^(−2t), so Simpson's rule on
/// t ∈ [0, 30] converges; for r ≫ h each cancels the half-space's 1/r tail, and the zero mode
/// (C_zz → 0 as k → 0, the uniaxial stiffness E(1−ν)/((1+ν)(1−2ν)h), infinite at ν = 0.5) needs
/// no special case. Adding them times the cell area to the half-space cell coefficients gives
/// the layer's coefficients for a laterally unbounded layer (no periodic images); they are smooth
/// on the scale h, so taking them at the cell centre costs O((cell/h)²).
#[derive(Debug, Clone)]
pub(crate) struct LayerCorrection {
    step_mm: f64,
    /// [normal, a, b, f] at r = k·step.
    values: [Vec<f64>; 4],
}

impl LayerCorrection {
    /// Tabulates the responses for 0 ≤ r ≤ `r_max_mm` at a step of `step_mm`.
    pub(crate) fn new(
        youngs_kpa: f64,
        poisson: f64,
        thickness_mm: f64,
        r_max_mm: f64,
        step_mm: f64,
    ) -> LayerCorrection {
        let nu = poisson;
        let e_star = youngs_kpa / (1.0 - nu * nu);
        let shear_kpa = youngs_kpa / (2.0 * (1.0 + nu));
        let rho_max = r_max_mm / (2.0 * thickness_mm);
        let s_max = 60.0;
        // ≥ 40 samples per period of the Bessel functions and per unit of s.
        let ds_target = (2.0 * std::f64::consts::PI / (40.0 * rho_max.max(1e-9))).min(0.025);
        let intervals = ((s_max / ds_target).ceil() as usize).next_multiple_of(2);
        let ds = s_max / intervals as f64;
        let dt = 0.5 * ds;
        // (s, Simpson-weighted integrands [normal in s, a, b, f in t]).
        let weighted: Vec<(f64, [f64; 4])> = (0..=intervals)
            .map(|k| {
                let s = k as f64 * ds;
                let w = if k == 0 || k == intervals {
                    1.0
                } else if k % 2 == 1 {
                    4.0
                } else {
                    2.0
                } / 3.0;
                let c = LayerCompliance::at(0.5 * s, nu);
                (
                    s,
                    [
                        w * ds * (layer_ratio(s, nu) - 1.0),
                        w * dt * (c.longitudinal + c.transverse - (2.0 - nu)),
                        w * dt * (c.longitudinal - c.transverse + nu),
                        w * dt * (c.coupling - 0.5 * (1.0 - 2.0 * nu)),
                    ],
                )
            })
            .collect();
        let count = (r_max_mm / step_mm).ceil() as usize + 2;
        let pi = std::f64::consts::PI;
        let scales = [
            1.0 / (2.0 * pi * e_star * thickness_mm),
            1.0 / (4.0 * pi * shear_kpa * thickness_mm),
            -1.0 / (4.0 * pi * shear_kpa * thickness_mm),
            1.0 / (2.0 * pi * shear_kpa * thickness_mm),
        ];
        let rows: Vec<[f64; 4]> = (0..count)
            .map(|k| {
                // s ρ_s = t ρ with ρ_s = r/2h, ρ = r/h.
                let rho_s = k as f64 * step_mm / (2.0 * thickness_mm);
                let mut sums = [0.0; 4];
                for &(s, w) in &weighted {
                    let x = s * rho_s;
                    let (j0, j1, j2) = (bessel_j0(x), bessel_j1(x), bessel_j2(x));
                    sums[0] += w[0] * j0;
                    sums[1] += w[1] * j0;
                    sums[2] += w[2] * j2;
                    sums[3] += w[3] * j1;
                }
                std::array::from_fn(|c| scales[c] * sums[c])
            })
            .collect();
        LayerCorrection {
            step_mm,
            values: std::array::from_fn(|c| rows.iter().map(|r| r[c]).collect()),
        }
    }

    /// Table `c` at r by linear interpolation.
    fn table_at(&self, c: usize, r_mm: f64) -> f64 {
        let values = &self.values[c];
        let t = r_mm / self.step_mm;
        let k = (t.floor() as usize).min(values.len() - 2);
        let w = t - k as f64;
        values[k] * (1.0 - w) + values[k + 1] * w
    }

    /// The correction to `component`'s point-force response at offset (x, y) mm (mm per
    /// kPa·mm²; for [`Component::Zx`] and [`Component::Zy`] the surface's move into the gel).
    pub(crate) fn at(&self, component: Component, x: f64, y: f64) -> f64 {
        let r = x.hypot(y);
        // cos θ, sin θ; at r = 0 the odd and anisotropic terms vanish (b(0) = f(0) = 0).
        let (c, s) = if r > 0.0 { (x / r, y / r) } else { (0.0, 0.0) };
        match component {
            Component::Zz => self.table_at(0, r),
            Component::Xx => self.table_at(1, r) + self.table_at(2, r) * (c * c - s * s),
            Component::Yy => self.table_at(1, r) - self.table_at(2, r) * (c * c - s * s),
            Component::Xy => self.table_at(2, r) * 2.0 * c * s,
            Component::Zx => self.table_at(3, r) * c,
            Component::Zy => self.table_at(3, r) * s,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn love_centre_value_matches_closed_form() {
        // Centre of a uniformly loaded square of side 2a: u_z = (4 a / (π E*)) · 2 asinh(1)
        // (Johnson 1985, §3.5).
        let (e, nu, cell) = (300.0, 0.3, 0.2);
        let e_star = e / (1.0 - nu * nu);
        let u = halfspace_cell(Component::Zz, 0.0, 0.0, cell, e, nu);
        let expected = 4.0 * 0.1 / (std::f64::consts::PI * e_star) * 2.0 * 1f64.asinh();
        assert!((u - expected).abs() < 1e-12 * expected);
    }

    #[test]
    fn far_field_is_the_point_force() {
        let (e, nu, cell) = (300.0, 0.4, 0.05);
        let g = e / (2.0 * (1.0 + nu));
        let e_star = e / (1.0 - nu * nu);
        let (x, y) = (1.3, -0.7);
        let r = f64::hypot(x, y);
        let area = cell * cell;
        let pi = std::f64::consts::PI;
        let cases = [
            (Component::Zz, area / (pi * e_star * r)),
            (
                Component::Xx,
                area / (2.0 * pi * g) * ((1.0 - nu) / r + nu * x * x / r.powi(3)),
            ),
            (
                Component::Yy,
                area / (2.0 * pi * g) * ((1.0 - nu) / r + nu * y * y / r.powi(3)),
            ),
            (
                Component::Xy,
                area / (2.0 * pi * g) * nu * x * y / r.powi(3),
            ),
        ];
        for (c, expected) in cases {
            let u = halfspace_cell(c, x, y, cell, e, nu);
            assert!(
                (u - expected).abs() < 1e-3 * expected.abs(),
                "{c:?}: {u} vs {expected}"
            );
        }
    }

    #[test]
    fn layer_ratio_limits() {
        for nu in [0.0, 0.3, 0.49, 0.5] {
            // Half-space for qh → ∞.
            assert!((layer_ratio(80.0, nu) - 1.0).abs() < 1e-12);
            assert!((layer_ratio(1e4, nu) - 1.0).abs() < 1e-12);
            // Uniaxial compression for qh → 0: C(0) = (1+ν)(1−2ν)h/(E(1−ν)), so
            // N/D ≈ (E*|q|/2) C(0) = s (1−2ν)/(4(1−ν)²) with s = 2qh.
            let s = 1e-4;
            let expected = s * (1.0 - 2.0 * nu) / (4.0 * (1.0 - nu) * (1.0 - nu));
            let got = layer_ratio(s, nu);
            if nu < 0.5 {
                assert!(
                    (got - expected).abs() < 1e-3 * expected,
                    "ν={nu}: {got} {expected}"
                );
            } else {
                // Incompressible: N ~ s³/6, D → 8(1−ν)² = 2.
                assert!((got - s.powi(3) / 12.0).abs() < 1e-3 * s.powi(3) / 12.0);
            }
        }
    }

    #[test]
    fn bessel_values() {
        // Abramowitz & Stegun, Table 9.1.
        for (x, j0) in [
            (0.0, 1.0),
            (1.0, 0.7651976866),
            (5.0, -0.1775967713),
            (10.0, -0.2459357645),
        ] {
            assert!((bessel_j0(x) - j0).abs() < 1e-8, "J0({x})");
        }
    }

    #[test]
    fn layer_correction_cancels_boussinesq_far_away() {
        let (e, nu, h) = (300.0, 0.45, 1.0);
        let e_star = e / (1.0 - nu * nu);
        let table = LayerCorrection::new(e, nu, h, 12.0, 0.01);
        let r = 10.0;
        let expected = -1.0 / (std::f64::consts::PI * e_star * r);
        assert!((table.at(Component::Zz, r, 0.0) - expected).abs() < 2e-3 * expected.abs());
    }

    #[test]
    fn bessel_j1_j2_values() {
        // Abramowitz & Stegun, Table 9.1.
        for (x, j1, j2) in [
            (0.0, 0.0, 0.0),
            (0.5, 0.2422684577, 0.0306040235),
            (1.0, 0.4400505857, 0.1149034849),
            (5.0, -0.3275791376, 0.0465651163),
            (10.0, 0.0434727462, 0.2546303137),
        ] {
            assert!((bessel_j1(x) - j1).abs() < 1e-8, "J1({x})");
            assert!((bessel_j2(x) - j2).abs() < 1e-8, "J2({x})");
        }
    }

    #[test]
    fn layer_compliance_limits() {
        for nu in [0.0, 0.3, 0.48, 0.5] {
            // Half-space for kh → ∞ (Cerruti and the coupling of Johnson eq. 3.19a).
            let c = LayerCompliance::at(40.0, nu);
            assert!((c.longitudinal - (1.0 - nu)).abs() < 1e-12);
            assert!((c.transverse - 1.0).abs() < 1e-12);
            assert!((c.coupling - 0.5 * (1.0 - 2.0 * nu)).abs() < 1e-12);
            // A sheared slab for kh → 0: u = q h / G.
            let t = 1e-4;
            let c = LayerCompliance::at(t, nu);
            assert!((c.longitudinal - t).abs() < 1e-3 * t, "ν={nu}");
            assert!((c.transverse - t).abs() < 1e-6 * t);
        }
        // Incompressible: the squeeze-flow coupling −t²/2 (see the lubrication test below).
        let t = 1e-3;
        let c = LayerCompliance::at(t, 0.5);
        assert!((c.coupling + 0.5 * t * t).abs() < 1e-3 * t * t);
    }

    /// The normal compliance of the same general solution is Carbone & Mangialardi's (A.30),
    /// derived separately: a check of the longitudinal and coupling terms' common algebra.
    #[test]
    fn normal_compliance_matches_carbone_mangialardi() {
        for nu in [0.0, 0.3, 0.48, 0.5] {
            for t in [0.05, 0.3, 1.0, 2.5, 8.0] {
                let w = (-2.0f64 * t).exp();
                let kappa = 3.0 - 4.0 * nu;
                let d =
                    kappa * (1.0 + w * w) + (10.0 - 24.0 * nu + 16.0 * nu * nu + 4.0 * t * t) * w;
                let normal = (1.0 - nu) * (kappa * (1.0 - w * w) - 4.0 * t * w) / d;
                let carbone = (1.0 - nu) * layer_ratio(2.0 * t, nu);
                assert!(
                    (normal - carbone).abs() < 1e-9 * carbone.max(1e-6),
                    "ν={nu}, t={t}: {normal} vs {carbone}"
                );
            }
        }
    }

    /// Cell coefficients of the layer: half-space cell plus the correction times the area.
    fn layer_cell(layer: &LayerCorrection, c: Component, x: f64, y: f64, cell: f64) -> f64 {
        halfspace_cell(c, x, y, cell, 300.0, 0.5) + layer.at(c, x, y) * cell * cell
    }

    /// Sums of the layer's coefficients over offsets much wider than the layer are its response
    /// to uniform loads, known from slab theory: a uniform shear traction q shears it by q h/G
    /// (and nothing across), and a pressure gradient ∂p/∂x on an incompressible layer drives the
    /// squeeze flow whose surface moves by −h² ∂p/∂x/(2G) (lubrication: G u'' = ∂p/∂x,
    /// u(−h) = 0, u'(0) = 0).
    #[test]
    fn layer_sums_are_slab_theory() {
        let (e, nu, h, cell) = (300.0, 0.5, 1.0, 0.1);
        let g = e / (2.0 * (1.0 + nu));
        let half_cells = 160;
        let r_max = 1.5 * half_cells as f64 * cell;
        let layer = LayerCorrection::new(e, nu, h, r_max, 0.01);
        let (mut shear, mut across, mut squeeze) = (0.0, 0.0, 0.0);
        for j in -half_cells..=half_cells {
            for i in -half_cells..=half_cells {
                let (x, y) = (i as f64 * cell, j as f64 * cell);
                shear += layer_cell(&layer, Component::Xx, x, y, cell);
                across += layer_cell(&layer, Component::Xy, x, y, cell);
                squeeze += layer_cell(&layer, Component::Zx, x, y, cell) * x;
            }
        }
        let shear_expected = h / g;
        assert!(
            (shear - shear_expected).abs() < 1e-2 * shear_expected,
            "uniform shear: {shear} vs {shear_expected}"
        );
        assert!(across.abs() < 1e-9 * shear_expected);
        let squeeze_expected = -h * h / (2.0 * g);
        assert!(
            (squeeze - squeeze_expected).abs() < 1e-2 * squeeze_expected.abs(),
            "squeeze flow: {squeeze} vs {squeeze_expected}"
        );
    }

    #[test]
    fn layer_corrections_cancel_cerruti_far_away() {
        let (e, nu, h) = (300.0, 0.3, 1.0);
        let g = e / (2.0 * (1.0 + nu));
        let table = LayerCorrection::new(e, nu, h, 12.0, 0.01);
        let (x, y) = (6.0, 8.0);
        let r = 10.0;
        let pi = std::f64::consts::PI;
        let cases = [
            (
                Component::Xx,
                -((1.0 - nu) / r + nu * x * x / r.powi(3)) / (2.0 * pi * g),
            ),
            (Component::Xy, -nu * x * y / r.powi(3) / (2.0 * pi * g)),
            (
                Component::Zx,
                -(1.0 - 2.0 * nu) * x / (r * r) / (4.0 * pi * g),
            ),
        ];
        for (c, expected) in cases {
            let got = table.at(c, x, y);
            assert!(
                (got - expected).abs() < 5e-3 * expected.abs(),
                "{c:?}: {got} vs {expected}"
            );
        }
    }

    #[test]
    fn coupling_cell_far_field_is_the_point_force() {
        let (e, nu, cell) = (300.0, 0.3, 0.05);
        let g = e / (2.0 * (1.0 + nu));
        let (x, y) = (1.3, -0.7);
        let r2 = x * x + y * y;
        let area = cell * cell;
        let pi = std::f64::consts::PI;
        for (c, along) in [(Component::Zx, x), (Component::Zy, y)] {
            let expected = area * (1.0 - 2.0 * nu) * along / (4.0 * pi * g * r2);
            let u = halfspace_cell(c, x, y, cell, e, nu);
            assert!(
                (u - expected).abs() < 1e-3 * expected.abs(),
                "{c:?}: {u} vs {expected}"
            );
        }
        // Odd in its own axis, even in the other, zero at the cell's own centre.
        let zx = |x, y| halfspace_cell(Component::Zx, x, y, cell, e, nu);
        assert_eq!(zx(0.0, 0.3), 0.0);
        assert!((zx(0.2, 0.3) + zx(-0.2, 0.3)).abs() < 1e-15);
        assert!((zx(0.2, 0.3) - zx(0.2, -0.3)).abs() < 1e-15);
    }
}
