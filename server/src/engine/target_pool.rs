//! Amortised diffusion targets for Algorithm 1 (issue 21).
//!
//! Module map: [`AmortisedTargets`] (the job's settings, stored in its spec), [`TargetPool`]
//! (the cache of (t, target, evaluation point) triples and its refresh schedule).
//!
//! Why: an Algorithm 1 step spends almost all of its time in the two frozen diffusion models
//! (2 x 8.2 GFLOP of TemporalUnet against 0.04 GFLOP of reward net at the benchmark's size),
//! recomputed for every batch. The targets do not depend on rho, so they can be computed once
//! in large passes and each reused several times, like a replay buffer: the pool holds
//! `pool_size` triples; a training batch draws `batch_size` of them uniformly with
//! replacement; every *epoch* (`ceil(pool_size * reuse / batch_size)` steps, so that each
//! triple is drawn `reuse` times per epoch on average) the oldest `refresh_fraction` of the
//! pool is replaced by fresh draws of (x_0, t, noise). A triple therefore lives
//! `1 / refresh_fraction` epochs and is used about `reuse / refresh_fraction` times, and the
//! diffusion models run `batch_size * refresh_fraction / reuse` items per step instead of
//! `batch_size`.
//!
//! Resumable without storing the pool: the contents of the pool at any step are a function of
//! the job's seed alone. Generation 0 fills every slot; generation g >= 1 refreshes the `r`
//! slots starting at `((g - 1) r) mod P`, round robin, from its own random stream
//! (`Rng::new(mix(seed, g))`). A resumed job recomputes, for each slot, the draw of the last
//! generation that wrote it (the draws are cheap; only those slots go through the models), so a
//! restart costs one pool's worth of model passes and never reads half-written state.

use tch::{Kind, Tensor};

use super::data::TrainingData;
use super::diffusion::DiffusionModel;
use super::relative_reward::{ConditionEntries, EvalPoint, Target, noised_target_and_point};
use super::rng::Rng;
use crate::error::Result;

/// Items per pass through the frozen models when (re)filling the pool: large enough that the
/// passes run at the models' batched speed, small enough to bound their activations.
const PASS_ITEMS: usize = 1024;

/// The option's settings and their checks are the job spec's (shared schema).
pub use relreward_proto::schema::job::{AmortisedTargets, MAX_POOL_BYTES};

/// What the pool computes its targets with.
pub struct TargetSource<'a> {
    pub base: &'a DiffusionModel,
    pub expert: &'a mut DiffusionModel,
    pub data: &'a TrainingData,
    /// Entries kept clean in x_t (the job's `inpaint_condition`).
    pub condition: Option<ConditionEntries>,
    pub target: Target,
    pub eval_point: EvalPoint,
}

/// The cache of Algorithm 1 triples (see the module documentation).
pub struct TargetPool {
    settings: AmortisedTargets,
    seed: u64,
    batch: usize,
    t_max: u64,
    /// Generation the pool holds (None: not filled yet).
    generation: Option<u64>,
    t: Tensor,
    target: Tensor,
    point: Tensor,
    /// Items that went through the frozen models so far (for the job's log and the tests).
    pub computed: u64,
}

impl TargetPool {
    pub fn new(settings: AmortisedTargets, seed: u64, batch: usize, t_max: u64) -> Self {
        Self {
            settings,
            seed,
            batch,
            t_max,
            generation: None,
            t: Tensor::new(),
            target: Tensor::new(),
            point: Tensor::new(),
            computed: 0,
        }
    }

    /// The generation that training step `step` (1-based) draws from.
    pub fn generation_for_step(&self, step: u64) -> u64 {
        step.saturating_sub(1) / self.settings.steps_per_epoch(self.batch)
    }

    /// The random stream of generation `g`'s draws.
    fn stream(&self, g: u64) -> Rng {
        Rng::new(self.seed ^ 0xa3b1_7a2e_0000_0000 ^ g.wrapping_mul(0x9E37_79B9_7F4A_7C15).rotate_left(17))
    }

    /// (generation, index within that generation's draws) that last wrote `slot`, as of
    /// generation `g`.
    fn last_writer(&self, slot: usize, g: u64) -> (u64, usize) {
        let (p, r) = (self.settings.pool_size as u64, self.settings.refresh_items() as u64);
        let covered = g * r; // refresh positions 0..covered, position k at slot k mod P
        let slot = slot as u64;
        if covered <= slot {
            return (0, slot as usize);
        }
        let k = slot + p * ((covered - 1 - slot) / p);
        (k / r + 1, (k % r) as usize)
    }

    /// Makes the pool hold the generation step `step` draws from: the first call fills it
    /// (for a resumed job, with the content it had at that step), later calls apply the
    /// refreshes in between.
    pub fn ensure(&mut self, step: u64, src: &mut TargetSource) -> Result<()> {
        let g = self.generation_for_step(step);
        match self.generation {
            Some(have) if have >= g => Ok(()),
            Some(have) => {
                for next in have + 1..=g {
                    self.refresh(next, src)?;
                }
                Ok(())
            }
            None => self.fill(g, src),
        }
    }

    /// The whole pool as of generation `g`: each slot from the draw of its last writer.
    fn fill(&mut self, g: u64, src: &mut TargetSource) -> Result<()> {
        let p = self.settings.pool_size;
        let mut by_generation: std::collections::BTreeMap<u64, (Vec<i64>, Vec<i64>)> = Default::default();
        for slot in 0..p {
            let (gen_, j) = self.last_writer(slot, g);
            let entry = by_generation.entry(gen_).or_default();
            entry.0.push(j as i64);
            entry.1.push(slot as i64);
        }
        let mut parts: Vec<(Vec<i64>, Tensor, Tensor, Tensor)> = Vec::new();
        for (gen_, (js, slots)) in by_generation {
            let (t, target, point) = self.compute(gen_, Some(&js), src)?;
            parts.push((slots, t, target, point));
        }
        // Assemble in slot order.
        let (_, t0, tg0, _) = &parts[0];
        let mut shape = vec![p as i64];
        shape.extend(&tg0.size()[1..]);
        let device = tg0.device();
        let mut t = Tensor::zeros([p as i64], (t0.kind(), device));
        let mut target = Tensor::zeros(&shape, (Kind::Float, device));
        let mut point = Tensor::zeros(&shape, (Kind::Float, device));
        for (slots, tt, tg, pt) in &parts {
            let idx = crate::engine::upload(&Tensor::from_slice(slots), device)?;
            let _ = t.index_copy_(0, &idx, tt);
            let _ = target.index_copy_(0, &idx, tg);
            let _ = point.index_copy_(0, &idx, pt);
        }
        self.t = t;
        self.target = target;
        self.point = point;
        self.generation = Some(g);
        Ok(())
    }

    /// Applies refresh generation `g` (>= 1) to a filled pool.
    fn refresh(&mut self, g: u64, src: &mut TargetSource) -> Result<()> {
        let (p, r) = (self.settings.pool_size, self.settings.refresh_items());
        let start = ((g - 1) as u128 * r as u128 % p as u128) as usize;
        let slots: Vec<i64> = (0..r).map(|j| ((start + j) % p) as i64).collect();
        let (t, target, point) = self.compute(g, None, src)?;
        let idx = crate::engine::upload(&Tensor::from_slice(&slots), self.target.device())?;
        let _ = self.t.index_copy_(0, &idx, &t);
        let _ = self.target.index_copy_(0, &idx, &target);
        let _ = self.point.index_copy_(0, &idx, &point);
        self.generation = Some(g);
        Ok(())
    }

    /// Generation `g`'s draws (all of them, cheap), then targets for those at `keep` (all if
    /// None) through the frozen models in passes of [`PASS_ITEMS`].
    fn compute(&mut self, g: u64, keep: Option<&[i64]>, src: &mut TargetSource) -> Result<(Tensor, Tensor, Tensor)> {
        let n = if g == 0 { self.settings.pool_size } else { self.settings.refresh_items() };
        let mut rng = self.stream(g);
        let x0 = src.data.batch(&mut rng, n);
        let device = x0.device();
        let t = rng.randint(self.t_max, n, device);
        let noise = rng.randn(&x0.size(), device);
        let (x0, t, noise) = match keep {
            Some(js) if js.len() < n => {
                let idx = crate::engine::upload(&Tensor::from_slice(js), device)?;
                (x0.index_select(0, &idx), t.index_select(0, &idx), noise.index_select(0, &idx))
            }
            _ => (x0, t, noise),
        };
        let m = x0.size()[0];
        let (mut targets, mut points) = (Vec::new(), Vec::new());
        let mut at = 0i64;
        while at < m {
            let len = (PASS_ITEMS as i64).min(m - at);
            let (tg, pt) = noised_target_and_point(
                src.base,
                &mut *src.expert,
                &x0.narrow(0, at, len),
                &t.narrow(0, at, len),
                &noise.narrow(0, at, len),
                src.condition,
                src.target,
                src.eval_point,
            )?;
            targets.push(tg);
            points.push(pt);
            at += len;
        }
        self.computed += m as u64;
        Ok((t, Tensor::cat(&targets, 0), Tensor::cat(&points, 0)))
    }

    /// A training batch of (t, target, evaluation point), drawn uniformly with replacement
    /// with the training loop's stream.
    pub fn sample(&self, rng: &mut Rng) -> (Tensor, Tensor, Tensor) {
        let idx = rng.randint(self.settings.pool_size as u64, self.batch, self.t.device());
        (self.t.index_select(0, &idx), self.target.index_select(0, &idx), self.point.index_select(0, &idx))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn pool(p: usize, f: f64) -> TargetPool {
        TargetPool::new(AmortisedTargets { pool_size: p, reuse: 2, refresh_fraction: f }, 7, 4, 10)
    }

    /// The last writer of every slot, computed in closed form, equals a replay of the refreshes.
    #[test]
    fn last_writer_matches_a_replay_of_the_refreshes() {
        for (p, f) in [(10, 0.3), (7, 1.0), (16, 0.25), (5, 0.01), (9, 0.5)] {
            let pl = pool(p, f);
            let r = pl.settings.refresh_items();
            let mut owner: Vec<(u64, usize)> = (0..p).map(|s| (0, s)).collect();
            for g in 0..40u64 {
                if g > 0 {
                    let start = ((g - 1) as usize * r) % p;
                    for j in 0..r {
                        owner[(start + j) % p] = (g, j);
                    }
                }
                for (slot, want) in owner.iter().enumerate() {
                    assert_eq!(pl.last_writer(slot, g), *want, "P {p}, f {f}, slot {slot}, generation {g}");
                }
            }
        }
    }

    fn models(mean_e: &[f32]) -> (DiffusionModel, DiffusionModel) {
        use crate::engine::diffusion::testing::AnalyticGaussian;
        use crate::engine::manifest::{DiffusionManifest, Parametrization, ScheduleSpec, Space};
        use crate::engine::normalizer::Normalizer;
        use crate::engine::schedule::Schedule;
        let manifest = DiffusionManifest {
            parametrization: Parametrization::Epsilon,
            schedule: ScheduleSpec::Cosine { s: 0.008 },
            n_timesteps: 10,
            clip_denoised: false,
            space: Space::Sample { shape: vec![2] },
            normalizer: Normalizer::Identity,
            architecture: None,
            conditioning: None,
        };
        let s = Schedule::new(&manifest.schedule, 10).expect("schedule");
        let model = |mean: &[f32]| {
            DiffusionModel::new(manifest.clone(), Box::new(AnalyticGaussian::new(&s, mean, &[2], false)))
                .expect("model")
        };
        (model(&[0.0, 0.0]), model(mean_e))
    }

    /// A pool filled at generation g (what a resumed job does) holds exactly what a pool that
    /// went through every refresh since generation 0 holds, and only one pool's worth of items
    /// went through the models to rebuild it.
    #[test]
    fn a_resumed_pool_equals_the_pool_that_never_stopped() {
        let (base, mut expert) = models(&[1.0, -2.0]);
        let rows = Tensor::randn([300, 2], (Kind::Float, tch::Device::Cpu));
        let data =
            TrainingData::new(&rows, &crate::engine::normalizer::Normalizer::Identity, 1, None, None, 3).expect("data");
        let mut src = TargetSource {
            base: &base,
            expert: &mut expert,
            data: &data,
            condition: None,
            target: Target::Mean,
            eval_point: EvalPoint::XT,
        };
        for f in [0.3, 1.0, 0.05] {
            let settings = AmortisedTargets { pool_size: 50, reuse: 2, refresh_fraction: f };
            // batch 10: an epoch is 10 steps.
            let mut live = TargetPool::new(settings, 5, 10, 10);
            for step in 1..=137 {
                live.ensure(step, &mut src).expect("ensure");
            }
            let mut resumed = TargetPool::new(settings, 5, 10, 10);
            resumed.ensure(137, &mut src).expect("fill");
            assert_eq!(resumed.computed, 50, "f {f}");
            assert_eq!(live.generation, Some(13));
            assert_eq!(resumed.generation, live.generation);
            assert!(resumed.t.equal(&live.t), "f {f}: t differs");
            for (a, b) in [(&resumed.target, &live.target), (&resumed.point, &live.point)] {
                let diff = (a - b).abs().max().double_value(&[]);
                assert!(diff < 1e-6, "f {f}: pools differ by {diff}");
            }
            // Mean target for this pair is c_t (m_e - m_b): every row is parallel to (1, -2).
            let cross =
                (resumed.target.select(1, 0) * -2.0 - resumed.target.select(1, 1)).abs().max().double_value(&[]);
            assert!(cross < 1e-5, "targets must be parallel to the mean difference: {cross}");
            // Batches come from the pool, with the caller's stream.
            let (t, target, point) = resumed.sample(&mut Rng::new(1));
            assert_eq!((t.size(), target.size(), point.size()), (vec![10], vec![10, 2], vec![10, 2]));
        }
    }

    #[test]
    fn epochs_and_refresh_sizes() {
        let s = AmortisedTargets { pool_size: 1000, reuse: 3, refresh_fraction: 0.25 };
        assert_eq!((s.refresh_items(), s.steps_per_epoch(64)), (250, 47));
        let pl = TargetPool::new(s, 1, 64, 10);
        assert_eq!((pl.generation_for_step(1), pl.generation_for_step(47), pl.generation_for_step(48)), (0, 0, 1));
        assert!(AmortisedTargets { refresh_fraction: 0.0, ..s }.validate().is_err());
        assert!(AmortisedTargets { reuse: 0, ..s }.validate().unwrap_err().to_string().contains("reuse"));
        assert!(AmortisedTargets { pool_size: 1 << 22, ..s }.check_memory(1024).is_err());
        assert!(AmortisedTargets::DEFAULT.validate().is_ok());
    }
}
