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
//! Normal–tangential coupling (terms ∝ (1−2ν)) is neglected (Goodman's approximation, Johnson
//! §7.2); it vanishes for an incompressible gel (ν = 0.5).

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
    }
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

/// The bonded layer's normal compliance minus the half-space's, in real space, tabulated in r.
///
/// With ũ_z = C(q) p̃, the layer's C_layer(q) = (2/(E*|q|)) · N/D ([`layer_ratio`]) and the
/// half-space's 2/(E*|q|), the point-force difference is the Hankel transform
/// c(r) = (1/2π) ∫₀^∞ [C_layer − C_half] J₀(qr) q dq = Φ(r/2h)/(2π E* h),
/// Φ(ρ) = ∫₀^∞ (N/D − 1)(s) J₀(sρ) ds. The integrand is bounded (−1 at s = 0) and decays like
/// s² e^(−s), so Simpson's rule on s ∈ [0, 60] converges; for r ≫ h, c → −1/(πE* r) cancels the
/// Boussinesq tail, and the zero mode (N/D → 0 as q → 0, the uniaxial stiffness E(1−ν)/((1+ν)
/// (1−2ν)h), infinite at ν = 0.5) needs no special case. Adding c(r)·cell area to the half-space
/// cell coefficient gives the layer's coefficient for a laterally unbounded layer (no periodic
/// images); c is smooth on the scale h, so taking it at the cell centre costs O((cell/h)²).
#[derive(Debug, Clone)]
pub(crate) struct LayerCorrection {
    step_mm: f64,
    values: Vec<f64>,
}

impl LayerCorrection {
    /// Tabulates c(r) (mm per kPa·mm²) for 0 ≤ r ≤ `r_max_mm` at a step of `step_mm`.
    pub(crate) fn new(
        youngs_kpa: f64,
        poisson: f64,
        thickness_mm: f64,
        r_max_mm: f64,
        step_mm: f64,
    ) -> LayerCorrection {
        let e_star = youngs_kpa / (1.0 - poisson * poisson);
        let rho_max = r_max_mm / (2.0 * thickness_mm);
        let s_max = 60.0;
        // ≥ 40 samples per period of J₀(sρ) and per unit of s.
        let ds_target = (2.0 * std::f64::consts::PI / (40.0 * rho_max.max(1e-9))).min(0.025);
        let intervals = ((s_max / ds_target).ceil() as usize).next_multiple_of(2);
        let ds = s_max / intervals as f64;
        let weighted: Vec<(f64, f64)> = (0..=intervals)
            .map(|k| {
                let s = k as f64 * ds;
                let w = if k == 0 || k == intervals {
                    1.0
                } else if k % 2 == 1 {
                    4.0
                } else {
                    2.0
                };
                (s, w * ds / 3.0 * (layer_ratio(s, poisson) - 1.0))
            })
            .collect();
        let count = (r_max_mm / step_mm).ceil() as usize + 2;
        let scale = 1.0 / (2.0 * std::f64::consts::PI * e_star * thickness_mm);
        let values = (0..count)
            .map(|k| {
                let rho = k as f64 * step_mm / (2.0 * thickness_mm);
                scale
                    * weighted
                        .iter()
                        .map(|&(s, w)| w * bessel_j0(s * rho))
                        .sum::<f64>()
            })
            .collect();
        LayerCorrection { step_mm, values }
    }

    /// c(r) by linear interpolation in the table (mm per kPa·mm²).
    pub(crate) fn at(&self, r_mm: f64) -> f64 {
        let t = r_mm / self.step_mm;
        let k = (t.floor() as usize).min(self.values.len() - 2);
        let w = t - k as f64;
        self.values[k] * (1.0 - w) + self.values[k + 1] * w
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
        assert!((table.at(r) - expected).abs() < 2e-3 * expected.abs());
    }
}
