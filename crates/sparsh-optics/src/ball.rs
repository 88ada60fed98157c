//! The gel surface under a calibration ball whose contact circle a pack marks: Hertz's
//! displacement field of an elastic half-space pressed by a rigid sphere (closed form), or a rung
//! of the solver ladder pressed until its contact circle has the marked radius.

use serde::{Deserialize, Serialize};
use sparsh_contact::{ContactInput, NormalControl, solver_for};
use sparsh_scene::{GapField, Gel, Grid, SolverKind};

/// The mechanics a calibration assumes between the marked contact circle and the gel's surface.
/// A map fitted under one is the map a scene on that rung should render with: the same real
/// frame, explained by another surface, gives other slopes and so another slope → colour map.
#[derive(Debug, Clone, Copy, PartialEq, Default, Serialize, Deserialize)]
#[serde(rename_all = "snake_case", tag = "model")]
pub enum BallMechanics {
    /// Hertz's half-space field in closed form ([`ball_press_uz_mm`]).
    #[default]
    Hertz,
    /// The geometric rung (clipped penetration smoothed over half the gel's thickness).
    Geometric {
        /// Gel thickness (mm).
        thickness_mm: f64,
    },
    /// The half-space boundary-element rung (the numerical twin of [`BallMechanics::Hertz`]).
    Halfspace,
    /// The layered boundary-element rung: a gel layer bonded to its rigid window.
    Layered {
        /// Gel thickness (mm).
        thickness_mm: f64,
        /// Poisson ratio ν of the gel.
        poisson_ratio: f64,
    },
}

impl BallMechanics {
    /// One-line name for messages and tables (`hertz`, `layered (3 mm, ν 0.49)`, …).
    pub fn describe(&self) -> String {
        match self {
            BallMechanics::Hertz => "hertz".into(),
            BallMechanics::Geometric { thickness_mm } => format!("geometric ({thickness_mm} mm)"),
            BallMechanics::Halfspace => "halfspace".into(),
            BallMechanics::Layered {
                thickness_mm,
                poisson_ratio,
            } => format!("layered ({thickness_mm} mm, ν {poisson_ratio})"),
        }
    }

    /// The rung and gel a [`BallMechanics`] other than Hertz solves with; `None` for Hertz.
    /// Only the surface's shape matters under displacement control, so E is a placeholder.
    fn rung(&self) -> Option<(SolverKind, Gel)> {
        let gel = |thickness_mm: f64, poisson_ratio: f64| Gel {
            youngs_modulus_kpa: 250.0,
            poisson_ratio,
            thickness_mm,
            friction: 0.0,
        };
        match *self {
            BallMechanics::Hertz => None,
            BallMechanics::Geometric { thickness_mm } => {
                Some((SolverKind::Geometric, gel(thickness_mm, 0.5)))
            }
            // The half-space has no thickness; the rung refuses presses deeper than the gel.
            BallMechanics::Halfspace => Some((SolverKind::Halfspace, gel(1e3, 0.5))),
            BallMechanics::Layered {
                thickness_mm,
                poisson_ratio,
            } => Some((SolverKind::Layered, gel(thickness_mm, poisson_ratio))),
        }
    }

    /// Refuses a thickness or Poisson ratio no rung takes, naming the field.
    pub fn check(&self) -> Result<(), String> {
        if let Some((_, gel)) = self.rung() {
            if !(gel.thickness_mm.is_finite() && gel.thickness_mm > 0.0) {
                return Err(format!(
                    "mechanics: thickness_mm must be > 0, got {}",
                    gel.thickness_mm
                ));
            }
            if !(gel.poisson_ratio.is_finite()
                && gel.poisson_ratio > -1.0
                && gel.poisson_ratio <= 0.5)
            {
                return Err(format!(
                    "mechanics: poisson_ratio must be in (−1, 0.5], got {}",
                    gel.poisson_ratio
                ));
            }
        }
        Ok(())
    }

    /// The surface u_z (mm, negative towards the camera) on `grid` under a ball of radius
    /// `ball_radius_mm` whose contact circle, centred at `centre_mm`, has radius
    /// `contact_radius_mm`: [`ball_press_uz_mm`] for Hertz, else [`rung_ball_press_uz_mm`].
    pub fn uz_mm(
        &self,
        grid: Grid,
        centre_mm: [f64; 2],
        contact_radius_mm: f64,
        ball_radius_mm: f64,
    ) -> Result<Vec<f64>, String> {
        match self.rung() {
            None => ball_press_uz_mm(grid, centre_mm, contact_radius_mm, ball_radius_mm),
            Some((kind, gel)) => rung_ball_press_uz_mm(
                grid,
                centre_mm,
                contact_radius_mm,
                ball_radius_mm,
                kind,
                &gel,
            ),
        }
    }
}

/// Depth d (mm) of a ball of radius R whose contact circle has radius a, from the sphere's
/// geometry a² = 2Rd − d², so d = R − √(R² − a²). Errors when a ≥ R.
pub fn depth_from_contact_radius(
    contact_radius_mm: f64,
    ball_radius_mm: f64,
) -> Result<f64, String> {
    let (a, r) = (contact_radius_mm, ball_radius_mm);
    if !(r.is_finite() && r > 0.0) {
        return Err(format!("ball radius must be > 0 mm, got {r}"));
    }
    if !(a.is_finite() && a > 0.0 && a < r) {
        return Err(format!(
            "contact radius {a:.4} mm must be in (0, {r}) mm, the ball radius"
        ));
    }
    Ok(r - (r * r - a * a).sqrt())
}

/// Hertz normal displacement (mm, positive into the gel) at distance r from the centre of a
/// contact of radius a under a rigid sphere of radius R (Johnson, *Contact Mechanics* 1985,
/// eqs. 3.41a and 3.42b, with the approach δ = a²/R):
/// u(r) = δ − r²/(2R) for r ≤ a; u(r) = δ/(πa²)·[(2a² − r²)·asin(a/r) + a·√(r² − a²)] for r > a.
/// The second form decays as (4/3)δa/(πr) far away and meets the first at r = a with u = δ/2.
pub fn hertz_sphere_displacement_mm(r_mm: f64, contact_radius_mm: f64, ball_radius_mm: f64) -> f64 {
    let (r, a) = (r_mm.abs(), contact_radius_mm);
    let delta = a * a / ball_radius_mm;
    if r <= a {
        delta - r * r / (2.0 * ball_radius_mm)
    } else {
        delta / (std::f64::consts::PI * a * a)
            * ((2.0 * a * a - r * r) * (a / r).asin() + a * (r * r - a * a).sqrt())
    }
}

/// The normal displacement field u_z (mm, negative towards the camera, as in
/// [`crate::Surface`]) of the gel pressed by a ball of radius `ball_radius_mm` whose contact
/// circle, centred at `centre_mm` in the grid's frame, has radius `contact_radius_mm`.
/// Errors when the contact radius is not smaller than the ball's.
pub fn ball_press_uz_mm(
    grid: Grid,
    centre_mm: [f64; 2],
    contact_radius_mm: f64,
    ball_radius_mm: f64,
) -> Result<Vec<f64>, String> {
    depth_from_contact_radius(contact_radius_mm, ball_radius_mm)?;
    Ok((0..grid.len())
        .map(|c| {
            let (i, j) = (c % grid.nx, c / grid.nx);
            let r = (grid.x_mm(i) - centre_mm[0]).hypot(grid.y_mm(j) - centre_mm[1]);
            -hertz_sphere_displacement_mm(r, contact_radius_mm, ball_radius_mm)
        })
        .collect())
}

/// Cells across the contact radius of a rung's solve: fine enough that the contact radius,
/// counted in cells, moves by well under 1 % per cell added to the rim.
const CELLS_PER_CONTACT_RADIUS: f64 = 24.0;

/// The surface under a ball pressed on a rung of the solver ladder until the rung's contact
/// circle (radius √(A/π) of its contact area A) has the marked radius: the approach is found by
/// the Hertz-scaled secant d ← d·(a/a_k)², kept inside a bracket and bisected when it leaves it.
/// The rung solves on cells of a/24 (never finer than `grid`) over a window centred on the
/// contact that reaches every pixel of `grid`; u_z is interpolated bilinearly onto `grid`. Errors when
/// a ≥ R, or when no approach gives the radius within half a solver cell.
pub fn rung_ball_press_uz_mm(
    grid: Grid,
    centre_mm: [f64; 2],
    contact_radius_mm: f64,
    ball_radius_mm: f64,
    kind: SolverKind,
    gel: &Gel,
) -> Result<Vec<f64>, String> {
    let (a, r) = (contact_radius_mm, ball_radius_mm);
    depth_from_contact_radius(a, r)?;
    let cell_mm = (a / CELLS_PER_CONTACT_RADIUS).max(grid.cell_mm);
    // Wide enough to reach every pixel of `grid` from the contact's centre.
    let cells = |centre: f64, n: usize| {
        let half_mm = centre.abs() + n as f64 * grid.cell_mm / 2.0;
        2 * ((half_mm / cell_mm).ceil() as usize).max(4)
    };
    let coarse = Grid {
        nx: cells(centre_mm[0], grid.nx),
        ny: cells(centre_mm[1], grid.ny),
        cell_mm,
    };
    let mut solver = solver_for(kind, gel, coarse);
    let shift = vec![[0.0; 2]; coarse.len()];
    // The ball's gap over the undeformed surface at approach d, the contact in the middle.
    let gap_at = |d: f64| GapField {
        grid: coarse,
        gap_mm: (0..coarse.len())
            .map(|c| {
                let rho = coarse.x_mm(c % coarse.nx).hypot(coarse.y_mm(c / coarse.nx));
                let cap = if rho < r {
                    r - (r * r - rho * rho).sqrt()
                } else {
                    r + (rho - r)
                };
                cap - d
            })
            .collect(),
    };
    let mut solve = |d: f64| -> Result<(f64, Vec<f64>), String> {
        solver.reset();
        let gap = gap_at(d);
        let fields = solver
            .solve(&ContactInput {
                gap: &gap,
                normal: NormalControl::Approach,
                rigid_shift_mm: &shift,
            })
            .map_err(|e| e.to_string())?;
        let radius = (fields.contact_area_mm2() / std::f64::consts::PI).sqrt();
        Ok((radius, fields.uz_mm))
    };
    let (mut lo, mut hi) = (0.0f64, f64::INFINITY);
    let mut depth = a * a / r;
    let mut best: Option<(f64, Vec<f64>)> = None;
    for _ in 0..40 {
        let (radius, uz) = solve(depth)?;
        let miss = radius - a;
        if best.as_ref().is_none_or(|(m, _)| miss.abs() < m.abs()) {
            best = Some((miss, uz));
        }
        if miss.abs() <= 1e-3 * a {
            break;
        }
        if miss < 0.0 {
            lo = lo.max(depth);
        } else {
            hi = hi.min(depth);
        }
        if hi - lo < 1e-9 * depth {
            break;
        }
        let secant = (depth * (a / radius.max(1e-3 * a)).powi(2)).clamp(0.25 * depth, 4.0 * depth);
        depth = if secant > lo && secant < hi {
            secant
        } else if hi.is_finite() {
            0.5 * (lo + hi)
        } else {
            2.0 * depth
        };
    }
    let (miss, uz) = best.expect("at least one solve");
    if miss.abs() > 0.5 * cell_mm {
        return Err(format!(
            "{}: no approach gives the contact radius {a:.4} mm (closest {:.4} mm)",
            kind.name(),
            a + miss
        ));
    }
    Ok(interpolate(&uz, coarse, grid, centre_mm))
}

/// Bilinear interpolation of a field on `coarse` (centred at the origin) onto `fine`, with the
/// coarse grid's origin placed at `centre_mm` of the fine grid; 0 outside the coarse grid.
fn interpolate(values: &[f64], coarse: Grid, fine: Grid, centre_mm: [f64; 2]) -> Vec<f64> {
    let at = |i: isize, j: isize| {
        if i < 0 || j < 0 || i as usize >= coarse.nx || j as usize >= coarse.ny {
            0.0
        } else {
            values[j as usize * coarse.nx + i as usize]
        }
    };
    (0..fine.len())
        .map(|c| {
            // Coarse cell coordinates: x_mm(i) = (i + 0.5 − nx/2)·cell.
            let u = (fine.x_mm(c % fine.nx) - centre_mm[0]) / coarse.cell_mm
                + coarse.nx as f64 / 2.0
                - 0.5;
            let v = (fine.y_mm(c / fine.nx) - centre_mm[1]) / coarse.cell_mm
                + coarse.ny as f64 / 2.0
                - 0.5;
            let (i, j) = (u.floor(), v.floor());
            let (fu, fv) = (u - i, v - j);
            let (i, j) = (i as isize, j as isize);
            (1.0 - fv) * ((1.0 - fu) * at(i, j) + fu * at(i + 1, j))
                + fv * ((1.0 - fu) * at(i, j + 1) + fu * at(i + 1, j + 1))
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn depth_inverts_the_sphere_relation() {
        let (r, d) = (2.0f64, 0.37f64);
        let a = (2.0 * r * d - d * d).sqrt();
        assert!((depth_from_contact_radius(a, r).unwrap() - d).abs() < 1e-12);
        assert!(depth_from_contact_radius(2.5, 2.0).is_err());
    }

    #[test]
    fn hertz_field_is_continuous_and_decays_like_a_point_load() {
        let (a, r) = (0.8, 2.0);
        let delta = a * a / r;
        let inside = hertz_sphere_displacement_mm(a, a, r);
        let outside = hertz_sphere_displacement_mm(a * (1.0 + 1e-9), a, r);
        assert!((inside - delta / 2.0).abs() < 1e-12);
        assert!((outside - inside).abs() < 1e-6);
        // Far field: (4/3)·δ·a/(π r) (series of asin and the square root).
        let far = 200.0 * a;
        let expect = 4.0 / 3.0 * delta * a / (std::f64::consts::PI * far);
        assert!((hertz_sphere_displacement_mm(far, a, r) / expect - 1.0).abs() < 1e-4);
        // Slope is continuous at the rim: −a/R on both sides.
        let h = 1e-6;
        let s_in =
            (hertz_sphere_displacement_mm(a, a, r) - hertz_sphere_displacement_mm(a - h, a, r)) / h;
        let s_out = (hertz_sphere_displacement_mm(a + 2.0 * h, a, r)
            - hertz_sphere_displacement_mm(a + h, a, r))
            / h;
        assert!(
            (s_in + a / r).abs() < 1e-4 && (s_out + a / r).abs() < 1e-2,
            "{s_in} {s_out}"
        );
    }

    /// The grid of a small pack: 0.025 mm pixels, 6 × 4.8 mm (the rungs solve on a/24).
    const PACK: Grid = Grid {
        nx: 240,
        ny: 192,
        cell_mm: 0.025,
    };

    #[test]
    fn the_halfspace_rung_pressed_to_the_marked_radius_is_hertz() {
        // Closed form against boundary elements. The rung's contact radius, counted in cells
        // carrying pressure, is 2.4 % short of Hertz's at its approach on 24 cells a radius (the
        // same count `sparsh validate` grades at 2 %), so it presses up to 8 % deeper to reach
        // the marked circle; the shape of the surface, depth for depth, is Hertz's.
        let (a, r, centre) = (0.8, 2.0, [0.4, -0.3]);
        let hertz = ball_press_uz_mm(PACK, centre, a, r).unwrap();
        let rung = BallMechanics::Halfspace.uz_mm(PACK, centre, a, r).unwrap();
        let delta = a * a / r;
        let deepest = rung.iter().copied().fold(0.0, f64::min);
        assert!(
            (deepest / -delta - 1.0).abs() < 0.08,
            "{deepest} vs {delta}"
        );
        let worst = hertz
            .iter()
            .zip(&rung)
            .map(|(h, b)| (h / delta - b / deepest.abs()).abs())
            .fold(0.0, f64::max);
        assert!(worst < 0.02, "shape differs by {worst} of the depth");
    }

    #[test]
    fn a_thick_layer_is_the_half_space_and_a_thin_one_is_not() {
        let (a, r, centre) = (0.8, 2.0, [0.0, 0.0]);
        let hertz = ball_press_uz_mm(PACK, centre, a, r).unwrap();
        let delta = a * a / r;
        let layered = |thickness_mm| {
            BallMechanics::Layered {
                thickness_mm,
                poisson_ratio: 0.49,
            }
            .uz_mm(PACK, centre, a, r)
            .unwrap()
        };
        let worst = |uz: &[f64]| {
            hertz
                .iter()
                .zip(uz)
                .map(|(h, b)| (h - b).abs())
                .fold(0.0, f64::max)
        };
        assert!(worst(&layered(40.0)) < 0.04 * delta);
        // A bonded incompressible layer 1.25a thick: the rim is the marked one, the surface
        // another (the layer cannot spread the load as far), so the fits differ.
        let thin = layered(1.0);
        assert!(worst(&thin) > 0.1 * delta);
        // At the rim the surface meets the ball: u_z = −(d − a²/2R) with d the centre's depth.
        let depth = -thin[PACK.len() / 2 + PACK.nx / 2];
        let (i, j) = (PACK.nx / 2 + 31, PACK.ny / 2); // x = 0.7875 mm, inside a
        let rho = PACK.x_mm(i).hypot(PACK.y_mm(j));
        let on_ball = depth - (r - (r * r - rho * rho).sqrt());
        assert!((-thin[j * PACK.nx + i] - on_ball).abs() < 0.02 * depth);
    }

    #[test]
    fn the_geometric_rung_presses_to_the_cap_depth() {
        // Its contact is the clipped penetration, so the marked circle is the sphere's cut
        // through the undeformed surface: depth R − √(R² − a²).
        let (a, r) = (0.8, 2.0);
        let uz = BallMechanics::Geometric { thickness_mm: 2.0 }
            .uz_mm(PACK, [0.0, 0.0], a, r)
            .unwrap();
        let deepest = -uz.iter().copied().fold(0.0, f64::min);
        let cap = depth_from_contact_radius(a, r).unwrap();
        assert!((deepest / cap - 1.0).abs() < 0.02, "{deepest} vs {cap}");
    }

    #[test]
    fn bad_mechanics_are_refused_by_name() {
        let layered = |thickness_mm, poisson_ratio| BallMechanics::Layered {
            thickness_mm,
            poisson_ratio,
        };
        assert!(
            layered(0.0, 0.49)
                .check()
                .unwrap_err()
                .contains("thickness_mm")
        );
        assert!(
            layered(3.0, 0.6)
                .check()
                .unwrap_err()
                .contains("poisson_ratio")
        );
        assert!(layered(3.0, 0.49).check().is_ok());
        let err = BallMechanics::Halfspace
            .uz_mm(PACK, [0.0, 0.0], 2.5, 2.0)
            .unwrap_err();
        assert!(err.contains("contact radius"), "{err}");
        // A calibration's record reads back as what was written.
        let json = serde_json::to_value(layered(3.0, 0.49)).unwrap();
        assert_eq!(json["model"], "layered");
        let back: BallMechanics = serde_json::from_value(json).unwrap();
        assert_eq!(back, layered(3.0, 0.49));
    }
}
