//! How the evaluation gets its rewards: [`Scorer`] scores a range of the items under evaluation
//! (rho per item, optionally each of its windows' values), and [`score_all`] asks for every item
//! in batches, a few in flight, and puts the answers together in order.
//!
//! The toolkit opens no connection: the `relreward` CLI's operations implement [`Scorer`] over
//! the server's `Score` (a connected client, a reward model, a diffusion time), and tests can
//! implement it with a formula.

use std::future::Future;
use std::ops::Range;

use futures::StreamExt;

/// The scores of one batch of items, as the scorer got them.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct BatchScores {
    /// rho of each item of the batch.
    pub rewards: Vec<f32>,
    /// With `per_window`: `(K, values)`, the `K` window values of each item, row-major `[len, K]`.
    pub per_window: Option<(usize, Vec<f32>)>,
}

/// The scores of every item: rho `[n]` and, when asked, the windows' values `(K, [n, K])`.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct Scores {
    pub rewards: Vec<f64>,
    pub per_window: Option<(usize, Vec<f64>)>,
}

/// A reward model as the evaluation sees it: the scores of items `range` of the items it was
/// made for (indices into them, in order).
pub trait Scorer {
    type Error;

    /// Scores items `range`; with `per_window`, also their windows' values (a windowed reward's
    /// own outputs; `K` is the same for every batch).
    fn score(&self, range: Range<usize>, per_window: bool) -> impl Future<Output = Result<BatchScores, Self::Error>>;
}

/// What can go wrong putting the scores together.
#[derive(Debug, thiserror::Error)]
pub enum ScoreError<E> {
    /// The scorer's own failure, with the items it was asked for.
    #[error("scoring items {}..{}", range.start, range.end)]
    Scorer { range: Range<usize>, error: E },
    /// A batch came back with the wrong number of values.
    #[error("items {}..{}: {what}", range.start, range.end)]
    Shape { range: Range<usize>, what: String },
    /// A reward that is not a finite number.
    #[error("a non-finite reward ({0})")]
    NonFinite(f64),
}

/// Scores items `0..n` in batches of `batch`, `in_flight` requests at once, in order; calls
/// `on_batch` with each batch's size as it arrives (a progress bar).
pub async fn score_all<S: Scorer>(
    scorer: &S,
    n: usize,
    batch: usize,
    in_flight: usize,
    per_window: bool,
    mut on_batch: impl FnMut(usize),
) -> Result<Scores, ScoreError<S::Error>> {
    let ranges = batches(n, batch);
    let requests = ranges.iter().cloned().map(|range| async move {
        let answer = scorer.score(range.clone(), per_window).await;
        (range, answer)
    });
    let mut answers = futures::stream::iter(requests).buffered(in_flight.max(1));
    let mut scores = Scores { rewards: Vec::with_capacity(n), per_window: None };
    while let Some((range, answer)) = answers.next().await {
        let answer = answer.map_err(|error| ScoreError::Scorer { range: range.clone(), error })?;
        let b = range.len();
        if answer.rewards.len() != b {
            let what = format!("{} rewards for {b} items", answer.rewards.len());
            return Err(ScoreError::Shape { range, what });
        }
        scores.rewards.extend(answer.rewards.iter().copied().map(f64::from));
        if per_window {
            let Some((k, values)) = answer.per_window else {
                return Err(ScoreError::Shape { range, what: "no per-window values".to_owned() });
            };
            let (width, all) = scores.per_window.get_or_insert_with(|| (k, Vec::new()));
            if k != *width || values.len() != b * k {
                let what = format!("{} per-window values for {b} items of {width} windows", values.len());
                return Err(ScoreError::Shape { range, what });
            }
            all.extend(values.into_iter().map(f64::from));
        }
        on_batch(b);
    }
    if let Some(&bad) = scores.rewards.iter().find(|v| !v.is_finite()) {
        return Err(ScoreError::NonFinite(bad));
    }
    Ok(scores)
}

/// Consecutive ranges of at most `batch` items covering `0..n`.
pub fn batches(n: usize, batch: usize) -> Vec<Range<usize>> {
    (0..n).step_by(batch.max(1)).map(|s| s..(s + batch).min(n)).collect()
}

#[cfg(test)]
mod tests {
    use std::cell::RefCell;

    use super::*;

    /// rho of item i is i; windows (i, -i); refuses items from `fail_at` on.
    struct Formula {
        fail_at: usize,
        asked: RefCell<Vec<Range<usize>>>,
    }

    impl Scorer for Formula {
        type Error = String;

        async fn score(&self, range: Range<usize>, per_window: bool) -> Result<BatchScores, String> {
            self.asked.borrow_mut().push(range.clone());
            if range.end > self.fail_at {
                return Err("refused".to_owned());
            }
            let rewards = range.clone().map(|i| i as f32).collect();
            let per_window = per_window.then(|| (2, range.flat_map(|i| [i as f32, -(i as f32)]).collect()));
            Ok(BatchScores { rewards, per_window })
        }
    }

    fn block_on<F: Future>(f: F) -> F::Output {
        futures::executor::block_on(f)
    }

    #[test]
    fn every_item_is_scored_once_in_order() {
        let scorer = Formula { fail_at: usize::MAX, asked: RefCell::default() };
        let mut seen = 0;
        let scores = block_on(score_all(&scorer, 7, 3, 2, true, |b| seen += b)).expect("scores");
        assert_eq!(scores.rewards, [0.0, 1.0, 2.0, 3.0, 4.0, 5.0, 6.0]);
        let (k, values) = scores.per_window.expect("windows");
        assert_eq!((k, &values[..4]), (2, &[0.0, -0.0, 1.0, -1.0][..]));
        assert_eq!(seen, 7);
        assert_eq!(*scorer.asked.borrow(), [0..3, 3..6, 6..7]);
    }

    #[test]
    fn a_failed_batch_names_its_items() {
        let scorer = Formula { fail_at: 4, asked: RefCell::default() };
        let err = block_on(score_all(&scorer, 7, 3, 1, false, |_| {})).expect_err("refused");
        assert!(matches!(&err, ScoreError::Scorer { range, error } if *range == (3..6) && error == "refused"));
    }
}
