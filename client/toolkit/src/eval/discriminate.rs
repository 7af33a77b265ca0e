//! Discriminability (paper section 5.1, "Discriminability Results"): can a logistic regression
//! on the scalar reward alone tell held-out expert trajectories from base ones?
//!
//! The protocol, and the passage each step follows:
//! 1. Balanced classes: "we train a logistic regression classifier per expert model on a
//!    balanced dataset of base and expert trajectories". Each class keeps
//!    `min(n_base, n_expert, max_per_class)` windows, a seeded uniform subset
//!    ([`balanced_subsets`]); the windows are chosen before scoring so that no score is wasted.
//! 2. Scores at diffusion time t = 0 (clean trajectories), by the caller.
//! 3. Winsorization of the pooled scores at the 1st and 99th percentiles (the authors' code, as
//!    docs/method.md section 4 records: "The authors winsorize scores at 1%"), so a few extreme
//!    rewards cannot dominate the standardisation and the fit.
//! 4. A stratified, seeded 80/20 train/test split of each class.
//! 5. "using only the predicted reward as input": a one-feature logistic regression
//!    ([`Logistic`], standardised feature, class-balanced weights as the authors', a tiny L2).
//! 6. Held-out (test) accuracy and balanced accuracy; the paper reports accuracies of 65.33%
//!    to 97.26%, mean 83.76%, over maze goals and seeds ("We repeat this process for each goal
//!    position with 5 different seeds, and average accuracies across seeds": run the command
//!    once per seed and average).

use super::logistic::{Logistic, accuracy, balanced_accuracy, roc_auc};
use super::stats::{Rng, mean, std, winsorize};

/// The protocol's knobs.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Protocol {
    /// Winsorize the pooled scores at the `p` and `1 - p` quantiles (0.01: the paper's 1%).
    pub winsorize: f64,
    /// Fraction of each class used for training (0.8).
    pub train_fraction: f64,
    /// L2 penalty on the standardised weight (tiny: only keeps separable fits finite).
    pub l2: f64,
}

impl Default for Protocol {
    fn default() -> Self {
        Self { winsorize: 0.01, train_fraction: 0.8, l2: 1e-4 }
    }
}

/// What is reported about one class.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ClassSummary {
    pub n: usize,
    pub n_train: usize,
    pub n_test: usize,
    /// Mean and standard deviation of the scores before winsorization.
    pub mean: f64,
    pub std: f64,
    /// Mean after winsorization.
    pub mean_winsorized: f64,
}

/// The outcome of [`discriminate`].
#[derive(Debug, Clone, PartialEq)]
pub struct Discrimination {
    /// The winsorization limits (reward units).
    pub limits: (f64, f64),
    pub model: Logistic,
    pub train_accuracy: f64,
    pub train_balanced_accuracy: f64,
    pub test_accuracy: f64,
    pub test_balanced_accuracy: f64,
    /// ROC AUC of the (winsorized) reward itself on the test set.
    pub test_auc: f64,
    pub base: ClassSummary,
    pub expert: ClassSummary,
    /// Winsorized scores, as used for the fit (for pictures).
    pub base_winsorized: Vec<f64>,
    pub expert_winsorized: Vec<f64>,
}

/// Indices of the windows to score: the same number from each class, at most `max_per_class`,
/// drawn uniformly without replacement (ascending within each class).
pub fn balanced_subsets(
    n_base: usize,
    n_expert: usize,
    max_per_class: usize,
    rng: &mut Rng,
) -> (Vec<usize>, Vec<usize>) {
    let k = n_base.min(n_expert).min(max_per_class);
    (rng.subset(n_base, k), rng.subset(n_expert, k))
}

/// Splits `0..n` into (train, test) at `fraction`, shuffled; both non-empty when `n >= 2`.
fn split(n: usize, fraction: f64, rng: &mut Rng) -> (Vec<usize>, Vec<usize>) {
    let mut order: Vec<usize> = (0..n).collect();
    rng.shuffle(&mut order);
    let k = ((fraction * n as f64).round() as usize).clamp(n.min(1), n.saturating_sub(1).max(n.min(1)));
    let test = order.split_off(k);
    (order, test)
}

/// Runs steps 3 to 6 of the protocol on the scores of the two classes (step 1's subsets, step
/// 2's scores). Each class needs at least 2 scores (one to train on, one to test).
pub fn discriminate(base: &[f64], expert: &[f64], protocol: Protocol, rng: &mut Rng) -> Result<Discrimination, String> {
    for (name, scores) in [("base", base), ("expert", expert)] {
        if scores.len() < 2 {
            return Err(format!(
                "the {name} class has {} scored window(s); a train/test split needs at least 2 per class",
                scores.len()
            ));
        }
        if let Some(v) = scores.iter().find(|v| !v.is_finite()) {
            return Err(format!("the {name} class has a non-finite score ({v})"));
        }
    }
    let mut pooled: Vec<f64> = base.iter().chain(expert).copied().collect();
    let limits = winsorize(&mut pooled, protocol.winsorize);
    let expert_w = pooled.split_off(base.len());
    let base_w = pooled;

    let (base_train, base_test) = split(base_w.len(), protocol.train_fraction, rng);
    let (expert_train, expert_test) = split(expert_w.len(), protocol.train_fraction, rng);
    let gather = |base_idx: &[usize], expert_idx: &[usize]| -> (Vec<f64>, Vec<bool>) {
        let x = base_idx.iter().map(|&i| base_w[i]).chain(expert_idx.iter().map(|&i| expert_w[i])).collect();
        let y = std::iter::repeat_n(false, base_idx.len()).chain(std::iter::repeat_n(true, expert_idx.len())).collect();
        (x, y)
    };
    let (x_train, y_train) = gather(&base_train, &expert_train);
    let (x_test, y_test) = gather(&base_test, &expert_test);
    let model = Logistic::fit(&x_train, &y_train, protocol.l2);
    let predict = |x: &[f64]| x.iter().map(|&r| model.predict(r)).collect::<Vec<bool>>();
    let (p_train, p_test) = (predict(&x_train), predict(&x_test));
    let summary = |raw: &[f64], winsorized: &[f64], train: usize, test: usize| ClassSummary {
        n: raw.len(),
        n_train: train,
        n_test: test,
        mean: mean(raw),
        std: std(raw),
        mean_winsorized: mean(winsorized),
    };
    Ok(Discrimination {
        limits,
        model,
        train_accuracy: accuracy(&p_train, &y_train),
        train_balanced_accuracy: balanced_accuracy(&p_train, &y_train),
        test_accuracy: accuracy(&p_test, &y_test),
        test_balanced_accuracy: balanced_accuracy(&p_test, &y_test),
        test_auc: roc_auc(&x_test, &y_test),
        base: summary(base, &base_w, base_train.len(), base_test.len()),
        expert: summary(expert, &expert_w, expert_train.len(), expert_test.len()),
        base_winsorized: base_w,
        expert_winsorized: expert_w,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn subsets_are_balanced_and_bounded() {
        let mut rng = Rng::new(0);
        let (b, e) = balanced_subsets(1000, 30, 20_000, &mut rng);
        assert_eq!((b.len(), e.len()), (30, 30));
        assert_eq!(e, (0..30).collect::<Vec<_>>());
        let (b, e) = balanced_subsets(1000, 500, 100, &mut rng);
        assert_eq!((b.len(), e.len()), (100, 100));
        assert!(b.iter().all(|&i| i < 1000) && e.iter().all(|&i| i < 500));
        // Seeded: the same seed, the same windows.
        assert_eq!(balanced_subsets(50, 60, 10, &mut Rng::new(4)), balanced_subsets(50, 60, 10, &mut Rng::new(4)));
    }

    #[test]
    fn splits_are_stratified_80_20_and_disjoint() {
        let (train, test) = split(10, 0.8, &mut Rng::new(1));
        assert_eq!((train.len(), test.len()), (8, 2));
        let mut all: Vec<usize> = train.iter().chain(&test).copied().collect();
        all.sort_unstable();
        assert_eq!(all, (0..10).collect::<Vec<_>>());
        // Two items: one each way.
        let (train, test) = split(2, 0.8, &mut Rng::new(1));
        assert_eq!((train.len(), test.len()), (1, 1));
        let (train, test) = split(3, 0.99, &mut Rng::new(1));
        assert_eq!((train.len(), test.len()), (2, 1));
    }

    #[test]
    fn separated_classes_are_discriminated_and_reported() {
        let base: Vec<f64> = (0..100).map(|i| f64::from(i) / 100.0).collect();
        let mut expert: Vec<f64> = (0..100).map(|i| 2.0 + f64::from(i) / 100.0).collect();
        expert[0] = 1e9; // an outlier the winsorization clips
        let d = discriminate(&base, &expert, Protocol::default(), &mut Rng::new(2)).expect("discriminate");
        assert_eq!((d.test_accuracy, d.test_balanced_accuracy, d.train_accuracy), (1.0, 1.0, 1.0));
        assert_eq!((d.base.n, d.base.n_train, d.base.n_test), (100, 80, 20));
        assert_eq!((d.expert.n_train, d.expert.n_test), (80, 20));
        assert!(d.limits.1 < 3.0, "{:?}", d.limits);
        assert!(d.expert.mean > 1e6 && d.expert.mean_winsorized < 3.0);
        assert!((d.base.mean - 0.495).abs() < 1e-12);
        assert_eq!(d.test_auc, 1.0);
        assert!(d.model.weight > 0.0);
    }

    #[test]
    fn identical_classes_are_at_chance() {
        let scores: Vec<f64> = (0..400).map(|i| f64::from(i % 37)).collect();
        let d = discriminate(&scores, &scores, Protocol::default(), &mut Rng::new(5)).expect("discriminate");
        assert!((d.test_balanced_accuracy - 0.5).abs() < 0.15, "{}", d.test_balanced_accuracy);
        assert!(discriminate(&[1.0], &scores, Protocol::default(), &mut Rng::new(5)).is_err());
        assert!(discriminate(&[1.0, f64::NAN], &scores, Protocol::default(), &mut Rng::new(5)).is_err());
    }
}
