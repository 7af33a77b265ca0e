//! The Maze2D reward heatmap and goal recovery (paper section 5.1, "Visualization of Learned
//! Reward Functions", and appendix "Quantitative Evaluation in Maze2D").
//!
//! - "we use our model to predict rewards for fixed-length sub-trajectories in the base
//!   dataset. We then generate a 2D heatmap by averaging the rewards of all sub-trajectories
//!   that pass through each grid cell": each scored sub-trajectory adds its (winsorized,
//!   min-max scaled) reward ONCE to every bin that one of its states lies in
//!   ([`Accumulator::add`]), and a bin's value is the mean over the sub-trajectories that
//!   passed through it. A bin crossed by fewer than `min_count` of them is masked
//!   ([`Accumulator::means`]; docs/method.md section 4: 10 bins per cell, fewer than 5 samples
//!   masked).
//! - Cells follow D4RL: cell (row i, column j) is the unit square centred at (x, y) = (i, j),
//!   so x runs along rows and y along columns ([`Grid`]).
//! - "We first smoothed the reward functions slightly to remove artifacts and verified whether
//!   the position of the global reward maximum was within 1 grid cell of the correct goal
//!   position": [`smooth`] (a Gaussian over unmasked bins, normalised by the weights it
//!   found, so masked bins neither count nor receive a value), [`argmax`], and
//!   [`goal_recovered`]: the Chebyshev distance between the centre of the arg-max bin and
//!   the goal, in cell units, is at most [`RECOVERY_RADIUS`] = 1 (the goal itself is a disc of
//!   half a cell's diameter in the data generator, which is why the paper allows the margin).

/// Goal recovery: the arg-max must lie within this Chebyshev distance (cells) of the goal.
pub const RECOVERY_RADIUS: f64 = 1.0;

/// A rectangle of maze cells, cut into `bins_per_cell` x `bins_per_cell` bins each.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Grid {
    /// Index of the first row (x) and column (y) of cells.
    pub row0: i64,
    pub col0: i64,
    /// Number of rows and columns of cells.
    pub rows: usize,
    pub cols: usize,
    pub bins_per_cell: usize,
}

impl Grid {
    /// The grid of a maze whose walls array is `[rows, cols]`: cells (0, 0) to (rows-1, cols-1).
    pub fn of_maze(rows: usize, cols: usize, bins_per_cell: usize) -> Self {
        Self { row0: 0, col0: 0, rows, cols, bins_per_cell: bins_per_cell.max(1) }
    }

    /// The smallest grid of whole cells that holds every point (`None` for no finite point).
    pub fn covering(points: impl IntoIterator<Item = (f64, f64)>, bins_per_cell: usize) -> Option<Self> {
        let (mut lo, mut hi) = ((i64::MAX, i64::MAX), (i64::MIN, i64::MIN));
        for (x, y) in points {
            if !(x.is_finite() && y.is_finite()) {
                continue;
            }
            let (i, j) = cell_of(x, y);
            lo = (lo.0.min(i), lo.1.min(j));
            hi = (hi.0.max(i), hi.1.max(j));
        }
        (lo.0 <= hi.0).then(|| Self {
            row0: lo.0,
            col0: lo.1,
            rows: (hi.0 - lo.0 + 1) as usize,
            cols: (hi.1 - lo.1 + 1) as usize,
            bins_per_cell: bins_per_cell.max(1),
        })
    }

    /// Bins along x (rows) and along y (columns).
    pub fn shape(&self) -> (usize, usize) {
        (self.rows * self.bins_per_cell, self.cols * self.bins_per_cell)
    }

    pub fn len(&self) -> usize {
        let (nx, ny) = self.shape();
        nx * ny
    }

    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// Lower edges of the grid: x of the first row's top, y of the first column's left.
    pub fn origin(&self) -> (f64, f64) {
        (self.row0 as f64 - 0.5, self.col0 as f64 - 0.5)
    }

    /// Side of a bin, in cells.
    pub fn bin_size(&self) -> f64 {
        1.0 / self.bins_per_cell as f64
    }

    /// The flat index (`a * ny + b`) of the bin holding (x, y); `None` outside the grid.
    pub fn bin_of(&self, x: f64, y: f64) -> Option<usize> {
        let (x0, y0) = self.origin();
        let (nx, ny) = self.shape();
        let a = ((x - x0) * self.bins_per_cell as f64).floor();
        let b = ((y - y0) * self.bins_per_cell as f64).floor();
        if a >= 0.0 && b >= 0.0 && a < nx as f64 && b < ny as f64 { Some(a as usize * ny + b as usize) } else { None }
    }

    /// Centre (x, y) of flat bin `k`.
    pub fn bin_centre(&self, k: usize) -> (f64, f64) {
        let (_, ny) = self.shape();
        let (x0, y0) = self.origin();
        let s = self.bin_size();
        (x0 + ((k / ny) as f64 + 0.5) * s, y0 + ((k % ny) as f64 + 0.5) * s)
    }
}

/// The cell (row i, column j) holding (x, y): the nearest integer point.
pub fn cell_of(x: f64, y: f64) -> (i64, i64) {
    (x.round() as i64, y.round() as i64)
}

/// Chebyshev (max-norm) distance between two positions, in cells.
pub fn chebyshev(a: (f64, f64), b: (f64, f64)) -> f64 {
    (a.0 - b.0).abs().max((a.1 - b.1).abs())
}

/// Whether a reward maximum at `argmax` recovers `goal` (see the module docs).
pub fn goal_recovered(argmax: (f64, f64), goal: (f64, f64)) -> bool {
    chebyshev(argmax, goal) <= RECOVERY_RADIUS
}

/// Sums and counts per bin of the sub-trajectories that passed through it.
#[derive(Debug, Clone)]
pub struct Accumulator {
    pub grid: Grid,
    sum: Vec<f64>,
    count: Vec<u32>,
    /// States that fell outside the grid.
    pub outside: usize,
    touched: Vec<usize>,
}

impl Accumulator {
    pub fn new(grid: Grid) -> Self {
        Self { grid, sum: vec![0.0; grid.len()], count: vec![0; grid.len()], outside: 0, touched: Vec::new() }
    }

    /// Adds one sub-trajectory with reward `value`: once to every distinct bin its states
    /// `points` lie in.
    pub fn add(&mut self, points: impl IntoIterator<Item = (f64, f64)>, value: f64) {
        self.touched.clear();
        for (x, y) in points {
            match self.grid.bin_of(x, y) {
                Some(k) => self.touched.push(k),
                None => self.outside += 1,
            }
        }
        self.touched.sort_unstable();
        self.touched.dedup();
        for &k in &self.touched {
            self.sum[k] += value;
            self.count[k] += 1;
        }
    }

    /// Sub-trajectories counted in each bin.
    pub fn counts(&self) -> &[u32] {
        &self.count
    }

    /// The mean reward of each bin, `None` (masked) for bins crossed by fewer than
    /// `min_count` sub-trajectories (and always for bins crossed by none).
    pub fn means(&self, min_count: u32) -> Vec<Option<f64>> {
        self.sum.iter().zip(&self.count).map(|(&s, &c)| (c >= min_count.max(1)).then(|| s / f64::from(c))).collect()
    }
}

/// Gaussian smoothing with standard deviation `sigma_bins` (in bins; 0: none) over the
/// unmasked bins of a `grid`-shaped map: each unmasked bin becomes the kernel-weighted mean of
/// the unmasked bins around it (within 3 sigma); masked bins stay masked.
pub fn smooth(grid: &Grid, values: &[Option<f64>], sigma_bins: f64) -> Vec<Option<f64>> {
    if sigma_bins.is_nan() || sigma_bins <= 0.0 {
        return values.to_vec();
    }
    let (nx, ny) = grid.shape();
    let radius = (3.0 * sigma_bins).ceil() as isize;
    let kernel: Vec<f64> = (-radius..=radius).map(|d| (-0.5 * (d as f64 / sigma_bins).powi(2)).exp()).collect();
    // Normalised convolution: blur value * mask and mask with the separable kernel, divide.
    let mut num: Vec<f64> = values.iter().map(|v| v.unwrap_or(0.0)).collect();
    let mut den: Vec<f64> = values.iter().map(|v| if v.is_some() { 1.0 } else { 0.0 }).collect();
    let pass = |field: &[f64], along_x: bool| -> Vec<f64> {
        let mut out = vec![0.0; field.len()];
        for a in 0..nx {
            for b in 0..ny {
                let mut acc = 0.0;
                for (t, w) in kernel.iter().enumerate() {
                    let d = t as isize - radius;
                    let (aa, bb) = if along_x { (a as isize + d, b as isize) } else { (a as isize, b as isize + d) };
                    if aa >= 0 && bb >= 0 && (aa as usize) < nx && (bb as usize) < ny {
                        acc += w * field[aa as usize * ny + bb as usize];
                    }
                }
                out[a * ny + b] = acc;
            }
        }
        out
    };
    for along_x in [true, false] {
        num = pass(&num, along_x);
        den = pass(&den, along_x);
    }
    values.iter().zip(num.iter().zip(&den)).map(|(v, (&n, &d))| v.and_then(|_| (d > 0.0).then(|| n / d))).collect()
}

/// The flat index and value of the largest unmasked bin (the first of equals).
pub fn argmax(values: &[Option<f64>]) -> Option<(usize, f64)> {
    values.iter().enumerate().filter_map(|(k, v)| v.map(|v| (k, v))).fold(None, |best: Option<(usize, f64)>, (k, v)| {
        match best {
            Some((_, bv)) if bv >= v => best,
            _ => Some((k, v)),
        }
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn cells_are_unit_squares_centred_on_integer_points() {
        let g = Grid::of_maze(3, 4, 2);
        assert_eq!((g.shape(), g.len(), g.origin()), ((6, 8), 48, (-0.5, -0.5)));
        // (0, 0) is the centre of cell (0, 0): the upper-right bin of its four.
        assert_eq!(g.bin_of(0.0, 0.0), Some(8 + 1));
        assert_eq!(g.bin_of(-0.5, -0.5), Some(0));
        assert_eq!(g.bin_of(-0.26, -0.01), Some(0));
        assert_eq!(g.bin_of(-0.51, 0.0), None);
        assert_eq!(g.bin_of(2.49, 3.49), Some(47));
        assert_eq!(g.bin_of(2.5, 0.0), None, "the upper edge belongs to no cell of the grid");
        assert_eq!(g.bin_centre(0), (-0.25, -0.25));
        assert_eq!(g.bin_centre(47), (2.25, 3.25));
        // x runs along rows: x = 1 is row 1, bins 2 and 3 along x.
        assert_eq!(g.bin_of(1.1, 0.2), Some(3 * 8 + 1));
        assert_eq!(cell_of(1.4, 2.6), (1, 3));
        let c = Grid::covering([(1.2, -0.4), (3.6, 2.0), (f64::NAN, 0.0)], 10).expect("grid");
        assert_eq!((c.row0, c.col0, c.rows, c.cols), (1, 0, 4, 3));
        assert!(Grid::covering([], 10).is_none());
    }

    #[test]
    fn bins_average_the_sub_trajectories_that_pass_through_them() {
        // A 1 x 2 maze, 2 bins per cell: bins are [x in (-0.5, 0) | (0, 0.5)] x 4 along y.
        let g = Grid::of_maze(1, 2, 2);
        let mut acc = Accumulator::new(g);
        // Sub-trajectory A (reward 1.0) visits bin 0 twice and bin 1 once: counted once each.
        acc.add([(-0.4, -0.4), (-0.3, -0.2), (-0.3, 0.2)], 1.0);
        // B (reward 0.0) visits bins 1 and 5, and leaves the grid once.
        acc.add([(-0.1, 0.1), (0.2, 0.1), (9.0, 9.0)], 0.0);
        // C (reward 0.5) visits bin 1 only.
        acc.add([(-0.2, 0.3)], 0.5);
        assert_eq!(acc.counts(), &[1, 3, 0, 0, 0, 1, 0, 0]);
        assert_eq!(acc.outside, 1);
        let all = acc.means(1);
        assert_eq!(all, vec![Some(1.0), Some(0.5), None, None, None, Some(0.0), None, None]);
        // Masking: fewer than 2 sub-trajectories.
        assert_eq!(acc.means(2), vec![None, Some(0.5), None, None, None, None, None, None]);
        // min_count 0 still masks empty bins.
        assert_eq!(acc.means(0)[2], None);
    }

    #[test]
    fn smoothing_averages_unmasked_neighbours_and_keeps_the_mask() {
        let g = Grid::of_maze(1, 1, 3);
        let v = vec![Some(9.0), None, Some(0.0), None, Some(0.0), None, Some(0.0), None, Some(0.0)];
        assert_eq!(smooth(&g, &v, 0.0), v);
        let s = smooth(&g, &v, 1.0);
        for (a, b) in s.iter().zip(&v) {
            assert_eq!(a.is_some(), b.is_some());
        }
        // The peak is lowered, its neighbours raised, values stay within [0, 9].
        let (p, q) = (s[0].expect("kept"), s[4].expect("kept"));
        assert!(p < 9.0 && p > q && q > 0.0, "{s:?}");
        // By hand, for bin 4 (the centre): weights over unmasked bins at distances (1,1) x 4
        // corners... all four corners and the centre: w(0)^2 = 1 for itself, w(1)^2 = e^-1 for
        // each corner; only corner 0 holds 9.
        let w = (-1.0f64).exp();
        assert!((q - 9.0 * w / (1.0 + 4.0 * w)).abs() < 1e-12, "{q}");
        // A constant map stays constant.
        let flat = vec![Some(2.0); 9];
        assert!(smooth(&g, &flat, 2.0).iter().all(|v| (v.expect("kept") - 2.0).abs() < 1e-12));
    }

    #[test]
    fn the_maximum_is_recovered_within_one_cell() {
        assert_eq!(argmax(&[None, Some(1.0), Some(3.0), Some(3.0), None]), Some((2, 3.0)));
        assert_eq!(argmax(&[None, None]), None);
        assert_eq!(chebyshev((1.0, 2.0), (2.5, 1.5)), 1.5);
        assert!(goal_recovered((1.0, 1.0), (2.0, 2.0)), "a diagonal neighbour's centre is 1 cell away");
        assert!(goal_recovered((1.05, 1.95), (1.0, 1.0)));
        assert!(!goal_recovered((1.0, 2.01), (1.0, 1.0)));
        assert!(!goal_recovered((3.0, 1.0), (1.0, 1.0)));
        // On a grid: the centre of the arg-max bin is what is compared.
        let g = Grid::of_maze(3, 3, 10);
        let mut values = vec![Some(0.0); g.len()];
        let k = g.bin_of(1.96, 0.04).expect("in grid");
        values[k] = Some(1.0);
        let (best, _) = argmax(&values).expect("max");
        let pos = g.bin_centre(best);
        assert!((pos.0 - 1.95).abs() < 1e-12 && (pos.1 - 0.05).abs() < 1e-12, "{pos:?}");
        assert!(goal_recovered(pos, (1.0, 0.0)) && !goal_recovered(pos, (0.0, 1.2)));
    }
}
