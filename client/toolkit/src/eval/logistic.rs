//! One-feature logistic regression, fitted by Newton's method (IRLS) with a line search, and
//! the classification scores the discriminability evaluation reports.
//!
//! The model is `P(expert | r) = sigmoid(w z + b)` with `z = (r - mean) / std` standardised on
//! the training set. The objective is the class-weighted mean log-loss plus `l2 / 2 * w^2`
//! (the intercept is not penalised), with scikit-learn's `class_weight = "balanced"` weights
//! `n / (2 n_class)`: what the authors used (docs/method.md section 4). The tiny penalty keeps
//! the optimum finite on separable data, where the unpenalised weight would grow without
//! bound; the objective is then strictly convex and Newton converges in a few dozen steps.

/// A fitted model.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Logistic {
    /// Weight of the standardised feature.
    pub weight: f64,
    pub bias: f64,
    /// Standardisation: `z = (r - mean) / scale`.
    pub mean: f64,
    pub scale: f64,
    pub l2: f64,
    /// Newton iterations taken, and whether the gradient fell below the tolerance.
    pub iterations: usize,
    pub converged: bool,
    /// The training objective at the optimum.
    pub loss: f64,
}

/// Largest number of Newton iterations.
const MAX_ITERATIONS: usize = 200;
/// Convergence: largest gradient component.
const GRAD_TOLERANCE: f64 = 1e-10;

/// `log(1 + exp(s))` without overflow.
fn softplus(s: f64) -> f64 {
    s.max(0.0) + (-s.abs()).exp().ln_1p()
}

fn sigmoid(s: f64) -> f64 {
    if s >= 0.0 {
        1.0 / (1.0 + (-s).exp())
    } else {
        let e = s.exp();
        e / (1.0 + e)
    }
}

/// Per-sample weights `n / (2 n_class)` (1 for balanced classes).
fn balanced_weights(y: &[bool]) -> Vec<f64> {
    let n = y.len() as f64;
    let pos = y.iter().filter(|&&v| v).count() as f64;
    let neg = n - pos;
    let (wp, wn) = (if pos > 0.0 { n / (2.0 * pos) } else { 0.0 }, if neg > 0.0 { n / (2.0 * neg) } else { 0.0 });
    y.iter().map(|&v| if v { wp } else { wn }).collect()
}

impl Logistic {
    /// Fits `y` (true: expert) on the scalar feature `x`; `l2` is the penalty on the
    /// standardised weight. Empty input gives the zero model.
    pub fn fit(x: &[f64], y: &[bool], l2: f64) -> Self {
        assert_eq!(x.len(), y.len(), "one label per value");
        let n = x.len().max(1) as f64;
        let mean = if x.is_empty() { 0.0 } else { x.iter().sum::<f64>() / n };
        let var = x.iter().map(|v| (v - mean) * (v - mean)).sum::<f64>() / n;
        let scale = if var > 0.0 && var.is_finite() { var.sqrt() } else { 1.0 };
        let z: Vec<f64> = x.iter().map(|v| (v - mean) / scale).collect();
        let c = balanced_weights(y);
        let objective = |w: f64, b: f64| -> f64 {
            let data: f64 = z
                .iter()
                .zip(y)
                .zip(&c)
                .map(|((&zi, &yi), &ci)| {
                    let s = w * zi + b;
                    ci * (softplus(s) - if yi { s } else { 0.0 })
                })
                .sum();
            data / n + 0.5 * l2 * w * w
        };
        let (mut w, mut b) = (0.0f64, 0.0f64);
        let mut loss = objective(w, b);
        let mut iterations = 0;
        let mut converged = x.is_empty();
        while !converged && iterations < MAX_ITERATIONS {
            iterations += 1;
            let (mut gw, mut gb, mut hww, mut hwb, mut hbb) = (0.0, 0.0, 0.0, 0.0, 0.0);
            for ((&zi, &yi), &ci) in z.iter().zip(y).zip(&c) {
                let p = sigmoid(w * zi + b);
                let r = ci * (p - if yi { 1.0 } else { 0.0 });
                let h = ci * p * (1.0 - p);
                gw += r * zi;
                gb += r;
                hww += h * zi * zi;
                hwb += h * zi;
                hbb += h;
            }
            let (gw, gb) = (gw / n + l2 * w, gb / n);
            if gw.abs().max(gb.abs()) < GRAD_TOLERANCE {
                converged = true;
                break;
            }
            // A small ridge keeps the 2x2 system solvable when every p is saturated.
            let (hww, hwb, hbb) = (hww / n + l2 + 1e-12, hwb / n, hbb / n + 1e-12);
            let det = hww * hbb - hwb * hwb;
            let (mut dw, mut db) = if det > 0.0 && det.is_finite() {
                ((hbb * gw - hwb * gb) / det, (hww * gb - hwb * gw) / det)
            } else {
                (gw, gb)
            };
            // Backtracking (Armijo) line search on the objective.
            let slope = gw * dw + gb * db;
            let mut step = 1.0;
            let mut accepted = false;
            for _ in 0..60 {
                let trial = objective(w - step * dw, b - step * db);
                if trial <= loss - 1e-4 * step * slope {
                    w -= step * dw;
                    b -= step * db;
                    loss = trial;
                    accepted = true;
                    break;
                }
                step *= 0.5;
            }
            if !accepted {
                // No decrease is representable any more: the optimum, to machine precision.
                converged = true;
            }
            dw *= step;
            db *= step;
            if dw.abs().max(db.abs()) < 1e-14 * (1.0 + w.abs().max(b.abs())) {
                converged = true;
            }
        }
        Self { weight: w, bias: b, mean, scale, l2, iterations, converged, loss }
    }

    /// `P(expert | r)`.
    pub fn probability(&self, r: f64) -> f64 {
        sigmoid(self.weight * (r - self.mean) / self.scale + self.bias)
    }

    /// Expert when `P(expert | r) >= 0.5`.
    pub fn predict(&self, r: f64) -> bool {
        self.probability(r) >= 0.5
    }

    /// `(w, b)` of the same model in reward units: `P = sigmoid(w r + b)`.
    pub fn raw_coefficients(&self) -> (f64, f64) {
        let w = self.weight / self.scale;
        (w, self.bias - w * self.mean)
    }

    /// The reward at which the prediction changes (`None` for a zero weight).
    pub fn threshold(&self) -> Option<f64> {
        let (w, b) = self.raw_coefficients();
        (w != 0.0).then(|| -b / w)
    }
}

/// Fraction of correct predictions (NaN for none).
pub fn accuracy(predicted: &[bool], y: &[bool]) -> f64 {
    let correct = predicted.iter().zip(y).filter(|(p, t)| p == t).count();
    if y.is_empty() { f64::NAN } else { correct as f64 / y.len() as f64 }
}

/// Mean of the recalls of the two classes (the accuracy a balanced test set would give); the
/// plain accuracy when only one class is present.
pub fn balanced_accuracy(predicted: &[bool], y: &[bool]) -> f64 {
    let recall = |class: bool| {
        let (hit, all) = predicted
            .iter()
            .zip(y)
            .filter(|&(_, &t)| t == class)
            .fold((0usize, 0usize), |(h, a), (&p, _)| (h + usize::from(p == class), a + 1));
        (all > 0).then(|| hit as f64 / all as f64)
    };
    match (recall(true), recall(false)) {
        (Some(a), Some(b)) => 0.5 * (a + b),
        (Some(a), None) | (None, Some(a)) => a,
        (None, None) => f64::NAN,
    }
}

/// Area under the ROC curve of `scores` for `y` (Mann-Whitney U with ties counted half): the
/// probability that an expert item scores above a base item. NaN without both classes.
pub fn roc_auc(scores: &[f64], y: &[bool]) -> f64 {
    let mut order: Vec<usize> = (0..scores.len()).collect();
    order.sort_by(|&a, &b| scores[a].total_cmp(&scores[b]));
    // Average ranks (1-based) over ties.
    let mut ranks = vec![0.0; scores.len()];
    let mut i = 0;
    while i < order.len() {
        let mut j = i;
        while j + 1 < order.len() && scores[order[j + 1]] == scores[order[i]] {
            j += 1;
        }
        let rank = (i + j) as f64 / 2.0 + 1.0;
        for &k in &order[i..=j] {
            ranks[k] = rank;
        }
        i = j + 1;
    }
    let pos = y.iter().filter(|&&v| v).count() as f64;
    let neg = y.len() as f64 - pos;
    if pos == 0.0 || neg == 0.0 {
        return f64::NAN;
    }
    let rank_sum: f64 = ranks.iter().zip(y).filter(|(_, v)| **v).map(|(r, _)| r).sum();
    (rank_sum - pos * (pos + 1.0) / 2.0) / (pos * neg)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::eval::stats::Rng;

    /// The best balanced accuracy any threshold rule `r >= c` or `r < c` reaches on the data.
    fn best_threshold_balanced_accuracy(x: &[f64], y: &[bool]) -> f64 {
        let mut cuts: Vec<f64> = x.to_vec();
        cuts.push(f64::INFINITY);
        cuts.into_iter()
            .flat_map(|c| {
                let above: Vec<bool> = x.iter().map(|&v| v >= c).collect();
                let below: Vec<bool> = above.iter().map(|v| !v).collect();
                [balanced_accuracy(&above, y), balanced_accuracy(&below, y)]
            })
            .fold(0.0, f64::max)
    }

    /// Approximately normal values (sum of 12 uniforms), mean `mu`, std 1.
    fn normal(rng: &mut Rng, mu: f64) -> f64 {
        let s: f64 = (0..12).map(|_| (rng.next_u64() >> 11) as f64 / (1u64 << 53) as f64).sum();
        mu + s - 6.0
    }

    #[test]
    fn separable_data_is_classified_perfectly() {
        let x: Vec<f64> = (0..40).map(|i| f64::from(i) * 0.1 + if i >= 20 { 5.0 } else { 0.0 }).collect();
        let y: Vec<bool> = (0..40).map(|i| i >= 20).collect();
        let m = Logistic::fit(&x, &y, 1e-4);
        assert!(m.converged, "{m:?}");
        assert!(m.weight > 0.0 && m.weight.is_finite(), "{m:?}");
        let predicted: Vec<bool> = x.iter().map(|&r| m.predict(r)).collect();
        assert_eq!(accuracy(&predicted, &y), 1.0);
        assert_eq!(balanced_accuracy(&predicted, &y), 1.0);
        // The boundary lies in the gap between the classes (1.9 .. 7.0), near its middle by symmetry.
        let c = m.threshold().expect("threshold");
        assert!((1.9..7.0).contains(&c), "{c}");
        assert!((c - 4.45).abs() < 0.2, "{c}");
        // Reversed labels: a negative weight, the same accuracy.
        let flipped: Vec<bool> = y.iter().map(|v| !v).collect();
        let m = Logistic::fit(&x, &flipped, 1e-4);
        assert!(m.weight < 0.0);
        let predicted: Vec<bool> = x.iter().map(|&r| m.predict(r)).collect();
        assert_eq!(accuracy(&predicted, &flipped), 1.0);
    }

    #[test]
    fn overlapping_gaussians_match_the_known_optimum_and_the_best_threshold() {
        // Two unit-variance classes at -1 and +1: the Bayes boundary is r = 0, the true logit
        // is 2 r (w = 2 in reward units) and the best balanced accuracy is Phi(1) = 0.8413.
        let mut rng = Rng::new(3);
        let mut x = Vec::new();
        let mut y = Vec::new();
        for i in 0..20_000 {
            let expert = i % 2 == 0;
            x.push(normal(&mut rng, if expert { 1.0 } else { -1.0 }));
            y.push(expert);
        }
        let m = Logistic::fit(&x, &y, 1e-6);
        assert!(m.converged && m.iterations < 50, "{m:?}");
        let (w, b) = m.raw_coefficients();
        assert!((w - 2.0).abs() < 0.1, "w = {w}");
        assert!(b.abs() < 0.05, "b = {b}");
        let predicted: Vec<bool> = x.iter().map(|&r| m.predict(r)).collect();
        let ours = balanced_accuracy(&predicted, &y);
        let best = best_threshold_balanced_accuracy(&x, &y);
        assert!((ours - 0.8413).abs() < 0.01, "{ours}");
        assert!(ours <= best + 1e-12 && best - ours < 0.005, "logistic {ours} vs best threshold {best}");
        // AUC of N(1, 1) against N(-1, 1): Phi(2 / sqrt 2) = 0.9214.
        assert!((roc_auc(&x, &y) - 0.9214).abs() < 0.01);
    }

    #[test]
    fn the_fit_is_invariant_to_the_units_of_the_reward() {
        let x: Vec<f64> = [0.1, 0.5, 0.2, 0.9, 0.4, 0.8, 0.3, 0.7].to_vec();
        let y = [false, true, false, true, true, true, false, false];
        let a = Logistic::fit(&x, &y, 1e-4);
        let scaled: Vec<f64> = x.iter().map(|v| 1000.0 * v - 7.0).collect();
        let b = Logistic::fit(&scaled, &y, 1e-4);
        assert!((a.weight - b.weight).abs() < 1e-8 && (a.bias - b.bias).abs() < 1e-8);
        // Constant feature: no information, a zero weight, chance accuracy.
        let m = Logistic::fit(&[1.0; 6], &[true, false, true, false, true, false], 1e-4);
        assert!(m.weight.abs() < 1e-12 && (m.probability(1.0) - 0.5).abs() < 1e-9);
    }

    #[test]
    fn imbalanced_classes_are_weighted_equally() {
        // 90 base at 0, 10 expert at 1, overlapping with 10 base at 1: unweighted fits would
        // call everything base; balanced weights put the boundary between 0 and 1.
        let mut x = vec![0.0; 90];
        x.extend([1.0; 20]);
        let mut y = vec![false; 100];
        y.extend([true; 10]);
        let m = Logistic::fit(&x, &y, 1e-6);
        assert!(m.predict(1.0) && !m.predict(0.0), "{m:?}");
        let predicted: Vec<bool> = x.iter().map(|&r| m.predict(r)).collect();
        assert!((balanced_accuracy(&predicted, &y) - 0.95).abs() < 1e-12);
    }

    #[test]
    fn scores_by_hand() {
        let y = [true, true, false, false];
        assert_eq!(accuracy(&[true, false, false, false], &y), 0.75);
        assert_eq!(balanced_accuracy(&[true, false, false, false], &y), 0.75);
        assert_eq!(balanced_accuracy(&[true, true, true, true], &y), 0.5);
        assert_eq!(roc_auc(&[3.0, 4.0, 1.0, 2.0], &y), 1.0);
        assert_eq!(roc_auc(&[1.0, 1.0, 1.0, 1.0], &y), 0.5);
        assert_eq!(roc_auc(&[1.0, 3.0, 2.0, 4.0], &y), 0.25);
        assert_eq!(roc_auc(&[1.0, 4.0, 2.0, 3.0], &y), 0.5);
        assert!(roc_auc(&[1.0], &[true]).is_nan());
    }
}
