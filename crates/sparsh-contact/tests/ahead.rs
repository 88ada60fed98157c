//! Solving each frame's normal problem ahead, beside the last frame's tangential one
//! (`ContactSolver::solve_ahead`), against solving the frames one after the other: the same
//! computation on the same inputs, so the same bits, whatever the rung, the normal control and
//! whether the frame announced as next is the one that comes.

use sparsh_contact::{
    Bem, ContactError, ContactInput, ContactSolver, Fields, NextFrame, NormalControl,
};
use sparsh_scene::{GapField, Gel, Grid};

const GRID: Grid = Grid {
    nx: 81,
    ny: 81,
    cell_mm: 0.05,
};

const GEL: Gel = Gel {
    youngs_modulus_kpa: 300.0,
    poisson_ratio: 0.48,
    thickness_mm: 1.5,
    friction: 0.5,
};

/// A sphere of 3 mm radius centred at `x_mm` on the axis, pressed `depth_mm` (the gap field
/// alone: under load control its approach is found by the solver).
fn sphere(x_mm: f64, depth_mm: f64) -> GapField {
    let gap_mm = (0..GRID.len())
        .map(|k| {
            let (i, j) = (k % GRID.nx, k / GRID.nx);
            let r = f64::hypot(GRID.x_mm(i) - x_mm, GRID.y_mm(j));
            r * r / 6.0 - depth_mm
        })
        .collect();
    GapField { grid: GRID, gap_mm }
}

/// A press then a slide of 24 frames: the gap fields, their normal control and the rigid shift
/// since the frame before.
fn trajectory(load_control: bool) -> Vec<(GapField, NormalControl, [f64; 2])> {
    (0..24)
        .map(|k| {
            let press = (k as f64 / 8.0).min(1.0);
            let x_mm = 0.01 * (k as f64 - 8.0).max(0.0);
            let shift = if k > 8 { [0.01, 0.0] } else { [0.0, 0.0] };
            // The first frame does not touch: the path history starts at the second.
            let depth_mm = 0.04 * press - 0.005;
            let normal = if load_control && k > 0 {
                NormalControl::Force(0.02 * press)
            } else {
                NormalControl::Approach
            };
            (sphere(x_mm, depth_mm), normal, shift)
        })
        .collect()
}

fn solve(
    solver: &mut Bem,
    (gap, normal, shift): &(GapField, NormalControl, [f64; 2]),
    next: Option<&(GapField, NormalControl, [f64; 2])>,
) -> Result<Fields, ContactError> {
    let shift = vec![*shift; GRID.len()];
    let input = ContactInput {
        gap,
        normal: *normal,
        rigid_shift_mm: &shift,
    };
    let next = next.map(|(gap, normal, _)| NextFrame {
        gap,
        normal: *normal,
    });
    solver.solve_ahead(&input, next)
}

/// Every frame of `frames` one after the other, and solved ahead with `announce(k)` given as
/// the next frame of frame k.
fn both_ways<'a>(
    make: impl Fn() -> Bem,
    frames: &'a [(GapField, NormalControl, [f64; 2])],
    announce: impl Fn(usize) -> Option<&'a (GapField, NormalControl, [f64; 2])>,
) {
    let (mut plain, mut ahead) = (make(), make());
    let mut pressed = 0;
    for (k, frame) in frames.iter().enumerate() {
        let one = solve(&mut plain, frame, None).expect("one after the other");
        let two = solve(&mut ahead, frame, announce(k)).expect("solved ahead");
        assert!(one == two, "frame {k}: the fields differ");
        assert_eq!(
            plain.stats().normal_convolutions,
            ahead.stats().normal_convolutions,
            "frame {k}"
        );
        pressed += usize::from(one.contact.contains(&true));
    }
    assert!(pressed >= 20, "{pressed} frames in contact");
}

#[test]
fn solved_ahead_equals_one_after_the_other() {
    for load_control in [false, true] {
        let frames = trajectory(load_control);
        for make in [(|| Bem::halfspace(GEL, GRID)) as fn() -> Bem, || {
            Bem::layered(GEL, GRID)
        }] {
            both_ways(make, &frames, |k| frames.get(k + 1));
        }
    }
}

/// A frame announced but not the one that comes (a different gap, then a different control) is
/// solved afresh, with the same bits.
#[test]
fn a_frame_other_than_the_announced_one_is_solved_afresh() {
    let frames = trajectory(false);
    let wrong_gap: Vec<_> = frames
        .iter()
        .map(|(gap, normal, shift)| {
            // 0.1 µm shallower everywhere: a different contact, so using its solution for the
            // frame that comes would show.
            let mut gap = gap.clone();
            gap.gap_mm.iter_mut().for_each(|g| *g += 1e-4);
            (gap, *normal, *shift)
        })
        .collect();
    let wrong_control: Vec<_> = frames
        .iter()
        .map(|(gap, _, shift)| (gap.clone(), NormalControl::Force(0.01), *shift))
        .collect();
    let make = || Bem::halfspace(GEL, GRID);
    both_ways(make, &frames, |k| {
        (k % 2 == 0).then(|| &wrong_gap[(k + 1).min(frames.len() - 1)])
    });
    both_ways(make, &frames, |k| {
        (k % 3 == 0).then(|| &wrong_control[(k + 1).min(frames.len() - 1)])
    });
}

/// A frame that fails drops the normal problem solved from it: the frames after it come out as
/// they do one after the other, where the failed frame leaves the last good frame's history.
#[test]
fn a_failed_frame_drops_what_was_solved_from_it() {
    let mut frames = trajectory(false);
    // Frame 12 presses through the gel: refused on every rung.
    frames[12].0 = sphere(0.04, 2.0);
    let (mut plain, mut ahead) = (Bem::halfspace(GEL, GRID), Bem::halfspace(GEL, GRID));
    let mut failed = Vec::new();
    for (k, frame) in frames.iter().enumerate() {
        let one = solve(&mut plain, frame, None);
        let two = solve(&mut ahead, frame, frames.get(k + 1));
        match (one, two) {
            (Ok(one), Ok(two)) => assert!(one == two, "frame {k}: the fields differ"),
            (Err(a), Err(b)) => {
                assert_eq!(a.to_string(), b.to_string());
                failed.push(k);
            }
            (one, two) => panic!("frame {k}: {one:?} against {two:?}"),
        }
    }
    assert_eq!(failed, [12]);
}
