//! Each rung's validity limits (`sparsh_scene::validity`, read from the compiled-in solver
//! table) against the study's stability map and against the analytic layer effect.

use sparsh_contact::reference::bonded_layer_force_factor;
use sparsh_scene::auto::SolverTable;
use sparsh_scene::{RungLimits, SolverKind};

/// The half-space rung ignores the gel's bottom, so on an incompressible bonded layer it misses
/// the force by 1 − F_Hertz/F_layer (Garcia & Garcia 2018 up to a/h = 0.5; the exact layer
/// solution at 1). Its a/h limit at each tolerance must be the last studied a/h that this
/// analytic error allows, within the finest grid's own error (0.5 %).
#[test]
fn the_half_space_limit_is_the_layer_effect() {
    let table = SolverTable::builtin();
    let mut studied: Vec<f64> = table
        .rows
        .iter()
        .filter(|r| r.rung == SolverKind::Halfspace && r.depth_over_h == 0.0)
        .map(|r| r.a_over_h)
        .collect();
    studied.sort_by(f64::total_cmp);
    studied.dedup();
    let layer_error = |a_over_h: f64| 1.0 - 1.0 / bonded_layer_force_factor(a_over_h).unwrap();
    let grid_error = 0.005;
    for tolerance in [0.01, 0.02, 0.05, 0.1, 0.3] {
        let limits = RungLimits::of(table, SolverKind::Halfspace, tolerance, 0.0);
        let limit = limits
            .max_a_over_h
            .expect("meets loose tolerances somewhere");
        assert!(
            layer_error(limit) <= tolerance + grid_error,
            "tolerance {tolerance}: a/h {limit} misses by {}",
            layer_error(limit)
        );
        if let Some(&next) = studied.iter().find(|&&a| a > limit) {
            assert!(
                layer_error(next) > tolerance - grid_error,
                "tolerance {tolerance}: a/h {next} meets it ({}) yet is past the limit {limit}",
                layer_error(next)
            );
        }
    }
}

/// Each rung's depth limit at the study's pass mark (2 %) and each swept friction is the deepest
/// swept δ/h up to which the stability map passes every swept depth at that friction and every
/// smaller one (the sweep's shallowest depth stands for the small-strain regime, so a rung's limit
/// is never shallower than it) — a sliding contact's over the press-and-slide points too — and
/// the geometric rung has no a/h range at all.
#[test]
fn depth_limits_match_the_stability_map() {
    let path = concat!(
        env!("CARGO_MANIFEST_DIR"),
        "/../../assets/readme/study/stability.csv"
    );
    let mut reader = csv::Reader::from_path(path).unwrap();
    let headers = reader.headers().unwrap().clone();
    let column = |name: &str| headers.iter().position(|h| h == name).unwrap();
    let (sweep, value, friction, rung, outcome) = (
        column("sweep"),
        column("value"),
        column("friction"),
        column("rung"),
        column("outcome"),
    );
    // (rung, friction, depth, passed, slide)
    let mut map: Vec<(SolverKind, f64, f64, bool, bool)> = Vec::new();
    for record in reader.records() {
        let record = record.unwrap();
        // presses bound every frame, presses-and-slides the sliding ones as well
        if !matches!(&record[sweep], "depth_over_thickness" | "press_slide") {
            continue;
        }
        let depth: f64 = record[value]
            .trim_start_matches("δ/h ")
            .split(',')
            .next()
            .unwrap()
            .parse()
            .unwrap();
        map.push((
            record[rung].parse().unwrap(),
            record[friction].parse().unwrap(),
            depth,
            &record[outcome] == "ok",
            &record[sweep] == "press_slide",
        ));
    }
    let mut frictions: Vec<f64> = map.iter().map(|m| m.1).collect();
    frictions.sort_by(f64::total_cmp);
    frictions.dedup();
    assert!(frictions.len() >= 4, "swept frictions {frictions:?}");
    for kind in SolverKind::ALL {
        for &mu in &frictions {
            let mut depths: Vec<f64> = map.iter().filter(|m| m.0 == kind).map(|m| m.2).collect();
            depths.sort_by(f64::total_cmp);
            depths.dedup();
            assert!(depths.len() >= 6, "{kind:?}: {} swept depths", depths.len());
            let passed = |d: f64, sliding: bool| {
                map.iter()
                    .filter(|m| m.0 == kind && m.2 == d && m.1 <= mu && (sliding || !m.4))
                    .all(|m| m.3)
            };
            let from_map = |sliding: bool| {
                depths
                    .iter()
                    .copied()
                    .take_while(|&d| passed(d, sliding))
                    .last()
                    .unwrap_or(depths[0])
            };
            let limits = RungLimits::of(SolverTable::builtin(), kind, 0.02, mu);
            assert_eq!(
                limits.max_depth_over_h,
                from_map(false),
                "{kind:?} at μ {mu}"
            );
            assert_eq!(
                limits.max_sliding_depth_over_h,
                from_map(true),
                "{kind:?} sliding at μ {mu}"
            );
        }
    }
    let geometric = RungLimits::of(SolverTable::builtin(), SolverKind::Geometric, 0.02, 1.0);
    assert_eq!(geometric.max_a_over_h, None);
    assert_eq!(geometric.check(true, 0.1, 0.0, false).name(), "rung");
}
