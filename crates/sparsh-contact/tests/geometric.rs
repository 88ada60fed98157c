//! The geometric rung against its own closed form: a flat punch on a Winkler bed of modulus
//! k = E*/h carries F = k·d·πa².

use glam::DVec3;
use sparsh_contact::{ContactInput, ContactSolver, Geometric, NormalControl};
use sparsh_scene::{GapField, Gel, Grid, Indenter, Pose};

const GRID: Grid = Grid {
    nx: 128,
    ny: 128,
    cell_mm: 0.05,
};

fn punch_gap(depth_mm: f64) -> GapField {
    let punch = Indenter::Cylinder {
        radius_mm: 1.5,
        height_mm: 5.0,
    };
    let pose = Pose {
        position_mm: DVec3::new(0.0, 0.0, -depth_mm),
        rotation_deg: DVec3::ZERO,
    };
    GapField::cast(&punch, &pose, GRID)
}

#[test]
fn flat_punch_on_winkler_bed_carries_k_d_area() {
    let gel = Gel::default();
    let k_kpa_per_mm = gel.effective_modulus_kpa() / gel.thickness_mm;
    let depth_mm = 0.1;
    let gap = punch_gap(depth_mm);
    let shift = vec![[0.0; 2]; GRID.len()];
    let mut solver = Geometric::new(gel, GRID);
    let fields = solver
        .solve(&ContactInput {
            gap: &gap,
            normal: NormalControl::Approach,
            rigid_shift_mm: &shift,
        })
        .unwrap();
    let area_mm2 = std::f64::consts::PI * 1.5 * 1.5;
    let expected_n = k_kpa_per_mm * depth_mm * area_mm2 * 1e-3;
    let rel = (fields.force_n[2] / expected_n - 1.0).abs();
    assert!(rel < 0.01, "{} N vs {expected_n} N", fields.force_n[2]);
    assert!((fields.contact_area_mm2() / area_mm2 - 1.0).abs() < 0.01);
    // The surface conforms to the punch face inside the contact.
    let centre = (GRID.ny / 2) * GRID.nx + GRID.nx / 2;
    assert!((fields.uz_mm[centre] + depth_mm).abs() < 1e-12);
    assert_eq!(fields.force_n[0], 0.0);
}

#[test]
fn load_control_finds_the_winkler_approach() {
    let gel = Gel::default();
    let k_kpa_per_mm = gel.effective_modulus_kpa() / gel.thickness_mm;
    // Punch face 0.05 mm above the gel; 0.2 N needs d = F/(k·A) of penetration.
    let gap = punch_gap(-0.05);
    let shift = vec![[0.0; 2]; GRID.len()];
    let mut solver = Geometric::new(gel, GRID);
    let fields = solver
        .solve(&ContactInput {
            gap: &gap,
            normal: NormalControl::Force(0.2),
            rigid_shift_mm: &shift,
        })
        .unwrap();
    assert!((fields.force_n[2] - 0.2).abs() < 1e-9);
    let cells = fields.contact.iter().filter(|&&c| c).count() as f64;
    let depth_mm = 0.2 / (k_kpa_per_mm * cells * GRID.cell_area_mm2() * 1e-3);
    assert!((fields.approach_offset_mm - (0.05 + depth_mm)).abs() < 1e-9);
}

/// A press at or past the gel's thickness is refused by every rung, whatever it models below
/// the gel (the half-space has no bottom, the Winkler bed no depth limit of its own).
#[test]
fn every_rung_refuses_a_press_through_the_gel() {
    let gel = Gel {
        thickness_mm: 0.5,
        ..Gel::default()
    };
    let gap = punch_gap(0.6);
    let shift = vec![[0.0; 2]; GRID.len()];
    for kind in sparsh_scene::SolverKind::ALL {
        let mut solver = sparsh_contact::solver_for(kind, &gel, GRID);
        let err = solver
            .solve(&ContactInput {
                gap: &gap,
                normal: NormalControl::Approach,
                rigid_shift_mm: &shift,
            })
            .expect_err("a 0.6 mm press into a 0.5 mm gel");
        assert!(
            matches!(err, sparsh_contact::ContactError::OutOfValidity { .. }),
            "{kind:?}: {err}"
        );
        assert!(err.to_string().contains("0.5 mm"), "{kind:?}: {err}");
    }
}
