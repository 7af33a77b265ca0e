//! Small statistics the evaluation protocols share: percentiles, winsorization, min-max
//! scaling and a seedable random stream for subsets and splits.

/// The `q`-quantile (`q` in [0, 1]) of sorted values, interpolating linearly between the two
/// nearest ranks (numpy's default `percentile`); NaN for no values.
pub fn quantile_sorted(sorted: &[f64], q: f64) -> f64 {
    match sorted {
        [] => f64::NAN,
        [only] => *only,
        _ => {
            let pos = q.clamp(0.0, 1.0) * (sorted.len() - 1) as f64;
            let lo = pos.floor() as usize;
            let hi = (lo + 1).min(sorted.len() - 1);
            let frac = pos - lo as f64;
            sorted[lo] + (sorted[hi] - sorted[lo]) * frac
        }
    }
}

/// The `p` and `1 - p` quantiles of `values` (any order), the limits [`winsorize`] clips to.
pub fn winsor_limits(values: &[f64], p: f64) -> (f64, f64) {
    let mut sorted = values.to_vec();
    sorted.sort_by(f64::total_cmp);
    (quantile_sorted(&sorted, p), quantile_sorted(&sorted, 1.0 - p))
}

/// Clips every value to the `p` and `1 - p` quantiles of the values themselves (`p = 0.01`:
/// the 1st and 99th percentiles), as `np.clip(x, *np.percentile(x, [100 p, 100 (1 - p)]))`.
/// Returns the limits. `p = 0` leaves the values as they are.
pub fn winsorize(values: &mut [f64], p: f64) -> (f64, f64) {
    let (lo, hi) = winsor_limits(values, p);
    if p > 0.0 {
        for v in values.iter_mut() {
            *v = v.clamp(lo, hi);
        }
    }
    (lo, hi)
}

/// Scales values linearly to [0, 1] (all to 0.5 when they are all equal). Returns (min, max).
pub fn min_max_scale(values: &mut [f64]) -> (f64, f64) {
    let lo = values.iter().copied().fold(f64::INFINITY, f64::min);
    let hi = values.iter().copied().fold(f64::NEG_INFINITY, f64::max);
    let span = hi - lo;
    for v in values.iter_mut() {
        *v = if span > 0.0 { (*v - lo) / span } else { 0.5 };
    }
    (lo, hi)
}

/// Arithmetic mean (NaN for no values).
pub fn mean(values: &[f64]) -> f64 {
    if values.is_empty() { f64::NAN } else { values.iter().sum::<f64>() / values.len() as f64 }
}

/// Population standard deviation (NaN for no values).
pub fn std(values: &[f64]) -> f64 {
    let m = mean(values);
    mean(&values.iter().map(|v| (v - m) * (v - m)).collect::<Vec<_>>()).sqrt()
}

/// SplitMix64 (Steele, Lea and Flood 2014): a small, fast, seedable stream, so that every
/// subset and split of an evaluation is reproduced by its `--seed` on any machine.
#[derive(Debug, Clone)]
pub struct Rng(u64);

impl Rng {
    pub fn new(seed: u64) -> Self {
        Self(seed)
    }

    pub fn next_u64(&mut self) -> u64 {
        self.0 = self.0.wrapping_add(0x9E37_79B9_7F4A_7C15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        z ^ (z >> 31)
    }

    /// Uniform in `0..n` (`n > 0`), without modulo bias (Lemire's multiply-shift with rejection).
    pub fn below(&mut self, n: usize) -> usize {
        let n = n as u64;
        loop {
            let m = u128::from(self.next_u64()) * u128::from(n);
            if (m as u64) >= n.wrapping_neg() % n {
                return (m >> 64) as usize;
            }
        }
    }

    /// Fisher-Yates shuffle.
    pub fn shuffle<T>(&mut self, items: &mut [T]) {
        for i in (1..items.len()).rev() {
            let j = self.below(i + 1);
            items.swap(i, j);
        }
    }

    /// `k` distinct indices of `0..n` drawn uniformly (all of them when `k >= n`), ascending.
    pub fn subset(&mut self, n: usize, k: usize) -> Vec<usize> {
        let mut all: Vec<usize> = (0..n).collect();
        if k < n {
            // Partial Fisher-Yates: the first k places end up a uniform k-subset.
            for i in 0..k {
                let j = i + self.below(n - i);
                all.swap(i, j);
            }
            all.truncate(k);
            all.sort_unstable();
        }
        all
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn quantiles_interpolate_like_numpy() {
        let v: Vec<f64> = (0..=10).map(f64::from).collect();
        assert_eq!(quantile_sorted(&v, 0.0), 0.0);
        assert_eq!(quantile_sorted(&v, 1.0), 10.0);
        assert!((quantile_sorted(&v, 0.25) - 2.5).abs() < 1e-12);
        // np.percentile([1, 2, 3, 4], [1, 99]) = [1.03, 3.97]
        let w = [1.0, 2.0, 3.0, 4.0];
        assert!((quantile_sorted(&w, 0.01) - 1.03).abs() < 1e-12);
        assert!((quantile_sorted(&w, 0.99) - 3.97).abs() < 1e-12);
        assert!(quantile_sorted(&[], 0.5).is_nan());
        assert_eq!(quantile_sorted(&[7.0], 0.3), 7.0);
    }

    #[test]
    fn winsorization_clips_both_tails_at_the_percentiles() {
        // 0..=100 with two outliers: the 1st and 99th percentiles of 103 values.
        let mut v: Vec<f64> = (0..=100).map(f64::from).collect();
        v.push(1e6);
        v.push(-1e6);
        let (lo, hi) = winsorize(&mut v, 0.01);
        let mut sorted: Vec<f64> = (0..=100).map(f64::from).collect();
        sorted.push(1e6);
        sorted.insert(0, -1e6);
        // rank 0.01 * 102 = 1.02 and 0.99 * 102 = 100.98
        assert!((lo - (0.0 + 0.02 * 1.0)).abs() < 1e-9, "{lo}");
        assert!((hi - (99.0 + 0.98 * 1.0)).abs() < 1e-9, "{hi}");
        assert_eq!(v.iter().copied().fold(f64::INFINITY, f64::min), lo);
        assert_eq!(v.iter().copied().fold(f64::NEG_INFINITY, f64::max), hi);
        // Values inside the limits are untouched.
        assert_eq!(v[50], 50.0);
        // p = 0: nothing changes.
        let mut u = vec![3.0, -1.0, 2.0];
        assert_eq!(winsorize(&mut u, 0.0), (-1.0, 3.0));
        assert_eq!(u, vec![3.0, -1.0, 2.0]);
    }

    #[test]
    fn min_max_scaling_maps_to_the_unit_interval() {
        let mut v = vec![2.0, 4.0, 3.0];
        assert_eq!(min_max_scale(&mut v), (2.0, 4.0));
        assert_eq!(v, vec![0.0, 1.0, 0.5]);
        let mut same = vec![1.0, 1.0];
        min_max_scale(&mut same);
        assert_eq!(same, vec![0.5, 0.5]);
    }

    #[test]
    fn the_random_stream_is_seeded_and_subsets_are_distinct() {
        let a: Vec<u64> = {
            let mut r = Rng::new(7);
            (0..4).map(|_| r.next_u64()).collect()
        };
        let b: Vec<u64> = {
            let mut r = Rng::new(7);
            (0..4).map(|_| r.next_u64()).collect()
        };
        assert_eq!(a, b);
        let mut r = Rng::new(1);
        let s = r.subset(100, 10);
        assert_eq!(s.len(), 10);
        assert!(s.windows(2).all(|w| w[0] < w[1]) && s[9] < 100);
        assert_eq!(r.subset(5, 9), vec![0, 1, 2, 3, 4]);
        // below() is uniform enough: every value of 0..4 appears in 400 draws.
        let mut seen = [0; 4];
        for _ in 0..400 {
            seen[r.below(4)] += 1;
        }
        assert!(seen.iter().all(|&c| c > 50), "{seen:?}");
        let mut v: Vec<usize> = (0..20).collect();
        r.shuffle(&mut v);
        let mut sorted = v.clone();
        sorted.sort_unstable();
        assert_eq!(sorted, (0..20).collect::<Vec<_>>());
    }
}
