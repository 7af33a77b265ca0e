//! relreward's maze generator against MuJoCo's PointMaze on the same actions: the recording
//! `tests/data/pointmaze_mujoco.npz` (made by `tests/data/make_pointmaze_fixture.py` with
//! gymnasium-robotics: D4RL's `open` maze, one sequence in free space, one pushing into a wall
//! past the velocity clip and sliding along it) is replayed through [`PointMass::step_with`].
//! [`Physics::MUJOCO`] must follow MuJoCo row for row (one row = one simulator step); the
//! default [`Physics::RELREWARD`] is checked to be what its documentation says it is: twice
//! the simulated time per row.

use std::path::Path;

use relreward_toolkit::maze::{LayoutName, Physics, PointMass};
use relreward_toolkit::npz::read_numbers;

struct Sequence {
    start: [f64; 2],
    actions: Vec<[f64; 2]>,
    /// Before the first action, then after each.
    positions: Vec<[f64; 2]>,
}

fn sequence(k: usize) -> Sequence {
    let path = Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/data/pointmaze_mujoco.npz");
    let read = |key: &str| -> Vec<[f64; 2]> {
        let (shape, v) = read_numbers(&path, &format!("{key}_{k}")).expect("readable").expect(key);
        assert_eq!(*shape.last().expect("shape"), 2, "{key}");
        v.chunks_exact(2).map(|c| [c[0], c[1]]).collect()
    };
    Sequence { start: read("start")[0], actions: read("actions"), positions: read("positions") }
}

/// Positions after each action (the start first) under `physics`.
fn replay(s: &Sequence, physics: &Physics) -> Vec<[f64; 2]> {
    let open = LayoutName::Open.layout();
    let mut p = PointMass::at_rest(s.start);
    let mut out = vec![p.pos];
    for &a in &s.actions {
        p.step_with(&open, a, physics);
        out.push(p.pos);
    }
    out
}

fn max_error(a: &[[f64; 2]], b: &[[f64; 2]]) -> (f64, usize) {
    assert_eq!(a.len(), b.len());
    a.iter()
        .zip(b)
        .enumerate()
        .map(|(t, (p, q))| ((p[0] - q[0]).abs().max((p[1] - q[1]).abs()), t))
        .fold((0.0, 0), |m, x| if x.0 > m.0 { x } else { m })
}

/// Mean distance moved per row.
fn motion_per_row(p: &[[f64; 2]]) -> f64 {
    p.windows(2).map(|w| ((w[1][0] - w[0][0]).powi(2) + (w[1][1] - w[0][1]).powi(2)).sqrt()).sum::<f64>()
        / (p.len() - 1) as f64
}

#[test]
fn matched_physics_follows_mujoco_row_for_row_in_free_space() {
    let s = sequence(0);
    let mujoco = replay(&s, &Physics::MUJOCO);
    // MuJoCo's state is float64 and our arithmetic is the same formula: only rounding differs.
    let (err, t) = max_error(&mujoco, &s.positions);
    assert!(err < 1e-5, "free space: max |error| {err} at row {t}");
    // The fixture does move: over half a cell in total (at 0.006 per row, 1000 times the bound).
    let travelled = motion_per_row(&s.positions) * s.actions.len() as f64;
    assert!(travelled > 0.5, "travelled {travelled}");
}

#[test]
fn matched_physics_follows_mujoco_into_a_wall_and_along_it() {
    let s = sequence(1);
    let mujoco = replay(&s, &Physics::MUJOCO);
    // The velocity clip (5 per second) is reached before the wall: without it the point would
    // arrive earlier. MuJoCo's soft contact sinks up to about 0.03 into the wall and springs
    // back where ours stops at the face; along the wall both slide without friction.
    let (err, t) = max_error(&mujoco, &s.positions);
    assert!(err < 0.035, "wall contact: max |error| {err} at row {t}");
    let last = (s.positions.last().expect("rows"), mujoco.last().expect("rows"));
    assert!((last.0[0] - 3.4).abs() < 0.01 && (last.1[0] - 3.4).abs() < 1e-6, "resting against the wall: {last:?}");
    assert!((last.0[1] - last.1[1]).abs() < 0.01, "sliding along it: {last:?}");
    // Before contact (the first 35 rows) the two agree as in free space.
    let (err, t) = max_error(&mujoco[..35], &s.positions[..35]);
    assert!(err < 1e-5, "before contact: max |error| {err} at row {t}");
}

#[test]
fn the_default_physics_takes_twice_the_time_per_row() {
    let s = sequence(0);
    let ours = replay(&s, &Physics::RELREWARD);
    let ratio = motion_per_row(&ours) / motion_per_row(&s.positions);
    // Two substeps of nearly the same dynamics: each row covers twice the time, so under the
    // same open-loop pushes the velocity grows twice as fast and the distance about four times
    // (under the closed-loop controller, which brakes into each waypoint, it is about 2.1: the
    // module docs).
    assert!((3.5..4.5).contains(&ratio), "default / MuJoCo motion per row: {ratio}");
    let (err, _) = max_error(&ours, &s.positions);
    assert!(err > 0.1, "the default is not MuJoCo's time scale: max |error| {err}");
}
