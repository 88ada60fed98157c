//! Analytic contact solutions, the references of the tests and of `sparsh validate`.
//!
//! Rigid indenters on an elastic body with E* = E/(1 − ν²), G = E/(2(1 + ν)); K. L. Johnson,
//! *Contact Mechanics* (1985), unless noted. Units: mm, kPa, N (1 kPa · mm² = 1 mN).

use std::f64::consts::PI;

/// Hertz: rigid sphere (paraboloid) of radius R on a half-space (Johnson §4.2).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Hertz {
    /// Indenter radius R (mm).
    pub radius_mm: f64,
    /// Plane-strain modulus E* (kPa).
    pub effective_modulus_kpa: f64,
}

impl Hertz {
    /// Normal load P = (4/3) E* R^(1/2) δ^(3/2) (N) at approach δ (mm).
    pub fn force_n(&self, approach_mm: f64) -> f64 {
        4.0 / 3.0
            * self.effective_modulus_kpa
            * self.radius_mm.sqrt()
            * approach_mm.powf(1.5)
            * 1e-3
    }

    /// Contact radius a = (3PR/(4E*))^(1/3) (mm) at load P (N).
    pub fn contact_radius_mm(&self, force_n: f64) -> f64 {
        (3.0 * force_n * 1e3 * self.radius_mm / (4.0 * self.effective_modulus_kpa)).cbrt()
    }

    /// Approach δ = a²/R (mm) at load P (N).
    pub fn approach_mm(&self, force_n: f64) -> f64 {
        self.contact_radius_mm(force_n).powi(2) / self.radius_mm
    }

    /// Peak pressure p₀ = 3P/(2πa²) (kPa) at load P (N).
    pub fn peak_pressure_kpa(&self, force_n: f64) -> f64 {
        3.0 * force_n * 1e3 / (2.0 * PI * self.contact_radius_mm(force_n).powi(2))
    }
}

/// Flat cylindrical punch of radius a pressed δ into a half-space: P = 2aE*δ (N; Boussinesq,
/// Johnson §3.8).
pub fn flat_punch_force_n(radius_mm: f64, depth_mm: f64, effective_modulus_kpa: f64) -> f64 {
    2.0 * radius_mm * effective_modulus_kpa * depth_mm * 1e-3
}

/// Rigid cone of semi-angle α (axis to face) pressed δ into a half-space (Sneddon 1965; Johnson
/// §5.6): contact radius a = (2/π) δ tan α (mm).
pub fn cone_contact_radius_mm(depth_mm: f64, half_angle_rad: f64) -> f64 {
    2.0 / PI * depth_mm * half_angle_rad.tan()
}

/// Rigid cone: P = (2/π) E* δ² tan α (N).
pub fn cone_force_n(depth_mm: f64, half_angle_rad: f64, effective_modulus_kpa: f64) -> f64 {
    2.0 / PI * effective_modulus_kpa * depth_mm * depth_mm * half_angle_rad.tan() * 1e-3
}

/// Rigid *sphere* (not Hertz's paraboloid) of radius R pressed δ into a half-space, exact in
/// linear elasticity (Sneddon, Int. J. Eng. Sci. 3, 1965): the contact radius a solves
/// δ = (a/2) ln((R + a)/(R − a)) (mm). `None` unless δ and R are finite and positive.
pub fn sneddon_sphere_contact_radius_mm(radius_mm: f64, depth_mm: f64) -> Option<f64> {
    if !(radius_mm > 0.0 && radius_mm.is_finite() && depth_mm > 0.0 && depth_mm.is_finite()) {
        return None;
    }
    let depth_at = |a: f64| 0.5 * a * ((radius_mm + a) / (radius_mm - a)).ln();
    // δ(a) rises monotonically from 0 at a = 0 to ∞ as a → R: bisect to the last bit.
    let (mut lo, mut hi) = (0.0, radius_mm);
    for _ in 0..200 {
        let mid = 0.5 * (lo + hi);
        if mid <= lo || mid >= hi {
            break;
        }
        if depth_at(mid) < depth_mm {
            lo = mid;
        } else {
            hi = mid;
        }
    }
    Some(0.5 * (lo + hi))
}

/// Rigid sphere on a half-space, exact in linear elasticity (Sneddon 1965):
/// P = (E*/2) [(a² + R²) ln((R + a)/(R − a)) − 2aR] (N) with a from
/// [`sneddon_sphere_contact_radius_mm`]; Hertz's (4/3) E* R^(1/2) δ^(3/2) is its limit δ ≪ R.
/// `None` where the contact radius is.
pub fn sneddon_sphere_force_n(
    radius_mm: f64,
    depth_mm: f64,
    effective_modulus_kpa: f64,
) -> Option<f64> {
    let a = sneddon_sphere_contact_radius_mm(radius_mm, depth_mm)?;
    let r = radius_mm;
    let log = ((r + a) / (r - a)).ln();
    Some(0.5 * effective_modulus_kpa * ((a * a + r * r) * log - 2.0 * a * r) * 1e-3)
}

/// Cattaneo–Mindlin: a sphere under constant normal load P, then a monotonic tangential load Q <
/// μP (Johnson §7.2, Goodman's approximation: no normal–tangential coupling).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct CattaneoMindlin {
    /// Hertz contact radius a (mm).
    pub contact_radius_mm: f64,
    /// Normal load P (N).
    pub normal_force_n: f64,
    /// Friction coefficient μ.
    pub friction: f64,
    /// Shear modulus G (kPa).
    pub shear_modulus_kpa: f64,
    /// Poisson ratio ν.
    pub poisson_ratio: f64,
}

impl CattaneoMindlin {
    /// Stick radius c = a (1 − Q/(μP))^(1/3) (mm), Johnson eq. 7.41.
    pub fn stick_radius_mm(&self, q_over_mu_p: f64) -> f64 {
        self.contact_radius_mm * (1.0 - q_over_mu_p).cbrt()
    }

    /// Rigid tangential shift δ_t = 3μP(2 − ν)/(16Ga) · [1 − (1 − Q/(μP))^(2/3)] (mm), Johnson
    /// eq. 7.42.
    pub fn shift_mm(&self, q_over_mu_p: f64) -> f64 {
        3.0 * self.friction * self.normal_force_n * 1e3 * (2.0 - self.poisson_ratio)
            / (16.0 * self.shear_modulus_kpa * self.contact_radius_mm)
            * (1.0 - (1.0 - q_over_mu_p).powf(2.0 / 3.0))
    }
}

/// Bottom-effect correction for a paraboloid on an incompressible layer bonded to a rigid base,
/// F/F_Hertz = 1 + 1.133χ + 1.497χ² + 1.469χ³ + 0.755χ⁴ with χ = √(Rδ)/h (Garcia & Garcia,
/// Biophys. J. 114, 2018).
pub fn garcia_bottom_effect(chi: f64) -> f64 {
    1.0 + chi * (1.133 + chi * (1.497 + chi * (1.469 + chi * 0.755)))
}

/// F/F_Hertz of a paraboloid on an incompressible bonded layer where a reference is known:
/// Garcia & Garcia's fit for χ ≤ 0.5 (within 0.7 % of the exact Fourier-domain layer solution
/// there), and that exact solution, 5.11, at χ = 1, where the published fits disagree (Garcia &
/// Garcia 5.85, Dimitriadis et al. 4.28). The 5.11 (with 1.518 at χ = 0.3 and 2.156 at 0.5) is
/// an independent numerical solution of the Carbone & Mangialardi layer compliance (eq. A.30),
/// converged in grid and box size at ν = 0.4999, made outside this crate's solvers. `None`
/// elsewhere.
pub fn bonded_layer_force_factor(chi: f64) -> Option<f64> {
    const EXACT_AT_CHI_1: f64 = 5.11;
    if (0.0..=0.5).contains(&chi) {
        Some(garcia_bottom_effect(chi))
    } else if (chi - 1.0).abs() <= 1e-6 {
        Some(EXACT_AT_CHI_1)
    } else {
        None
    }
}

/// F/F_Hertz of a rigid sphere pressed to δ/R = `depth_over_radius` into an incompressible
/// neo-Hookean half-space, in the closed form attributed to Lin et al. (Biomech. Model.
/// Mechanobiol. 8, 2009) as implemented in AtomicJ and ISR3D: F = (80/9) a² P(λ) with a = √(Rδ),
/// λ = 1 − 0.2 a/R and P the uniaxial nominal stress 2C₁₀(λ⁻² − λ); that is
/// (75 − 15x + x²)/(3(5 − x)²) with x = √(δ/R). It is Hertz's mean pressure written as a
/// constraint factor 80/(9π) times E ε at Tabor's representative strain ε = 0.2 a/R, with E ε
/// replaced by the neo-Hookean stress in uniaxial compression at λ = 1 − ε: a one-point
/// surrogate, not a solution of the contact problem, stiffer than Hertz at every depth because
/// that stress is convex in ε. A reported comparison, not a pass mark.
pub fn lin_neo_hookean_factor(depth_over_radius: f64) -> f64 {
    let x = depth_over_radius.sqrt();
    (75.0 - 15.0 * x + x * x) / (3.0 * (5.0 - x) * (5.0 - x))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn hertz_is_self_consistent() {
        let h = Hertz {
            radius_mm: 5.0,
            effective_modulus_kpa: 400.0,
        };
        let delta = 0.07;
        let f = h.force_n(delta);
        assert!((h.approach_mm(f) - delta).abs() < 1e-12);
        // Stiffness dP/dδ = 2aE*.
        let e = 1e-7;
        let stiffness = (h.force_n(delta + e) - h.force_n(delta - e)) / (2.0 * e);
        let expected = 2.0 * h.contact_radius_mm(f) * 400.0 * 1e-3;
        assert!((stiffness - expected).abs() < 1e-6 * expected);
    }

    /// Sneddon's sphere against two answers it does not compute with: Hertz in the limit δ ≪ R,
    /// and the force integrated from the stiffness dP/dδ = 2aE*, which holds for any
    /// axisymmetric rigid indenter in linear elasticity (Pharr, Oliver & Brotzen, J. Mater. Res.
    /// 7, 1992), with the contact radius alone from Sneddon.
    #[test]
    fn sneddon_sphere_meets_hertz_and_its_own_stiffness() {
        let (r, e_star) = (5.0, 400.0);
        let hertz = Hertz {
            radius_mm: r,
            effective_modulus_kpa: e_star,
        };
        let shallow = 1e-4;
        let p = sneddon_sphere_force_n(r, shallow, e_star).unwrap();
        assert!((p / hertz.force_n(shallow) - 1.0).abs() < 1e-4);
        for depth in [0.25_f64, 1.0, 2.5] {
            // Simpson's rule on P(δ) = ∫₀^δ 2 a(s) E* ds (a ~ √s near 0: substitute s = t²).
            let n = 2000;
            let h = depth.sqrt() / n as f64;
            let f = |t: f64| {
                let a = if t == 0.0 {
                    0.0
                } else {
                    sneddon_sphere_contact_radius_mm(r, t * t).unwrap()
                };
                2.0 * a * e_star * 2.0 * t
            };
            let mut sum = f(0.0) + f(depth.sqrt());
            for i in 1..n {
                sum += f(i as f64 * h) * if i % 2 == 1 { 4.0 } else { 2.0 };
            }
            let integrated = sum * h / 3.0 * 1e-3;
            let closed = sneddon_sphere_force_n(r, depth, e_star).unwrap();
            assert!(
                (integrated / closed - 1.0).abs() < 1e-6,
                "δ = {depth}: ∫2aE* dδ = {integrated}, closed form {closed}"
            );
            // the exact sphere is softer than the paraboloid at the same depth
            assert!(closed < hertz.force_n(depth));
        }
        assert_eq!(sneddon_sphere_force_n(r, 0.0, e_star), None);
        assert_eq!(sneddon_sphere_force_n(r, f64::NAN, e_star), None);
        assert_eq!(sneddon_sphere_contact_radius_mm(-1.0, 0.1), None);
        assert_eq!(sneddon_sphere_contact_radius_mm(f64::INFINITY, 0.1), None);
    }

    /// The Lin et al. factor against its construction computed step by step: Hertz's mean
    /// pressure at a = √(Rδ) with E ε (ε = 0.2 a/R) replaced by the incompressible neo-Hookean
    /// uniaxial nominal stress 2C₁₀(λ⁻² − λ), λ = 1 − ε, E = 6C₁₀.
    #[test]
    fn lin_factor_is_tabor_strain_in_uniaxial_compression() {
        let (r, c10) = (5.0, 50.0);
        let e = 6.0 * c10;
        let hertz = Hertz {
            radius_mm: r,
            effective_modulus_kpa: e / (1.0 - 0.25),
        };
        for depth in [0.01, 0.25, 1.0, 2.0] {
            let a = (r * depth).sqrt();
            let strain = 0.2 * a / r;
            let mean_pressure = hertz.force_n(depth) * 1e3 / (PI * a * a);
            let constraint = mean_pressure / (e * strain);
            let stretch = 1.0 - strain;
            let stress = 2.0 * c10 * (stretch.powi(-2) - stretch);
            let surrogate = constraint * stress * PI * a * a * 1e-3;
            let factor = lin_neo_hookean_factor(depth / r);
            assert!((surrogate / hertz.force_n(depth) - factor).abs() < 1e-12);
            assert!(factor > 1.0, "stiffer than Hertz at every depth");
        }
    }

    #[test]
    fn mindlin_initial_stiffness() {
        // dQ/dδ_t at Q = 0 is 8Ga/(2 − ν) (Johnson eq. 7.43).
        let cm = CattaneoMindlin {
            contact_radius_mm: 1.0,
            normal_force_n: 0.05,
            friction: 0.8,
            shear_modulus_kpa: 100.0,
            poisson_ratio: 0.5,
        };
        let r = 1e-6;
        let q = r * 0.8 * 0.05;
        let stiffness = q / cm.shift_mm(r);
        let expected = 8.0 * 100.0 * 1.0 / 1.5 * 1e-3;
        assert!((stiffness - expected).abs() < 1e-5 * expected);
    }
}
