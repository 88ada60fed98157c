//! Time per frame on a DIGIT-sized grid (320 × 240 cells of 0.0532 mm): a sphere of 6 mm
//! diameter pressed 0.3 mm into the gel in 30 frames, then slid 0.6 mm along +x in 90 frames
//! (stick, partial slip, gross sliding). Run with RAYON_NUM_THREADS=1 or 2.
//!
//! `cargo run --release --example bench -- [halfspace|layered] [normal|slip]`, or
//! `cargo run --release --example bench -- scene <scene.toml> [stride] [halfspace|layered]
//! [compare]` to time a scene's contact solves on its mechanics grid (stride and rung overriding
//! the scene's), with `compare` also by FISTA and from a cold start, as ratios.
//!
//! `cargo run --release --example bench -- fem [frames]`: the finite-element rung's deep press, a
//! sphere of 6 mm radius pressed 1 mm into a 3 mm DIGIT gel (E = 300 kPa, ν = 0.48, μ = 1) in
//! `frames` equal steps (default 20), fields on the 320 × 240 grid: seconds and Newton iterations
//! per frame with and without warm start, against the layered rung on the same frames, and on
//! stderr where the time went (factorisations, preconditioned CG iterations, multiplier updates,
//! the share of assembly, factorisation, solves and line searches), and warm with each solve
//! starting from the last one's friction bounds, with the kept factor tried however many
//! surface nodes changed state, or with the consistent slip tangent alone (no secant step after
//! a shortened one), as baselines; `fem [frames] warm`:
//! warm start only; `fem [frames] default`: the default rung alone beside the layered one;
//! `fem [frames] [warm|default|both] [friction]`: the same press at another friction
//! coefficient (μ = 0: the frictionless press the layered rung's coupling is measured against).
//!
//! `cargo run --release --example bench -- fem-slide [friction] [depth/thickness]
//! [elements per radius] [Anderson|plain] [frames] [update cap]`: the study's press-and-slide
//! reference (a 5 mm sphere pressed into a 2 mm incompressible layer, then slid half its
//! footprint radius in `frames` frames, on cells of 0.05 mm; defaults μ = 1.5, δ/h = 0.05, 12
//! elements per radius, 5 frames, the rung's cap on multiplier updates), with the multiplier
//! updates mixed by Anderson acceleration and plain (or only the one named): seconds,
//! multiplier updates and Newton iterations per frame, and the forces.
use std::alloc::{GlobalAlloc, Layout, System};
use std::sync::atomic::{AtomicUsize, Ordering};
use std::time::Instant;

use glam::DVec3;
use sparsh_contact::{
    Bem, BemOptions, BemStats, ContactInput, ContactSolver, Fem, FemOptions, FemStats, NextFrame,
    NormalControl, TangentialMethod, rigid_shift_mm, solver_for,
};
use sparsh_scene::{GapField, Gel, Grid, Indenter, Pose, SolverKind};

/// A DIGIT-sized grid: 320 × 240 cells of 0.0532 mm.
const DIGIT_GRID: Grid = Grid {
    nx: 320,
    ny: 240,
    cell_mm: 0.0532,
};

/// The benchmarks' gel: E = 300 kPa, ν = 0.48, 3 mm thick, μ = 1.
const DIGIT_GEL: Gel = Gel {
    youngs_modulus_kpa: 300.0,
    poisson_ratio: 0.48,
    thickness_mm: 3.0,
    friction: 1.0,
};

fn main() {
    let args: Vec<String> = std::env::args().collect();
    if args.get(1).map(String::as_str) == Some("scene") {
        let mut scene = sparsh_scene::Scene::load(std::path::Path::new(&args[2])).expect("scene");
        if let Some(stride) = args.get(3) {
            scene.mechanics_stride = stride.parse().expect("stride");
        }
        let kind = match args.get(4).map(String::as_str) {
            Some("halfspace") => SolverKind::Halfspace,
            Some("layered") => SolverKind::Layered,
            _ => scene.solver,
        };
        let newton = time_scene(
            &scene,
            kind,
            BemOptions::default(),
            "semi-smooth Newton, warm",
            false,
        );
        let ahead = time_scene(
            &scene,
            kind,
            BemOptions::default(),
            "each normal problem solved beside the last frame's tangential one",
            true,
        );
        println!(
            "  solved ahead / one after the other: {:.2}× the time",
            ahead.total_s / newton.total_s
        );
        if args.get(5).map(String::as_str) == Some("compare") {
            for (label, options) in [
                (
                    "FISTA, warm",
                    BemOptions {
                        tangential_method: TangentialMethod::Fista,
                        ..BemOptions::default()
                    },
                ),
                (
                    "semi-smooth Newton, cold",
                    BemOptions {
                        warm_start: false,
                        ..BemOptions::default()
                    },
                ),
            ] {
                let other = time_scene(&scene, kind, options, label, false);
                println!(
                    "  {label} / semi-smooth Newton, warm: {:.2}× the time, {:.2}× the tangential time, {:.2}× the tangential convolutions",
                    other.total_s / newton.total_s,
                    other.tangential_s / newton.tangential_s,
                    other.tangential_convolutions as f64 / newton.tangential_convolutions as f64
                );
            }
        }
        return;
    }
    if args.get(1).map(String::as_str) == Some("fem") {
        let frames = args.get(2).map_or(20, |f| f.parse().expect("frames"));
        let friction = args
            .get(4)
            .map_or(DIGIT_GEL.friction, |f| f.parse().expect("friction"));
        let variants = match args.get(3).map(String::as_str) {
            Some("warm") => FemVariants::Warm,
            Some("default") => FemVariants::Default,
            _ => FemVariants::All,
        };
        deep_press(frames, variants, friction);
        return;
    }
    if args.get(1).map(String::as_str) == Some("fem-slide") {
        let number =
            |k: usize, default: f64| args.get(k).map_or(default, |v| v.parse().expect("number"));
        let only = args.get(5).map(String::as_str);
        let frames = number(6, 5.0) as usize;
        let max_updates = number(7, FemOptions::default().max_updates as f64) as usize;
        press_and_slide(
            number(2, 1.5),
            number(3, 0.05),
            number(4, 12.0),
            only,
            [frames, max_updates],
        );
        return;
    }
    let kind = match args.get(1).map(String::as_str) {
        Some("layered") => SolverKind::Layered,
        _ => SolverKind::Halfspace,
    };
    let slide = args.get(2).map(String::as_str) != Some("normal");
    let (grid, gel) = (DIGIT_GRID, DIGIT_GEL);
    let indenter = Indenter::Sphere { radius_mm: 3.0 };
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

/// Times the contact solves of a scene's frames on its mechanics grid (the simulator's grid: the
/// image at `mechanics_stride` pixels per cell plus the margin) and prints the boundary-element
/// rung's breakdown per frame; returns the sums over the frames.
fn time_scene(
    scene: &sparsh_scene::Scene,
    kind: SolverKind,
    options: BemOptions,
    label: &str,
    ahead: bool,
) -> BemStats {
    let grid = scene.mechanics_grid();
    let mut solver = match kind {
        SolverKind::Halfspace => Bem::halfspace(scene.gel, grid),
        SolverKind::Layered => Bem::layered(scene.gel, grid),
        other => panic!("the scene benchmark times the boundary-element rungs, not {other:?}"),
    }
    .with_options(options);
    let (mut worst_s, mut previous) = (0.0f64, None::<Pose>);
    let mut sum = BemStats::default();
    let frames = scene.frames();
    let cast = |f: &sparsh_scene::FrameTarget| GapField::cast(&scene.indenter, &f.pose, grid);
    let control = |f: &sparsh_scene::FrameTarget| {
        f.normal_force_n
            .map_or(NormalControl::Approach, NormalControl::Force)
    };
    let allocations_before = ALLOCATIONS.load(Ordering::Relaxed);
    let mut next_gap = frames.first().map(cast);
    for (k, f) in frames.iter().enumerate() {
        let gap = next_gap.take().expect("this frame's gap");
        next_gap = frames.get(k + 1).map(cast);
        let next = frames.get(k + 1).filter(|_| ahead).map(|f| NextFrame {
            gap: next_gap.as_ref().expect("the next frame's gap"),
            normal: control(f),
        });
        let shift = match &previous {
            Some(p) => rigid_shift_mm(p, &f.pose, &gap),
            None => vec![[0.0; 2]; grid.len()],
        };
        let input = ContactInput {
            gap: &gap,
            normal: control(f),
            rigid_shift_mm: &shift,
        };
        let start = Instant::now();
        solver.solve_ahead(&input, next).expect("solve");
        let t = start.elapsed().as_secs_f64();
        worst_s = worst_s.max(t);
        let s = solver.stats();
        sum.normal_convolutions += s.normal_convolutions;
        sum.normal_windows += s.normal_windows;
        sum.tangential_convolutions += s.tangential_convolutions;
        sum.normal_s += s.normal_s;
        sum.tangential_s += s.tangential_s;
        sum.kernel_s += s.kernel_s;
        sum.total_s += t;
        previous = Some(f.pose);
    }
    let n = frames.len() as f64;
    // Allocations per frame, casting the gap field and the rigid shifts included (3 per frame).
    let allocations = (ALLOCATIONS.load(Ordering::Relaxed) - allocations_before) as f64 / n;
    println!(
        "{kind:?}, {label}, {}×{} cells of {:.4} mm: {:.1} ms/frame mean, {:.1} ms worst, {} frames (threads {}), {allocations:.0} allocations/frame",
        grid.nx,
        grid.ny,
        grid.cell_mm,
        1e3 * sum.total_s / n,
        1e3 * worst_s,
        frames.len(),
        rayon::current_num_threads()
    );
    // Solved ahead, a frame's normal problem runs inside the previous call: no split of the
    // call's time.
    if ahead {
        return sum;
    }
    println!(
        "  per frame: normal {:.1} ms ({:.1} convolutions, {:.2} windows), tangential {:.1} ms ({:.1} convolutions), rest {:.1} ms; kernel spectra of new window sizes {:.1} ms",
        1e3 * sum.normal_s / n,
        sum.normal_convolutions as f64 / n,
        sum.normal_windows as f64 / n,
        1e3 * sum.tangential_s / n,
        sum.tangential_convolutions as f64 / n,
        1e3 * (sum.total_s - sum.normal_s - sum.tangential_s) / n,
        1e3 * sum.kernel_s / n,
    );
    sum
}

/// Counts heap allocations, to show what a frame allocates.
struct CountingAllocator;

static ALLOCATIONS: AtomicUsize = AtomicUsize::new(0);

// SAFETY: forwards every call to the system allocator unchanged.
unsafe impl GlobalAlloc for CountingAllocator {
    unsafe fn alloc(&self, layout: Layout) -> *mut u8 {
        ALLOCATIONS.fetch_add(1, Ordering::Relaxed);
        // SAFETY: the caller's contract is the system allocator's.
        unsafe { System.alloc(layout) }
    }
    unsafe fn dealloc(&self, ptr: *mut u8, layout: Layout) {
        // SAFETY: as above.
        unsafe { System.dealloc(ptr, layout) }
    }
    unsafe fn realloc(&self, ptr: *mut u8, layout: Layout, new_size: usize) -> *mut u8 {
        ALLOCATIONS.fetch_add(1, Ordering::Relaxed);
        // SAFETY: as above.
        unsafe { System.realloc(ptr, layout, new_size) }
    }
}

#[global_allocator]
static GLOBAL: CountingAllocator = CountingAllocator;

/// Which finite-element variants the deep press runs.
#[derive(Clone, Copy, PartialEq)]
enum FemVariants {
    /// The default rung alone.
    Default,
    /// Every warm-started variant.
    Warm,
    /// Every variant, from rest too.
    All,
}

/// The deep-press benchmark of the finite-element rung (see the module comment).
fn deep_press(frames: usize, variants: FemVariants, friction: f64) {
    let grid = DIGIT_GRID;
    let gel = Gel {
        friction,
        ..DIGIT_GEL
    };
    let indenter = Indenter::Sphere { radius_mm: 6.0 };
    let gaps: Vec<GapField> = (1..=frames)
        .map(|k| {
            let pose = Pose {
                position_mm: DVec3::new(0.0, 0.0, -(k as f64) / frames as f64),
                rotation_deg: DVec3::ZERO,
            };
            GapField::cast(&indenter, &pose, grid)
        })
        .collect();
    let still = vec![[0.0; 2]; grid.len()];
    // (label, seconds per frame, worst, Newton iterations per frame, final force)
    let mut rows = Vec::new();
    let mut works = Vec::new();
    let mut layered = sparsh_contact::Bem::layered(gel, grid);
    let (mean, worst, _, force) = time_frames(&gaps, |gap| {
        (
            layered.solve(&pressed(gap, &still)).expect("layered solve"),
            0,
        )
    });
    rows.push((
        "layered (boundary elements)".to_string(),
        mean,
        worst,
        0.0,
        force,
    ));
    let fem_variants = [
        ("fem, warm start", FemOptions::default()),
        (
            "fem, warm start, each solve from the last one's friction bounds",
            FemOptions {
                predict_bounds: false,
                ..FemOptions::default()
            },
        ),
        (
            "fem, warm start, always trying the kept factor first",
            FemOptions {
                max_changed_nodes: usize::MAX,
                ..FemOptions::default()
            },
        ),
        (
            "fem, warm start, consistent slip tangent only",
            FemOptions {
                slip_secant: false,
                ..FemOptions::default()
            },
        ),
        (
            "fem, from rest each frame",
            FemOptions {
                warm_start: false,
                ..FemOptions::default()
            },
        ),
    ];
    for (label, options) in fem_variants {
        let skip = match variants {
            FemVariants::Default => options != FemOptions::default(),
            FemVariants::Warm => !options.warm_start,
            FemVariants::All => false,
        };
        if skip {
            continue;
        }
        let mut fem = Fem::new(gel, grid).with_options(options);
        let (mut work, mut largest) = (FemStats::default(), [0usize; 2]);
        let (mean, worst, its, force) = time_frames(&gaps, |gap| {
            let fields = fem.solve(&pressed(gap, &still)).expect("fem solve");
            let stats = fem.stats();
            work.accumulate(&stats);
            largest = [
                largest[0].max(stats.dofs),
                largest[1].max(stats.factor_nonzeros),
            ];
            (fields, stats.newton_iterations)
        });
        rows.push((label.to_string(), mean, worst, its, force));
        works.push((label, work, largest));
    }
    let base = rows[0].1;
    let per_frame = |x: usize| x as f64 / frames as f64;
    for (label, w, [dofs, nonzeros]) in &works {
        let total = w.assemble_s + w.factor_s + w.solve_s + w.line_search_s;
        eprintln!(
            "{label}: per frame {:.1} factorisations, {:.1} preconditioned CG iterations, {:.1} multiplier updates; \
             at most {} unknowns, {} nonzeros in the factor; time in assembly {:.0} %, factorisation {:.0} %, \
             solves {:.0} %, line searches {:.0} %",
            per_frame(w.factorizations),
            per_frame(w.pcg_iterations),
            per_frame(w.updates),
            dofs,
            nonzeros,
            100.0 * w.assemble_s / total,
            100.0 * w.factor_s / total,
            100.0 * w.solve_s / total,
            100.0 * w.line_search_s / total,
        );
    }
    println!(
        "deep press: R = 6 mm sphere, 1 mm into a 3 mm gel in {frames} frames, μ = {friction}, 320 × 240 grid, {} threads",
        rayon::current_num_threads()
    );
    println!(
        "| solver | s/frame (mean) | s/frame (worst) | Newton iterations/frame | × layered | force at 1 mm (N) |"
    );
    println!("|---|---|---|---|---|---|");
    for (label, mean, worst, its, force) in rows {
        let its = if its > 0.0 {
            format!("{its:.1}")
        } else {
            "–".into()
        };
        println!(
            "| {label} | {mean:.3} | {worst:.3} | {its} | {:.0} | {force:.3} |",
            mean / base
        );
    }
}

/// Solves every frame in order: mean and worst seconds per frame, mean iterations per frame (as
/// `solve` reports them) and the last frame's normal force.
fn time_frames(
    gaps: &[GapField],
    mut solve: impl FnMut(&GapField) -> (sparsh_contact::Fields, usize),
) -> (f64, f64, f64, f64) {
    let (mut total, mut worst, mut iterations, mut force) = (0.0f64, 0.0f64, 0usize, 0.0);
    for gap in gaps {
        let start = Instant::now();
        let (fields, its) = solve(gap);
        let t = start.elapsed().as_secs_f64();
        total += t;
        worst = worst.max(t);
        iterations += its;
        force = fields.force_n[2];
    }
    let n = gaps.len() as f64;
    (total / n, worst, iterations as f64 / n, force)
}

/// Displacement control, the indenter not moving sideways.
/// The study's press-and-slide reference with and without Anderson mixing of the multiplier
/// updates (see the module comment).
fn press_and_slide(
    friction: f64,
    depth_over_h: f64,
    elements_per_radius: f64,
    only: Option<&str>,
    [slide_frames, max_updates]: [usize; 2],
) {
    let (radius, h, cell) = (5.0, 2.0, 0.05);
    let depth = depth_over_h * h;
    let footprint = (2.0 * radius * depth - depth * depth).sqrt();
    let slide = 0.5 * footprint;
    let box_mm = 3.2 * footprint + 1.0 + 2.0 * slide;
    let n = ((box_mm / cell).round() as usize / 2 * 2 + 1).max(9);
    let grid = Grid {
        nx: n,
        ny: n,
        cell_mm: cell,
    };
    let gel = Gel {
        youngs_modulus_kpa: 300.0,
        poisson_ratio: 0.5,
        thickness_mm: h,
        friction,
    };
    let indenter = Indenter::Sphere { radius_mm: radius };
    let poses: Vec<Pose> = (0..=slide_frames)
        .map(|k| Pose {
            position_mm: DVec3::new(slide * k as f64 / slide_frames as f64, 0.0, -depth),
            rotation_deg: DVec3::ZERO,
        })
        .collect();
    println!(
        "press and slide: R = 5 mm sphere {depth} mm into a 2 mm layer (ν = 0.5, μ = {friction}), \
         slid {slide:.3} mm in {slide_frames} frames, {n} × {n} cells of {cell} mm, {elements_per_radius} elements per radius"
    );
    println!("| multiplier update | frame | s | updates | Newton iterations | F_x (N) | F_z (N) |");
    println!("|---|---|---|---|---|---|---|");
    let mut totals = Vec::new();
    for (label, depth) in [("Anderson, 5", 5), ("plain", 0)] {
        if only.is_some_and(|o| !label.starts_with(o)) {
            continue;
        }
        let mut fem = Fem::new(gel, grid).with_options(FemOptions {
            elements_per_radius,
            anderson_depth: depth,
            max_updates,
            ..FemOptions::default()
        });
        let mut previous: Option<Pose> = None;
        let mut total = 0.0;
        for (frame, pose) in poses.iter().enumerate() {
            let gap = GapField::cast(&indenter, pose, grid);
            let shift = match &previous {
                Some(p) => rigid_shift_mm(p, pose, &gap),
                None => vec![[0.0; 2]; grid.len()],
            };
            previous = Some(*pose);
            let clock = Instant::now();
            let solved = fem.solve(&pressed(&gap, &shift));
            let seconds = clock.elapsed().as_secs_f64();
            total += seconds;
            let stats = fem.stats();
            let forces = match solved {
                Ok(f) => format!("{:.4} | {:.4}", f.force_n[0], f.force_n[2]),
                Err(e) => format!("{e} | –"),
            };
            println!(
                "| {label} | {frame} | {seconds:.1} | {} | {} | {forces} |",
                stats.updates, stats.newton_iterations
            );
        }
        totals.push((label, total));
    }
    if let [(a, ta), (b, tb)] = totals[..] {
        println!(
            "total: {a} {ta:.1} s, {b} {tb:.1} s ({:.2}× the time)",
            ta / tb
        );
    }
}

fn pressed<'a>(gap: &'a GapField, still: &'a [[f64; 2]]) -> ContactInput<'a> {
    ContactInput {
        gap,
        normal: NormalControl::Approach,
        rigid_shift_mm: still,
    }
}
