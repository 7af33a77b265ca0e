"""PyTorch references for relreward's training and sampling: what a researcher would run
instead of the service, written the way the paper's code (Diffuser's GaussianDiffusion and
Trainer, the authors' relative-reward trainer) writes it.

- `Diffusion`: Diffuser's GaussianDiffusion buffers and formulas (x0 or eps parametrization,
  clip_denoised, posterior mean and log-variance, q_sample), from a relreward diffusion manifest.
- `ddpm_step`: one DDPM training step (Diffuser's `p_losses` with `action_weight`, backward,
  Adam, EMA).
- `alg1_step`: one step of the paper's Algorithm 1: x_t from the forward process, target
  mu_expert - mu_base (or s_expert - s_base) under no-grad, loss mean_b || grad_x rho(x_eval, t)
  - target ||^2 with grad_x taken with create_graph=True, backward through it, Adam, EMA.
- `guided_sample`: Diffuser's `p_sample_loop` with `n_step_guided_p_sample` and
  `apply_conditioning`.
- `count_macs`: multiply-accumulates of a module's forward pass (Linear, Conv1d,
  ConvTranspose1d, Conv2d), counted with forward hooks on the real modules and shapes.

The networks are not redefined here: they are the cross-checked reference nets of the
development package, dev/python (`relreward_dev.nets`: TemporalUnet, MLP denoiser;
`relreward_dev.reward_nets`: windowed MLP, ValueFunction, conv encoder, MLP), which load
relreward's safetensors strictly. The schedule tables come from `relreward_dev.schedule`
(float64, cast to float32 as Diffuser registers its buffers).

Used by bench/reference/crosscheck.py (server/tests/training_vs_pytorch.rs: same numbers as
relreward on the same weights and inputs) and bench/reference/bench.py (timings).
"""

import copy

import numpy as np
import torch

from relreward_dev.nets import item_shape
from relreward_dev.schedule import schedule_tables

# relreward's threshold (server/src/engine/normalizer.rs): narrower ranges are constant
# coordinates and normalize to 0.
MIN_RANGE = 1e-12


def extract(table, t, ndim):
    """Diffuser's `extract`: table[t] shaped [B, 1, ..., 1] to broadcast against x."""
    return table.gather(-1, t).reshape(t.shape[0], *((1,) * (ndim - 1)))


class Diffusion:
    """Diffuser's GaussianDiffusion around a denoiser network, configured by a relreward
    diffusion manifest (dict, as relreward stores it)."""

    def __init__(self, net, manifest):
        self.net = net
        self.manifest = manifest
        self.predict_epsilon = manifest["parametrization"] == "epsilon"
        self.clip_denoised = bool(manifest.get("clip_denoised", False))
        self.n_timesteps = int(manifest["n_timesteps"])
        space = manifest["space"]
        self.action_dim = space.get("action_dim", 0) if space["kind"] == "trajectory" else 0
        tables = schedule_tables(manifest["schedule"], self.n_timesteps)
        self.buffers = {name: values.to(torch.float32) for name, values in tables.items()}

    def buf(self, name, t, ndim):
        return extract(self.buffers[name], t, ndim)

    def q_sample(self, x0, t, noise):
        return self.buf("sqrt_alphas_cumprod", t, x0.dim()) * x0 + self.buf(
            "sqrt_one_minus_alphas_cumprod", t, x0.dim()
        ) * noise

    def predict_start_from_noise(self, x_t, t, out):
        if self.predict_epsilon:
            return self.buf("sqrt_recip_alphas_cumprod", t, x_t.dim()) * x_t - self.buf(
                "sqrt_recipm1_alphas_cumprod", t, x_t.dim()
            ) * out
        return out

    def x0_hat(self, x_t, t, clip):
        x0 = self.predict_start_from_noise(x_t, t, self.net(x_t, t))
        return x0.clamp(-1.0, 1.0) if clip else x0

    def q_posterior_mean(self, x0, x_t, t):
        return self.buf("posterior_mean_coef1", t, x_t.dim()) * x0 + self.buf(
            "posterior_mean_coef2", t, x_t.dim()
        ) * x_t

    def posterior_mean(self, x_t, t, clip):
        return self.q_posterior_mean(self.x0_hat(x_t, t, clip), x_t, t)

    def score(self, x_t, t):
        """-eps_hat / sqrt(1 - abar_t); for an x0 net, eps_hat from its raw x0 prediction."""
        out = self.net(x_t, t)
        if self.predict_epsilon:
            eps = out
        else:
            eps = (self.buf("sqrt_recip_alphas_cumprod", t, x_t.dim()) * x_t - out) / self.buf(
                "sqrt_recipm1_alphas_cumprod", t, x_t.dim()
            )
        return -eps / self.buf("sqrt_one_minus_alphas_cumprod", t, x_t.dim())

    def loss(self, x0, t, noise, action_weight=1.0):
        """Diffuser's p_losses with WeightedL2: the first transition's actions weighted by
        `action_weight`, mean over every element (no conditioning of x_t, as relreward)."""
        x_t = self.q_sample(x0, t, noise)
        pred = self.net(x_t, t)
        target = noise if self.predict_epsilon else x0
        sq = (pred - target) ** 2
        if action_weight != 1.0:
            weights = torch.ones(x0.shape[1:], dtype=x0.dtype)
            weights[0, : self.action_dim] = action_weight
            sq = sq * weights
        return sq.mean()


class Ema:
    """Diffuser's EMA (Trainer.step_ema): every `every` steps, before `start` the average is
    reset to the model's weights, afterwards ema = decay * ema + (1 - decay) * model."""

    def __init__(self, model, decay=0.995, every=10, start=2000):
        self.model = copy.deepcopy(model)
        self.decay, self.every, self.start = decay, every, start
        for p in self.model.parameters():
            p.requires_grad_(False)

    @torch.no_grad()
    def after_step(self, model, step):
        if step % self.every != 0:
            return
        model = getattr(model, "_orig_mod", model)  # a torch.compile wrapper: its module
        if step < self.start:
            self.model.load_state_dict(model.state_dict())
            return
        for averaged, current in zip(self.model.parameters(), model.parameters()):
            averaged.mul_(self.decay).add_(current, alpha=1.0 - self.decay)


def ddpm_step(diffusion, optimizer, ema, step, x0, t, noise, action_weight=1.0):
    """One DDPM training step (Diffuser's Trainer.train inner loop); returns the loss."""
    loss = diffusion.loss(x0, t, noise, action_weight)
    loss.backward()
    optimizer.step()
    optimizer.zero_grad(set_to_none=True)
    ema.after_step(diffusion.net, step)
    return loss.detach()


def alignment_target(base, expert, x_t, t, target="mean", eval_point="x_t"):
    """(target, evaluation point) of Algorithm 1 under no-grad: expert minus base, posterior
    means taken without clipping x0_hat (as relreward's engine/relative_reward.rs)."""
    with torch.no_grad():
        mu_base = base.posterior_mean(x_t, t, clip=False)
        if target == "mean":
            y = expert.posterior_mean(x_t, t, clip=False) - mu_base
        else:
            y = expert.score(x_t, t) - base.score(x_t, t)
        point = x_t if eval_point == "x_t" else mu_base
    return y, point


def entry_weights(horizon, action_dim, obs_dim, action_weight=1.0, condition_weight=1.0):
    """[H, A + O] weights of the alignment loss: the first step's action entries action_weight,
    its observation entries condition_weight, 1 elsewhere."""
    w = torch.ones(horizon, action_dim + obs_dim)
    w[0, :action_dim] = action_weight
    w[0, action_dim:] = condition_weight
    return w


def alignment_loss(reward, point, t, target, rho_l2=0.0, weights=None):
    """mean_b sum(weights * (grad_x rho(point_b, t_b) - target_b)^2) (+ rho_l2 mean rho^2),
    differentiable in the reward's parameters through the double backward (weights None: 1)."""
    x = point.detach().requires_grad_(True)
    rho = reward(x, t)
    (grad_x,) = torch.autograd.grad(rho.sum(), x, create_graph=True)
    sq = (grad_x - target).pow(2)
    if weights is not None:
        sq = sq * weights
    loss = sq.flatten(1).sum(dim=1).mean()
    if rho_l2 > 0:
        loss = loss + rho_l2 * reward(point, t).pow(2).mean()
    return loss


def alg1_step(base, expert, reward, optimizer, ema, step, x0, t, noise, target="mean", eval_point="x_t", rho_l2=0.0,
              weights=None):
    """One step of Algorithm 1 with a dataset; returns the loss."""
    with torch.no_grad():
        x_t = base.q_sample(x0, t, noise)
    y, point = alignment_target(base, expert, x_t, t, target, eval_point)
    loss = alignment_loss(reward, point, t, y, rho_l2, weights)
    loss.backward()
    optimizer.step()
    optimizer.zero_grad(set_to_none=True)
    ema.after_step(reward, step)
    return loss.detach()


def apply_conditioning(x, conditions, action_dim):
    """Diffuser's apply_conditioning: x[:, i, action_dim:] = state for each (i, state)."""
    for index, state in conditions:
        x[:, index, action_dim:] = state
    return x


def guided_step(diffusion, reward, x, t, conditions, noise, omega, n_guide_steps, t_stopgrad, scale_grad_by_std):
    """Diffuser's n_step_guided_p_sample at one t for the whole batch, then conditioning;
    `noise` is z (ignored where t == 0). Returns (x_{t-1}, rho at the last guide point)."""
    log_var = diffusion.buf("posterior_log_variance_clipped", t, x.dim())
    std, var = torch.exp(0.5 * log_var), torch.exp(log_var)
    y = None
    for _ in range(n_guide_steps):
        with torch.enable_grad():
            x = x.detach().requires_grad_(True)
            y = reward(x, t)
            (grad,) = torch.autograd.grad(y.sum(), x)
        x = x.detach()
        if scale_grad_by_std:
            grad = var * grad
        grad[t < t_stopgrad] = 0
        x = apply_conditioning(x + omega * grad, conditions, diffusion.action_dim)
    mean = diffusion.posterior_mean(x, t, diffusion.clip_denoised)
    noise = noise.clone()
    noise[t == 0] = 0
    return apply_conditioning(mean + std * noise, conditions, diffusion.action_dim), y


@torch.no_grad()
def guided_sample(diffusion, reward, n, conditions, omega, n_guide_steps=1, t_stopgrad=0, scale_grad_by_std=False,
                  noises=None):
    """Diffuser's p_sample_loop with guidance. `noises` (optional) is the list of draws in
    relreward's order: x_T first, then one z per step with t > 0; otherwise torch.randn."""
    shape = (n, *item_shape(diffusion.manifest["space"]))
    draws = iter(noises) if noises is not None else None
    x = next(draws).clone() if draws else torch.randn(shape)
    x = apply_conditioning(x, conditions, diffusion.action_dim)
    y = None
    for i in reversed(range(diffusion.n_timesteps)):
        t = torch.full((n,), i, dtype=torch.long)
        z = (next(draws) if draws else torch.randn(shape)) if i > 0 else torch.zeros(shape)
        x, y = guided_step(diffusion, reward, x, t, conditions, z, omega, n_guide_steps, t_stopgrad,
                           scale_grad_by_std)
    return x, y


# ---------------------------------------------------------------------------------------------
# Data: a D4RL-style .npz as relreward's Algorithm 1 and diffusion jobs read it


def limits_normalizer(rows):
    """relreward's default for trajectories (Diffuser's LimitsNormalizer), from the rows."""
    lo, hi = rows.min(axis=0).astype(np.float64), rows.max(axis=0).astype(np.float64)
    offset = (lo + hi) / 2
    scale = np.where(hi - lo > MIN_RANGE, 2.0 / np.maximum(hi - lo, MIN_RANGE), 0.0)
    return offset, scale


class Windows:
    """Sub-trajectories of length `horizon` inside episodes (ended by terminals or timeouts),
    rows [action | observation] normalized to [-1, 1]; a batch is one gather."""

    def __init__(self, npz_path, horizon):
        data = np.load(npz_path)
        rows = np.concatenate([data["actions"], data["observations"]], axis=1).astype(np.float32)
        offset, scale = limits_normalizer(rows)
        self.rows = torch.from_numpy(((rows - offset) * scale).astype(np.float32))
        ends = np.zeros(len(rows), dtype=bool)
        for name in ("terminals", "timeouts"):
            if name in data:
                ends |= data[name].astype(bool)
        starts, begin = [], 0
        for end in list(np.flatnonzero(ends) + 1) + [len(rows)]:
            if end - begin >= horizon:
                starts.extend(range(begin, end - horizon + 1))
            begin = max(begin, end)
        self.starts = torch.tensor(starts, dtype=torch.long)
        self.offsets = torch.arange(horizon)
        self.horizon = horizon

    def batch(self, size, generator=None):
        pick = self.starts[torch.randint(len(self.starts), (size,), generator=generator)]
        index = (pick[:, None] + self.offsets[None, :]).reshape(-1)
        return self.rows.index_select(0, index).reshape(size, self.horizon, -1)


# ---------------------------------------------------------------------------------------------
# Counting multiply-accumulates


def count_macs(module, *inputs):
    """Multiply-accumulates of one forward pass of `module` on `inputs`, by layer kind:
    Linear: out elements x in_features; ConvNd: out elements x in_channels / groups x kernel
    size; ConvTranspose1d: in elements x out_channels / groups x kernel size (each input element
    is scattered through the whole kernel). Normalisations, activations and elementwise ops are
    not counted (O(elements), small beside the matmuls)."""
    totals = {}

    def hook(layer, args, out):
        x = args[0]
        if isinstance(layer, torch.nn.Linear):
            macs = out.numel() * layer.in_features
        elif isinstance(layer, torch.nn.ConvTranspose1d):
            macs = x.numel() * layer.out_channels // layer.groups * layer.kernel_size[0]
        elif isinstance(layer, (torch.nn.Conv1d, torch.nn.Conv2d)):
            macs = out.numel() * layer.in_channels // layer.groups * int(np.prod(layer.kernel_size))
        else:
            return
        kind = type(layer).__name__
        totals[kind] = totals.get(kind, 0) + macs

    handles = [m.register_forward_hook(hook) for m in module.modules()
               if isinstance(m, (torch.nn.Linear, torch.nn.Conv1d, torch.nn.Conv2d, torch.nn.ConvTranspose1d))]
    try:
        with torch.no_grad():
            module(*inputs)
    finally:
        for h in handles:
            h.remove()
    return totals


def peak_rss_mib():
    """This process's peak resident set (VmHWM), MiB."""
    with open("/proc/self/status") as f:
        for line in f:
            if line.startswith("VmHWM:"):
                return int(line.split()[1]) / 1024.0
    return float("nan")
