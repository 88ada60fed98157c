//! The solver table behind `solver = "auto"`: parsing, safe-side lookup and the choice rule, on a
//! hand-written table.

use sparsh_scene::SolverKind;
use sparsh_scene::auto::{AutoChoice, SolverTable, choose, most_accurate};

const TABLE: &str =
    "rung,a_over_cell,a_over_h,depth_over_h,friction,slide_over_a,rel_error,ms_per_frame
halfspace,5,0.002,0,0,0,0.03,1
halfspace,10,0.002,0,0,0,0.01,4
halfspace,10,0.5,0,0,0,0.4,4
layered,5,0.002,0,0,0,0.03,2
layered,5,0.5,0,0,0,0.05,2
layered,10,0.002,0,0,0,0.01,8
layered,10,0.5,0,0,0,0.012,8
geometric,5,0.002,0,0,0,inf,0.1
layered,3,0.5,0.1,0,0,0.01,8
layered,3,0.8,0.3,0,0,0.015,8
layered,3,0.9,0.4,0,0,0.018,8
layered,3,0.5,0.1,1,0,0.012,8
layered,3,0.8,0.3,1,0,0.035,8
layered,3,0.9,0.4,1,0,0.001,8
fem,10,0.5,0,0,0,0.008,2000
fem,3,0.8,0.3,0,0,0.004,2000
fem,3,0.8,0.3,1,0,0.004,2000
layered,3,0.8,0.3,1,0.5,0.05,8
fem,3,0.8,0.3,1,0.5,0.005,2000
";

#[test]
fn table_parses_and_round_trips() {
    let table = SolverTable::parse(TABLE).unwrap();
    assert_eq!(table.rows.len(), 19);
    assert!(table.rows[7].rel_error.is_infinite());
    assert_eq!(SolverTable::parse(&table.to_csv()).unwrap(), table);
    for (bad, why) in [
        ("rung,a\n", "first row"),
        (
            "rung,a_over_cell,a_over_h,rel_error,ms_per_frame\nlayered,1,1,1,1\n",
            "first row",
        ),
        // the headers of tables written before the friction and the slide columns
        (
            "rung,a_over_cell,a_over_h,depth_over_h,rel_error,ms_per_frame\nlayered,1,1,0,1,1\n",
            "first row",
        ),
        (
            "rung,a_over_cell,a_over_h,depth_over_h,friction,rel_error,ms_per_frame\nlayered,1,1,0,0,1,1\n",
            "first row",
        ),
        (
            "rung,a_over_cell,a_over_h,depth_over_h,friction,slide_over_a,rel_error,ms_per_frame\nbogus,1,1,0,0,0,1,1\n",
            "unknown solver",
        ),
        (
            "rung,a_over_cell,a_over_h,depth_over_h,friction,slide_over_a,rel_error,ms_per_frame\nlayered,1,1,0,0,0,x,1\n",
            "not a number",
        ),
        (
            "rung,a_over_cell,a_over_h,depth_over_h,friction,slide_over_a,rel_error,ms_per_frame\nlayered,0,1,0,0,0,1,1\n",
            "must be > 0",
        ),
        (
            "rung,a_over_cell,a_over_h,depth_over_h,friction,slide_over_a,rel_error,ms_per_frame\nlayered,1,1,-1,0,0,1,1\n",
            "depth_over_h",
        ),
        (
            "rung,a_over_cell,a_over_h,depth_over_h,friction,slide_over_a,rel_error,ms_per_frame\nlayered,1,1,0.1,-1,0,1,1\n",
            "friction",
        ),
        (
            "rung,a_over_cell,a_over_h,depth_over_h,friction,slide_over_a,rel_error,ms_per_frame\nlayered,1,1\n",
            "8 fields",
        ),
        (
            "rung,a_over_cell,a_over_h,depth_over_h,friction,slide_over_a,rel_error,ms_per_frame\nlayered,1,1,0.1,1,-0.5,1,1\n",
            "slide_over_a",
        ),
        (
            "rung,a_over_cell,a_over_h,depth_over_h,friction,slide_over_a,rel_error,ms_per_frame\nlayered,1,1,0,1,0.5,1,1\n",
            "needs depth_over_h > 0",
        ),
    ] {
        let err = SolverTable::parse(bad).unwrap_err();
        assert!(err.contains(why), "{err}");
    }
    // The compiled-in table parses and covers every rung.
    let builtin = SolverTable::builtin();
    for rung in SolverKind::ALL {
        assert!(builtin.rows.iter().any(|r| r.rung == rung), "{rung:?}");
    }
}

#[test]
fn lookup_takes_the_hard_side() {
    let table = SolverTable::parse(TABLE).unwrap();
    // 7 cells per radius is bounded by the 5-cell row, a/h = 0.1 by the 0.5 layer.
    let row = table.predict(SolverKind::Layered, 7.0, 0.1).unwrap();
    assert_eq!((row.a_over_cell, row.a_over_h), (5.0, 0.5));
    let row = table.predict(SolverKind::Layered, 12.0, 0.1).unwrap();
    assert_eq!((row.a_over_cell, row.a_over_h), (10.0, 0.5));
    // Coarser than studied, or thinner than studied: no prediction.
    assert!(table.predict(SolverKind::Layered, 4.0, 0.001).is_none());
    assert!(table.predict(SolverKind::Layered, 12.0, 0.7).is_none());
}

fn choice(solver: SolverKind, stride: usize, error: f64, ms: f64) -> AutoChoice {
    AutoChoice {
        solver,
        mechanics_stride: stride,
        tolerance: 0.02,
        contact_radius_mm: 1.0,
        a_over_h: 0.1,
        depth_over_h: 0.01,
        sliding: false,
        predicted_rel_error: error,
        predicted_ms_per_frame: ms,
    }
}

#[test]
fn choice_is_the_cheapest_that_meets_the_tolerance() {
    let candidates = [
        choice(SolverKind::Halfspace, 4, 0.4, 1.0),
        choice(SolverKind::Layered, 4, 0.015, 2.0),
        choice(SolverKind::Layered, 2, 0.015, 2.0),
        choice(SolverKind::Layered, 1, 0.005, 8.0),
    ];
    let c = choose(&candidates).unwrap();
    assert_eq!((c.solver, c.mechanics_stride), (SolverKind::Layered, 4));
    assert!(c.meets_tolerance());
    let best = most_accurate(&candidates).unwrap();
    assert_eq!(best.mechanics_stride, 1);
    // Nothing meets 0.1 %: the most accurate is taken, and says so.
    let strict: Vec<AutoChoice> = candidates
        .iter()
        .map(|c| AutoChoice {
            tolerance: 0.001,
            ..*c
        })
        .collect();
    let c = choose(&strict).unwrap();
    assert_eq!(c.mechanics_stride, 1);
    assert!(!c.meets_tolerance());
    assert!(choose(&[]).is_none());
}

/// The shipped table and what the study writes are plain CSV: the `csv` crate's default reader
/// takes the header from the first line and every row has the header's eight fields.
#[test]
fn tables_read_with_default_csv_readers() {
    let written = SolverTable::parse(TABLE).unwrap().to_csv();
    for text in [sparsh_scene::auto::SOLVER_TABLE_CSV, written.as_str()] {
        let mut reader = csv::Reader::from_reader(text.as_bytes());
        let header: Vec<String> = reader.headers().unwrap().iter().map(String::from).collect();
        assert_eq!(
            header,
            [
                "rung",
                "a_over_cell",
                "a_over_h",
                "depth_over_h",
                "friction",
                "slide_over_a",
                "rel_error",
                "ms_per_frame"
            ]
        );
        let rows: Vec<csv::StringRecord> = reader.records().map(|r| r.unwrap()).collect();
        assert!(!rows.is_empty());
        for r in &rows {
            assert_eq!(r.len(), 8, "{r:?}");
            r[1].parse::<f64>().unwrap();
        }
    }
}

#[test]
fn a_deep_press_takes_the_finite_elements() {
    // The depth sweep's rows bound each rung's error by the depth over thickness and the
    // friction: frictionless, a layered rung holds 2 % to δ/h = 0.4; with μ = 1 it misses 2 % at
    // 0.3, where only the finite elements hold.
    let table = SolverTable::parse(TABLE).unwrap();
    let layered =
        |depth: f64, friction: f64| table.depth_error(SolverKind::Layered, depth, friction, false);
    let sliding =
        |depth: f64, friction: f64| table.depth_error(SolverKind::Layered, depth, friction, true);
    // Shallower than the sweep: the small-strain rows decide.
    assert_eq!(layered(0.05, 1.0), 0.0);
    assert_eq!(layered(0.1, 1.0), 0.0);
    assert_eq!(layered(0.15, 0.0), 0.015);
    assert_eq!(layered(0.35, 0.0), 0.018);
    assert_eq!(layered(0.15, 1.0), 0.035);
    // a rung that missed at 0.3 is not trusted again at 0.4, where it happens to land close
    assert_eq!(layered(0.35, 1.0), 0.035);
    // between swept frictions the larger one bounds it; past the largest, all of them
    assert_eq!(layered(0.15, 0.5), 0.035);
    assert_eq!(layered(0.15, 2.0), 0.035);
    assert!(layered(0.5, 0.0).is_infinite());
    // A sliding contact is held to the slides' rows as well, at their frictions only.
    assert_eq!(sliding(0.1, 1.0), 0.0);
    assert_eq!(sliding(0.15, 1.0), 0.05);
    assert_eq!(sliding(0.35, 1.0), 0.05);
    assert_eq!(sliding(0.15, 0.0), 0.015);
    assert_eq!(
        table.depth_error(SolverKind::Halfspace, 0.5, 1.0, true),
        0.0
    );
    assert_eq!(table.swept_frictions(), [0.0, 1.0]);
    let mut sensor = sparsh_scene::SensorConfig::preset("digit").unwrap();
    (sensor.width_px, sensor.height_px, sensor.mm_per_px) = (100, 100, 0.1);
    let choose_for = |depth_mm: f64, friction: f64, sliding: bool, tolerance: f64| {
        let gel = sparsh_scene::Gel {
            thickness_mm: 2.0,
            friction,
            ..sparsh_scene::Gel::default()
        };
        let all = sparsh_scene::auto::candidates(
            &table, &sensor, &gel, 1.0, depth_mm, sliding, tolerance,
        );
        choose(&all).unwrap()
    };
    let pick = |depth_mm: f64, friction: f64| choose_for(depth_mm, friction, false, 0.02);
    let shallow = pick(0.1, 1.0);
    assert_eq!(shallow.solver, SolverKind::Layered);
    let deep = pick(0.5, 1.0);
    assert_eq!(deep.solver, SolverKind::Fem, "{deep:?}");
    assert!(deep.meets_tolerance() && deep.depth_over_h == 0.25);
    // Frictionless, the same press stays on the layered rung.
    let slippery = pick(0.5, 0.0);
    assert_eq!(slippery.solver, SolverKind::Layered, "{slippery:?}");
    // At 4 % the press holds on the layered rung; the same depth sliding needs the elements.
    let press = choose_for(0.5, 1.0, false, 0.04);
    assert_eq!(press.solver, SolverKind::Layered, "{press:?}");
    let slide = choose_for(0.5, 1.0, true, 0.04);
    assert_eq!(slide.solver, SolverKind::Fem, "{slide:?}");
    assert!(slide.sliding && slide.meets_tolerance());
}

/// `auto` reads the slides' rows only for a trajectory that moves the indenter along the gel
/// while it is pressed in: a press, a press moved sideways only above the gel, and a press
/// that then slides (or turns).
#[test]
fn auto_knows_when_a_trajectory_slides() {
    let scene = |keyframes: &str| {
        let text = format!(
            "seed = 1\nsolver = \"auto\"\n[sensor]\npreset = \"digit\"\n[gel]\nthickness_mm = 3.0\n\
             friction = 1.0\n[indenter]\nshape = \"sphere\"\nradius_mm = 6.0\n{keyframes}"
        );
        let path = std::path::Path::new("slide.toml");
        let scene = sparsh_scene::Scene::parse(path, text).unwrap();
        scene.auto.unwrap().sliding
    };
    let keyframe = |t: f64, x: f64, z: f64, turn: f64| {
        format!(
            "[[trajectory]]\ntime_s = {t}\nposition_mm = [{x}, 0.0, {z}]\nrotation_deg = [0.0, 0.0, {turn}]\n"
        )
    };
    let press = keyframe(0.0, 0.0, 0.5, 0.0) + &keyframe(0.5, 0.0, -0.2, 0.0);
    assert!(!scene(&press));
    let over_then_press = keyframe(0.0, -1.0, 0.5, 0.0)
        + &keyframe(0.2, 0.0, 0.5, 0.0)
        + &keyframe(0.5, 0.0, -0.2, 0.0);
    assert!(!scene(&over_then_press));
    assert!(scene(&(press.clone() + &keyframe(1.0, 1.0, -0.2, 0.0))));
    assert!(scene(&(press + &keyframe(1.0, 0.0, -0.2, 10.0))));
}
