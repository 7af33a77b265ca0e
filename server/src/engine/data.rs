//! Training batches from a stored dataset: sub-trajectories of length H drawn from within
//! episodes (trajectory datasets), or single samples (sample datasets), in normalized units.
//!
//! The whole dataset is normalized once into one tensor; a batch is an `index_select` of
//! precomputed window starts, so drawing a batch costs one gather, not a copy per item.

use tch::{Kind, Tensor};

use super::normalizer::{Normalize, Normalizer};
use super::rng::Rng;
use crate::error::{Error, Result};

/// Fraction of windows held out for the evaluation loss.
const HELD_OUT: f64 = 0.05;

pub struct TrainingData {
    /// Normalized rows: [N, D] for trajectories, [N, *shape] for samples.
    rows: Tensor,
    /// Horizon H for trajectories; `None` for samples (a batch item is one row).
    horizon: Option<i64>,
    train: Vec<i64>,
    held_out: Vec<i64>,
    /// Class labels of sample datasets, int64 [N] (conditional training).
    labels: Option<Tensor>,
}

/// Start indices of every length-`horizon` window lying inside one episode. `ends_after[i]`
/// marks the last row of an episode (terminals, timeouts); `starts_at[i]` the first.
pub fn window_starts(n: usize, horizon: usize, ends_after: &[bool], starts_at: &[bool]) -> Vec<i64> {
    let mut starts = Vec::new();
    let mut begin = 0usize;
    let flush = |begin: usize, end: usize, starts: &mut Vec<i64>| {
        if end >= begin + horizon {
            starts.extend((begin..=end - horizon).map(|s| s as i64));
        }
    };
    for i in 0..n {
        if i > begin && starts_at.get(i).copied().unwrap_or(false) {
            flush(begin, i, &mut starts);
            begin = i;
        }
        if ends_after.get(i).copied().unwrap_or(false) {
            flush(begin, i + 1, &mut starts);
            begin = i + 1;
        }
    }
    flush(begin, n, &mut starts);
    starts
}

impl TrainingData {
    /// `rows` in raw units ([N, D] or [N, *shape]); `starts` the window starts (trajectories)
    /// or `None` (samples). A seeded shuffle holds out 5% of the items for evaluation.
    pub fn new(
        rows: &Tensor,
        normalizer: &Normalizer,
        item_dims: usize,
        horizon: Option<usize>,
        starts: Option<Vec<i64>>,
        seed: u64,
    ) -> Result<Self> {
        let n = rows.size()[0];
        let mut items: Vec<i64> = match starts {
            Some(s) => s,
            None => (0..n).collect(),
        };
        if items.is_empty() {
            return Err(Error::invalid("dataset: no training items (no episode is as long as the horizon)"));
        }
        let mut rng = Rng::new(seed ^ 0x5eed_da7a);
        for i in (1..items.len()).rev() {
            items.swap(i, rng.below(i as u64 + 1) as usize);
        }
        let n_held = if items.len() >= 20 { ((items.len() as f64) * HELD_OUT).ceil() as usize } else { 0 };
        let held_out = items.split_off(items.len() - n_held);
        let normalized = tch::no_grad(|| normalizer.normalize(rows, item_dims).to_kind(Kind::Float));
        Ok(Self { rows: normalized, horizon: horizon.map(|h| h as i64), train: items, held_out, labels: None })
    }

    /// The same items with a label each (int64 `[N]`, one per row of a sample dataset), drawn
    /// along with their rows by [`Self::labeled_batch`].
    pub fn with_labels(self, labels: Tensor) -> Result<Self> {
        if self.horizon.is_some() || labels.size() != [self.rows.size()[0]] || labels.kind() != Kind::Int64 {
            return Err(Error::internal(
                "training data",
                format!("labels {:?} for {} sample rows", labels.size(), self.rows.size()[0]),
            ));
        }
        Ok(Self { labels: Some(labels.to_device(self.rows.device())), ..self })
    }

    pub fn train_len(&self) -> usize {
        self.train.len()
    }

    /// The same items with their rows on `device` (batches are gathered there).
    pub fn to_device(self, device: tch::Device) -> Self {
        Self { rows: self.rows.to_device(device), labels: self.labels.map(|l| l.to_device(device)), ..self }
    }

    fn gather(&self, starts: &[i64]) -> Tensor {
        let idx = super::upload(&Tensor::from_slice(starts), self.rows.device()).expect("an int64 upload");
        match self.horizon {
            Some(h) => {
                let offsets = Tensor::arange(h, (Kind::Int64, self.rows.device()));
                let full = (idx.unsqueeze(1) + offsets.unsqueeze(0)).flatten(0, 1);
                let d = self.rows.size()[1];
                self.rows.index_select(0, &full).reshape([starts.len() as i64, h, d])
            }
            None => self.rows.index_select(0, &idx),
        }
    }

    fn labels_of(&self, picks: &[i64]) -> Option<Tensor> {
        let labels = self.labels.as_ref()?;
        let idx = super::upload(&Tensor::from_slice(picks), labels.device()).expect("an int64 upload");
        Some(labels.index_select(0, &idx))
    }

    /// A training batch of `batch` items drawn uniformly with replacement.
    pub fn batch(&self, rng: &mut Rng, batch: usize) -> Tensor {
        self.labeled_batch(rng, batch).0
    }

    /// [`Self::batch`] with the items' labels (None without labels); the same draws.
    pub fn labeled_batch(&self, rng: &mut Rng, batch: usize) -> (Tensor, Option<Tensor>) {
        let picks: Vec<i64> = (0..batch).map(|_| self.train[rng.below(self.train.len() as u64) as usize]).collect();
        (self.gather(&picks), self.labels_of(&picks))
    }

    /// The first `max` held-out items (the same every call), or `None` if nothing was held out.
    pub fn held_out(&self, max: usize) -> Option<Tensor> {
        self.labeled_held_out(max).map(|(x, _)| x)
    }

    /// [`Self::held_out`] with the items' labels.
    pub fn labeled_held_out(&self, max: usize) -> Option<(Tensor, Option<Tensor>)> {
        let picks = &self.held_out[..self.held_out.len().min(max)];
        (!picks.is_empty()).then(|| (self.gather(picks), self.labels_of(picks)))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn windows_stay_inside_episodes() {
        // Episodes [0, 4), [4, 10), [10, 12) by terminal flags; horizon 3.
        let mut ends = vec![false; 12];
        ends[3] = true;
        ends[9] = true;
        let starts = window_starts(12, 3, &ends, &[]);
        assert_eq!(starts, vec![0, 1, 4, 5, 6, 7]);
        let mut begins = vec![false; 12];
        begins[6] = true;
        assert_eq!(window_starts(12, 6, &[], &begins), vec![0, 6]);
    }

    #[test]
    fn batches_are_contiguous_normalized_windows() {
        let n = 100;
        let raw: Vec<f32> = (0..n * 2).map(|i| i as f32).collect();
        let rows = Tensor::from_slice(&raw).reshape([n, 2]);
        let norm = Normalizer::Identity;
        let data = TrainingData::new(&rows, &norm, 1, Some(4), Some((0..97).collect()), 1).expect("data");
        let b = data.batch(&mut Rng::new(3), 8);
        assert_eq!(b.size(), vec![8, 4, 2]);
        // Consecutive rows within a window: each next row is 2 more than the previous.
        let diff = b.narrow(1, 1, 3) - b.narrow(1, 0, 3);
        assert!(diff.eq(2.0).all().int64_value(&[]) == 1);
        assert_eq!(data.train_len() + data.held_out.len(), 97);
        assert!(data.held_out(1000).is_some());
    }
}
