//! The boundary-element rungs against closed-form contact solutions, on small grids.

use proptest::prelude::*;
use sparsh_contact::reference::{self, CattaneoMindlin, Hertz};
use sparsh_contact::{
    Bem, BemOptions, ContactError, ContactInput, ContactSolver, Fields, NormalControl, SlipState,
};
use sparsh_scene::{GapField, Gel, Grid};

fn gel(poisson_ratio: f64, thickness_mm: f64, friction: f64) -> Gel {
    Gel {
        youngs_modulus_kpa: 300.0,
        poisson_ratio,
        thickness_mm,
        friction,
    }
}

/// Gap of an axisymmetric profile z(r) centred at (cx, cy), pressed `depth_mm`.
fn gap(grid: Grid, depth_mm: f64, centre: [f64; 2], profile: impl Fn(f64) -> f64) -> GapField {
    let gap_mm = (0..grid.len())
        .map(|k| {
            let (i, j) = (k % grid.nx, k / grid.nx);
            let r = f64::hypot(grid.x_mm(i) - centre[0], grid.y_mm(j) - centre[1]);
            profile(r) - depth_mm
        })
        .collect();
    GapField { grid, gap_mm }
}

fn paraboloid(grid: Grid, radius_mm: f64, depth_mm: f64) -> GapField {
    gap(grid, depth_mm, [0.0, 0.0], |r| r * r / (2.0 * radius_mm))
}

fn solve(solver: &mut dyn ContactSolver, gap: &GapField, normal: NormalControl) -> Fields {
    let shift = vec![[0.0; 2]; gap.grid.len()];
    solver
        .solve(&ContactInput {
            gap,
            normal,
            rigid_shift_mm: &shift,
        })
        .expect("solve")
}

fn contact_radius_mm(f: &Fields) -> f64 {
    (f.contact_area_mm2() / std::f64::consts::PI).sqrt()
}

fn rel(a: f64, b: f64) -> f64 {
    (a - b) / b
}

const GRID: Grid = Grid {
    nx: 65,
    ny: 65,
    cell_mm: 0.1,
};

#[test]
fn hertz_under_displacement_control() {
    let g = gel(0.48, 3.0, 1.0);
    let hertz = Hertz {
        radius_mm: 100.0,
        effective_modulus_kpa: g.effective_modulus_kpa(),
    };
    let f = solve(
        &mut Bem::halfspace(g, GRID),
        &paraboloid(GRID, 100.0, 0.01),
        NormalControl::Approach,
    );
    let force = hertz.force_n(0.01);
    assert!(rel(f.force_n[2], force).abs() < 0.01, "{}", f.force_n[2]);
    assert!(rel(contact_radius_mm(&f), hertz.contact_radius_mm(force)).abs() < 0.03);
    let peak = f.pressure_kpa.iter().copied().fold(0.0, f64::max);
    assert!(rel(peak, hertz.peak_pressure_kpa(force)).abs() < 0.03);
    // Pressure profile p₀√(1 − r²/a²) inside the contact, well away from its edge.
    let a = hertz.contact_radius_mm(force);
    for (k, p) in f.pressure_kpa.iter().enumerate() {
        let r = f64::hypot(GRID.x_mm(k % GRID.nx), GRID.y_mm(k / GRID.nx));
        if r < 0.8 * a {
            let expected = hertz.peak_pressure_kpa(force) * (1.0 - r * r / (a * a)).sqrt();
            assert!((p - expected).abs() < 0.03 * hertz.peak_pressure_kpa(force));
        }
    }
    // Surface displacement outside the contact (Johnson eq. 3.42b:
    // u_z = p₀ [(2a² − r²) asin(a/r) + a √(r² − a²)]/(2aE*)), uz < 0 towards the camera.
    let e_star = g.effective_modulus_kpa();
    let p0 = hertz.peak_pressure_kpa(force);
    let r = 2.0 * a;
    let k = 32 * GRID.nx + 32 + 20; // r = 2.0 mm along +x
    assert!((GRID.x_mm(32 + 20) - r).abs() < 1e-12);
    let expected = p0 * ((2.0 * a * a - r * r) * (a / r).asin() + a * (r * r - a * a).sqrt())
        / (2.0 * a * e_star);
    assert!(
        rel(-f.uz_mm[k], expected).abs() < 0.02,
        "{} {}",
        f.uz_mm[k],
        expected
    );
}

#[test]
fn hertz_under_load_control() {
    let g = gel(0.3, 3.0, 1.0);
    let hertz = Hertz {
        radius_mm: 100.0,
        effective_modulus_kpa: g.effective_modulus_kpa(),
    };
    let load_n = 0.004;
    let f = solve(
        &mut Bem::halfspace(g, GRID),
        &paraboloid(GRID, 100.0, 0.0),
        NormalControl::Force(load_n),
    );
    assert!(rel(f.force_n[2], load_n).abs() < 1e-9);
    assert!(rel(f.approach_offset_mm, hertz.approach_mm(load_n)).abs() < 0.02);
}

#[test]
fn flat_punch_force() {
    let g = gel(0.45, 3.0, 1.0);
    let depth = 0.02;
    let gap = gap(GRID, depth, [0.0, 0.0], |r| {
        if r < 1.0 { 0.0 } else { f64::INFINITY }
    });
    let f = solve(&mut Bem::halfspace(g, GRID), &gap, NormalControl::Approach);
    let expected = reference::flat_punch_force_n(1.0, depth, g.effective_modulus_kpa());
    assert!(rel(f.force_n[2], expected).abs() < 0.03, "{}", f.force_n[2]);
}

#[test]
fn cone_force_and_radius() {
    let g = gel(0.48, 3.0, 1.0);
    let alpha = 80f64.to_radians();
    let depth = 0.28;
    let gap = gap(GRID, depth, [0.0, 0.0], |r| r / alpha.tan());
    let f = solve(&mut Bem::halfspace(g, GRID), &gap, NormalControl::Approach);
    let force = reference::cone_force_n(depth, alpha, g.effective_modulus_kpa());
    assert!(rel(f.force_n[2], force).abs() < 0.03);
    let a = reference::cone_contact_radius_mm(depth, alpha);
    assert!(rel(contact_radius_mm(&f), a).abs() < 0.03);
}

#[test]
fn cattaneo_mindlin_partial_slip_then_gross_sliding() {
    let g = gel(0.5, 3.0, 0.5);
    let grid = Grid {
        nx: 81,
        ny: 81,
        cell_mm: 0.05,
    };
    let (radius, depth) = (100.0, 0.01);
    let hertz = Hertz {
        radius_mm: radius,
        effective_modulus_kpa: g.effective_modulus_kpa(),
    };
    let load = hertz.force_n(depth);
    let cm = CattaneoMindlin {
        contact_radius_mm: hertz.contact_radius_mm(load),
        normal_force_n: load,
        friction: g.friction,
        shear_modulus_kpa: g.youngs_modulus_kpa / 3.0,
        poisson_ratio: 0.5,
    };
    let mut solver = Bem::halfspace(g, grid);
    let field = paraboloid(grid, radius, depth);
    let first = solve(&mut solver, &field, NormalControl::Approach);
    assert_eq!(first.slip_state(), SlipState::Stick);
    let ratio = 0.5;
    let shift = vec![[cm.shift_mm(ratio), 0.0]; grid.len()];
    let f = solver
        .solve(&ContactInput {
            gap: &field,
            normal: NormalControl::Approach,
            rigid_shift_mm: &shift,
        })
        .expect("tangential step");
    assert_eq!(f.slip_state(), SlipState::Partial);
    assert!(rel(f.force_n[0], ratio * g.friction * load).abs() < 0.01);
    assert!(f.force_n[1].abs() < 1e-9 * load);
    let stick = f.contact.iter().zip(&f.slip).filter(|(c, s)| **c && !**s);
    let c = (stick.count() as f64 * grid.cell_area_mm2() / std::f64::consts::PI).sqrt();
    assert!(rel(c, cm.stick_radius_mm(ratio)).abs() < 0.05, "{c}");
    // Coulomb everywhere; tractions in the slip zone at the bound.
    for k in 0..grid.len() {
        let q = f.traction_x_kpa[k].hypot(f.traction_y_kpa[k]);
        assert!(q <= g.friction * f.pressure_kpa[k] * (1.0 + 1e-9) + 1e-12);
        if f.slip[k] {
            assert!(q >= g.friction * f.pressure_kpa[k] * (1.0 - 1e-6));
        }
    }
    // Beyond Mindlin's δ_t at Q = μP the whole contact slides at Q = μP.
    let more = vec![[cm.shift_mm(1.0), 0.0]; grid.len()];
    let f = solver
        .solve(&ContactInput {
            gap: &field,
            normal: NormalControl::Approach,
            rigid_shift_mm: &more,
        })
        .expect("sliding step");
    assert_eq!(f.slip_state(), SlipState::Gross);
    // Every cell at the bound; in one large step the slip directions still fan out slightly,
    // so Q_x is just under μP.
    let bound_n: f64 = (0..grid.len())
        .map(|k| f.traction_x_kpa[k].hypot(f.traction_y_kpa[k]))
        .sum::<f64>()
        * grid.cell_area_mm2()
        * 1e-3;
    assert!(rel(bound_n, g.friction * f.force_n[2]).abs() < 1e-6);
    assert!(rel(f.force_n[0], g.friction * f.force_n[2]).abs() < 2e-3);
}

#[test]
fn incompressible_bonded_layer_against_garcia() {
    let g = gel(0.5, 2.0, 1.0);
    let grid = Grid {
        nx: 81,
        ny: 81,
        cell_mm: 0.08,
    };
    let (radius, depth) = (100.0, 0.01);
    let f = solve(
        &mut Bem::layered(g, grid),
        &paraboloid(grid, radius, depth),
        NormalControl::Approach,
    );
    let hertz = Hertz {
        radius_mm: radius,
        effective_modulus_kpa: g.effective_modulus_kpa(),
    };
    let chi = (radius * depth).sqrt() / g.thickness_mm;
    let expected = hertz.force_n(depth) * reference::garcia_bottom_effect(chi);
    assert!(
        rel(f.force_n[2], expected).abs() < 0.02,
        "{}",
        rel(f.force_n[2], expected)
    );
    assert!(f.pressure_kpa.iter().all(|p| p.is_finite()));
    assert!(f.uz_mm.iter().all(|u| u.is_finite()));
}

#[test]
fn thick_layer_is_a_half_space() {
    let g = gel(0.45, 500.0, 1.0);
    let field = paraboloid(GRID, 100.0, 0.01);
    let half = solve(
        &mut Bem::halfspace(g, GRID),
        &field,
        NormalControl::Approach,
    );
    let layer = solve(&mut Bem::layered(g, GRID), &field, NormalControl::Approach);
    assert!(rel(layer.force_n[2], half.force_n[2]).abs() < 0.01);
}

#[test]
fn nan_gap_is_an_error() {
    let mut field = paraboloid(GRID, 100.0, 0.01);
    field.gap_mm[7] = f64::NAN;
    let shift = vec![[0.0; 2]; GRID.len()];
    let r = Bem::halfspace(gel(0.48, 3.0, 1.0), GRID).solve(&ContactInput {
        gap: &field,
        normal: NormalControl::Approach,
        rigid_shift_mm: &shift,
    });
    assert!(matches!(r, Err(ContactError::OutOfValidity { .. })));
}

#[test]
fn contact_at_the_grid_edge_is_an_error() {
    // A 3.5 mm contact radius on a 6.5 mm wide grid.
    let field = paraboloid(GRID, 100.0, 0.1225);
    let shift = vec![[0.0; 2]; GRID.len()];
    let r = Bem::halfspace(gel(0.48, 3.0, 1.0), GRID).solve(&ContactInput {
        gap: &field,
        normal: NormalControl::Approach,
        rigid_shift_mm: &shift,
    });
    assert!(
        matches!(r, Err(ContactError::OutOfValidity { .. })),
        "{r:?}"
    );
}

#[test]
fn no_contact_gives_empty_fields() {
    let field = paraboloid(GRID, 100.0, -0.01);
    let f = solve(
        &mut Bem::halfspace(gel(0.48, 3.0, 1.0), GRID),
        &field,
        NormalControl::Approach,
    );
    assert_eq!(f, Fields::zero(GRID));
    assert_eq!(f.slip_state(), SlipState::NoContact);
}

#[test]
fn iteration_cap_is_reported() {
    let options = BemOptions {
        max_iterations: 2,
        ..BemOptions::default()
    };
    let field = paraboloid(GRID, 100.0, 0.01);
    let shift = vec![[0.0; 2]; GRID.len()];
    let r = Bem::halfspace(gel(0.48, 3.0, 1.0), GRID)
        .with_options(options)
        .solve(&ContactInput {
            gap: &field,
            normal: NormalControl::Approach,
            rigid_shift_mm: &shift,
        });
    assert!(matches!(r, Err(ContactError::NotConverged { .. })), "{r:?}");
}

#[test]
fn same_bits_on_one_and_two_threads() {
    let grid = Grid {
        nx: 201,
        ny: 161,
        cell_mm: 0.05,
    };
    let field = gap(grid, 0.012, [0.3, -0.2], |r| r * r / 200.0);
    let shift = vec![[0.002, 0.001]; grid.len()];
    let run = |threads: usize| {
        let pool = rayon::ThreadPoolBuilder::new()
            .num_threads(threads)
            .build()
            .expect("pool");
        pool.install(|| {
            let mut solver = Bem::layered(gel(0.48, 3.0, 0.8), grid);
            solve(&mut solver, &field, NormalControl::Approach);
            solver
                .solve(&ContactInput {
                    gap: &field,
                    normal: NormalControl::Force(0.01),
                    rigid_shift_mm: &shift,
                })
                .expect("solve")
        })
    };
    assert_eq!(run(1), run(2));
}

#[test]
fn validation_cases_pass() {
    let dir = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../../scenes/validation");
    let report = sparsh_contact::validation::run_cases(&dir).expect("validation run");
    for row in &report.rows {
        assert!(row.passed(), "{row:?}");
    }
    assert!(report.rows.len() >= 20);
}

proptest! {
    // a fixed seed: every run draws the same cases
    #![proptest_config(ProptestConfig {
        cases: 12,
        rng_seed: proptest::test_runner::RngSeed::Fixed(11),
        ..ProptestConfig::default()
    })]

    /// Under load control, Σ p dA equals the applied load.
    #[test]
    fn load_control_balances_the_load(
        load_n in 0.0005f64..0.02,
        radius_mm in 20.0f64..200.0,
        cx in -0.5f64..0.5,
        cy in -0.5f64..0.5,
    ) {
        let grid = Grid { nx: 48, ny: 40, cell_mm: 0.12 };
        // keep the Hertz contact, a = (3 F R / 4 E*)^(1/3), two cells inside the 5.76 × 4.8 mm
        // grid: beyond it the half-space solver reports out-of-validity instead of a load
        let e_star_n_per_mm2 = 0.3 / (1.0 - 0.45 * 0.45);
        let a_mm = (3.0 * load_n * radius_mm / (4.0 * e_star_n_per_mm2)).cbrt();
        prop_assume!(a_mm + cx.abs().max(cy.abs()) < 2.4 - 2.0 * grid.cell_mm);
        let field = gap(grid, 0.0, [cx, cy], |r| r * r / (2.0 * radius_mm));
        let f = solve(
            &mut Bem::halfspace(gel(0.45, 3.0, 1.0), grid),
            &field,
            NormalControl::Force(load_n),
        );
        let total = f.pressure_kpa.iter().sum::<f64>() * grid.cell_area_mm2() * 1e-3;
        prop_assert!((total - load_n).abs() < 1e-9 * load_n);
        prop_assert!((f.force_n[2] - load_n).abs() < 1e-9 * load_n);
    }

    /// An axisymmetric indenter centred on a square grid gives pressures with the grid's
    /// symmetries (mirror in x, in y, and the diagonal). The draws are of the rigid contact
    /// radius √(Rδ), at most 1.4 mm on the 4.1 mm wide grid, so every contact stays well inside
    /// it and every case is solved and checked.
    #[test]
    fn axisymmetric_contact_stays_symmetric(
        rigid_radius_mm in 0.3f64..1.4,
        radius_mm in 20.0f64..200.0,
        layered in any::<bool>(),
    ) {
        let n = 41;
        let grid = Grid { nx: n, ny: n, cell_mm: 0.1 };
        let depth_mm = rigid_radius_mm * rigid_radius_mm / radius_mm;
        let field = paraboloid(grid, radius_mm, depth_mm);
        let g = gel(0.49, 2.0, 1.0);
        let mut solver = if layered { Bem::layered(g, grid) } else { Bem::halfspace(g, grid) };
        let f = solver
            .solve(&ContactInput {
                gap: &field,
                normal: NormalControl::Approach,
                rigid_shift_mm: &vec![[0.0; 2]; grid.len()],
            })
            .expect("a contact inside the grid");
        prop_assert!(f.force_n[2] > 0.0);
        let peak = f.pressure_kpa.iter().copied().fold(0.0, f64::max);
        for j in 0..n {
            for i in 0..n {
                let p = f.pressure_kpa[j * n + i];
                for q in [
                    f.pressure_kpa[j * n + (n - 1 - i)],
                    f.pressure_kpa[(n - 1 - j) * n + i],
                    f.pressure_kpa[i * n + j],
                ] {
                    prop_assert!((p - q).abs() <= 1e-8 * peak, "{} {} at {},{}", p, q, i, j);
                }
            }
        }
    }
}

/// A flat rectangular face pressed and then twisted: cells the face leaves had pressure in the
/// previous frame (regression: their infinite gap once poisoned the warm start).
#[test]
fn twisting_flat_face_stays_finite() {
    let grid = Grid {
        nx: 61,
        ny: 61,
        cell_mm: 0.1,
    };
    let face = |angle: f64| {
        let (s, c) = angle.sin_cos();
        let gap_mm = (0..grid.len())
            .map(|k| {
                let (x, y) = (grid.x_mm(k % grid.nx), grid.y_mm(k / grid.nx));
                let (u, v) = (c * x + s * y, -s * x + c * y);
                if u.abs() < 1.5 && v.abs() < 1.0 {
                    -0.02
                } else {
                    f64::INFINITY
                }
            })
            .collect();
        GapField { grid, gap_mm }
    };
    for mut solver in [
        Bem::halfspace(gel(0.48, 3.0, 1.0), grid),
        Bem::layered(gel(0.48, 3.0, 1.0), grid),
    ] {
        solve(&mut solver, &face(0.0), NormalControl::Approach);
        let turn = 10f64.to_radians();
        let twisted = face(turn);
        let shift: Vec<[f64; 2]> = (0..grid.len())
            .map(|k| {
                let (x, y) = (grid.x_mm(k % grid.nx), grid.y_mm(k / grid.nx));
                let (s, c) = turn.sin_cos();
                [x - (c * x + s * y), y - (-s * x + c * y)]
            })
            .collect();
        let f = solver
            .solve(&ContactInput {
                gap: &twisted,
                normal: NormalControl::Approach,
                rigid_shift_mm: &shift,
            })
            .expect("twisted frame");
        assert!(f.force_n[2] > 0.0 && f.force_n.iter().all(|v| v.is_finite()));
        assert!(f.pressure_kpa.iter().all(|p| p.is_finite() && *p >= 0.0));
        // Tractions respect Coulomb's bound.
        for k in 0..grid.len() {
            let q = f.traction_x_kpa[k].hypot(f.traction_y_kpa[k]);
            assert!(q <= f.pressure_kpa[k] * (1.0 + 1e-9) + 1e-12);
        }
    }
}
