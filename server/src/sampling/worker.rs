//! The sampling workers: named threads (`sample-N`) that take queued runs in arrival order and
//! compute them, one at a time each, under an inference slot.
//!
//! A run samples in batches of `batch` with the engine's [`GuidedSampler`] (DDPM, or DDIM when
//! the request asked) under the model's
//! lock, on the engine's device, its noise from its own seeded [`Rng`] (so a seed fixes the
//! samples). Each batch is checked finite (in normalized and in raw units), copied to the
//! host once, and sent as rows; the worker waits for the client to read (backpressure), and
//! stops at the next denoising step when the client went away or the `sampling` group's token
//! was cancelled (shutdown). [`Run`]'s drop ends a stream that did not finish with an error,
//! so a run dropped anywhere (still queued at shutdown, or a panic) never looks complete.

use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};

use futures::executor::block_on;
use tch::{Kind, Tensor};
use tokio::sync::{Mutex, OwnedSemaphorePermit, Semaphore, mpsc};
use tokio_util::sync::CancellationToken;

use super::{Plan, SampleRow, stopping};
use crate::engine::normalizer::Normalize;
use crate::engine::rng::Rng;
use crate::engine::sampling::{Condition, Guidance, GuidedSampler, RewardFn, Step};
use crate::error::{Error, Result};
use crate::registry::{ServedReward, SharedDiffusion, SharedReward};
use crate::tasks::Tasks;

/// One queued Sample request: its models, its validated plan and where its rows go.
pub(super) struct Run {
    model: SharedDiffusion,
    reward: Option<SharedReward>,
    plan: Plan,
    rows: mpsc::Sender<Result<SampleRow>>,
    /// Set once the stream's end (its last row, or its error) is decided.
    ended: bool,
}

impl Run {
    pub(super) fn new(
        model: SharedDiffusion,
        reward: Option<SharedReward>,
        plan: Plan,
        rows: mpsc::Sender<Result<SampleRow>>,
    ) -> Self {
        Self { model, reward, plan, rows, ended: false }
    }
}

impl Drop for Run {
    fn drop(&mut self) {
        if !self.ended {
            // Nothing was sent yet for a queued run, so there is room; a run cut off while
            // its client had stopped reading loses this, as it loses its connection.
            let _ = self.rows.try_send(Err(Error::Unavailable(
                "the sampling run stopped before it finished (the server is shutting down)".into(),
            )));
        }
    }
}

/// Starts `workers` threads in `tasks` taking runs from `runs`.
pub(super) fn start(workers: usize, runs: mpsc::Receiver<Run>, slots: Arc<Semaphore>, tasks: &Tasks) {
    let runs = Arc::new(Mutex::new(runs));
    for i in 0..workers {
        let (runs, slots, token, tracked) =
            (Arc::clone(&runs), Arc::clone(&slots), tasks.token().clone(), tasks.enlist());
        let spawned = std::thread::Builder::new().name(format!("sample-{i}")).spawn(move || {
            let _tracked = tracked;
            work(&runs, &slots, &token);
        });
        if let Err(e) = spawned {
            // Fewer workers still serve; none at all leaves runs queued until the queue is full.
            tracing::error!(error = %e, worker = i, "cannot start a sampling worker");
        }
    }
}

/// One worker's loop, until the token is cancelled; then the runs still queued are answered.
fn work(runs: &Mutex<mpsc::Receiver<Run>>, slots: &Arc<Semaphore>, token: &CancellationToken) {
    while let Some(mut run) = block_on(next_run(runs, token)) {
        if run.rows.is_closed() {
            // The caller went away while the run waited.
            run.ended = true;
            continue;
        }
        let Some(_slot) = block_on(slot(slots, token)) else {
            run.end(Err(stopping()), token);
            break;
        };
        run.execute(token);
    }
    // Stopping: refuse new runs, and end those still queued (their drop says why).
    let mut queue = block_on(runs.lock());
    queue.close();
    while queue.try_recv().is_ok() {}
}

async fn next_run(runs: &Mutex<mpsc::Receiver<Run>>, token: &CancellationToken) -> Option<Run> {
    let mut queue = tokio::select! {
        biased;
        () = token.cancelled() => return None,
        queue = runs.lock() => queue,
    };
    tokio::select! {
        biased;
        () = token.cancelled() => None,
        run = queue.recv() => run,
    }
}

async fn slot(slots: &Arc<Semaphore>, token: &CancellationToken) -> Option<OwnedSemaphorePermit> {
    tokio::select! {
        biased;
        () = token.cancelled() => None,
        permit = Arc::clone(slots).acquire_owned() => permit.ok(),
    }
}

/// A reward model used for guidance: locked for each pass only (a guided step's forward and
/// backward, as one Gradient query is), so that a long sampling run does not hold off the
/// model's Score/Gradient queries.
struct PerCall<'a>(&'a ServedReward);

impl RewardFn for PerCall<'_> {
    fn rho(&self, x: &Tensor, t: &Tensor) -> Result<Tensor> {
        self.0.lock().rho(x, t)
    }

    fn rho_and_grad(&self, x: &Tensor, t: &Tensor) -> Result<(Tensor, Tensor)> {
        RewardFn::rho_and_grad(&*self.0.lock(), x, t)
    }
}

impl Run {
    /// Computes the run and ends its stream: after its last row, with its error, or with
    /// nothing when its client went away.
    fn execute(&mut self, token: &CancellationToken) {
        let gone = AtomicBool::new(false);
        let result = self.sample_all(token, &gone);
        match result {
            Ok(()) => self.ended = true,
            Err(_) if gone.load(Ordering::Relaxed) => self.ended = true,
            Err(e) => self.end(Err(e), token),
        }
    }

    /// Sends the stream's last item, waiting for the client to make room unless the server
    /// is stopping (then it is sent only if there is room).
    fn end(&mut self, last: Result<SampleRow>, token: &CancellationToken) {
        self.ended = true;
        if token.is_cancelled() {
            let _ = self.rows.try_send(last);
        } else {
            let _ = self.rows.blocking_send(last);
        }
    }

    /// Sends one row, waiting for the client to read; false when the client went away.
    fn send(&self, row: SampleRow, token: &CancellationToken) -> Result<bool> {
        block_on(async {
            tokio::select! {
                biased;
                () = token.cancelled() => Err(stopping()),
                sent = self.rows.send(Ok(row)) => Ok(sent.is_ok()),
            }
        })
    }

    fn sample_all(&self, token: &CancellationToken, gone: &AtomicBool) -> Result<()> {
        let plan = &self.plan;
        let model = self.model.lock();
        let _no_grad = tch::no_grad_guard();
        let conditions: Vec<Condition> = plan
            .conditions
            .iter()
            .map(|(index, v)| Condition { index: *index, state: Tensor::from_slice(v) })
            .collect();
        let per_call = self.reward.as_deref().map(PerCall);
        let recipe = plan.recipe.as_ref().map(|r| r.recipe());
        if let Some(r) = &recipe {
            r.validate(&model, "recipe")?;
        }
        let mut sampler = GuidedSampler::new(&model).on_device(crate::engine::device()).with_conditions(conditions);
        if let Some(r) = &recipe {
            sampler = sampler.with_recipe(r);
        }
        if let Some(d) = plan.ddim {
            sampler = sampler.with_ddim(d);
        }
        if let Some(r) = &per_call {
            sampler = sampler.with_guidance(Guidance {
                reward: r,
                omega: plan.omega,
                n_guide_steps: plan.n_guide_steps,
                t_stopgrad: plan.t_stopgrad,
                scale_grad_by_std: plan.scale_grad_by_std,
            });
        }
        let mut rng = Rng::new(plan.seed);
        let space = &self.model.manifest.space;
        let normalizer = &self.model.manifest.normalizer;
        let item_dims = space.normalizer_dims();
        let per_item = (space.item_shape().iter().product::<i64>() as usize).max(1);
        let mut done = 0usize;
        while done < plan.n {
            let b = plan.batch.min(plan.n - done);
            let rows = &self.rows;
            let mut stop_if_gone = |_: &Step<'_>| -> Result<()> {
                if rows.is_closed() {
                    gone.store(true, Ordering::Relaxed);
                    return Err(Error::Unavailable("client went away".into()));
                }
                if token.is_cancelled() {
                    return Err(stopping());
                }
                Ok(())
            };
            let prompts = plan.recipe.as_ref().map(|r| r.prompts(done, b));
            let sampled = sampler.sample_prompted(b, prompts.as_ref(), &mut rng, &mut stop_if_gone)?;
            if !bool::try_from(sampled.x.f_isfinite()?.f_all()?).unwrap_or(false) {
                // Refused rather than sent as Inf or NaN. With guidance acting, omega is the
                // likely cause; without it, the model itself diverged.
                return Err(if per_call.is_some() && plan.omega != 0.0 {
                    Error::invalid(format!(
                        "omega: the samples of batch {} are not finite with omega = {}; lower omega or n_guide_steps",
                        done / plan.batch,
                        plan.omega
                    ))
                } else {
                    Error::FailedPrecondition(format!(
                        "model '{}': its unguided samples of batch {} are not finite (the model's outputs overflow or are NaN at these inputs)",
                        plan.model,
                        done / plan.batch
                    ))
                });
            }
            let rewards = match &per_call {
                Some(r) => {
                    let t0 = Tensor::zeros([b as i64], (Kind::Int64, sampled.x.device()));
                    Some(
                        Vec::<f64>::try_from(
                            &r.rho(&sampled.x, &t0)?.to_kind(Kind::Double).to_device(tch::Device::Cpu),
                        )
                        .map_err(|e| Error::internal("reading rewards", e))?,
                    )
                }
                None => None,
            };
            // One copy of the batch to the host (a no-op on the CPU), then per-item rows.
            let x_host = sampled.x.to_device(tch::Device::Cpu);
            let raw = normalizer.unnormalize(&x_host, item_dims);
            if !bool::try_from(raw.f_isfinite()?.f_all()?).unwrap_or(false) {
                return Err(Error::FailedPrecondition(format!(
                    "model '{}': the samples of batch {} overflow float32 in raw units (the normalizer's scale is too large for them)",
                    plan.model,
                    done / plan.batch
                )));
            }
            let (raw, normalized) = (host_f32(&raw)?, host_f32(&x_host)?);
            for (i, (x, x_normalized)) in raw.chunks(per_item).zip(normalized.chunks(per_item)).enumerate() {
                let row = SampleRow {
                    index: (done + i) as u32,
                    x: x.to_vec(),
                    x_normalized: x_normalized.to_vec(),
                    reward: rewards.as_ref().map(|r| r[i]),
                    prompt: plan.recipe.as_ref().map(|r| r.prompt(done + i)),
                };
                if !self.send(row, token)? {
                    gone.store(true, Ordering::Relaxed);
                    return Ok(());
                }
            }
            done += b;
        }
        Ok(())
    }
}

/// All values of a host tensor as float32, row-major (one copy).
fn host_f32(t: &Tensor) -> Result<Vec<f32>> {
    let flat = t.f_to_kind(Kind::Float)?.f_contiguous()?;
    let numel = flat.numel();
    let mut values = vec![0f32; numel];
    flat.f_copy_data(&mut values, numel).map_err(|e| Error::internal("reading a sampled batch", e))?;
    Ok(values)
}

#[cfg(test)]
mod tests {
    use tch::Device;

    use super::*;
    use crate::engine::manifest::Space;
    use crate::engine::nets::{RewardArchitecture, RewardNet};
    use crate::engine::normalizer::Normalizer;
    use crate::engine::relative_reward::RewardManifest;
    use crate::engine::reward_model::RewardModel;

    /// A served run's guidance takes the native reward's own gradient (Gradient's, bit for
    /// bit), not autograd through its rho.
    #[test]
    fn guidance_takes_the_served_rewards_own_gradient() {
        for architecture in [
            RewardArchitecture::WindowedMlp { window: 2, hidden: vec![16] },
            RewardArchitecture::ValueFunction { widths: vec![32] },
        ] {
            let dir = tempfile::tempdir().expect("tmp");
            let path = dir.path().join("w.safetensors");
            RewardNet::new(&architecture, &[8, 3], 0, Device::Cpu).expect("net").save(&path).expect("save");
            let space = Space::Trajectory { horizon: 8, action_dim: 1, obs_dim: 2 };
            let manifest = RewardManifest::for_tests(architecture.clone(), space, Normalizer::Identity, 10);
            let model = RewardModel::load(manifest, &path, dir.path(), Device::Cpu).expect("load");
            let served = ServedReward::for_tests(model);
            let x = Tensor::randn([6, 8, 3], (Kind::Float, Device::Cpu));
            let t = Tensor::arange(6, (Kind::Int64, Device::Cpu));
            let (rho, grad) = PerCall(&served).rho_and_grad(&x, &t).expect("guidance");
            let (want_rho, want_grad) = served.lock().grad(&x, &t).expect("gradient");
            assert!(rho.equal(&want_rho) && grad.equal(&want_grad), "{architecture}");
        }
    }
}
