//! Algorithms 1 and 2 of "Extracting Reward Functions from Diffusion Models" as one engine
//! type, [`RelativeRewardTrainer`]: it owns the frozen base and expert models, the reward
//! network rho being fitted and the training pairs, and gives the loss of a training batch and
//! the held-out error. Whoever drives it (the reward job: jobs/reward.rs) owns the optimiser,
//! checkpoints, events and registration; nothing here knows of jobs or the store.
//!
//! - [`TrainingPairs`]: where the pairs come from. Algorithm 1 ([`TrainingPairs::Dataset`]):
//!   clean items noised at every step, the target computed from both models at x_t (or drawn
//!   from the amortised [`TargetPool`]). Algorithm 2 ([`TrainingPairs::chains`]): recorded
//!   steps of chains run from noise, both models stepped from each state with the same noise,
//!   standardised per step ([`ChainPairs`]).
//! - [`AlignmentSettings`]: the job's choices that shape the math (target, evaluation point,
//!   entry weights, conditioning, regulariser, amortised targets, batch size, seed).
//! - [`RelativeRewardTrainer`]: [`RelativeRewardTrainer::loss`] for a step and
//!   [`RelativeRewardTrainer::held_out_error`] for an evaluation
//!   ([`super::relative_reward`]'s alignment objective).

use std::cell::RefCell;

use tch::{Kind, Tensor};

use super::data::TrainingData;
use super::diffusion::DiffusionModel;
use super::nets::reward::{RewardArchitecture, RewardNet};
use super::optim::StepLoss;
use super::recipe::{Predictor, Recipe};
use super::relative_reward::{
    ConditionEntries, EvalPoint, Target, alignment_error, alignment_step, entry_weights, noised_target_and_point,
};
use super::rng::Rng;
use super::schedule::Table;
use super::target_pool::{AmortisedTargets, TargetPool, TargetSource};
use super::{device, upload};
use crate::error::{Error, Result};

/// Held-out items per evaluation.
pub const EVAL_ITEMS: usize = 256;

/// The choices of a relative-reward extraction that shape its computation.
#[derive(Debug, Clone)]
pub struct AlignmentSettings {
    pub architecture: RewardArchitecture,
    pub target: Target,
    pub eval_point: EvalPoint,
    /// Weight of the rho^2 regularizer (0: off).
    pub rho_l2: f64,
    /// Weights of the first step's action and observation entries ([`entry_weights`]).
    pub action_weight: f64,
    pub condition_weight: f64,
    /// Fit on x_t with the first observation clean ([`ConditionEntries`]).
    pub inpaint_condition: bool,
    /// Algorithm 1's amortised targets (None: targets computed for every batch).
    pub amortised_targets: Option<AmortisedTargets>,
    pub batch_size: usize,
    /// Seeds rho's initialisation, Algorithm 2's chains, the target pool and the evaluation.
    pub seed: u64,
    /// The request field the settings came from, named in errors (e.g. "spec.reward").
    pub field: &'static str,
}

/// Where training items come from.
pub enum TrainingPairs {
    /// Algorithm 1: clean items, noised at every step.
    Dataset(TrainingData),
    /// Algorithm 2: recorded chain steps.
    Chains(ChainPairs),
}

impl TrainingPairs {
    /// Algorithm 2's pairs from `num_chains` chains run from noise; generated identically from
    /// `seed` alone (a resumed job regenerates them rather than checkpointing them). The two
    /// models must share a normalizer: both step from one chain state in one unit system. A
    /// conditional model steps through its side's recipe ([`ChainRecipe`]).
    pub fn chains(base: ChainSide<'_>, expert: ChainSide<'_>, num_chains: usize, seed: u64) -> Result<Self> {
        if super::relative_reward::Alignment::between(base.model, expert.model).is_some() {
            return Err(Error::invalid(
                "spec.reward: base and expert models have different normalizers; Algorithm 2 needs one shared normalizer",
            ));
        }
        let mut rng = Rng::new(seed ^ 0xa162);
        Ok(Self::Chains(chain_pairs(base, expert, num_chains, &mut rng)?))
    }

    /// Items training draws from (the rest are held out).
    pub fn train_len(&self) -> usize {
        match self {
            Self::Dataset(d) => d.train_len(),
            Self::Chains(c) => c.train as usize,
        }
    }
}

/// rho being fitted to the difference of a frozen expert and base model (module docs).
pub struct RelativeRewardTrainer {
    base: DiffusionModel,
    /// Borrowed mutably by each target computation (it runs on a helper thread beside the
    /// base, engine/threads.rs), from the step's loss and the evaluation alike.
    expert: RefCell<DiffusionModel>,
    reward: RewardNet,
    pairs: TrainingPairs,
    settings: AlignmentSettings,
    /// Per-entry weights of the alignment loss (None: unweighted).
    entry_weights: Option<Tensor>,
    condition: Option<ConditionEntries>,
    /// Amortised targets, filled and refreshed on the step schedule (Algorithm 1 only).
    pool: Option<RefCell<TargetPool>>,
}

impl RelativeRewardTrainer {
    /// A freshly initialised rho (drawn from `settings.seed`: the same seed gives the same
    /// initial weights) for the base model's item shape, on the engine's device.
    pub fn new(
        base: DiffusionModel,
        expert: DiffusionModel,
        pairs: TrainingPairs,
        settings: AlignmentSettings,
    ) -> Result<Self> {
        let device = device();
        let space = base.manifest.space.clone();
        // The seed draws the first weights only; every later draw uses the caller's Rng.
        let reward = RewardNet::new(&settings.architecture, &space.item_shape(), settings.seed, device)?;
        let entry_weights =
            entry_weights(&space, settings.action_weight, settings.condition_weight, device, settings.field)?;
        let condition = settings
            .inpaint_condition
            .then(|| ConditionEntries::of(&space, &format!("{}.inpaint_condition", settings.field)))
            .transpose()?;
        let t_max = base.manifest.n_timesteps as u64;
        let pool = match (&settings.amortised_targets, &pairs) {
            (Some(a), TrainingPairs::Dataset(_)) => {
                Some(RefCell::new(TargetPool::new(*a, settings.seed, settings.batch_size, t_max)))
            }
            _ => None,
        };
        Ok(Self { base, expert: RefCell::new(expert), reward, pairs, settings, entry_weights, condition, pool })
    }

    /// The network being fitted (its `VarStore` is what the caller optimises).
    pub fn reward(&self) -> &RewardNet {
        &self.reward
    }

    pub fn train_len(&self) -> usize {
        self.pairs.train_len()
    }

    /// The amortised-target settings in use (None where targets are computed every batch,
    /// always for Algorithm 2).
    pub fn amortised_targets(&self) -> Option<AmortisedTargets> {
        self.pool.as_ref().and(self.settings.amortised_targets)
    }

    /// Algorithm 2's per-step standardisation tables, stored beside the weights (empty for
    /// Algorithm 1).
    pub fn step_normalization(&self) -> Vec<(String, Tensor)> {
        match &self.pairs {
            TrainingPairs::Chains(c) => c.step_norm.iter().map(|(n, t)| (n.clone(), t.shallow_clone())).collect(),
            TrainingPairs::Dataset(_) => Vec::new(),
        }
    }

    /// The differentiable loss of training step `step` (counted from 1, as the caller's loop
    /// does; it schedules the target pool's refreshes), its batch drawn with `rng`.
    pub fn loss(&self, step: u64, rng: &mut Rng) -> Result<StepLoss> {
        let (t, target, point) = match (&self.pool, &self.pairs) {
            (Some(pool), TrainingPairs::Dataset(data)) => {
                let mut pool = pool
                    .try_borrow_mut()
                    .map_err(|_| Error::internal("relative reward trainer", "the target pool is already in use"))?;
                let mut expert = self.expert_mut()?;
                let mut src = TargetSource {
                    base: &self.base,
                    expert: &mut expert,
                    data,
                    condition: self.condition,
                    target: self.settings.target,
                    eval_point: self.settings.eval_point,
                };
                pool.ensure(step, &mut src)?;
                pool.sample(rng)
            }
            _ => self.draw(rng, false)?.ok_or_else(|| Error::internal("relative reward trainer", "empty batch"))?,
        };
        alignment_step(&self.reward, &point, &t, &target, self.entry_weights.as_ref(), self.settings.rho_l2)
    }

    /// The training objective on up to [`EVAL_ITEMS`] held-out items (entry weights included,
    /// from a gradient without a graph), drawn the same way at every evaluation; None when
    /// nothing is held out.
    pub fn held_out_error(&self) -> Result<Option<f64>> {
        let mut eval_rng = Rng::new(self.settings.seed ^ 0xe7a1);
        let Some((t, target, point)) = self.draw(&mut eval_rng, true)? else { return Ok(None) };
        let (_, grad) = self.reward.grad(&point, &t)?;
        Ok(Some(alignment_error(&grad, &target, self.entry_weights.as_ref())?.double_value(&[])))
    }

    fn expert_mut(&self) -> Result<std::cell::RefMut<'_, DiffusionModel>> {
        self.expert
            .try_borrow_mut()
            .map_err(|_| Error::internal("relative reward trainer", "the expert model is already in use"))
    }

    /// (t, target, evaluation point) for a training batch, or for the held-out items.
    fn draw(&self, rng: &mut Rng, held_out: bool) -> Result<Option<(Tensor, Tensor, Tensor)>> {
        let device = device();
        let batch = self.settings.batch_size;
        match &self.pairs {
            TrainingPairs::Dataset(data) => {
                let x0 = if held_out {
                    match data.held_out(EVAL_ITEMS) {
                        Some(x) => x,
                        None => return Ok(None),
                    }
                } else {
                    data.batch(rng, batch)
                };
                let n = x0.size()[0] as usize;
                let t = rng.randint(self.base.manifest.n_timesteps as u64, n, device);
                let noise = rng.randn(&x0.size(), device);
                let mut expert = self.expert_mut()?;
                let (target, point) = noised_target_and_point(
                    &self.base,
                    &mut expert,
                    &x0,
                    &t,
                    &noise,
                    self.condition,
                    self.settings.target,
                    self.settings.eval_point,
                )?;
                Ok(Some((t, target, point)))
            }
            TrainingPairs::Chains(c) => {
                let idx: Vec<i64> = if held_out {
                    (c.train..c.t.size()[0]).take(EVAL_ITEMS).collect()
                } else {
                    (0..batch).map(|_| rng.below(c.train as u64) as i64).collect()
                };
                if idx.is_empty() {
                    return Ok(None);
                }
                let idx = upload(&Tensor::from_slice(&idx), c.t.device())?;
                Ok(Some((c.t.index_select(0, &idx), c.target.index_select(0, &idx), c.x.index_select(0, &idx))))
            }
        }
    }
}

/// How one side of Algorithm 2's chains is sampled: a conditional model through `recipe`, each
/// chain with one condition drawn from `prompts` (int64 `[k]` labels or float32 `[k, dim]`).
pub struct ChainRecipe {
    pub recipe: Recipe,
    pub prompts: Tensor,
}

/// One side (base or expert) of Algorithm 2: the model, and its recipe when it is conditional.
#[derive(Clone, Copy)]
pub struct ChainSide<'a> {
    pub model: &'a DiffusionModel,
    pub recipe: Option<&'a ChainRecipe>,
}

impl<'a> ChainSide<'a> {
    /// An unconditional model, stepped as it is.
    pub fn plain(model: &'a DiffusionModel) -> Self {
        Self { model, recipe: None }
    }

    /// The side's predictor over `k` chains whose prompts are picked by `picks` (uniforms in
    /// [0, 1), one per chain; index floor(u k') in a set of k').
    fn predictor(&self, picks: &[f64], device: tch::Device) -> Result<Predictor<'a>> {
        let Some(r) = self.recipe else { return Predictor::new(self.model, None) };
        let n = r.prompts.size()[0];
        let idx: Vec<i64> = picks.iter().map(|u| ((u * n as f64) as i64).min(n - 1)).collect();
        let prompts = r.prompts.f_index_select(0, &Tensor::from_slice(&idx))?.f_to_device(device)?;
        Predictor::new(self.model, Some((&r.recipe, &prompts)))
    }
}

/// Algorithm 2's recorded steps: at x (time t) both models stepped from the same point with
/// the same noise; target = x_{t-1}^expert - x_{t-1}^base, both standardised per step (see
/// [`chain_pairs`]). The last 5% are held out.
pub struct ChainPairs {
    x: Tensor,
    t: Tensor,
    target: Tensor,
    train: i64,
    /// Per-step standardisation tables [T, *item] by time index: `input_mean` and `input_std`
    /// map a state at time t to rho's input; `target_std` scales the targets.
    step_norm: Vec<(String, Tensor)>,
}

/// Runs `k` chains from x_T ~ N(0, I); at every step both models' next states are computed
/// from the same x_t with the same noise, and the chain follows the base model's step in the
/// first half of the chains and the expert's in the second half (the paper's Algorithm 2).
/// With recipes, each chain draws its prompt once (after x_T, one uniform per chain shared by
/// both sides), and each side's mean is its recipe's (classifier-free and safety guidance).
fn chain_pairs(base_side: ChainSide<'_>, expert_side: ChainSide<'_>, k: usize, rng: &mut Rng) -> Result<ChainPairs> {
    let _guard = tch::no_grad_guard();
    let device = device();
    let base = base_side.model;
    let mut shape = vec![k as i64];
    shape.extend(base.item_shape());
    let mut x = rng.randn(&shape, device);
    let picks: Vec<f64> = if base_side.recipe.is_some() || expert_side.recipe.is_some() {
        (0..k).map(|_| rng.uniform()).collect()
    } else {
        Vec::new()
    };
    let mut base_pred = base_side.predictor(&picks, device)?;
    let mut expert_pred = expert_side.predictor(&picks, device)?;
    let half = (k / 2) as i64;
    let (mut xs, mut ts, mut targets) = (Vec::new(), Vec::new(), Vec::new());
    // Per-step statistics of the chain states, pooled over both halves: `level_stats[t]` is
    // the state the step at time index t starts from, and the (mean, std) of the states it
    // produces is the next entry.
    let mut in_stats = Vec::new();
    let mut out_stats = Vec::new();
    for step in (0..base.n_timesteps()).rev() {
        let t = Tensor::full([k as i64], step as i64, (Kind::Int64, device));
        let mu_b = base_pred.mean(&x, &t)?;
        let mu_e = expert_pred.mean(&x, &t)?;
        let (x_b, x_e) = if step > 0 {
            let sigma = base.schedule.extract(Table::PosteriorLogVarianceClipped, &t, shape.len())?;
            let noise = rng.randn(&shape, device) * (sigma * 0.5).exp();
            (mu_b + &noise, mu_e + noise)
        } else {
            (mu_b, mu_e)
        };
        in_stats.push(step_stats(&x));
        out_stats.push(step_stats(&Tensor::cat(&[&x_b, &x_e], 0)));
        xs.push(x.shallow_clone());
        ts.push(t);
        targets.push(&x_e - &x_b);
        x = Tensor::cat(&[x_b.narrow(0, 0, half), x_e.narrow(0, half, k as i64 - half)], 0);
    }
    // Standardise per step (the authors' treatment of Stable Diffusion latents): inputs with
    // their own step's statistics, targets by the scale of the states they point between.
    // Time index t = T-1-i for the i-th recorded step. The scales are one number per step (see
    // [`step_stats`]), so that within a step grad_x rho stays parallel to x^expert - x^base.
    let mut norm_x = Vec::with_capacity(xs.len());
    let mut norm_target = Vec::with_capacity(xs.len());
    for (i, (x, target)) in xs.iter().zip(&targets).enumerate() {
        let (mean, std) = &in_stats[i];
        norm_x.push((x - mean) / std);
        norm_target.push(target / &out_stats[i].1);
    }
    // Tables indexed by time index t (the recorded order runs from T-1 down to 0).
    let input_mean = Tensor::stack(&in_stats.iter().rev().map(|(m, _)| m.shallow_clone()).collect::<Vec<_>>(), 0);
    let input_std = Tensor::stack(&in_stats.iter().rev().map(|(_, s)| s.shallow_clone()).collect::<Vec<_>>(), 0);
    let target_std = Tensor::stack(&out_stats.iter().rev().map(|(_, s)| s.shallow_clone()).collect::<Vec<_>>(), 0);
    let x = Tensor::cat(&norm_x, 0);
    let t = Tensor::cat(&ts, 0);
    let target = Tensor::cat(&norm_target, 0);
    // Shuffle once (seeded) so the held-out tail covers every t.
    let n = x.size()[0];
    let mut order: Vec<i64> = (0..n).collect();
    for i in (1..order.len()).rev() {
        order.swap(i, rng.below(i as u64 + 1) as usize);
    }
    let order = upload(&Tensor::from_slice(&order), x.device())?;
    let train = n - (n / 20).max(1);
    Ok(ChainPairs {
        x: x.index_select(0, &order),
        t: t.index_select(0, &order),
        target: target.index_select(0, &order),
        train,
        step_norm: vec![
            ("input_mean".into(), input_mean),
            ("input_std".into(), input_std),
            ("target_std".into(), target_std),
        ],
    })
}

/// A step's standardisation: the per-element mean over the batch, and one standard deviation
/// pooled over the batch and every element (deviations from that mean), broadcast to the item
/// shape; floored at 1e-6 so that a constant step standardises to 0 instead of dividing by zero.
///
/// Why one scale per step and not one per element: rho is fitted in standardised coordinates
/// z = (x - mean) / std to target / target_std, so in the state's own coordinates
/// grad_x rho = (x^expert - x^base) / (std * target_std). Per-element scales would reweight the
/// target element by element: on images, the background pixels that every model keeps nearly
/// constant have scales near 0 (the noise of the last steps, the spread of the denoised mean),
/// and their tiny, meaningless disagreements then outweighed the digit strokes by orders of
/// magnitude (Algorithm 2 on scikit-learn's digits: docs/results.md). One scale per step only
/// rescales the target per t, as the models' own noise levels do. The per-element mean is a
/// translation and leaves gradients unchanged.
fn step_stats(x: &Tensor) -> (Tensor, Tensor) {
    let mean = x.mean_dim(0, false, Kind::Float);
    let std = (x - &mean).square().mean(Kind::Float).sqrt().clamp_min(1e-6);
    let std = std.expand(mean.size(), false).contiguous();
    (mean, std)
}

#[cfg(test)]
mod tests {
    use tch::Device;

    use super::*;

    /// Elements with spreads from 1e-3 to 3 (an image's near-constant background beside its
    /// strokes) share one scale per step: the pooled root-mean-square deviation from the
    /// per-element mean, so standardised targets keep the direction of x^expert - x^base.
    #[test]
    fn step_stats_share_one_scale_over_the_elements() {
        tch::manual_seed(7);
        let n = 20_000;
        let scales = [1e-3, 0.5, 1.0, 2.0, 0.0, 3.0];
        let offsets = [-1.0, 0.0, 2.0, 0.5, -0.3, 4.0];
        let s = Tensor::from_slice(&scales).reshape([1, 2, 3]);
        let o = Tensor::from_slice(&offsets).reshape([1, 2, 3]);
        let x = (Tensor::randn([n, 2, 3], (Kind::Double, Device::Cpu)) * s + o).to_kind(Kind::Float);
        let (mean, std) = step_stats(&x);
        assert_eq!((mean.size(), std.size()), (vec![2, 3], vec![2, 3]));
        let std: Vec<f64> = Vec::try_from(std.flatten(0, -1).to_kind(Kind::Double)).expect("std");
        assert!(std.iter().all(|s| *s == std[0]), "one scale for every element: {std:?}");
        // sqrt(mean of scale^2) = sqrt(14.251 / 6), up to sampling error (~0.5%).
        let want = (scales.iter().map(|s| s * s).sum::<f64>() / 6.0).sqrt();
        assert!((std[0] - want).abs() < 0.01 * want, "pooled std {} vs {want}", std[0]);
        let mean: Vec<f64> = Vec::try_from(mean.flatten(0, -1).to_kind(Kind::Double)).expect("mean");
        for (m, o) in mean.iter().zip(offsets) {
            assert!((m - o).abs() < 0.05, "per-element mean {m} vs {o}");
        }
        // A constant step standardises to 0 rather than dividing by zero.
        let (_, std) = step_stats(&Tensor::ones([8, 2, 3], (Kind::Float, Device::Cpu)));
        assert_eq!(std.min().double_value(&[]), 1e-6_f32 as f64);
    }
}
