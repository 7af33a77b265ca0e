//! [`PointMass`]: the agent's dynamics and its collisions with the walls (conventions in the
//! [module documentation](super)).

use super::{CONTACT_GAP, DAMPING, DT, FORCE_GAIN, FRAME_SKIP, Layout, RADIUS};

/// The dynamics of a step (module docs, "Dynamics" and "Matched physics").
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Physics {
    /// Substeps of [`DT`] per step (per dataset row), the action held throughout.
    pub frame_skip: u32,
    /// Acceleration per unit of action.
    pub force_gain: f64,
    /// Linear velocity damping, per second.
    pub damping: f64,
    /// Damping integrated implicitly (`v = (v + DT * gain * a) / (1 + DT * damping)`, MuJoCo's
    /// Euler) rather than explicitly (`v += DT * (gain * a - damping * v)`).
    pub implicit_damping: bool,
    /// Each velocity component is clipped to `[-max_speed, max_speed]` before each step
    /// (infinite: no clip).
    pub max_speed: f64,
}

impl Physics {
    /// relreward's generator, the default: [`FRAME_SKIP`] substeps, [`FORCE_GAIN`], [`DAMPING`].
    pub const RELREWARD: Physics = Physics {
        frame_skip: FRAME_SKIP,
        force_gain: FORCE_GAIN,
        damping: DAMPING,
        implicit_damping: false,
        max_speed: f64::INFINITY,
    };
    /// gymnasium-robotics' / D4RL's MuJoCo point: one step per row, gear 100 over the mass of a
    /// sphere of radius 0.1 and density 1000, joint damping 1 over the same mass, implicit
    /// damping, velocities clipped to 5.
    pub const MUJOCO: Physics = Physics {
        frame_skip: 1,
        force_gain: 100.0 / MUJOCO_MASS,
        damping: 1.0 / MUJOCO_MASS,
        implicit_damping: true,
        max_speed: 5.0,
    };
}

impl Default for Physics {
    fn default() -> Self {
        Physics::RELREWARD
    }
}

/// Mass of MuJoCo's point: a sphere of radius 0.1 at density 1000 (`4/3 pi r^3 rho`).
const MUJOCO_MASS: f64 = 4.0 / 3.0 * std::f64::consts::PI * 1e-3 * 1000.0;

/// Position `[x, y]` and velocity `[vx, vy]` of the agent.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PointMass {
    pub pos: [f64; 2],
    pub vel: [f64; 2],
}

impl PointMass {
    pub fn at_rest(pos: [f64; 2]) -> Self {
        Self { pos, vel: [0.0, 0.0] }
    }

    /// The observation `[x, y, vx, vy]`.
    pub fn observation(&self) -> [f64; 4] {
        [self.pos[0], self.pos[1], self.vel[0], self.vel[1]]
    }

    /// One step: [`FRAME_SKIP`] substeps under `action` (clipped to `[-1, 1]` per component).
    /// Returns whether a wall stopped the agent.
    #[inline]
    pub fn step(&mut self, layout: &Layout, action: [f64; 2]) -> bool {
        self.step_with(layout, action, &Physics::RELREWARD)
    }

    /// One step under `physics` (its velocity clip, then its substeps).
    #[inline]
    pub fn step_with(&mut self, layout: &Layout, action: [f64; 2], physics: &Physics) -> bool {
        let action = [action[0].clamp(-1.0, 1.0), action[1].clamp(-1.0, 1.0)];
        for v in &mut self.vel {
            *v = v.clamp(-physics.max_speed, physics.max_speed);
        }
        let mut hit = false;
        for _ in 0..physics.frame_skip {
            hit |= self.substep(layout, action, physics);
        }
        hit
    }

    /// One substep of [`DT`]: semi-implicit Euler, then the move along x and along y, each
    /// stopped at a wall face with its velocity component zeroed.
    #[inline]
    fn substep(&mut self, layout: &Layout, action: [f64; 2], physics: &Physics) -> bool {
        for (v, a) in self.vel.iter_mut().zip(action) {
            *v = if physics.implicit_damping {
                (*v + DT * physics.force_gain * a) / (1.0 + DT * physics.damping)
            } else {
                *v + DT * (physics.force_gain * a - physics.damping * *v)
            };
        }
        let hit_x = move_axis(layout, &mut self.pos, &mut self.vel, 0);
        let hit_y = move_axis(layout, &mut self.pos, &mut self.vel, 1);
        hit_x | hit_y
    }
}

/// Moves `pos[axis]` by `DT * vel[axis]`. The agent's square spans `(p - RADIUS, p + RADIUS)` on
/// each axis; the cells it overlaps along the other axis stay the same during the move, so the
/// move is stopped by the first row (or column) of cells, in the direction of motion, that has
/// a wall among them. Checking starts next to the cell holding the centre, which is free, and
/// ends at the cell the leading edge reaches: every crossed cell is checked.
#[inline]
fn move_axis(layout: &Layout, pos: &mut [f64; 2], vel: &mut [f64; 2], axis: usize) -> bool {
    let d = DT * vel[axis];
    if d == 0.0 {
        return false;
    }
    let other = 1 - axis;
    // Cells k with (k - 0.5, k + 0.5) overlapping the open interval (lo, hi): k in
    // floor(lo + 0.5) ..= ceil(hi - 0.5), i.e. k > lo - 0.5 and k < hi + 0.5.
    let (o_lo, o_hi) = overlapped(pos[other] - RADIUS, pos[other] + RADIUS);
    let wall_in_line =
        |k: i64| (o_lo..=o_hi).any(|o| if axis == 0 { !layout.free_at(k, o) } else { !layout.free_at(o, k) });
    let from = pos[axis].round() as i64;
    let target = pos[axis] + d;
    if d > 0.0 {
        let (_, reach) = overlapped(target - RADIUS, target + RADIUS);
        for k in from + 1..=reach {
            if wall_in_line(k) {
                pos[axis] = k as f64 - 0.5 - RADIUS - CONTACT_GAP;
                vel[axis] = 0.0;
                return true;
            }
        }
    } else {
        let (reach, _) = overlapped(target - RADIUS, target + RADIUS);
        for k in (reach..from).rev() {
            if wall_in_line(k) {
                pos[axis] = k as f64 + 0.5 + RADIUS + CONTACT_GAP;
                vel[axis] = 0.0;
                return true;
            }
        }
    }
    pos[axis] = target;
    false
}

/// The first and last cell index whose open unit interval meets the open interval (lo, hi).
#[inline]
fn overlapped(lo: f64, hi: f64) -> (i64, i64) {
    ((lo + 0.5).floor() as i64, (hi - 0.5).ceil() as i64)
}

#[cfg(test)]
mod tests {
    use super::super::{LayoutName, Rng, cell_of};
    use super::*;

    /// Whether the agent's square, shrunk by `margin`, lies in free cells only.
    fn clear(layout: &Layout, pos: [f64; 2], margin: f64) -> bool {
        let r = RADIUS - margin;
        [(-r, -r), (-r, r), (r, -r), (r, r)].iter().all(|(dx, dy)| layout.is_free_position(pos[0] + dx, pos[1] + dy))
    }

    #[test]
    fn overlap_ranges() {
        assert_eq!(overlapped(0.9, 1.1), (1, 1));
        assert_eq!(overlapped(0.4, 0.6), (0, 1));
        assert_eq!(overlapped(0.5, 0.7), (1, 1), "touching a face is no overlap");
        assert_eq!(overlapped(0.3, 0.5), (0, 0));
        assert_eq!(overlapped(-0.6, -0.4), (-1, 0));
    }

    #[test]
    fn free_flight_is_semi_implicit_euler() {
        let open = LayoutName::Open.layout();
        let mut p = PointMass::at_rest([2.0, 3.0]);
        p.step(&open, [1.0, -0.5]);
        // By hand: FRAME_SKIP substeps of v += DT (F a - c v); p += DT v.
        let (mut pos, mut vel) = ([2.0, 3.0], [0.0, 0.0]);
        for _ in 0..FRAME_SKIP {
            for (k, a) in [1.0, -0.5].into_iter().enumerate() {
                vel[k] += DT * (FORCE_GAIN * a - DAMPING * vel[k]);
                pos[k] += DT * vel[k];
            }
        }
        assert_eq!((p.pos, p.vel), (pos, vel));
        // Actions beyond [-1, 1] are clipped.
        let mut q = PointMass::at_rest([2.0, 3.0]);
        q.step(&open, [7.0, -0.5]);
        assert_eq!(q, p);
        // Damping slows a coasting agent.
        let mut c = PointMass { pos: [2.0, 3.0], vel: [1.0, 0.0] };
        c.step(&open, [0.0, 0.0]);
        assert_eq!(c.vel[0], (1.0 - DT * DAMPING) * (1.0 - DT * DAMPING));
    }

    #[test]
    fn walls_stop_the_agent_at_their_face() {
        let umaze = LayoutName::Umaze.layout();
        // Heading up (decreasing x) from (1, 1): row 0 is wall, its face at x = 0.5.
        let mut p = PointMass { pos: [1.0, 1.0], vel: [-100.0, 0.0] };
        assert!(p.step(&umaze, [-1.0, 0.0]));
        assert_eq!(p.vel[0], 0.0);
        assert!((p.pos[0] - (0.5 + RADIUS)).abs() < 1e-8, "{:?}", p.pos);
        // Sliding along the wall keeps the other component.
        let mut s = PointMass { pos: [0.6 + 1e-6, 1.0], vel: [-3.0, 2.0] };
        s.step(&umaze, [0.0, 0.0]);
        assert_eq!(s.vel[0], 0.0);
        assert!(s.vel[1] > 1.9 && s.pos[1] > 1.0);
        // A fast agent does not tunnel through the one-cell wall between rows 1 and 3.
        let mut t = PointMass { pos: [1.0, 1.0], vel: [250.0, 0.0] };
        t.step(&umaze, [1.0, 0.0]);
        assert!(t.pos[0] < 1.5 && t.vel[0] == 0.0, "{:?}", t.pos);
        // Corners: moving diagonally into the wall corner at (2, 2) from (1.35, 1.35).
        let mut d = PointMass { pos: [1.35, 1.35], vel: [10.0, 10.0] };
        for _ in 0..50 {
            d.step(&umaze, [1.0, 1.0]);
            assert!(clear(&umaze, d.pos, 1e-7), "{:?}", d.pos);
        }
        // It slides into the free corridor at column 3 (the y move is free once x is stopped).
        assert!(d.pos[1] > 2.4, "{:?}", d.pos);
    }

    #[test]
    fn random_forces_never_enter_a_wall() {
        for name in LayoutName::ALL {
            let layout = name.layout();
            let cells = layout.free_cells();
            let mut rng = Rng::new(3);
            for _ in 0..20 {
                let (i, j) = cells[rng.below(cells.len() as u64) as usize];
                let mut p = PointMass::at_rest([i as f64, j as f64]);
                for _ in 0..2_000 {
                    let a = [rng.uniform() * 2.0 - 1.0, rng.uniform() * 2.0 - 1.0];
                    p.step(&layout, a);
                    assert!(clear(&layout, p.pos, 1e-7), "{name}: {:?} in {:?}", p.pos, cell_of(p.pos[0], p.pos[1]));
                }
            }
        }
    }
}
