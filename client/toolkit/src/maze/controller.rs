//! The data-generating controller: [`Planner`] (shortest paths over free cells) and
//! [`Controller`] (waypoints followed with a clipped PD law), as docs/method.md section 5
//! describes D4RL's.

use super::{D_GAIN, Layout, P_GAIN, WAYPOINT_RADIUS, cell_of};

/// Distance of a cell that cannot reach the target (or is a wall).
pub const UNREACHABLE: u16 = u16::MAX;

/// Neighbour order of the search and of tie-breaking between equally short paths.
const NEIGHBOURS: [(i64, i64); 4] = [(-1, 0), (1, 0), (0, -1), (0, 1)];

/// Breadth-first distances over the 4-connected free cells, computed once per target cell and
/// kept: a next hop is then a look-up, without allocation. Cells are indexed row-major,
/// `row * cols + col`.
#[derive(Debug, Clone)]
pub struct Planner {
    rows: usize,
    cols: usize,
    free: Vec<bool>,
    /// Per target cell: every cell's distance to it in steps, once computed.
    to: Vec<Option<Box<[u16]>>>,
}

impl Planner {
    pub fn new(layout: &Layout) -> Self {
        let (rows, cols) = (layout.rows(), layout.cols());
        let free = (0..rows * cols).map(|c| layout.is_free(c / cols, c % cols)).collect();
        Self { rows, cols, free, to: vec![None; rows * cols] }
    }

    pub fn cols(&self) -> usize {
        self.cols
    }

    /// The index of cell (row, col).
    pub fn index(&self, row: usize, col: usize) -> usize {
        row * self.cols + col
    }

    /// (row, col) of a cell index.
    pub fn cell(&self, index: usize) -> (usize, usize) {
        (index / self.cols, index % self.cols)
    }

    /// Every cell's distance in steps to `target` ([`UNREACHABLE`] for walls and cells cut off
    /// from it); all [`UNREACHABLE`] when `target` is a wall.
    pub fn distances(&mut self, target: usize) -> &[u16] {
        if self.to[target].is_none() {
            let bfs = self.bfs(target);
            self.to[target] = Some(bfs);
        }
        self.to[target].as_deref().expect("just computed")
    }

    /// Steps on the shortest path between two free cells; `None` for a wall, a cell off the grid
    /// or cells that are not connected.
    pub fn distance(&mut self, from: (usize, usize), to: (usize, usize)) -> Option<usize> {
        if from.0 >= self.rows || from.1 >= self.cols || to.0 >= self.rows || to.1 >= self.cols {
            return None;
        }
        let (from, to) = (self.index(from.0, from.1), self.index(to.0, to.1));
        let d = self.distances(to)[from];
        (d != UNREACHABLE).then_some(usize::from(d))
    }

    fn bfs(&self, target: usize) -> Box<[u16]> {
        let mut dist = vec![UNREACHABLE; self.rows * self.cols].into_boxed_slice();
        if !self.free[target] {
            return dist;
        }
        let mut queue = std::collections::VecDeque::with_capacity(self.rows * self.cols);
        dist[target] = 0;
        queue.push_back(target);
        while let Some(c) = queue.pop_front() {
            for n in self.neighbours(c) {
                if dist[n] == UNREACHABLE {
                    dist[n] = dist[c] + 1;
                    queue.push_back(n);
                }
            }
        }
        dist
    }

    /// The free neighbours of cell `c`, in [`NEIGHBOURS`] order.
    fn neighbours(&self, c: usize) -> impl Iterator<Item = usize> + '_ {
        let (i, j) = ((c / self.cols) as i64, (c % self.cols) as i64);
        NEIGHBOURS.iter().filter_map(move |(di, dj)| {
            let (ni, nj) = (i + di, j + dj);
            let inside = ni >= 0 && nj >= 0 && (ni as usize) < self.rows && (nj as usize) < self.cols;
            let n = inside.then(|| ni as usize * self.cols + nj as usize)?;
            self.free[n].then_some(n)
        })
    }

    /// The first cell after `from` on the shortest path to `target` (the first neighbour in
    /// the order up, down, left, right, one step closer); `None` when `from == target` or no
    /// path exists.
    pub fn next_hop(&mut self, from: usize, target: usize) -> Option<usize> {
        self.distances(target);
        let dist = self.to[target].as_deref().expect("computed");
        let d = dist[from];
        if d == 0 || d == UNREACHABLE {
            return None;
        }
        self.neighbours(from).find(|&n| dist[n] == d - 1)
    }

    /// The shortest path from `from` to `to` as (row, col) cells, both ends included; `None`
    /// when either is a wall or they are not connected.
    pub fn shortest_path(&mut self, from: (usize, usize), to: (usize, usize)) -> Option<Vec<(usize, usize)>> {
        if from.0 >= self.rows || from.1 >= self.cols || to.0 >= self.rows || to.1 >= self.cols {
            return None;
        }
        let (mut c, target) = (self.index(from.0, from.1), self.index(to.0, to.1));
        if !self.free[c] || self.distances(target)[c] == UNREACHABLE {
            return None;
        }
        let mut path = vec![from];
        while let Some(n) = self.next_hop(c, target) {
            path.push(self.cell(n));
            c = n;
        }
        Some(path)
    }
}

/// The PD law: `P_GAIN * (waypoint - pos) - D_GAIN * vel`, clipped to `[-1, 1]` per component.
#[inline]
pub fn pd_action(waypoint: [f64; 2], pos: [f64; 2], vel: [f64; 2]) -> [f64; 2] {
    let a = |k: usize| (P_GAIN * (waypoint[k] - pos[k]) - D_GAIN * vel[k]).clamp(-1.0, 1.0);
    [a(0), a(1)]
}

/// Follows the shortest path to one goal position. The waypoints are the centres of the path's
/// cells after the agent's own and, for the goal's cell, the goal position itself. The agent is
/// expected between the last waypoint passed (`from`) and the current one (`way`); should it
/// be in any other cell, the path is planned again from there.
#[derive(Debug, Clone, PartialEq)]
pub struct Controller {
    goal: [f64; 2],
    goal_cell: usize,
    /// The cell of the last waypoint passed (at first, the agent's cell).
    from: usize,
    /// The cell of the current waypoint.
    way: usize,
}

impl Controller {
    /// A controller heading for `goal`, which must lie in a free cell, from `pos`, which must
    /// too.
    pub fn new(planner: &mut Planner, pos: [f64; 2], goal: [f64; 2]) -> Self {
        let goal_cell = cell_index(planner, goal);
        let mut controller = Self { goal, goal_cell, from: 0, way: 0 };
        controller.plan_from(planner, cell_index(planner, pos));
        controller
    }

    pub fn goal(&self) -> [f64; 2] {
        self.goal
    }

    /// The current waypoint.
    pub fn waypoint(&self, planner: &Planner) -> [f64; 2] {
        if self.way == self.goal_cell {
            self.goal
        } else {
            let (i, j) = planner.cell(self.way);
            [i as f64, j as f64]
        }
    }

    fn plan_from(&mut self, planner: &mut Planner, cell: usize) {
        self.from = cell;
        self.way = planner.next_hop(cell, self.goal_cell).unwrap_or(self.goal_cell);
    }

    /// The action at state (`pos`, `vel`): replans if the agent left its path, passes every
    /// waypoint it is within [`WAYPOINT_RADIUS`] of, then applies [`pd_action`] towards the
    /// current one.
    #[inline]
    pub fn act(&mut self, planner: &mut Planner, pos: [f64; 2], vel: [f64; 2]) -> [f64; 2] {
        let here = cell_index(planner, pos);
        if here != self.from && here != self.way {
            self.plan_from(planner, here);
        }
        let r2 = WAYPOINT_RADIUS * WAYPOINT_RADIUS;
        while self.way != self.goal_cell && dist2(self.waypoint(planner), pos) < r2 {
            let passed = self.way;
            self.way = planner.next_hop(passed, self.goal_cell).unwrap_or(self.goal_cell);
            self.from = passed;
        }
        pd_action(self.waypoint(planner), pos, vel)
    }
}

#[inline]
fn cell_index(planner: &Planner, pos: [f64; 2]) -> usize {
    let (i, j) = cell_of(pos[0], pos[1]);
    // Positions come from the simulation, which keeps them in free cells of the grid.
    debug_assert!(i >= 0 && j >= 0, "position {pos:?} outside the grid");
    i.max(0) as usize * planner.cols() + j.max(0) as usize
}

#[inline]
pub(crate) fn dist2(a: [f64; 2], b: [f64; 2]) -> f64 {
    let (dx, dy) = (a[0] - b[0], a[1] - b[1]);
    dx * dx + dy * dy
}

#[cfg(test)]
mod tests {
    use super::super::{GOAL_RADIUS, LayoutName, PointMass, RADIUS, Rng};
    use super::*;

    #[test]
    fn breadth_first_paths_are_shortest() {
        let umaze = LayoutName::Umaze.layout();
        let mut planner = Planner::new(&umaze);
        let path = planner.shortest_path((3, 1), (1, 1)).expect("path");
        assert_eq!(path, [(3, 1), (3, 2), (3, 3), (2, 3), (1, 3), (1, 2), (1, 1)]);
        assert_eq!(planner.shortest_path((1, 2), (1, 2)).expect("same"), [(1, 2)]);
        assert_eq!(planner.shortest_path((2, 2), (1, 1)), None, "from a wall");
        assert_eq!(planner.shortest_path((1, 1), (0, 0)), None, "to a wall");
        assert_eq!(planner.shortest_path((1, 1), (9, 9)), None, "off the grid");

        // Open: ties go up, down, left, right in that order; length is the Manhattan distance.
        let open = LayoutName::Open.layout();
        let mut planner = Planner::new(&open);
        assert_eq!(planner.shortest_path((3, 1), (1, 3)).expect("path"), [(3, 1), (2, 1), (1, 1), (1, 2), (1, 3)]);
        for (a, b) in [((1, 1), (3, 5)), ((2, 3), (1, 1)), ((3, 5), (3, 1))] {
            let p = planner.shortest_path(a, b).expect("path");
            assert_eq!(p.len() - 1, a.0.abs_diff(b.0) + a.1.abs_diff(b.1));
        }

        // Large: paths step between free neighbours and are no longer than the BFS distance.
        let large = LayoutName::Large.layout();
        let mut planner = Planner::new(&large);
        let cells = large.free_cells();
        let mut longest = 0;
        for &a in &cells {
            for &b in &cells {
                let p = planner.shortest_path(a, b).expect("connected");
                assert_eq!((p[0], *p.last().expect("end")), (a, b));
                for w in p.windows(2) {
                    assert_eq!(w[0].0.abs_diff(w[1].0) + w[0].1.abs_diff(w[1].1), 1);
                    assert!(large.is_free(w[1].0, w[1].1));
                }
                assert_eq!(Some(p.len() - 1), planner.distance(a, b));
                longest = longest.max(p.len() - 1);
            }
        }
        assert_eq!(longest, 19, "the diameter of the large maze");
    }

    #[test]
    fn pd_law_is_clipped() {
        assert_eq!(pd_action([1.0, 1.0], [1.0, 1.0], [0.0, 0.0]), [0.0, 0.0]);
        let a = pd_action([1.05, 0.0], [1.0, 0.0], [0.2, -0.3]);
        assert!((a[0] - 0.3).abs() < 1e-12 && a[1] == 0.3, "{a:?}");
        assert_eq!(pd_action([5.0, -5.0], [0.0, 0.0], [0.0, 0.0]), [1.0, -1.0]);
    }

    /// Runs the controller from `start` to `goal`; the step at which it is within GOAL_RADIUS.
    fn reach(layout: &Layout, planner: &mut Planner, start: [f64; 2], goal: [f64; 2], cap: u32) -> Option<u32> {
        let mut agent = PointMass::at_rest(start);
        let mut controller = Controller::new(planner, start, goal);
        for t in 1..=cap {
            let a = controller.act(planner, agent.pos, agent.vel);
            agent.step(layout, a);
            if dist2(agent.pos, goal) <= GOAL_RADIUS * GOAL_RADIUS {
                return Some(t);
            }
        }
        None
    }

    #[test]
    fn the_controller_reaches_goals_in_every_layout_within_the_cap() {
        for name in LayoutName::ALL {
            let layout = name.layout();
            let cap = name.max_episode_steps();
            let mut planner = Planner::new(&layout);
            let cells = layout.free_cells();
            let mut rng = Rng::new(11);
            // The farthest pair of cells, a few corners of cells, and random pairs.
            let mut farthest = ((0, 0), (0, 0), 0);
            for &a in &cells {
                for &b in &cells {
                    let d = planner.distance(a, b).expect("connected");
                    if d > farthest.2 {
                        farthest = (a, b, d);
                    }
                }
            }
            let centre = |c: (usize, usize)| [c.0 as f64, c.1 as f64];
            let corner = 0.5 - RADIUS - 1e-6;
            let (a, b, _) = farthest;
            let mut trials = vec![(centre(a), centre(b)), (centre(b), centre(a))];
            trials.push(([a.0 as f64 + corner, a.1 as f64 - corner], [b.0 as f64 - 0.3, b.1 as f64 + 0.3]));
            trials.push(([b.0 as f64 - corner, b.1 as f64 + corner], centre(a)));
            for _ in 0..30 {
                let s = cells[rng.below(cells.len() as u64) as usize];
                let g = cells[rng.below(cells.len() as u64) as usize];
                let jitter = |rng: &mut Rng| (rng.uniform() - 0.5) * 2.0 * corner;
                let start = [s.0 as f64 + jitter(&mut rng), s.1 as f64 + jitter(&mut rng)];
                let goal = [g.0 as f64 + jitter(&mut rng), g.1 as f64 + jitter(&mut rng)];
                trials.push((start, goal));
            }
            let mut slowest = 0;
            for (start, goal) in trials {
                let steps = reach(&layout, &mut planner, start, goal, cap)
                    .unwrap_or_else(|| panic!("{name}: {start:?} -> {goal:?} not reached in {cap} steps"));

                slowest = slowest.max(steps);
            }
            // Room to spare: even the longest path takes well under the cap.
            eprintln!("{name}: slowest {slowest} steps of cap {cap}");
            // Room to spare: even the longest path takes well under the cap.
            assert!(slowest < cap * 3 / 4, "{name}: slowest {slowest} of cap {cap}");
        }
    }

    #[test]
    fn an_agent_pushed_off_its_path_replans() {
        let large = LayoutName::Large.layout();
        let mut planner = Planner::new(&large);
        let mut controller = Controller::new(&mut planner, [1.0, 1.0], [7.0, 9.0]);
        // First waypoint: a neighbour of (1, 1).
        let w = controller.waypoint(&planner);
        assert!((w[0] - 1.0).abs() + (w[1] - 1.0).abs() == 1.0, "{w:?}");
        // Teleported far away: the next waypoint is adjacent to the new cell.
        controller.act(&mut planner, [5.0, 8.0], [0.0, 0.0]);
        let w = controller.waypoint(&planner);
        assert!((w[0] - 5.0).abs() + (w[1] - 8.0).abs() == 1.0, "{w:?}");
        // In the goal's cell the waypoint is the goal itself.
        controller.act(&mut planner, [7.2, 9.2], [0.0, 0.0]);
        assert_eq!(controller.waypoint(&planner), [7.0, 9.0]);
    }
}
