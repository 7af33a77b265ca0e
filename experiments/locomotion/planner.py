"""Diffuser-style planners over state-action windows, and the receding-horizon control loop.

Module map: `Schedule` (cosine betas and the posterior coefficients of docs/method.md section 2,
the same numbers the server uses because the manifest carries the betas explicitly),
`Denoiser` (MLP over a flattened [H, A + O] window plus a time embedding, predicting x0),
`Planner` (normaliser + schedule + denoiser: `windows`, `train`, `export` to TorchScript and a
relreward manifest, `load`), `sample` (the external planner's DDPM loop: inpaint the current
state, optional guidance by omega * grad rho (on x_t as Diffuser, or on the posterior mean) from any `grad_fn` (a relreward GradientStream,
or PyTorch in process), x0 prediction, posterior step), `act` / `act_many` (one env step's plans
and the chosen first action, for one episode or several in lockstep), `run_episode` /
`run_episodes` (receding horizon: plan, act, replan; one episode, or several seeds in lockstep
so that they share each denoising step's gradient round trip).

Why the planner is trained here and uploaded as TorchScript (not by the server's TrainDiffusion):
the external planner must run the base model's denoiser itself at every denoising step, and
relreward serves no denoiser outputs; uploading the same module makes the server-side `Sample`
mode and the external mode sample from one and the same base model.

    python experiments/locomotion/planner.py train --env hopper --data /tmp/loco-data --set medium-replay
"""

from __future__ import annotations

import argparse
import json
import math
import time
from pathlib import Path

import numpy as np
import torch
from torch import nn

from common import ENVS, PLANNERS, episodes


class Schedule:
    """Cosine schedule (Nichol & Dhariwal, s = 0.008) and DDPM posterior coefficients."""

    def __init__(self, n_timesteps: int):
        T = n_timesteps
        s = 0.008
        x = np.arange(T + 1, dtype=np.float64)
        ab = np.cos(((x / T) + s) / (1 + s) * math.pi / 2) ** 2
        ab = ab / ab[0]
        self.betas = np.clip(1 - ab[1:] / ab[:-1], 0, 0.999)
        alphas = 1 - self.betas
        abar = np.cumprod(alphas)
        abar_prev = np.concatenate([[1.0], abar[:-1]])
        self.T = T
        self.sqrt_abar = np.sqrt(abar)
        self.sqrt_1m_abar = np.sqrt(1 - abar)
        self.coef1 = self.betas * np.sqrt(abar_prev) / (1 - abar)
        self.coef2 = (1 - abar_prev) * np.sqrt(alphas) / (1 - abar)
        var = self.betas * (1 - abar_prev) / (1 - abar)
        self.log_var = np.log(np.maximum(var, 1e-20))


class Denoiser(nn.Module):
    """x0 prediction from a noisy window x [B, H, D] at steps t [B] (int64)."""

    def __init__(self, horizon: int, dim: int, hidden: int = 512, depth: int = 3, temb: int = 32):
        super().__init__()
        self.horizon, self.dim, self.temb = horizon, dim, temb
        self.time = nn.Sequential(nn.Linear(temb, 4 * temb), nn.Mish(), nn.Linear(4 * temb, temb))
        layers, width = [], horizon * dim + temb
        for _ in range(depth):
            layers += [nn.Linear(width, hidden), nn.Mish()]
            width = hidden
        layers.append(nn.Linear(width, horizon * dim))
        self.net = nn.Sequential(*layers)

    def forward(self, x: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
        half = self.temb // 2
        freqs = torch.exp(-math.log(10000.0) * torch.arange(half, dtype=torch.float32) / (half - 1))
        arg = t.to(torch.float32)[:, None] * freqs[None, :]
        emb = self.time(torch.cat([arg.sin(), arg.cos()], dim=1))
        h = torch.cat([x.reshape(x.shape[0], -1), emb], dim=1)
        return self.net(h).reshape(x.shape[0], self.horizon, self.dim)


class Planner:
    """A trained planner: limits normaliser (min-max to [-1, 1]), schedule and denoiser."""

    def __init__(self, env: str, horizon: int, act_dim: int, obs_dim: int, lo: np.ndarray, hi: np.ndarray,
                 n_timesteps: int = 20, hidden: int = 512, depth: int = 3):
        self.env, self.horizon, self.act_dim, self.obs_dim = env, horizon, act_dim, obs_dim
        self.lo, self.hi = lo.astype(np.float64), hi.astype(np.float64)
        self.sched = Schedule(n_timesteps)
        self.net = Denoiser(horizon, act_dim + obs_dim, hidden, depth)
        self.hidden, self.depth = hidden, depth

    # -- normaliser (the server's "limits": 2 (x - min) / (max - min) - 1) --
    def normalize(self, x):
        return 2 * (x - self.lo) / (self.hi - self.lo) - 1

    def unnormalize(self, x):
        return (x + 1) / 2 * (self.hi - self.lo) + self.lo

    def manifest(self) -> dict:
        return {"parametrization": "x0", "n_timesteps": self.sched.T, "clip_denoised": True,
                "schedule": {"kind": "betas", "betas": self.sched.betas.tolist()},
                "space": {"kind": "trajectory", "horizon": self.horizon, "action_dim": self.act_dim,
                          "obs_dim": self.obs_dim},
                "normalizer": {"kind": "limits", "min": self.lo.tolist(), "max": self.hi.tolist()}}

    def windows(self, data: dict, top_frac: float = 1.0) -> np.ndarray:
        """Normalised [N, H, A + O] windows inside episodes; with top_frac < 1 only the episodes
        with the highest returns (data weighting by return)."""
        eps = episodes(data)
        if top_frac < 1.0:
            rets = np.array([data["rewards"][s:e].sum() for s, e in eps])
            keep = np.argsort(-rets)[: max(1, int(round(top_frac * len(eps))))]
            eps = [eps[i] for i in sorted(keep)]
        rows = self.normalize(np.concatenate([data["actions"], data["observations"]], axis=1))
        H = self.horizon
        idx = [s + np.arange(e - s - H + 1) for s, e in eps if e - s >= H]
        idx = np.concatenate(idx)
        return rows[idx[:, None] + np.arange(H)[None, :]].astype(np.float32)

    def train(self, win: np.ndarray, steps: int, batch: int = 256, lr: float = 3e-4, action_weight: float = 10.0,
              seed: int = 0, log=print) -> list[float]:
        """Diffuser's objective: x0 MSE with the first action weighted by action_weight; the
        current state (row 0's observation) is inpainted in the noisy input as when planning."""
        g = torch.Generator().manual_seed(seed)
        torch.manual_seed(seed)
        opt = torch.optim.Adam(self.net.parameters(), lr=lr)
        sched = torch.optim.lr_scheduler.CosineAnnealingLR(opt, steps, eta_min=lr * 0.05)
        sa = torch.tensor(self.sched.sqrt_abar, dtype=torch.float32)
        s1 = torch.tensor(self.sched.sqrt_1m_abar, dtype=torch.float32)
        w = torch.ones(self.horizon, self.act_dim + self.obs_dim)
        w[0, : self.act_dim] = action_weight
        data = torch.from_numpy(win)
        A, losses, t0 = self.act_dim, [], time.time()
        self.net.train()
        for step in range(steps):
            x0 = data[torch.randint(len(data), (batch,), generator=g)]
            t = torch.randint(self.sched.T, (batch,), generator=g)
            eps = torch.randn(x0.shape, generator=g)
            xt = sa[t, None, None] * x0 + s1[t, None, None] * eps
            xt[:, 0, A:] = x0[:, 0, A:]
            loss = ((self.net(xt, t) - x0) ** 2 * w).mean()
            opt.zero_grad()
            loss.backward()
            opt.step()
            sched.step()
            losses.append(loss.item())
            if (step + 1) % max(1, steps // 10) == 0:
                log(f"step {step + 1}/{steps} loss {np.mean(losses[-100:]):.4f} {time.time() - t0:.0f}s")
        self.net.eval()
        return losses

    def action_error(self, win: np.ndarray, n: int = 512, seed: int = 0) -> float:
        """RMS error (normalised units) of the first action of plans sampled from data states,
        against the data's own action: how well the denoiser imitates its data."""
        rng = np.random.default_rng(seed)
        pick = win[rng.choice(len(win), size=min(n, len(win)), replace=False)]
        x = sample(self, pick[:, 0, self.act_dim:], n_plans=1, seed=seed)
        return float(np.sqrt(((x[:, 0, : self.act_dim] - pick[:, 0, : self.act_dim]) ** 2).mean()))

    # -- files: weights + meta (for the Python loop), TorchScript + manifest (for the server) --
    def save(self, out: Path, meta: dict) -> None:
        out.mkdir(parents=True, exist_ok=True)
        # One file for both ends: this process's sampling loop loads the same TorchScript module
        # the server runs.
        ts = torch.jit.trace(self.net, (torch.zeros(2, self.horizon, self.act_dim + self.obs_dim),
                                        torch.zeros(2, dtype=torch.int64)))
        ts.save(str(out / "denoiser.torchscript.pt"))
        (out / "manifest.json").write_text(json.dumps(self.manifest()) + "\n")
        meta = dict(meta, env=self.env, horizon=self.horizon, act_dim=self.act_dim, obs_dim=self.obs_dim,
                    n_timesteps=self.sched.T, hidden=self.hidden, depth=self.depth)
        (out / "planner.json").write_text(json.dumps(meta, indent=1) + "\n")

    @staticmethod
    def load(out: Path) -> "Planner":
        meta = json.loads((out / "planner.json").read_text())
        man = json.loads((out / "manifest.json").read_text())
        p = Planner(meta["env"], meta["horizon"], meta["act_dim"], meta["obs_dim"],
                    np.array(man["normalizer"]["min"]), np.array(man["normalizer"]["max"]),
                    meta["n_timesteps"], meta["hidden"], meta["depth"])
        p.net = torch.jit.load(str(out / "denoiser.torchscript.pt"))
        p.net.eval()
        return p


@torch.no_grad()
def _denoise(p: Planner, x: np.ndarray, t: int) -> np.ndarray:
    tt = torch.full((x.shape[0],), t, dtype=torch.int64)
    return p.net(torch.from_numpy(x.astype(np.float32)), tt).numpy().astype(np.float64)


GUIDE_AT = ("x_t", "mean")


def sample(p: Planner, state_norm: np.ndarray, n_plans: int, seed, grad_fn=None, omega: float = 0.0,
           t_stopgrad: int = 0, n_guide_steps: int = 1, guide_at: str = "x_t") -> np.ndarray:
    """DDPM sampling of n_plans plans per row of state_norm ([S, O] normalised; returns
    [S * n_plans, H, D] normalised), row 0's observation inpainted after every step and guide
    step. grad_fn(x, t) -> grad_x rho in normalised units, scale_grad_by_std off as in the
    paper's locomotion runs. guide_at, for t >= t_stopgrad:
      "x_t"   x_t += omega * grad rho(x_t, t) before the denoiser (Diffuser's
              n_step_guided_p_sample, the server's Sample, the paper's runs);
      "mean"  x_{t-1} = mu_base(x_t, t) + omega * grad rho(x_t, t) + sigma_t z (classifier
              guidance on the posterior mean; one gradient per step, n_guide_steps ignored).
    Why "mean": rho is fitted so that grad rho(x_t, t) ~ mu_expert(x_t, t) - mu_base(x_t, t),
    so at omega 1 a perfect rho turns the base's step into the expert's, including the last
    step (t = 0) that yields the executed action. An x0-predicting denoiser that reads the
    action off the inpainted state ignores a shift of its noisy input, so "x_t" guidance can
    leave the executed action almost where it was (docs/results.md, diagnose.py).

    seed: one int (one generator for the whole batch), or one per row of state_norm (episodes
    planned in lockstep): then row i's plans draw their noise from generator seed[i] alone, so
    they are the plans that row would get sampled by itself with that seed."""
    A, s = p.act_dim, p.sched
    cond = np.repeat(state_norm, n_plans, axis=0)
    shape = (p.horizon, A + p.obs_dim)
    if np.ndim(seed) == 0:
        rngs, per = [np.random.default_rng(seed)], len(cond)
    else:
        if len(seed) != len(state_norm):
            raise ValueError(f"seed: {len(seed)} seeds for {len(state_norm)} states")
        rngs, per = [np.random.default_rng(int(v)) for v in seed], n_plans

    def noise() -> np.ndarray:
        return np.concatenate([r.standard_normal((per, *shape)) for r in rngs])

    x = noise()
    x[:, 0, A:] = cond
    if guide_at not in GUIDE_AT:
        raise ValueError(f"guide_at: {guide_at!r} is not one of {GUIDE_AT}")
    for t in reversed(range(s.T)):
        guided = grad_fn is not None and omega != 0.0 and t >= t_stopgrad
        if guided and guide_at == "x_t":
            for _ in range(n_guide_steps):
                x = x + omega * grad_fn(x, t)
                x[:, 0, A:] = cond
        g = omega * grad_fn(x, t) if guided and guide_at == "mean" else 0.0
        x0 = np.clip(_denoise(p, x, t), -1, 1)
        x = s.coef1[t] * x0 + s.coef2[t] * x + g
        if t > 0:
            x = x + np.exp(0.5 * s.log_var[t]) * noise()
        x[:, 0, A:] = cond
    return x


def act_many(p: Planner, obs: np.ndarray, n_plans: int, seeds, grad_fn=None, omega: float = 0.0,
             t_stopgrad: int = 0, select_fn=None, guide_at: str = "x_t") -> np.ndarray:
    """Receding-horizon decisions for several episodes at once (obs [S, O], one planner seed
    each): n_plans plans per episode sampled as one batch (one gradient request per denoising
    step for all of them), in each episode the plan chosen by select_fn(plans) -> scores
    (argmax within the episode's plans) or its first plan; the chosen first actions [S, A] (raw
    units)."""
    lo, hi = p.lo[p.act_dim:], p.hi[p.act_dim:]
    # Clipped to the data's limits: a falling robot leaves them, and an out-of-range inpainted
    # state only feeds the denoiser inputs it never saw. (The server-side mode does not clip;
    # both modes gave the same returns in docs/results.md.)
    state = np.clip(2 * (np.asarray(obs) - lo) / (hi - lo) - 1, -1, 1)
    plans = sample(p, state, n_plans, list(seeds), grad_fn, omega, t_stopgrad, guide_at=guide_at)
    plans = plans.reshape(len(state), n_plans, *plans.shape[1:])
    if select_fn is not None:
        k = np.argmax(np.asarray(select_fn(plans.reshape(-1, *plans.shape[2:]))).reshape(len(state), n_plans), axis=1)
    else:
        k = np.zeros(len(state), dtype=int)
    return np.clip(p.unnormalize(plans[np.arange(len(state)), k, 0])[:, : p.act_dim], -1, 1)


def act(p: Planner, obs: np.ndarray, n_plans: int, seed: int, grad_fn=None, omega: float = 0.0,
        t_stopgrad: int = 0, select_fn=None, guide_at: str = "x_t") -> np.ndarray:
    """One episode's decision: `act_many` for a single observation."""
    return act_many(p, obs[None, :], n_plans, [seed], grad_fn, omega, t_stopgrad, select_fn, guide_at)[0]


def run_episode(env, decide, seed: int, max_steps: int) -> dict:
    """Plan, act, replan until the episode ends or max_steps; decide(obs, step) -> action."""
    obs, _ = env.reset(seed=seed)
    total, n, t0 = 0.0, 0, time.time()
    for n in range(1, max_steps + 1):
        obs, r, term, trunc, _ = env.step(decide(obs, n))
        total += r
        if term or trunc:
            break
    return dict(seed=seed, ret=float(total), length=n, seconds=time.time() - t0)


def run_episodes(make_env, decide_many, seeds, max_steps: int) -> list[dict]:
    """Episodes of several env seeds in lockstep: at every step the live episodes' actions come
    from one decide_many(obs [S, O], seeds [S], step) -> [S, A] call (one batch of plans, so one
    gradient round trip per denoising step serves all of them), each episode with its own env.
    Each step's wall time is shared equally among the episodes it served, so the episodes'
    seconds add up to the arm's wall time."""
    envs = [make_env() for _ in seeds]
    obs = [env.reset(seed=int(s))[0] for env, s in zip(envs, seeds)]
    eps = [dict(seed=int(s), ret=0.0, length=0, seconds=0.0) for s in seeds]
    live = list(range(len(seeds)))
    for n in range(1, max_steps + 1):
        if not live:
            break
        t0 = time.time()
        acts = decide_many(np.stack([obs[i] for i in live]), [eps[i]["seed"] for i in live], n)
        ended = set()
        for a, i in zip(acts, live):
            obs[i], r, term, trunc, _ = envs[i].step(a)
            eps[i]["ret"] += float(r)
            eps[i]["length"] = n
            if term or trunc:
                ended.add(i)
        dt = (time.time() - t0) / len(live)
        for i in live:
            eps[i]["seconds"] += dt
        live = [i for i in live if i not in ended]
    return eps


def evaluate(a) -> None:
    import gymnasium as gym

    from common import normalized_score

    pl = Planner.load(a.planner)
    env = gym.make(ENVS[a.env]["id"], max_episode_steps=a.max_steps)
    rets = []
    for k in range(a.episodes):
        s = a.seed_base + k
        ep = run_episode(env, lambda obs, n: act(pl, obs, a.n_plans, s * 100_003 + n), s, a.max_steps)
        rets.append(ep["ret"])
        print(json.dumps(ep), flush=True)
    z = dict(np.load(a.data))
    data = [z["rewards"][s:min(e, s + a.max_steps)].sum() for s, e in episodes(z)]
    print(json.dumps(dict(planner=float(normalized_score(a.env, rets).mean()),
                          data=float(normalized_score(a.env, data).mean()))), flush=True)


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    sub = p.add_subparsers(dest="cmd", required=True)
    tr = sub.add_parser("train", help="train a planner on a data set written by data.py")
    tr.add_argument("--env", required=True, choices=sorted(ENVS))
    tr.add_argument("--data", type=Path, required=True, help="directory of data.py's npz files")
    tr.add_argument("--set", required=True, choices=["medium-replay", "expert"])
    tr.add_argument("--horizon", type=int, default=8)
    tr.add_argument("--steps", type=int, default=8000)
    tr.add_argument("--batch", type=int, default=256)
    tr.add_argument("--hidden", type=int, default=512)
    tr.add_argument("--depth", type=int, default=3)
    tr.add_argument("--action-weight", type=float, default=10.0)
    tr.add_argument("--top-frac", type=float, default=1.0, help="train on this share of highest-return episodes")
    tr.add_argument("--seed", type=int, default=0)
    tr.add_argument("--out", type=Path, default=None, help=f"default {PLANNERS}/<env>-<set>")
    ev = sub.add_parser("eval", help="unsteered closed-loop return of a planner against its data's")
    ev.add_argument("--env", required=True, choices=sorted(ENVS))
    ev.add_argument("--planner", type=Path, required=True)
    ev.add_argument("--data", type=Path, required=True, help="the planner's training npz")
    ev.add_argument("--episodes", type=int, default=5)
    ev.add_argument("--seed-base", type=int, default=20_000, help="not the experiment's reported seeds")
    ev.add_argument("--max-steps", type=int, default=1000)
    ev.add_argument("--n-plans", type=int, default=16)
    a = p.parse_args()
    torch.set_num_threads(1)
    if a.cmd == "eval":
        evaluate(a)
        return
    base = np.load(a.data / f"{a.env}-medium-replay.npz")
    expert = np.load(a.data / f"{a.env}-expert.npz")
    # One normaliser for both planners (limits over the union): relreward's reward needs its
    # base and expert models to share normaliser and item shape.
    rows = np.concatenate([np.concatenate([d["actions"], d["observations"]], 1) for d in (base, expert)])
    lo, hi = rows.min(0), rows.max(0)
    hi = np.where(hi - lo < 1e-6, lo + 1e-6, hi)
    act_dim, obs_dim = base["actions"].shape[1], base["observations"].shape[1]
    torch.set_num_threads(1)
    torch.manual_seed(a.seed)
    pl = Planner(a.env, a.horizon, act_dim, obs_dim, lo, hi, hidden=a.hidden, depth=a.depth)
    data = dict(base if a.set == "medium-replay" else expert)
    win = pl.windows(data, a.top_frac)
    t0 = time.time()
    losses = pl.train(win, a.steps, a.batch, action_weight=a.action_weight, seed=a.seed,
                      log=lambda s: print(s, flush=True))
    secs = time.time() - t0
    err = pl.action_error(pl.windows(data), seed=a.seed + 1)
    out = a.out or PLANNERS / f"{a.env}-{a.set}"
    cmd = ("python experiments/locomotion/planner.py train " + " ".join(
        f"--{k.replace('_', '-')} {v}" for k, v in vars(a).items() if k not in ("cmd", "out", "data")))
    pl.save(out, dict(command=cmd, windows=len(win), train_seconds=secs, final_loss=float(np.mean(losses[-200:])),
                      first_action_rms_error=err, steps=a.steps, top_frac=a.top_frac,
                      action_weight=a.action_weight, set=a.set))
    print(json.dumps(dict(out=str(out), windows=len(win), seconds=secs, action_rms_error=err)), flush=True)


if __name__ == "__main__":
    main()
