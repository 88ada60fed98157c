//! Frames outside their rung's validity: recorded (`warn`), refused (`error`), or solved on the
//! next rung up (`escalate`), at the limits the study's table gives.

use std::path::Path;

use sparsh_scene::auto::SolverTable;
use sparsh_scene::{RungLimits, Scene, SolverKind, Validity};
use sparsh_sim::{SimError, Simulator};

/// The gel's friction coefficient in [`deep_press`]: the depth limits depend on it (frictionless,
/// the layered rung holds to δ/h = 0.3; with μ ≥ 0.5 to 0.1).
const FRICTION: f64 = 0.0;

/// A 2 mm sphere pressed 0.09 mm deeper each frame into a 2 mm gel, frames 0…10.
fn deep_press(solver: &str, policy: &str) -> Scene {
    let text = format!(
        r#"
solver = "{solver}"
validity = "{policy}"
[sensor]
preset = "digit"
width_px = 96
height_px = 64
mm_per_px = 0.1
fps = 10.0
[gel]
thickness_mm = 2.0
friction = {FRICTION}
[indenter]
shape = "sphere"
radius_mm = 2.0
[[trajectory]]
time_s = 0.0
position_mm = [0.0, 0.0, 0.0]
[[trajectory]]
time_s = 1.0
position_mm = [0.0, 0.0, -0.9]
"#
    );
    Scene::parse(Path::new("deep.toml"), text).unwrap()
}

/// Under `warn`, every frame whose rigid penetration over the gel thickness passes the layered
/// rung's depth limit is flagged with that limit, and no other frame is.
#[test]
fn warn_records_the_depth_limit_frame_by_frame() {
    let limits = RungLimits::of(SolverTable::builtin(), SolverKind::Layered, 0.02, FRICTION);
    assert!(
        limits.max_depth_over_h > 0.1 && limits.max_depth_over_h < 0.45,
        "{limits:?}"
    );
    let mut sim = Simulator::new(deep_press("layered", "warn")).unwrap();
    let mut flagged = 0;
    while let Some(frame) = sim.next_frame() {
        let frame = frame.unwrap();
        // The tip sits between four cell centres 0.05 mm off: the grid's deepest penetration.
        let depth_mm = 0.09 * frame.target.index as f64 - 0.05f64.hypot(0.05).powi(2) / 4.0;
        let depth_over_h = depth_mm / 2.0;
        assert_eq!(frame.solver, SolverKind::Layered);
        if depth_over_h > limits.max_depth_over_h {
            flagged += 1;
            match frame.validity {
                Validity::Outside { value, bound, .. } => {
                    assert_eq!(frame.validity.name(), "depth_over_h");
                    assert!(
                        (value - depth_over_h).abs() < 1e-6,
                        "{value} vs {depth_over_h}"
                    );
                    assert_eq!(bound, limits.max_depth_over_h);
                }
                Validity::Ok => panic!("frame {} at δ/h {depth_over_h}", frame.target.index),
            }
        } else {
            assert!(
                frame.validity.is_ok(),
                "frame {}: {}",
                frame.target.index,
                frame.validity
            );
        }
    }
    assert!(flagged >= 3, "{flagged} frames flagged");
}

/// Under `error`, the first frame past the depth limit stops the run, naming the frame.
#[test]
fn error_stops_at_the_first_frame_past_the_limit() {
    let limits = RungLimits::of(SolverTable::builtin(), SolverKind::Layered, 0.02, FRICTION);
    let first = (0..=10)
        .find(|&k| (0.09 * k as f64 - 0.0005) / 2.0 > limits.max_depth_over_h)
        .unwrap();
    let mut sim = Simulator::new(deep_press("layered", "error")).unwrap();
    for k in 0..first {
        assert!(sim.next_frame().unwrap().unwrap().validity.is_ok(), "{k}");
    }
    let err = sim.next_frame().unwrap().unwrap_err();
    assert!(
        matches!(err, SimError::OutsideValidity { frame, .. } if frame == first),
        "{err}"
    );
    let line = err.to_string();
    assert!(
        line.contains(&format!("frame {first}:"))
            && line.contains("layered")
            && line.contains("indentation depth")
            && !line.contains('\n'),
        "{line}"
    );
}

/// The geometric rung makes no force claim: every frame in contact is outside its validity.
#[test]
fn the_geometric_rung_is_never_within_a_force_tolerance() {
    let mut sim = Simulator::new(deep_press("geometric", "warn")).unwrap();
    while let Some(frame) = sim.next_frame() {
        let frame = frame.unwrap();
        let touching = frame.fields.contact.contains(&true);
        assert_eq!(
            frame.validity.name(),
            if touching { "rung" } else { "ok" },
            "frame {}",
            frame.target.index
        );
    }
}

/// A 6 mm sphere pressed 0.1 mm into a 73 mm gel while sliding: `auto` estimates the contact radius low (2/π
/// of the footprint; Hertz gives 1/√2), so it takes the half-space rung, whose a/h limit the
/// deepest frame then passes. Under `escalate` that frame is solved on the layered rung with
/// the layered rung's own history, so it equals the same frame of the scene run on the layered
/// rung throughout, bit for bit.
#[test]
fn escalate_climbs_to_the_next_rung_with_its_history() {
    let text = |solver: &str, extra: &str| {
        format!(
            r#"
solver = "{solver}"
{extra}
[sensor]
preset = "digit"
width_px = 96
height_px = 64
mm_per_px = 0.03
fps = 10.0
[gel]
thickness_mm = 73.0
[indenter]
shape = "sphere"
radius_mm = 6.0
[[trajectory]]
time_s = 0.0
position_mm = [0.0, 0.0, 0.0]
[[trajectory]]
time_s = 0.6
position_mm = [0.36, 0.0, -0.12]
"#
        )
    };
    let auto = Scene::parse(
        Path::new("thick.toml"),
        text("auto", "validity = \"escalate\""),
    )
    .unwrap();
    let choice = auto.auto.unwrap();
    assert_eq!(choice.solver, SolverKind::Halfspace, "{choice:?}");
    let stride = choice.mechanics_stride;
    let layered = Scene::parse(
        Path::new("thick.toml"),
        text("layered", &format!("mechanics_stride = {stride}")),
    )
    .unwrap();
    let run = |scene| {
        let mut sim = Simulator::new(scene).unwrap();
        std::iter::from_fn(move || sim.next_frame())
            .map(Result::unwrap)
            .collect::<Vec<_>>()
    };
    let (escalated, reference) = (run(auto), run(layered));
    let first_up = escalated
        .iter()
        .position(|f| f.solver == SolverKind::Layered)
        .expect("a frame escalates");
    assert!(first_up > 0);
    for (k, frame) in escalated.iter().enumerate() {
        assert!(frame.validity.is_ok(), "frame {k}: {}", frame.validity);
        if k < first_up {
            assert_eq!(frame.solver, SolverKind::Halfspace);
        } else {
            assert_eq!(frame.solver, SolverKind::Layered, "frame {k} stays up");
            assert_eq!(frame.fields, reference[k].fields, "frame {k}");
        }
    }
}
