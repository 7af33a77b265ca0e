//! A merged pass split by rows across the serving thread and helper threads
//! (`serving.pass_threads`, `serving.split_above_ms`), and the outputs of a pass either way.
//!
//! Module map: [`Outputs`] (what one pass computes, for any thread's handle on the model, and
//! the parts joined in row order), [`Split`] (whether and how a pass is split: its rows in
//! equal parts, one per free inference slot), [`Helpers`] (a serving thread's helper threads,
//! each with its own [`RewardModel::replica`]).
//!
//! Why by rows and not by libtorch's intra-op threads: one fork and join per pass instead of one
//! per operation, none of them spinning at an OpenMP barrier for a core the gRPC threads hold.
//! Why replicas: tch's tensor handles are not `Sync`; libtorch reads one tensor's storage from
//! several threads safely, so each thread gets its own handles on the same storage.

use std::sync::{Arc, mpsc};
use std::time::Duration;

use tch::Tensor;
use tokio::sync::OwnedSemaphorePermit;

use super::Inner;
use super::query::BatchKind;
use crate::engine::reward_model::RewardModel;
use crate::error::{Error, Result};
use crate::registry::SharedReward;

/// What one pass computes: rho, and what the batch's kind asks for beside it.
pub(super) struct Outputs {
    pub(super) rho: Tensor,
    pub(super) windows: Option<Tensor>,
    pub(super) steps: Option<Tensor>,
    pub(super) grad: Option<Tensor>,
}

impl Outputs {
    /// The pass of `kind` over rows `x`, `t` of one model (any thread's handle on it).
    fn of(model: &RewardModel, kind: BatchKind, x: &Tensor, t: &Tensor) -> Result<Self> {
        match kind {
            BatchKind::Score { per_window, per_step } => {
                let _no_grad = tch::no_grad_guard();
                // With per-window values, rho comes from the same pass (one network evaluation,
                // not two: half the cost of a Score that asks for both, as an RL wrapper's
                // every step).
                let (rho, windows) = if per_window {
                    let (rho, windows) = model.rho_and_windows(x, t)?;
                    (rho, Some(windows))
                } else {
                    (model.rho(x, t)?, None)
                };
                let steps = if per_step { Some(model.per_step(x, t)?) } else { None };
                Ok(Self { rho, windows, steps, grad: None })
            }
            BatchKind::Gradient => {
                let (rho, grad) = model.grad(x, t)?;
                Ok(Self { rho, windows: None, steps: None, grad: Some(grad) })
            }
        }
    }

    /// The parts' outputs joined in row order.
    fn join(parts: Vec<Self>) -> Result<Self> {
        let cat = |pick: fn(&Self) -> Option<&Tensor>| -> Result<Option<Tensor>> {
            let tensors: Option<Vec<&Tensor>> = parts.iter().map(pick).collect();
            Ok(match tensors {
                Some(ts) if !ts.is_empty() => Some(Tensor::f_cat(&ts, 0)?),
                _ => None,
            })
        };
        Ok(Self {
            rho: cat(|o| Some(&o.rho))?
                .ok_or_else(|| Error::internal("serving batch", "a split pass without parts"))?,
            windows: cat(|o| o.windows.as_ref())?,
            steps: cat(|o| o.steps.as_ref())?,
            grad: cat(|o| o.grad.as_ref())?,
        })
    }
}

/// Fewest rows a split pass gives one thread: below this the fixed cost of a pass (the
/// network's operations, oneDNN's per-call setup) outweighs the rows' share.
const MIN_PART_ROWS: i64 = 8;

/// How one pass is computed: on the serving thread alone, or with its rows split across it and
/// its helpers (`serving.pass_threads`, `serving.split_above_ms`), one part per free
/// inference slot. Rows are independent (the batcher's padding relies on it too), so the joined
/// parts are the whole pass's values (up to oneDNN's choice of kernel for the parts' batch
/// size, as for any batch size).
pub(super) struct Split<'a> {
    pub(super) inner: &'a Inner,
    pub(super) helpers: &'a mut Helpers,
    /// The model's last pass's compute per item on one thread (zero before the first).
    pub(super) cost_per_item: Duration,
}

impl Split<'_> {
    pub(super) fn evaluate(
        mut self,
        model: &SharedReward,
        kind: BatchKind,
        x: &Tensor,
        t: &Tensor,
    ) -> Result<(Outputs, usize)> {
        let rows = x.size()[0];
        let Some(slots) = self.extra_slots(model, rows) else {
            return Ok((Outputs::of(&model.lock(), kind, x, t)?, 1));
        };
        let parts = slots.len() + 1;
        let (base, rest) = (rows / parts as i64, rows % parts as i64);
        let lens: Vec<i64> = (0..parts as i64).map(|i| base + i64::from(i < rest)).collect();
        let mut replies = Vec::with_capacity(parts - 1);
        let mut at = lens[0];
        for (helper, &len) in self.helpers.threads.iter().zip(&lens[1..]) {
            let (reply, answer) = mpsc::sync_channel(1);
            let job = Job { kind, x: x.f_narrow(0, at, len)?, t: t.f_narrow(0, at, len)?, reply };
            let sent = helper.jobs.as_ref().is_some_and(|jobs| jobs.send(job).is_ok());
            replies.push(sent.then_some(answer));
            at += len;
        }
        let first = Outputs::of(&model.lock(), kind, &x.f_narrow(0, 0, lens[0])?, &t.f_narrow(0, 0, lens[0])?);
        // Every helper's answer is awaited (even after a failure here), so none is still busy
        // when the next pass starts.
        let others: Vec<Option<Result<Outputs>>> =
            replies.into_iter().map(|answer| answer.and_then(|a| a.recv().ok())).collect();
        drop(slots);
        let mut outputs = vec![first?];
        for other in others {
            match other {
                Some(result) => outputs.push(result?),
                None => {
                    // A helper thread is gone (it cannot be while it holds its receiver,
                    // short of a panic): start afresh next time.
                    self.helpers.threads.clear();
                    return Err(Error::internal("serving batch", "a helper thread of a split pass stopped"));
                }
            }
        }
        Ok((Outputs::join(outputs)?, parts))
    }

    /// The inference slots taken for the other parts of a split pass, or `None` to compute it
    /// whole: one thread configured, a CPU pass expected to be short, too few rows, no helper
    /// thread to be had, or no slot free.
    fn extra_slots(&mut self, model: &SharedReward, rows: i64) -> Option<Vec<OwnedSemaphorePermit>> {
        let config = &self.inner.config;
        let expected = self.cost_per_item.saturating_mul(u32::try_from(rows).unwrap_or(u32::MAX));
        if config.pass_threads < 2
            || rows < 2 * MIN_PART_ROWS
            || expected.as_secs_f64() * 1e3 < config.split_above_ms.max(f64::MIN_POSITIVE)
            || crate::engine::device() != tch::Device::Cpu
        {
            return None;
        }
        let want = (config.pass_threads - 1).min((rows / MIN_PART_ROWS) as usize - 1);
        let helpers = self.helpers.ensure(want, model);
        let mut slots = Vec::with_capacity(helpers);
        while slots.len() < helpers {
            match Arc::clone(&self.inner.slots).try_acquire_owned() {
                Ok(slot) => slots.push(slot),
                Err(_) => break,
            }
        }
        (!slots.is_empty()).then_some(slots)
    }
}

/// A serving thread's helper threads for split passes, started on the first pass worth
/// splitting and stopped (joined) with the serving thread. Each evaluates its own handle on the
/// model ([`RewardModel::replica`]: the same weight storage).
#[derive(Default)]
pub(super) struct Helpers {
    threads: Vec<Helper>,
    /// A helper could not be started (its replica or its thread).
    unsplittable: bool,
}

struct Helper {
    jobs: Option<mpsc::Sender<Job>>,
    thread: Option<std::thread::JoinHandle<()>>,
}

/// One part of a split pass.
struct Job {
    kind: BatchKind,
    x: Tensor,
    t: Tensor,
    reply: mpsc::SyncSender<Result<Outputs>>,
}

impl Helpers {
    /// Starts helpers until there are `want` (or none can be); returns how many there are.
    fn ensure(&mut self, want: usize, model: &SharedReward) -> usize {
        while self.threads.len() < want && !self.unsplittable {
            match self.start(model) {
                Ok(helper) => self.threads.push(helper),
                Err(e) => {
                    tracing::warn!(model = model.name, error = %e, "passes will not be split: no helper thread");
                    self.unsplittable = true;
                }
            }
        }
        self.threads.len().min(want)
    }

    fn start(&self, served: &SharedReward) -> Result<Helper> {
        let model = served.lock().replica()?;
        let (jobs, inbox) = mpsc::channel::<Job>();
        let thread = std::thread::Builder::new()
            .name(format!("serve+{}-{}", self.threads.len() + 1, served.name))
            .spawn(move || {
                for job in inbox {
                    let _ = job.reply.send(Outputs::of(&model, job.kind, &job.x, &job.t));
                }
            })
            .map_err(|e| Error::internal("starting a serving helper thread", e))?;
        Ok(Helper { jobs: Some(jobs), thread: Some(thread) })
    }
}

impl Drop for Helper {
    fn drop(&mut self) {
        // Closing the channel ends the helper's loop.
        drop(self.jobs.take());
        if let Some(thread) = self.thread.take() {
            let _ = thread.join();
        }
    }
}
