//! Time per frame on a DIGIT-sized grid (320 × 240 cells of 0.0532 mm): a sphere of 6 mm
//! diameter pressed 0.3 mm into the gel in 30 frames, then slid 0.6 mm along +x in 90 frames
//! (stick, partial slip, gross sliding). Run with RAYON_NUM_THREADS=1 or 2.
//!
//! `cargo run --release --example bench -- [halfspace|layered] [normal|slip]`, or
//! `cargo run --release --example bench -- scene <scene.toml>` to time a scene's contact solves.
use std::time::Instant;

use glam::DVec3;
use sparsh_contact::{ContactInput, ContactSolver, Fem, NormalControl, rigid_shift_mm, solver_for};
use sparsh_scene::{GapField, Gel, Grid, Indenter, IndenterSpec, Pose, ShapeKind, SolverKind};

fn main() {
    let args: Vec<String> = std::env::args().collect();
    if args.get(1).map(String::as_str) == Some("scene") {
        let scene = sparsh_scene::Scene::load(std::path::Path::new(&args[2])).expect("scene");
        let grid = scene.grid();
        let mut fem = (scene.solver == SolverKind::Fem).then(|| Fem::new(scene.gel, grid));
        let mut other = solver_for(scene.solver, &scene.gel, grid);
        let (mut total, mut worst, mut previous) = (0.0f64, 0.0f64, None::<Pose>);
        let frames = scene.frames();
        for f in &frames {
            let gap = GapField::cast(&scene.indenter, &f.pose, grid);
            let shift = match &previous {
                Some(p) => rigid_shift_mm(p, &f.pose, &gap),
                None => vec![[0.0; 2]; grid.len()],
            };
            let normal = f
                .normal_force_n
                .map_or(NormalControl::Approach, NormalControl::Force);
            let start = Instant::now();
            let input = ContactInput {
                gap: &gap,
                normal,
                rigid_shift_mm: &shift,
            };
            let fields = match fem.as_mut() {
                Some(f) => f.solve(&input),
                None => other.solve(&input),
            }
            .expect("solve");
            let t = start.elapsed().as_secs_f64();
            if let Some(f) = &fem {
                eprintln!(
                    "{:.3} s  F = {:.4} N  {:?}  {:?}",
                    t,
                    fields.force_n[2],
                    fields.slip_state(),
                    f.stats()
                );
            }
            total += t;
            worst = worst.max(t);
            previous = Some(f.pose);
        }
        println!(
            "{}: {:?} {:.1} ms/frame mean, {:.1} ms worst, {} frames (threads {})",
            args[2],
            scene.solver,
            1e3 * total / frames.len() as f64,
            1e3 * worst,
            frames.len(),
            rayon::current_num_threads()
        );
        return;
    }
    let kind = match args.get(1).map(String::as_str) {
        Some("layered") => SolverKind::Layered,
        _ => SolverKind::Halfspace,
    };
    let slide = args.get(2).map(String::as_str) != Some("normal");
    let grid = Grid {
        nx: 320,
        ny: 240,
        cell_mm: 0.0532,
    };
    let gel = Gel {
        youngs_modulus_kpa: 300.0,
        poisson_ratio: 0.48,
        thickness_mm: 3.0,
        friction: 1.0,
    };
    let spec = IndenterSpec {
        shape: ShapeKind::Sphere,
        radius_mm: Some(3.0),
        height_mm: None,
        half_angle_deg: None,
        size_mm: None,
        pattern: None,
        pitch_mm: None,
        depth_mm: None,
        crown_radius_mm: None,
        mesh: None,
        scale: None,
        units: None,
        anchor: None,
    };
    let indenter: Indenter = spec.build(std::path::Path::new(".")).expect("sphere");
    let mut solver = solver_for(kind, &gel, grid);
    let poses: Vec<Pose> = (0..120)
        .map(|k| {
            let depth = 0.3 * ((k + 1) as f64 / 30.0).min(1.0);
            let x = if slide && k >= 30 {
                0.6 * (k - 29) as f64 / 90.0
            } else {
                0.0
            };
            Pose {
                position_mm: DVec3::new(x, 0.0, -depth),
                rotation_deg: DVec3::ZERO,
            }
        })
        .collect();
    let mut total = 0.0;
    let mut previous: Option<Pose> = None;
    let mut states = std::collections::BTreeMap::new();
    for pose in &poses {
        let gap = GapField::cast(&indenter, pose, grid);
        let shift = match &previous {
            Some(p) => rigid_shift_mm(p, pose, &gap),
            None => vec![[0.0; 2]; grid.len()],
        };
        let start = Instant::now();
        let fields = solver
            .solve(&ContactInput {
                gap: &gap,
                normal: NormalControl::Approach,
                rigid_shift_mm: &shift,
            })
            .expect("solve");
        total += start.elapsed().as_secs_f64();
        *states.entry(fields.slip_state().name()).or_insert(0) += 1;
        previous = Some(*pose);
    }
    println!(
        "{:?} {}: {:.1} ms/frame over {} frames (threads {}), states {:?}",
        kind,
        if slide { "normal+tangential" } else { "normal" },
        1e3 * total / poses.len() as f64,
        poses.len(),
        rayon::current_num_threads(),
        states
    );
}
