//! `solver = "auto"` with `tolerance = 0.02` on scenes the solver table was not built from (other
//! indenters, sizes, Poisson ratios, loads, a layer thickness and a sensor resolution the study
//! did not run): the chosen rung and grid meet the tolerance against the analytic answer, and
//! cost no more than the most accurate fixed choice.

use std::path::Path;

use sparsh_contact::validation::{Case, Check, evaluate_case};
use sparsh_scene::Scene;
use sparsh_scene::auto::{SolverTable, candidates, most_accurate};

/// A 240 × 240 px sensor at 0.03 mm per pixel (the study's grids are odd and of other sizes).
fn scene(gel: &str, indenter: &str, depth_mm: f64) -> Scene {
    let text = format!(
        "solver = \"auto\"\ntolerance = 0.02\n[sensor]\npreset = \"digit\"\nwidth_px = 240\n\
         height_px = 240\nmm_per_px = 0.03\n[gel]\n{gel}\n[indenter]\n{indenter}\n\
         [[trajectory]]\ntime_s = 0.0\nposition_mm = [0.0, 0.0, {:?}]\n",
        -depth_mm
    );
    Scene::parse(Path::new("auto.toml"), text).expect("scene")
}

fn case(check: Check, q_over_mu_p: f64) -> Case {
    Case {
        check,
        q_over_mu_p,
        tangential_steps: 4,
    }
}

#[test]
fn auto_meets_its_tolerance_on_held_out_scenes_and_is_never_dearer() {
    let thick = "youngs_modulus_kpa = 250.0\npoisson_ratio = 0.48\nthickness_mm = 400.0";
    let held_out = [
        (
            "cone 80°",
            scene(
                thick,
                "shape = \"cone\"\nhalf_angle_deg = 80.0\nheight_mm = 2.0",
                0.277,
            ),
            case(Check::Cone, 0.0),
        ),
        (
            "cone 60°",
            scene(
                thick,
                "shape = \"cone\"\nhalf_angle_deg = 60.0\nheight_mm = 3.0",
                0.9,
            ),
            case(Check::Cone, 0.0),
        ),
        (
            "hertz R 50, ν 0.3",
            scene(
                "poisson_ratio = 0.3\nthickness_mm = 400.0",
                "shape = \"sphere\"\nradius_mm = 50.0",
                0.02,
            ),
            case(Check::Hertz, 0.0),
        ),
        (
            "flat punch a 0.8",
            scene(
                thick,
                "shape = \"cylinder\"\nradius_mm = 0.8\nheight_mm = 2.0",
                0.01,
            ),
            case(Check::FlatPunch, 0.0),
        ),
        (
            "mindlin Q/μP 0.8, μ 0.8",
            scene(
                "poisson_ratio = 0.5\nthickness_mm = 400.0\nfriction = 0.8",
                "shape = \"sphere\"\nradius_mm = 100.0",
                0.01,
            ),
            case(Check::CattaneoMindlin, 0.8),
        ),
        (
            "bonded layer a/h 0.3",
            scene(
                "poisson_ratio = 0.5\nthickness_mm = 3.3333",
                "shape = \"sphere\"\nradius_mm = 100.0",
                0.01,
            ),
            case(Check::BondedLayer, 0.0),
        ),
    ];
    let table = SolverTable::builtin();
    for (name, scene, case) in held_out {
        let choice = scene.auto.expect("auto records its choice");
        assert!(choice.meets_tolerance(), "{name}: {choice:?}");
        let evaluation =
            evaluate_case(&scene, &case, scene.mechanics_grid()).expect("auto's choice solves");
        let force = &evaluation.values[0];
        let error = force.rel_error();
        let all = candidates(
            table,
            &scene.sensor,
            &scene.gel,
            choice.contact_radius_mm,
            choice.depth_over_h * scene.gel.thickness_mm,
            choice.sliding,
            choice.tolerance,
        );
        let best = most_accurate(&all).expect("candidates");
        let cells = |stride: usize| (240 / stride) * (240 / stride);
        println!(
            "{name}: auto {} stride {} (a ≈ {:.3} mm, a/h {:.3}, predicted {:.2e} at {:.2} ms) \
             → error {:+.3e}; most accurate fixed {} stride {} predicted {:.2e} at {:.2} ms",
            choice.solver.name(),
            choice.mechanics_stride,
            choice.contact_radius_mm,
            choice.a_over_h,
            choice.predicted_rel_error,
            choice.predicted_ms_per_frame,
            error,
            best.solver.name(),
            best.mechanics_stride,
            best.predicted_rel_error,
            best.predicted_ms_per_frame,
        );
        assert!(
            error.abs() <= choice.tolerance,
            "{name}: {} stride {} misses: {error:+.3e}",
            choice.solver.name(),
            choice.mechanics_stride
        );
        // Never dearer than the most accurate fixed choice, counted in contact cells solved.
        assert!(cells(choice.mechanics_stride) <= cells(best.mechanics_stride));
    }
}

/// The quickstart under `solver = "auto"`: its press alone, a 6 mm-radius sphere 0.3 mm into a
/// 3 mm gel (δ/h = 0.1) with μ = 1, gets the layered rung on the grid the scene names, whose
/// studied depth limit for a press with friction is δ/h = 0.1 at 2 %, and with its slide (which
/// `auto` sees) the layered rung at the 5 % the scene states; the same press 0.85 mm deep (δ/h = 0.28) gets the finite elements with
/// friction, where a stuck surface at finite strain stiffens the press beyond the boundary
/// elements' linear coupling, and the layered rung again without friction (its frictionless
/// limit being 0.3); 1 mm deep (δ/h = 0.33) the finite elements either way, and 0.1 mm deep a
/// boundary-element rung.
#[test]
fn auto_takes_the_layer_for_the_quickstart_and_the_finite_elements_deeper() {
    let shipped = std::fs::read_to_string(
        Path::new(env!("CARGO_MANIFEST_DIR")).join("../../scenes/quickstart.toml"),
    )
    .expect("quickstart scene");
    // The quick start names the rung and grid that `auto` takes for its press alone, and states
    // the tolerance its slide needs.
    let named = "solver = \"layered\"\nmechanics_stride = 2\ntolerance = 0.05\n";
    assert!(shipped.contains(named) && shipped.contains("friction = 1.0"));
    let quickstart = shipped.replace(named, "solver = \"auto\"\n");
    let scene_with = |text: &str| Scene::parse(Path::new("quickstart.toml"), text.to_string());
    let press_alone =
        scene_with(&quickstart.replace("[1.0, 0.0, -0.3]", "[-1.0, 0.0, -0.3]")).expect("scene");
    let choice = press_alone.auto.expect("auto records its choice");
    assert!(!choice.sliding, "{choice:?}");
    assert_eq!(
        (press_alone.solver, press_alone.mechanics_stride),
        (sparsh_scene::SolverKind::Layered, 2),
        "{choice:?}"
    );
    assert!((choice.depth_over_h - 0.3 / 3.0).abs() < 0.02, "{choice:?}");
    // With its slide, `auto` knows the trajectory slides; at the scene's 5 % the layer holds.
    let sliding = scene_with(&quickstart).expect("scene");
    let choice = sliding.auto.expect("auto records its choice");
    assert!(choice.sliding, "{choice:?}");
    let loose = scene_with(&quickstart.replace(
        "solver = \"auto\"\n",
        "solver = \"auto\"\ntolerance = 0.05\n",
    ))
    .expect("scene");
    assert_eq!(
        loose.solver,
        sparsh_scene::SolverKind::Layered,
        "{:?}",
        loose.auto
    );
    let pressed = |depth: &str, friction: &str| {
        let text = quickstart
            .replace("[-1.0, 0.0, -0.3]", &format!("[-1.0, 0.0, -{depth}]"))
            .replace("[1.0, 0.0, -0.3]", &format!("[1.0, 0.0, -{depth}]"))
            .replace("friction = 1.0", &format!("friction = {friction}"));
        Scene::parse(Path::new("pressed.toml"), text).expect("scene")
    };
    let stuck = pressed("0.85", "1.0");
    let choice = stuck.auto.expect("auto records its choice");
    assert_eq!(stuck.solver, sparsh_scene::SolverKind::Fem, "{choice:?}");
    assert!(
        (choice.depth_over_h - 0.85 / 3.0).abs() < 0.02,
        "{choice:?}"
    );
    let slippery = pressed("0.85", "0.0");
    assert_eq!(
        slippery.solver,
        sparsh_scene::SolverKind::Layered,
        "{:?}",
        slippery.auto
    );
    for friction in ["0.0", "1.0"] {
        let deep = pressed("1.0", friction);
        let choice = deep.auto.expect("auto records its choice");
        assert_eq!(deep.solver, sparsh_scene::SolverKind::Fem, "{choice:?}");
        assert!((choice.depth_over_h - 1.0 / 3.0).abs() < 0.02, "{choice:?}");
    }
    let shallow = pressed("0.1", "1.0");
    assert_ne!(
        shallow.solver,
        sparsh_scene::SolverKind::Fem,
        "{:?}",
        shallow.auto
    );
}
