//! A sphere pressed into the gel and twisted about its axis, the twist reaching the boundary
//! elements through [`rigid_shift_mm`], against Lubkin's torsion of a circular contact (Johnson,
//! *Contact Mechanics* §7.3): fully stuck, M = 16Ga³β/3; sliding everywhere under the Hertz
//! pressure, M = 3πμPa/16; and in between, a moment that grows with the twist and stays under
//! both.

use glam::DVec3;
use sparsh_contact::reference::Hertz;
use sparsh_contact::{
    Bem, ContactInput, ContactSolver, Fields, NormalControl, SlipState, rigid_shift_mm,
};
use sparsh_scene::{GapField, Gel, Grid, Indenter, Pose};

const GRID: Grid = Grid {
    nx: 81,
    ny: 81,
    cell_mm: 0.05,
};
/// Sphere radius and approach: a Hertz contact radius √(Rδ) of 1 mm, 20 cells.
const RADIUS_MM: f64 = 100.0;
const DEPTH_MM: f64 = 0.01;

fn gel(thickness_mm: f64, friction: f64) -> Gel {
    Gel {
        youngs_modulus_kpa: 300.0,
        poisson_ratio: 0.5,
        thickness_mm,
        friction,
    }
}

fn pose(twist_rad: f64) -> Pose {
    Pose {
        position_mm: DVec3::new(0.0, 0.0, -DEPTH_MM),
        rotation_deg: DVec3::new(0.0, 0.0, twist_rad.to_degrees()),
    }
}

/// Twisting moment about the contact's centre, Σ (x q_y − y q_x) dA (N·mm).
fn moment_n_mm(f: &Fields) -> f64 {
    let g = f.grid;
    (0..g.len())
        .map(|k| {
            let (x, y) = (g.x_mm(k % g.nx), g.y_mm(k / g.nx));
            x * f.traction_y_kpa[k] - y * f.traction_x_kpa[k]
        })
        .sum::<f64>()
        * g.cell_area_mm2()
        * 1e-3
}

/// Presses the sphere, then twists it through `twists_rad` (cumulative angles, in order); the
/// fields of every twisted frame.
fn twist(solver: &mut dyn ContactSolver, twists_rad: &[f64]) -> Vec<Fields> {
    let sphere = Indenter::Sphere {
        radius_mm: RADIUS_MM,
    };
    let mut previous = pose(0.0);
    let mut out = Vec::new();
    for (k, &beta) in [0.0].iter().chain(twists_rad).enumerate() {
        let current = pose(beta);
        let gap = GapField::cast(&sphere, &current, GRID);
        let shift = rigid_shift_mm(&previous, &current, &gap);
        let f = solver
            .solve(&ContactInput {
                gap: &gap,
                normal: NormalControl::Approach,
                rigid_shift_mm: &shift,
            })
            .expect("twisted frame");
        if k > 0 {
            out.push(f);
        }
        previous = current;
    }
    out
}

const SHEAR_MODULUS_KPA: f64 = 100.0; // G = E/(2(1 + ν)) at E = 300 kPa, ν = 0.5

/// Hertz contact radius a = √(Rδ) (mm).
fn contact_radius_mm() -> f64 {
    (RADIUS_MM * DEPTH_MM).sqrt()
}

/// Lubkin, fully stuck: M = 16Ga³β/3 (N·mm; Johnson §7.3, β the rigid twist).
fn stuck_moment_n_mm(twist_rad: f64) -> f64 {
    16.0 / 3.0 * SHEAR_MODULUS_KPA * contact_radius_mm().powi(3) * twist_rad * 1e-3
}

/// Lubkin, sliding everywhere under the Hertz pressure: M = 3πμPa/16 (N·mm).
fn sliding_moment_n_mm(friction: f64) -> f64 {
    let hertz = Hertz {
        radius_mm: RADIUS_MM,
        effective_modulus_kpa: 400.0, // E* = E/(1 − ν²)
    };
    3.0 * std::f64::consts::PI / 16.0 * friction * hertz.force_n(DEPTH_MM) * contact_radius_mm()
}

/// Radial share of the tractions, Σ|q·r̂| / Σ|q|: a twist about the axis of an axisymmetric
/// contact drags the surface around it, not towards or away from it (on a square grid only the
/// stair-stepped rim departs from that).
fn radial_share(f: &Fields) -> f64 {
    let g = f.grid;
    let (mut radial, mut total) = (0.0, 0.0);
    for k in 0..g.len() {
        let (x, y) = (g.x_mm(k % g.nx), g.y_mm(k / g.nx));
        let (qx, qy) = (f.traction_x_kpa[k], f.traction_y_kpa[k]);
        if x.hypot(y) > 0.0 {
            radial += (qx * x + qy * y).abs() / x.hypot(y);
            total += qx.hypot(qy);
        }
    }
    radial / total
}

/// With friction high enough that no cell reaches μp, both rungs give the stuck moment within
/// 2 % (the tangential coefficients of the layered rung are the half-space's; a 500 mm layer
/// keeps its normal contact Hertz's).
#[test]
fn small_twist_with_high_friction_gives_the_stuck_moment() {
    let twist_rad = 1e-4;
    let expected = stuck_moment_n_mm(twist_rad);
    for mut solver in [
        Bem::halfspace(gel(3.0, 10.0), GRID),
        Bem::layered(gel(500.0, 10.0), GRID),
    ] {
        let f = twist(&mut solver, &[twist_rad]).remove(0);
        assert_eq!(f.slip_state(), SlipState::Stick, "{}", solver.name());
        let m = moment_n_mm(&f);
        let err = (m - expected) / expected;
        assert!(
            err.abs() < 0.02,
            "{}: {m} vs {expected} ({err:+.4})",
            solver.name()
        );
        // A pure twist: no net tangential force, tractions around the axis.
        let q_scale = m / contact_radius_mm();
        assert!(f.force_n[0].abs() < 1e-9 * q_scale && f.force_n[1].abs() < 1e-9 * q_scale);
        assert!(radial_share(&f) < 0.03, "{}", radial_share(&f));
    }
}

/// At μ = 0.5, twisted in 40 steps to ten times β* = 9πμP/(256Ga²) (where the stuck line meets
/// the sliding moment): the moment rises with every step, by less each step (the slip annulus
/// only grows), stays under both limits, and ends within 0.2 % of 3πμPa/16; the cells that
/// stick form a central disc that shrinks, the others slip at μp.
#[test]
fn twist_moment_rises_from_the_stuck_line_to_the_sliding_limit() {
    let friction = 0.5;
    let sliding = sliding_moment_n_mm(friction);
    let beta_star = sliding / stuck_moment_n_mm(1.0);
    let twists: Vec<f64> = (1..=40).map(|k| 0.25 * beta_star * k as f64).collect();
    let mut solver = Bem::halfspace(gel(3.0, friction), GRID);
    let frames = twist(&mut solver, &twists);
    let moments: Vec<f64> = frames.iter().map(moment_n_mm).collect();
    let mut last_rise = f64::INFINITY;
    let mut last_stuck = usize::MAX;
    for ((f, &m), (&beta, previous)) in frames
        .iter()
        .zip(&moments)
        .zip(twists.iter().zip([0.0].iter().chain(&moments)))
    {
        let rise = m - previous;
        // Within the tangential solver's tolerance once the moment has levelled off.
        let slack = 1e-6 * sliding;
        assert!(
            rise > -slack && rise <= last_rise + slack,
            "{rise} after {last_rise}"
        );
        last_rise = rise;
        assert!(m <= stuck_moment_n_mm(beta) * 1.02, "{m} at {beta}");
        assert!(m <= sliding * (1.0 + 1e-3), "{m} over {sliding}");
        assert_eq!(f.slip_state(), SlipState::Partial);
        assert!(radial_share(f) < 0.01, "{}", radial_share(f));
        // Coulomb: |q| ≤ μp everywhere, = μp where a cell slips.
        let r = |k: usize| f64::hypot(GRID.x_mm(k % GRID.nx), GRID.y_mm(k / GRID.nx));
        for k in 0..GRID.len() {
            let q = f.traction_x_kpa[k].hypot(f.traction_y_kpa[k]);
            assert!(q <= friction * f.pressure_kpa[k] * (1.0 + 1e-9) + 1e-12);
            if f.slip[k] {
                assert!(q >= friction * f.pressure_kpa[k] * (1.0 - 1e-6));
            }
        }
        // Stick inside, slip outside: no stuck cell lies beyond the innermost slipping one
        // by more than a cell.
        let stuck: Vec<usize> = (0..GRID.len())
            .filter(|&k| f.contact[k] && !f.slip[k])
            .collect();
        let inner_slip = (0..GRID.len())
            .filter(|&k| f.slip[k])
            .map(r)
            .fold(f64::INFINITY, f64::min);
        let outer_stuck = stuck.iter().map(|&k| r(k)).fold(0.0, f64::max);
        assert!(
            outer_stuck <= inner_slip + GRID.cell_mm,
            "{outer_stuck} {inner_slip}"
        );
        assert!(stuck.len() <= last_stuck);
        last_stuck = stuck.len();
    }
    let end = moments[moments.len() - 1];
    let err = (end - sliding) / sliding;
    assert!(err.abs() < 0.002, "{end} vs {sliding} ({err:+.5})");
}
