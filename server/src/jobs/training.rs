//! The optimisation loop every training job shares: Adam with optional clipping, EMA weights,
//! held-out evaluation, progress events, checkpoints (and resuming from them), stopping at
//! the next step on cancel or shutdown, and writing the final EMA weights. A runner supplies
//! only its loss and its evaluation.

use std::collections::HashMap;
use std::path::Path;

use serde::{Deserialize, Serialize};
use sha2::{Digest, Sha256};
use tch::{Kind, Tensor};

use super::context::{JobContext, StepReport, Stop};
use crate::engine::optim::{Adam, Ema, StepLoss, named_parameters};
use crate::engine::rng::Rng;
use crate::engine::step_checks_on_device;
use crate::error::{Error, Result};
use relreward_proto::schema::job::Optimization;

/// What a checkpoint's `state.json` holds besides the tensors.
#[derive(Serialize, Deserialize)]
struct TrainState {
    step: u64,
    rng: Rng,
    adam_steps: u64,
    loss: f64,
}

/// Non-finite steps in a row (each skipped, weights untouched) after which a job has diverged.
const MAX_NON_FINITE_STEPS: u32 = 10;

/// Steps checked on the device whose figures may wait unread (each a pair of 0-dim tensors).
const MAX_UNREAD_STEPS: usize = 100;

/// A step whose loss and gradient norm are queued but not read yet (0-dim tensors).
struct Queued {
    step: u64,
    loss: Tensor,
    grad_norm: Tensor,
}

pub struct TrainLoop {
    opt: Optimization,
    /// Adam decides each step's skip and clip on the device, and the steps' figures are read
    /// together where something looks at them (`engine.step_checks`; see [`TrainLoop::run`]).
    on_device: bool,
    /// Every variable of the network (parameters and buffers), sharing storage with it.
    vars: HashMap<String, Tensor>,
    params: Vec<(String, Tensor)>,
    adam: Adam,
    ema: Ema,
    pub rng: Rng,
    pub step: u64,
    pub loss: f64,
    pub eval_loss: Option<f64>,
}

impl TrainLoop {
    pub fn new(vs: &tch::nn::VarStore, opt: &Optimization, seed: u64) -> Self {
        let params = named_parameters(vs);
        let on_device = step_checks_on_device(vs.device());
        // Adam rebinds the parameters to views of one flat tensor; the EMA averages that.
        let adam = Adam::new(&params, opt.learning_rate).deciding_on_device(on_device);
        let ema = Ema::new(&params, opt.ema_decay, opt.ema_every, opt.ema_start, adam.flat_params(&params));
        Self {
            opt: opt.clone(),
            on_device,
            vars: vs.variables(),
            adam,
            ema,
            params,
            rng: Rng::new(seed),
            step: 0,
            loss: f64::NAN,
            eval_loss: None,
        }
    }

    /// Restores the job's newest intact checkpoint, if it has one; returns the step resumed
    /// at. Each checkpoint's files are checked against their digests first (once, here); a
    /// corrupt latest checkpoint falls back to the previous one, and a job whose every
    /// checkpoint is corrupt fails with `DataLoss` rather than silently starting over.
    /// On a fresh start, a job whose EMA would never begin (`ema_start` at or past `steps`)
    /// logs that its registered weights will be the last step's: the default `ema_start`
    /// (2000, Diffuser's) silently disables averaging for shorter jobs, and on small models the
    /// last Adam iterate's noise can swamp what the weights are used for (issue 20's DDPMs).
    pub fn resume(&mut self, ctx: &mut JobContext) -> Result<Option<u64>> {
        let Some((ckpt_step, dir)) = ctx.intact_checkpoint()? else {
            if let Some(note) = ema_note(&self.opt) {
                ctx.log(note)?;
            }
            return Ok(None);
        };
        self.restore(&dir, ckpt_step)?;
        ctx.log(format!("resumed from the checkpoint at step {}", self.step))?;
        Ok(Some(self.step))
    }

    /// Loads one checkpoint directory into the network, the optimiser and the loop state.
    fn restore(&mut self, dir: &Path, ckpt_step: u64) -> Result<()> {
        let stored: HashMap<String, Tensor> = Tensor::read_safetensors(dir.join("weights.safetensors"))
            .map_err(|e| Error::DataLoss(format!("checkpoint weights unreadable: {e}")))?
            .into_iter()
            .collect();
        tch::no_grad(|| -> Result<()> {
            for (name, var) in &self.vars {
                let t = stored
                    .get(name)
                    .filter(|t| t.size() == var.size())
                    .ok_or_else(|| Error::DataLoss(format!("checkpoint lacks {name} of shape {:?}", var.size())))?;
                var.shallow_clone().copy_(t);
            }
            Ok(())
        })?;
        self.adam.load(&self.params, &dir.join("adam.safetensors"))?;
        self.ema.load(&self.params, &dir.join("ema.safetensors"))?;
        let state: TrainState = serde_json::from_slice(&std::fs::read(dir.join("state.json"))?)
            .map_err(|e| Error::DataLoss(format!("checkpoint state unreadable: {e}")))?;
        if state.step != ckpt_step {
            return Err(Error::DataLoss(format!(
                "checkpoint says step {} but was recorded at {ckpt_step}",
                state.step
            )));
        }
        self.step = state.step;
        self.rng = state.rng;
        self.adam.set_steps(state.adam_steps);
        self.loss = state.loss;
        Ok(())
    }

    /// Runs to `opt.steps`. `loss_fn` draws a batch with the loop's RNG and returns the
    /// differentiable loss; `eval_fn` returns the held-out loss (None: nothing held out).
    ///
    /// With the steps checked on the device, the steps' losses and norms are left on the device
    /// and read together (one copy, the one wait for the device) where something looks at
    /// them: a step that reports progress, evaluates or checkpoints, the last step, a stop, or
    /// [`MAX_UNREAD_STEPS`] of them. Each is then acted on in order, as on the host: the same
    /// events, written later.
    pub fn run<L: Into<StepLoss>>(
        &mut self,
        ctx: &mut JobContext,
        mut loss_fn: impl FnMut(&mut Rng) -> Result<L>,
        mut eval_fn: impl FnMut() -> Result<Option<f64>>,
    ) -> std::result::Result<(), Stop> {
        let mut last_checkpoint = self.step;
        // Steps in a row whose loss or gradient was not finite (skipped by Adam::step).
        let mut non_finite = 0u32;
        let mut unread: Vec<Queued> = Vec::new();
        while self.step < self.opt.steps {
            if let Err(stop) = ctx.check_stop() {
                self.read(ctx, std::mem::take(&mut unread), &mut non_finite, &mut eval_fn)?;
                // A shutdown keeps the job RUNNING: checkpoint first so the restart loses nothing.
                if matches!(stop, Stop::Interrupted) && self.step > last_checkpoint {
                    self.checkpoint(ctx)?;
                }
                return Err(stop);
            }
            self.step += 1;
            let step_loss = match loss_fn(&mut self.rng) {
                Ok(step_loss) => step_loss,
                Err(e) => {
                    // The steps before it are acted on first, as the host's checks would have.
                    self.read(ctx, std::mem::take(&mut unread), &mut non_finite, &mut eval_fn)?;
                    return Err(e.into());
                }
            };
            let (loss, grad_norm) = match step_loss.into() {
                StepLoss::Graph(loss) => {
                    loss.backward();
                    let norm = self.adam.step(&self.params, self.opt.grad_clip);
                    (loss.detach(), norm)
                }
                StepLoss::Computed { loss, grads } => {
                    let norm = self.adam.step_with(&self.params, grads, self.opt.grad_clip);
                    (loss, norm)
                }
            };
            if self.on_device {
                // What `read` decides on the host: a step counts if its loss and gradient are finite.
                let counts = grad_norm.isfinite().logical_and(&loss.isfinite());
                self.ema.after_step(&self.params, self.step, Some(&counts));
            }
            unread.push(Queued { step: self.step, loss, grad_norm });
            let checkpoint_due = self.step.is_multiple_of(self.opt.checkpoint_every) && self.step < self.opt.steps;
            let looked_at = checkpoint_due || self.eval_due(self.step) || ctx.reports_at(self.step);
            if !self.on_device || looked_at || unread.len() >= MAX_UNREAD_STEPS {
                self.read(ctx, std::mem::take(&mut unread), &mut non_finite, &mut eval_fn)?;
            }
            // A skipped step still reaches its checkpoint: the schedule is by step number.
            if checkpoint_due {
                self.checkpoint(ctx)?;
                last_checkpoint = self.step;
            }
        }
        Ok(())
    }

    /// Reads queued steps' losses and gradient norms (in one copy) and acts on each in order.
    fn read(
        &mut self,
        ctx: &mut JobContext,
        queued: Vec<Queued>,
        non_finite: &mut u32,
        eval_fn: &mut impl FnMut() -> Result<Option<f64>>,
    ) -> std::result::Result<(), Stop> {
        let figures: Vec<f64> = match queued.as_slice() {
            [] => return Ok(()),
            [one] => vec![one.loss.f_double_value(&[])?, one.grad_norm.f_double_value(&[])?],
            many => {
                let mut all = Vec::with_capacity(2 * many.len());
                for q in many {
                    let device = q.grad_norm.device();
                    all.push(q.loss.f_to_kind(Kind::Double)?.f_reshape([1])?.f_to_device(device)?);
                    all.push(q.grad_norm.f_reshape([1])?);
                }
                Vec::<f64>::try_from(Tensor::f_cat(&all, 0)?.f_to_device(tch::Device::Cpu)?)?
            }
        };
        for (q, pair) in queued.iter().zip(figures.chunks_exact(2)) {
            self.act_on(ctx, q.step, pair[0], pair[1], non_finite, eval_fn)?;
        }
        Ok(())
    }

    /// Whether step `step` is followed by an evaluation (if it applies).
    fn eval_due(&self, step: u64) -> bool {
        step.is_multiple_of(self.opt.eval_every) || step == self.opt.steps
    }

    /// Acts on a step's loss and gradient norm: progress, the EMA (when decided on the host),
    /// the evaluation, or the count of non-finite steps.
    ///
    /// Adam applies nothing when the gradient is not finite (as a non-finite loss makes it), so
    /// one bad batch (an inf in a double backward) costs one step, not the job; a run of them
    /// is a divergence, and fails the job before anything after its last checkpoint is kept.
    fn act_on(
        &mut self,
        ctx: &mut JobContext,
        step: u64,
        loss: f64,
        grad_norm: f64,
        non_finite: &mut u32,
        eval_fn: &mut impl FnMut() -> Result<Option<f64>>,
    ) -> std::result::Result<(), Stop> {
        if !(loss.is_finite() && grad_norm.is_finite()) {
            *non_finite += 1;
            if *non_finite >= MAX_NON_FINITE_STEPS {
                return Err(Stop::Failed(Error::FailedPrecondition(format!(
                    "training diverged at step {step} ({non_finite} steps in a row with loss {loss} or gradient norm \
                     {grad_norm} not finite); lower spec.optimization.learning_rate or set grad_clip"
                ))));
            }
            // Adam skipped the update only if the gradient was not finite.
            let update = if grad_norm.is_finite() { "update applied" } else { "update skipped" };
            ctx.log(format!("step {step}: loss {loss}, gradient norm {grad_norm}: not finite, {update}"))?;
            return Ok(());
        }
        *non_finite = 0;
        if !self.on_device {
            self.ema.after_step(&self.params, step, None);
        }
        self.loss = loss;
        let eval_loss = if self.eval_due(step) { eval_fn()? } else { None };
        if eval_loss.is_some() {
            self.eval_loss = eval_loss;
        }
        ctx.progress(StepReport { step, loss, grad_norm, learning_rate: self.opt.learning_rate, eval_loss })?;
        Ok(())
    }

    /// Writes a checkpoint: weights, EMA weights, Adam moments, and the step, RNG state and
    /// loss (`state.json`).
    fn checkpoint(&self, ctx: &mut JobContext) -> Result<()> {
        let state = TrainState { step: self.step, rng: self.rng, adam_steps: self.adam.steps(), loss: self.loss };
        let current: Vec<(String, Tensor)> = self.vars.iter().map(|(k, v)| (k.clone(), v.shallow_clone())).collect();
        ctx.checkpoint(self.step, |d| {
            write_weights(&current, &d.join("weights.safetensors"))?;
            write_weights(&self.ema.named(&self.params), &d.join("ema.safetensors"))?;
            self.adam.save(&self.params, &d.join("adam.safetensors"))?;
            let json = serde_json::to_vec(&state).map_err(|e| Error::internal("encoding state", e))?;
            std::fs::write(d.join("state.json"), json)?;
            Ok(())
        })
    }

    /// Copies the EMA weights into the network (what the registered model carries, as
    /// Diffuser samples with its EMA model).
    pub fn use_ema_weights(&self) {
        let _guard = tch::no_grad_guard();
        for (name, averaged) in self.ema.named(&self.params) {
            if let Some(var) = self.vars.get(&name) {
                var.shallow_clone().copy_(&averaged);
            }
        }
    }

    /// Writes every variable to `path` (safetensors) and returns its sha256 and size.
    pub fn write_final(&self, path: &Path) -> Result<(String, u64)> {
        let mut all: Vec<(String, Tensor)> = self.vars.iter().map(|(k, v)| (k.clone(), v.shallow_clone())).collect();
        all.sort_by(|a, b| a.0.cmp(&b.0));
        write_weights(&all, path)?;
        let bytes = std::fs::read(path)?;
        Ok((hex::encode(Sha256::digest(&bytes)), bytes.len() as u64))
    }
}

/// Writes from the CPU, so weights and checkpoints are the same files whatever device trained
/// them (read back, they load to the CPU and are copied onto the job's device).
fn write_weights(named: &[(String, Tensor)], path: &Path) -> Result<()> {
    let named: Vec<(&String, Tensor)> = named.iter().map(|(n, t)| (n, t.to_device(tch::Device::Cpu))).collect();
    Tensor::write_safetensors(&named, path).map_err(|e| Error::internal("writing weights", e))
}

/// Why a job's EMA will not average anything, if it will not.
fn ema_note(opt: &Optimization) -> Option<String> {
    (opt.ema_start >= opt.steps).then(|| {
        format!(
            "spec.optimization.ema_start ({}) is not below spec.optimization.steps ({}): the registered weights \
             are the last step's, not an average; set ema_start below steps to average them",
            opt.ema_start, opt.steps
        )
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_ema_note_names_both_fields_only_when_averaging_never_starts() {
        let opt = |steps, ema_start| Optimization {
            steps,
            batch_size: 8,
            learning_rate: 1e-3,
            grad_clip: None,
            ema_decay: 0.995,
            ema_every: 10,
            ema_start,
            checkpoint_every: 100,
            eval_every: 100,
            log_every: 10,
        };
        let note = ema_note(&opt(1200, 2000)).expect("never starts");
        assert!(note.contains("ema_start (2000)") && note.contains("steps (1200)"), "{note}");
        assert!(ema_note(&opt(2000, 2000)).is_some(), "starting at the last step averages nothing");
        assert_eq!(ema_note(&opt(1200, 400)), None);
    }
}
