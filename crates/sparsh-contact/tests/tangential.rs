//! The boundary-element rungs' tangential methods against each other, and warm starts against
//! cold ones: independent iterations, one answer.

use sparsh_contact::{
    Bem, BemOptions, ContactInput, ContactSolver, Fields, NormalControl, SlipState,
    TangentialMethod,
};
use sparsh_scene::{GapField, Gel, Grid};

const GRID: Grid = Grid {
    nx: 81,
    ny: 81,
    cell_mm: 0.05,
};

const GEL: Gel = Gel {
    youngs_modulus_kpa: 300.0,
    poisson_ratio: 0.5,
    thickness_mm: 3.0,
    friction: 0.5,
};

/// A paraboloid of radius `radius_mm` centred at `centre` (mm), pressed `depth_mm`.
fn paraboloid(radius_mm: f64, depth_mm: f64, centre: [f64; 2]) -> GapField {
    let gap_mm = (0..GRID.len())
        .map(|k| {
            let (i, j) = (k % GRID.nx, k / GRID.nx);
            let r = f64::hypot(GRID.x_mm(i) - centre[0], GRID.y_mm(j) - centre[1]);
            r * r / (2.0 * radius_mm) - depth_mm
        })
        .collect();
    GapField { grid: GRID, gap_mm }
}

fn step(solver: &mut Bem, gap: &GapField, shift_mm: [f64; 2]) -> Fields {
    let shift = vec![shift_mm; GRID.len()];
    solver
        .solve(&ContactInput {
            gap,
            normal: NormalControl::Approach,
            rigid_shift_mm: &shift,
        })
        .expect("solve")
}

/// Largest difference of two fields over the largest magnitude of the first.
fn max_rel_diff(a: &[f64], b: &[f64]) -> f64 {
    let scale = a.iter().fold(0.0f64, |m, v| m.max(v.abs()));
    a.iter()
        .zip(b)
        .fold(0.0f64, |m, (x, y)| m.max((x - y).abs()))
        / scale
}

/// Cells whose slip flag differs.
fn slip_differences(a: &Fields, b: &Fields) -> usize {
    a.slip.iter().zip(&b.slip).filter(|(x, y)| x != y).count()
}

#[test]
fn newton_agrees_with_fista_in_partial_slip() {
    // Hertz contact (a ≈ 1 mm, 40 cells across), then a shift at 30° to x worth Q ≈ 0.5 μP:
    // a crescent of slip whose directions fan out, so both the stick zone and the slip
    // directions are unknowns.
    let gap = paraboloid(100.0, 0.01, [0.0, 0.0]);
    let shift = [
        0.0035 * 30f64.to_radians().cos(),
        0.0035 * 30f64.to_radians().sin(),
    ];
    let run = |method, tangential_tolerance| {
        let options = BemOptions {
            tangential_method: method,
            tangential_tolerance,
            max_iterations: 100_000,
            ..BemOptions::default()
        };
        let mut solver = Bem::halfspace(GEL, GRID).with_options(options);
        step(&mut solver, &gap, [0.0; 2]);
        let f = step(&mut solver, &gap, shift);
        (f, solver.stats().tangential_convolutions)
    };
    let (newton, newton_convolutions) = run(TangentialMethod::SemismoothNewton, 1e-6);
    let (fista, fista_convolutions) = run(TangentialMethod::Fista, 1e-6);
    let (tight_newton, _) = run(TangentialMethod::SemismoothNewton, 1e-10);
    let (tight_fista, _) = run(TangentialMethod::Fista, 1e-10);
    let traction_diff = |a: &Fields, b: &Fields| {
        max_rel_diff(&a.traction_x_kpa, &b.traction_x_kpa)
            .max(max_rel_diff(&a.traction_y_kpa, &b.traction_y_kpa))
    };
    let tight = traction_diff(&tight_fista, &tight_newton);
    let newton_error = traction_diff(&tight_fista, &newton);
    let fista_error = traction_diff(&tight_fista, &fista);
    eprintln!(
        "tight Newton vs tight FISTA {tight:.2e}; at the default tolerance, Newton {newton_error:.2e} and FISTA {fista_error:.2e} from tight FISTA; {newton_convolutions} vs {fista_convolutions} convolutions"
    );
    // Converged tightly, the two methods give one answer; at the default tolerance Newton is
    // the closer to it.
    assert_eq!(newton.slip_state(), SlipState::Partial);
    assert!(tight < 1e-6, "{tight:e}");
    assert!(
        newton_error < 1e-4 && newton_error <= fista_error,
        "{newton_error:e}"
    );
    assert_eq!(slip_differences(&tight_fista, &newton), 0);
    assert!(max_rel_diff(&tight_fista.ux_mm, &newton.ux_mm) < 1e-5);
    assert!(newton_convolutions < fista_convolutions);
}

#[test]
fn warm_start_gives_the_cold_start_answer() {
    // Press, then slide across the grid: stick, partial slip, gross sliding.
    let frames: Vec<(GapField, [f64; 2])> = (0..12)
        .map(|k| {
            let depth = 0.01 * ((k + 1) as f64 / 4.0).min(1.0);
            let x = if k >= 4 { 0.004 * (k - 3) as f64 } else { 0.0 };
            let shift = if k >= 5 { [0.004, 0.0] } else { [0.0; 2] };
            (paraboloid(100.0, depth, [x, 0.0]), shift)
        })
        .collect();
    let run = |warm_start| {
        let options = BemOptions {
            warm_start,
            ..BemOptions::default()
        };
        let mut solver = Bem::halfspace(GEL, GRID).with_options(options);
        frames
            .iter()
            .map(|(gap, shift)| step(&mut solver, gap, *shift))
            .collect::<Vec<Fields>>()
    };
    let (warm, cold) = (run(true), run(false));
    let mut worst = [0.0f64; 3];
    for (w, c) in warm.iter().zip(&cold) {
        assert_eq!(w.contact, c.contact);
        worst[0] = worst[0].max(max_rel_diff(&c.pressure_kpa, &w.pressure_kpa));
        worst[1] = worst[1].max(max_rel_diff(&c.traction_x_kpa, &w.traction_x_kpa));
        worst[2] = worst[2].max(slip_differences(w, c) as f64);
    }
    eprintln!(
        "pressure {:.2e}, traction {:.2e}, slip cells differing {}",
        worst[0], worst[1], worst[2]
    );
    assert!(
        worst[0] < 1e-6 && worst[1] < 1e-4 && worst[2] <= 2.0,
        "{worst:?}"
    );
    let states: Vec<SlipState> = warm.iter().map(Fields::slip_state).collect();
    assert!(
        states.contains(&SlipState::Partial) && states.contains(&SlipState::Gross),
        "{states:?}"
    );
}
