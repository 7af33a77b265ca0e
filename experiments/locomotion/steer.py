"""Closed-loop steering of a Diffuser-style planner with a relative reward (paper section 5.2).

Module map: `start_server` (target/release/relreward-server on a loopback port with
TorchScript uploads allowed, through relreward_dev.launcher; `--endpoint` or RELREWARD_ENDPOINT
names a running server instead), `prepare` (upload the data sets and both
planners, train the relative reward (Algorithm 1, ValueFunction encoder) and the discriminator
of the same architecture), `Arm` / `decider` (one arm of the experiment: how plans are guided
and chosen, in the external-planner mode (this process's sampling loop over the base planner,
grad rho from a GradientStream) or the server-side mode (the `Sample` RPC, guidance and
inpainting on the server)), `sweep` (omega / t_stopgrad on sweep seeds, never the reported
ones), `experiment` (all arms on the same seeds, statistics), `report` (markdown table and a PNG
plot), `main` (CLI; `make steer ENV=hopper` calls it).

Arms (n plans per env step, the first action of the chosen plan executed, then replan):
  unsteered       no guidance, the first plan
  reward          guidance by grad rho, the plan with the highest rho
  discriminator   guidance by the discriminator's logit gradient, the plan it scores highest
Guidance enters the external planner's step by whichever rule the sweep seeds favour for that
arm (`--guide-at sweep`, the default): on the posterior mean (`--guide-at mean`; planner.sample
says why) or on x_t as in Diffuser (`--guide-at x_t`); the server-side mode's `Sample` always
guides x_t. The reward is trained with the first action weighted 10 and the inpainted first
observation 0 (`--reward-action-weight`, `--reward-condition-weight`; Config says why).
  select-reward   no guidance (omega 0), the plan with the highest rho
  select-disc     no guidance, the plan the discriminator scores highest
Seeds: episode k of every arm uses env seed `seed_base + k` and the same planner noise, so
arms are paired by seed. An arm's episodes run in lockstep (`--batch-episodes`): one batch of
plans and one gradient request per denoising step for all of them, which cuts the round trips
that dominate a guided step (BENCHMARKS.md) without changing any plan's noise.
"""

from __future__ import annotations

import argparse
import json
import os
import signal
import sys
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path

import gymnasium as gym
import numpy as np
import torch

import relreward
from common import ENVS, PLANNERS, episodes, normalized_score, paired, welch
from planner import GUIDE_AT, Planner, act_many, run_episodes
from relreward_dev.launcher import Binaries, Server, ServerStartError

REPO = Path(__file__).resolve().parents[2]
ARMS = ("unsteered", "reward", "discriminator", "select-reward", "select-disc")
# The paper's Table 2 (D4RL-normalised return: unsteered / discriminator / reward).
PAPER = {"halfcheetah": (30.38, 30.41, 31.65), "hopper": (24.67, 25.12, 27.04), "walker2d": (28.20, 27.98, 38.40)}


def start_server(data_dir: Path) -> Server:
    """relreward-server on a loopback port with its data in data_dir and its log beside it
    (server.log): TorchScript uploads on (the planners are TorchScript modules), two jobs at
    a time, one intra-op thread unless RELREWARD__ENGINE__INTRA_OP_THREADS says otherwise."""
    env = {"RELREWARD__MODELS__ALLOW_TORCHSCRIPT_UPLOAD": "true", "RELREWARD__JOBS__MAX_CONCURRENT": "2",
           "RELREWARD__ENGINE__INTRA_OP_THREADS": os.environ.get("RELREWARD__ENGINE__INTRA_OP_THREADS", "1")}
    try:
        return Server(Binaries.of_checkout(REPO), data_dir, env=env, log_path=data_dir.parent / "server.log")
    except ServerStartError as e:
        sys.exit(f"steer.py: the server did not start ({e}); run `make build` or pass --endpoint")


@dataclass
class Config:
    env: str
    data: Path
    planners: Path
    work: Path
    endpoint: str | None = None
    episodes: int = 5
    seed_base: int = 0
    sweep_seed_base: int = 10_000
    # Episodes per sweep setting (in lockstep, so about the cost of one): a single episode's
    # return moves more between seeds than most settings differ, so one seed picks by noise.
    sweep_episodes: int = 3
    max_steps: int = 1000
    n_plans: int = 16
    widths: tuple = (32, 64, 128)
    reward_steps: int = 1500
    disc_steps: int = 1500
    # The reward's loss weights on the first step's action and observation entries (TrainReward
    # action_weight / condition_weight). The target's action entries depend on the state (the
    # policy) and its state entries hardly on the action, which no gradient can fit at once
    # (diagnose.py's target_asymmetry); 10 and 0 move the unavoidable error off the executed
    # action and onto the inpainted state, where the planner discards it (docs/results.md:
    # Hopper +31 instead of +0.4). 1 and 1 are the paper's unweighted loss.
    reward_action_weight: float = 10.0
    reward_condition_weight: float = 0.0
    # Reward and discriminator trained on x_t with the current state clean (TrainReward /
    # TrainDiscriminator inpaint_condition), as the planners were trained and plan. Off by
    # default: it fits grad rho better on the planner's own samples (docs/results.md, session
    # 14) but did not yet turn guidance into a gain on the sweep seeds of Walker2d or HalfCheetah.
    inpaint_condition: bool = False
    batch_size: int = 128
    learning_rate: float = 2e-4
    # The sweep: omega over `omegas` at t_stopgrads[0], then the other t_stopgrads at the best
    # omega (coordinate-wise: 3 + 1 settings per guided arm). With guidance on the mean, omega 1
    # is the value at which a perfect rho makes the base's step the expert's; 3.0 because
    # Hopper's earlier sweep chose the top of {0.1, 0.3, 1.0}; t_stopgrad 0 first because the
    # last step (t = 0) is the one that sets the executed action.
    omegas: tuple = (0.3, 1.0, 3.0)
    t_stopgrads: tuple = (0, 2)
    omega: float | None = None
    t_stopgrad: int | None = None
    disc_omega: float | None = None
    disc_t_stopgrad: int | None = None
    # How the external planner applies grad rho (planner.sample): "mean" (on the posterior
    # mean), "x_t" (Diffuser's, the server's Sample, the paper's runs), or "sweep" (the
    # default): both rules in each guided arm's sweep, the arm then using the one it chose;
    # which rule steers further differed between environments and between reward and
    # discriminator (docs/results.md).
    guide_at: str = "sweep"
    arms: tuple = ARMS
    server_mode_episodes: int = 1
    # Episodes of an arm planned together in lockstep (0: all of them; 1: one at a time).
    batch_episodes: int = 0
    log: object = field(default=print)


def prepare(cfg: Config, client: relreward.Client) -> dict:
    """Uploads data and planners (once per name) and trains the reward and discriminator."""
    env, names = cfg.env, {}
    have_ds = {d.name for d in client.list_datasets()}
    have_m = {m.name for m in client.list_models()}
    for s in ("medium-replay", "expert"):
        n = f"{env}-{s}"
        if n not in have_ds:
            z = np.load(cfg.data / f"{env}-{s}.npz")
            client.upload_dataset(n, {k: z[k] for k in ("observations", "actions", "terminals", "timeouts")})
        pl = cfg.planners / f"{env}-{s}"
        m = f"{env}-{s}-planner"
        if m not in have_m:
            client.upload_model(pl / "denoiser.torchscript.pt", m, json.loads((pl / "manifest.json").read_text()),
                                description=f"planner trained by experiments/locomotion/planner.py on {n}")
        names[s] = m
    names["reward"], names["discriminator"] = f"{env}-reward", f"{env}-discriminator"
    arch = ("value_function", {"widths": list(cfg.widths)})
    t0 = time.time()
    # Both jobs are submitted at once (the server runs them side by side when
    # jobs.max_concurrent allows), then awaited.
    jobs = []
    if names["reward"] not in have_m:
        jobs.append(("reward", client.submit_job(relreward.RewardJob(
            names["reward"], names["medium-replay"], names["expert"], datasets=[f"{env}-medium-replay", f"{env}-expert"],
            architecture=arch, seed=0, action_weight=cfg.reward_action_weight,
            condition_weight=cfg.reward_condition_weight, inpaint_condition=cfg.inpaint_condition,
            optimization=relreward.Optimization(
                steps=cfg.reward_steps, batch_size=cfg.batch_size, learning_rate=cfg.learning_rate)))))
    if names["discriminator"] not in have_m:
        jobs.append(("discriminator", client.submit_job(relreward.DiscriminatorJob(
            names["discriminator"], f"{env}-medium-replay", f"{env}-expert", names["medium-replay"],
            architecture=arch, seed=0, inpaint_condition=cfg.inpaint_condition, optimization=relreward.Optimization(
                steps=cfg.disc_steps, batch_size=cfg.batch_size, learning_rate=cfg.learning_rate)))))
    for what, job in jobs:
        _finish(client, job, what, cfg.log)
    names["train_seconds"] = time.time() - t0
    return names


def _finish(client: relreward.Client, job, what: str, log) -> None:
    t0 = time.time()
    done = client.wait_job(job.id)
    if done.state is not relreward.JobState.SUCCEEDED:
        raise RuntimeError(f"{what} job {job.id} ended {done.state}: {done.error or done}")
    log(f"{what} trained in {time.time() - t0:.0f}s")


class Timer:
    """Seconds spent waiting for the service (or the in-process reward), per episode."""

    def __init__(self):
        self.wait = 0.0

    def wrap(self, fn):
        def timed(*a):
            t0 = time.perf_counter()
            try:
                return fn(*a)
            finally:
                self.wait += time.perf_counter() - t0
        return timed


def decider(arm: str, mode: str, planner: Planner, client, names: dict, cfg: Config, omega: float,
            t_stopgrad: int, timer: Timer, grad_source=None, guide_at: str | None = None):
    """decide(obs [S, O], seeds [S], step) -> actions [S, A] for one arm and mode, for the S
    episodes planned together; grad_source(model) overrides the external planner's gradient
    function (the in-process PyTorch reward of the benchmark); guide_at overrides cfg.guide_at
    (an arm's swept rule)."""
    guide_at = guide_at or cfg.guide_at
    if mode == "external" and guide_at not in GUIDE_AT:
        raise ValueError(f"guide_at: {guide_at!r} is not one of {GUIDE_AT} (an arm needs its swept rule)")
    model = {"reward": names["reward"], "select-reward": names["reward"],
             "discriminator": names["discriminator"], "select-disc": names["discriminator"]}.get(arm)
    guided = arm in ("reward", "discriminator") and omega != 0.0
    if mode == "server":
        # One Sample RPC per episode and step: a request carries one inpainting condition.
        def decide(obs, seeds, step):
            out = []
            for o, seed in zip(obs, seeds):
                t0 = time.perf_counter()
                b = client.sample(names["medium-replay"], reward_model=model or "", omega=omega if guided else 0.0,
                                  n=cfg.n_plans, seed=seed * 100_003 + step, n_guide_steps=1,
                                  t_stopgrad=t_stopgrad, conditions={0: o.astype(np.float32)})
                timer.wait += time.perf_counter() - t0
                k = int(np.argmax(b.rewards)) if model else 0
                out.append(np.clip(b.x[k, 0, : planner.act_dim], -1, 1))
            return np.stack(out)
        return decide, None
    stream = None
    grad_fn = select_fn = None
    if model is not None:
        if grad_source is not None:
            grad_fn, score_fn = grad_source(model)
        else:
            stream = client.gradient_stream(model, units="normalized", gradient_units="normalized")

            def grad_fn(x, t):
                return np.asarray(stream.gradient(x.astype(np.float32), int(t)).gradient, dtype=np.float64)

            def score_fn(x):
                return np.asarray(client.score(model, x.astype(np.float32), 0, units="normalized").rewards)
        select_fn = timer.wrap(score_fn)
        grad_fn = timer.wrap(grad_fn) if guided else None

    def decide(obs, seeds, step):
        return act_many(planner, obs, cfg.n_plans, [s * 100_003 + step for s in seeds], grad_fn,
                        omega if guided else 0.0, t_stopgrad, select_fn, guide_at)
    return decide, stream


def run_arm(arm: str, mode: str, seeds, planner, client, names, cfg, omega, t_stopgrad, grad_source=None,
            guide_at: str | None = None) -> list:
    """The arm's episodes, `cfg.batch_episodes` seeds at a time in lockstep (0: all at once).
    Planner noise depends only on (env seed, step), so the batching changes no plan; it only
    shares each denoising step's gradient round trip among the episodes."""
    seeds = list(seeds)
    k = cfg.batch_episodes or len(seeds)
    out = []
    for g in range(0, len(seeds), k):
        group = seeds[g:g + k]
        timer = Timer()
        decide, stream = decider(arm, mode, planner, client, names, cfg, omega, t_stopgrad, timer, grad_source,
                                 guide_at)
        try:
            eps = run_episodes(lambda: gym.make(ENVS[cfg.env]["id"], max_episode_steps=cfg.max_steps), decide,
                               group, cfg.max_steps)
        finally:
            if stream is not None:
                stream.close()
        total = sum(e["seconds"] for e in eps)
        for ep in eps:
            # The group's waiting shared as its wall time is (run_episodes' equal split per step).
            ep.update(arm=arm, mode=mode, omega=omega, t_stopgrad=t_stopgrad,
                      guide_at=(guide_at or cfg.guide_at) if mode == "external" else "x_t",
                      wait_seconds=timer.wait * ep["seconds"] / total if total > 0 else 0.0,
                      normalized=float(normalized_score(cfg.env, ep["ret"])))
            cfg.log(f"  {arm:14s} {mode:8s} seed {ep['seed']}: return {ep['ret']:.1f} (norm {ep['normalized']:.2f}) "
                    f"{ep['length']} steps {1e3 * ep['seconds'] / ep['length']:.1f} ms/step")
        out += eps
    return out


def sweep(cfg, planner, client, names, kind: str) -> tuple[str, float, int, list]:
    """The guidance rule, omega, then t_stopgrad, by mean return on the sweep seeds (disjoint
    from the reported ones): for each rule (both with `--guide-at sweep`), omega over cfg.omegas
    at cfg.t_stopgrads[0]; then the other t_stopgrads at the best (rule, omega). Ties keep the
    earlier setting (the first rule, the smaller omega, the first t_stopgrad)."""
    seeds = range(cfg.sweep_seed_base, cfg.sweep_seed_base + cfg.sweep_episodes)
    rules = GUIDE_AT if cfg.guide_at == "sweep" else (cfg.guide_at,)
    rows = []

    def run(rule, om, ts):
        eps = run_arm(kind, "external", seeds, planner, client, names, cfg, om, ts, guide_at=rule)
        rows.append(dict(guide_at=rule, omega=om, t_stopgrad=ts,
                         mean_normalized=float(np.mean([e["normalized"] for e in eps]))))
        cfg.log(f"sweep {kind}: guide at {rule} omega {om} t_stopgrad {ts}: {rows[-1]['mean_normalized']:.3f}")

    for rule in rules:
        for om in cfg.omegas:
            run(rule, om, cfg.t_stopgrads[0])
    first = max(rows, key=lambda r: r["mean_normalized"])
    for ts in cfg.t_stopgrads[1:]:
        run(first["guide_at"], first["omega"], ts)
    best = max(rows, key=lambda r: r["mean_normalized"])
    cfg.log(f"sweep {kind}: best guide at {best['guide_at']} omega {best['omega']} t_stopgrad {best['t_stopgrad']} "
            f"({best['mean_normalized']:.2f})")
    return best["guide_at"], best["omega"], best["t_stopgrad"], rows


def summarize(cfg: Config, episodes: list, data_mean: float) -> dict:
    ext = [e for e in episodes if e["mode"] == "external"]
    by = {a: sorted([e for e in ext if e["arm"] == a], key=lambda e: e["seed"]) for a in cfg.arms}
    base = [e["normalized"] for e in by.get("unsteered", [])]
    rows = {}
    for a, eps in by.items():
        v = np.array([e["normalized"] for e in eps])
        if not len(v):
            continue
        r = dict(n=len(v), mean=float(v.mean()), se=float(v.std(ddof=1) / np.sqrt(len(v))) if len(v) > 1 else float("nan"),
                 mean_length=float(np.mean([e["length"] for e in eps])),
                 ms_per_step=float(1e3 * sum(e["seconds"] for e in eps) / sum(e["length"] for e in eps)),
                 wait_share=float(sum(e["wait_seconds"] for e in eps) / sum(e["seconds"] for e in eps)))
        if a != "unsteered" and len(base) > 1 and len(v) > 1:
            r["welch"] = welch(v, base)
            r["paired"] = paired(v, base)
        rows[a] = r
    return dict(arms=rows, data_mean_normalized=data_mean,
                base_vs_data=rows["unsteered"]["mean"] / data_mean if "unsteered" in rows and data_mean else None)


def table(env: str, s: dict) -> str:
    lines = ["| arm | n | normalised return (mean +- se) | mean length | Welch p vs unsteered | paired diff (wins/n) | ms/step |",
             "|---|---|---|---|---|---|---|"]
    for a, r in s["arms"].items():
        w, pr = r.get("welch"), r.get("paired")
        wp = "" if w is None else f"{w['p']:.2g}"
        pd = "" if pr is None else f"{pr['mean']:+.2f} +- {pr['se']:.2f} ({pr['wins']}/{pr['n']})"
        lines.append(f"| {a} | {r['n']} | {r['mean']:.2f} +- {r['se']:.2f} | {r['mean_length']:.0f} | {wp} | {pd} | "
                     f"{r['ms_per_step']:.0f} |")
    p = PAPER.get(env)
    if p:
        lines.append(f"\nPaper, Table 2 ({env}): unsteered {p[0]}, discriminator {p[1]}, reward {p[2]}.")
    lines.append(f"Data (medium-replay) mean normalised return: {s['data_mean_normalized']:.2f}; "
                 f"unsteered / data = {s['base_vs_data']:.2f}.")
    return "\n".join(lines) + "\n"


def plot(path: Path, env: str, s: dict) -> None:
    """Bars of mean normalised return per arm with +-1 se, and the data's mean as a line."""
    from PIL import Image, ImageDraw

    arms = list(s["arms"])
    W, H, pad = 640, 360, 50
    img = Image.new("RGB", (W, H), "white")
    d = ImageDraw.Draw(img)
    vals = [s["arms"][a]["mean"] for a in arms]
    ses = [0.0 if np.isnan(s["arms"][a]["se"]) else s["arms"][a]["se"] for a in arms]
    top = max([v + e for v, e in zip(vals, ses)] + [s["data_mean_normalized"], 1e-6]) * 1.15
    lo = min([0.0] + [v - e for v, e in zip(vals, ses)])
    y = lambda v: H - pad - (v - lo) / (top - lo) * (H - 2 * pad)  # noqa: E731
    d.line([(pad, y(0)), (W - 10, y(0))], fill="black")
    d.line([(pad, pad), (pad, H - pad)], fill="black")
    colors = ["#888888", "#d62728", "#1f77b4", "#ff9896", "#aec7e8"]
    bw = (W - pad - 20) / len(arms)
    for i, (a, v, e) in enumerate(zip(arms, vals, ses)):
        x0 = pad + 10 + i * bw
        d.rectangle([x0, min(y(v), y(0)), x0 + bw * 0.7, max(y(v), y(0))], fill=colors[i % len(colors)])
        cx = x0 + bw * 0.35
        d.line([(cx, y(v - e)), (cx, y(v + e))], fill="black", width=2)
        d.text((x0, H - pad + 5), a, fill="black")
        d.text((x0, y(v + e) - 12), f"{v:.1f}", fill="black")
    dm = s["data_mean_normalized"]
    d.line([(pad, y(dm)), (W - 10, y(dm))], fill="#2ca02c", width=1)
    d.text((W - 150, y(dm) - 12), f"data mean {dm:.1f}", fill="#2ca02c")
    d.text((pad, 10), f"{env}: D4RL-normalised return per arm (mean +- se)", fill="black")
    for k in range(5):
        v = lo + (top - lo) * k / 4
        d.text((5, y(v) - 5), f"{v:.0f}", fill="black")
    img.save(path)


def data_mean(cfg: Config) -> float:
    """Mean normalised return of the base planner's data, its episodes cut at max_steps as the
    planner's are."""
    z = dict(np.load(cfg.data / f"{cfg.env}-medium-replay.npz"))
    rets = [z["rewards"][s:min(e, s + cfg.max_steps)].sum() for s, e in episodes(z)]
    return float(normalized_score(cfg.env, np.array(rets)).mean())


def experiment(cfg: Config) -> dict:
    # One thread: the planner's small matrices gain nothing from more, and on a shared machine
    # torch's default pool contends with the server for the same cores.
    torch.set_num_threads(1)
    cfg.work.mkdir(parents=True, exist_ok=True)
    data_dir = cfg.work / "server-data"
    data_dir.mkdir(exist_ok=True)
    server = None if cfg.endpoint else start_server(data_dir)
    try:
        client = relreward.Client(cfg.endpoint or server.addr)
        t0 = time.time()
        names = prepare(cfg, client)
        planner = Planner.load(cfg.planners / f"{cfg.env}-medium-replay")
        sweeps = {}
        om, ts, rule = cfg.omega, cfg.t_stopgrad, cfg.guide_at
        if "reward" in cfg.arms and (om is None or ts is None):
            rule, om, ts, sweeps["reward"] = sweep(cfg, planner, client, names, "reward")
        dom, dts, drule = cfg.disc_omega, cfg.disc_t_stopgrad, cfg.guide_at
        if "discriminator" in cfg.arms and (dom is None or dts is None):
            drule, dom, dts, sweeps["discriminator"] = sweep(cfg, planner, client, names, "discriminator")
        # Without a sweep (an arm not run), "sweep" falls back to the default rule.
        rule, drule = (r if r in GUIDE_AT else "mean" for r in (rule, drule))
        seeds = range(cfg.seed_base, cfg.seed_base + cfg.episodes)
        eps = []
        for arm in cfg.arms:
            # The select-only arms do not guide: their rule is moot, the reward arm's is kept.
            o, t, g = {"reward": (om, ts, rule), "discriminator": (dom, dts, drule)}.get(arm, (0.0, 0, rule))
            cfg.log(f"arm {arm} (guide at {g}, omega {o}, t_stopgrad {t})")
            eps += run_arm(arm, "external", seeds, planner, client, names, cfg, o, t, guide_at=g)
        # The server-side mode: the same arms through the Sample RPC on the first seeds.
        k = min(cfg.server_mode_episodes, cfg.episodes)
        for arm in [a for a in ("unsteered", "reward") if a in cfg.arms] if k else []:
            o, t = {"reward": (om, ts)}.get(arm, (0.0, 0))
            eps += run_arm(arm, "server", seeds[:k], planner, client, names, cfg, o, t)
        summary = summarize(cfg, eps, data_mean(cfg))
        summary["server_mode"] = {
            a: dict(n=len(v), mean=float(np.mean([e["normalized"] for e in v])),
                    ms_per_step=float(1e3 * sum(e["seconds"] for e in v) / sum(e["length"] for e in v)))
            for a in ("unsteered", "reward")
            if (v := [e for e in eps if e["mode"] == "server" and e["arm"] == a])}
        result = dict(env=cfg.env, guide_at=rule, omega=om, t_stopgrad=ts, disc_guide_at=drule, disc_omega=dom,
                      disc_t_stopgrad=dts, sweeps=sweeps,
                      names=names, summary=summary, episodes=eps, seconds=time.time() - t0,
                      config={k: (str(v) if isinstance(v, Path) else v) for k, v in cfg.__dict__.items()
                              if k != "log"})
        (cfg.work / f"{cfg.env}-results.json").write_text(json.dumps(result, indent=1, default=float) + "\n")
        (cfg.work / f"{cfg.env}-table.md").write_text(table(cfg.env, summary))
        plot(cfg.work / f"{cfg.env}-steer.png", cfg.env, summary)
        cfg.log(table(cfg.env, summary))
        return result
    finally:
        if server is not None:
            server.stop(grace=30)


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--env", required=True, choices=sorted(ENVS))
    p.add_argument("--data", type=Path, required=True, help="directory of data.py's npz files")
    p.add_argument("--planners", type=Path, default=PLANNERS)
    p.add_argument("--work", type=Path, default=None, help="results and server data (default: a temp dir)")
    p.add_argument("--endpoint", default=os.environ.get("RELREWARD_ENDPOINT"),
                   help="use this server (TorchScript uploads allowed); default: start one")
    p.add_argument("--episodes", type=int, default=5,
                   help="per arm; Hopper's returns vary little across seeds (docs/results.md)")
    p.add_argument("--seed-base", type=int, default=0)
    p.add_argument("--sweep-episodes", type=int, default=3,
                   help="episodes per sweep setting, on seeds 10000.. (in lockstep)")
    p.add_argument("--max-steps", type=int, default=1000)
    p.add_argument("--n-plans", type=int, default=16)
    p.add_argument("--reward-steps", type=int, default=1500)
    p.add_argument("--disc-steps", type=int, default=1500)
    p.add_argument("--lr", type=float, default=2e-4, help="the reward's and the discriminator's Adam learning rate")
    p.add_argument("--reward-action-weight", type=float, default=10.0,
                   help="the reward's loss weight on the first action (default 10; 1 is the paper's)")
    p.add_argument("--reward-condition-weight", type=float, default=0.0,
                   help="the reward's loss weight on the first observation, which the planner inpaints "
                        "(default 0: grad rho there is free; 1 is the paper's)")
    p.add_argument("--inpaint-condition", action="store_true",
                   help="train the reward and the discriminator on x_t with the current state clean, "
                        "as the planners see it (default: the paper's noising of the whole window)")
    p.add_argument("--omegas", default="0.3,1.0,3.0", help="the sweep's omegas (at the first t_stopgrad)")
    p.add_argument("--t-stopgrads", default="0,2",
                   help="the sweep's t_stopgrads: the first during the omega sweep, the rest then at the best omega")
    p.add_argument("--omega", type=float)
    p.add_argument("--t-stopgrad", type=int)
    p.add_argument("--disc-omega", type=float)
    p.add_argument("--disc-t-stopgrad", type=int)
    p.add_argument("--guide-at", default="sweep", choices=GUIDE_AT + ("sweep",),
                   help="external planner: guidance on the posterior mean or on x_t before the "
                        "denoiser (Diffuser's rule, which the server-side Sample mode always uses), or "
                        "'sweep' (default): each guided arm's sweep tries both and the arm uses the one it chose")
    p.add_argument("--server-mode-episodes", type=int, default=1,
                   help="episodes of the unsteered and reward arms through the Sample RPC")
    p.add_argument("--batch-episodes", type=int, default=0,
                   help="episodes of an arm planned in lockstep, sharing each gradient round trip "
                        "(0: all; 1: one at a time, as before; results are the same)")
    p.add_argument("--full", action="store_true",
                   help="the paper's sizes: ValueFunction widths (64, 64, 128, 128), 50k reward and "
                        "discriminator steps, 512 episodes per arm")
    a = p.parse_args()
    if a.guide_at == "sweep" and (a.omega is not None or a.disc_omega is not None):
        p.error("--guide-at sweep chooses the rule in the sweep: leave --omega and --disc-omega unset")
    cfg = Config(env=a.env, data=a.data, planners=a.planners,
                 work=a.work or Path(tempfile.mkdtemp(prefix=f"steer-{a.env}-")), endpoint=a.endpoint,
                 episodes=a.episodes, seed_base=a.seed_base, sweep_episodes=a.sweep_episodes, max_steps=a.max_steps,
                 n_plans=a.n_plans, reward_steps=a.reward_steps, disc_steps=a.disc_steps,
                 reward_action_weight=a.reward_action_weight, reward_condition_weight=a.reward_condition_weight,
                 inpaint_condition=a.inpaint_condition, learning_rate=a.lr,
                 omega=a.omega,
                 t_stopgrad=a.t_stopgrad, disc_omega=a.disc_omega, disc_t_stopgrad=a.disc_t_stopgrad,
                 server_mode_episodes=a.server_mode_episodes, guide_at=a.guide_at, batch_episodes=a.batch_episodes,
                 log=lambda s: print(s, flush=True),
                 omegas=tuple(float(v) for v in a.omegas.split(",")),
                 t_stopgrads=tuple(int(v) for v in a.t_stopgrads.split(",")))
    if a.full:
        cfg.widths, cfg.reward_steps, cfg.disc_steps, cfg.episodes = (64, 64, 128, 128), 50_000, 50_000, 512
    # A terminated run stops the server it started (the `finally` in experiment), rather than
    # leaving it orphaned on its data directory.
    signal.signal(signal.SIGTERM, lambda *_: sys.exit(128 + signal.SIGTERM))
    experiment(cfg)


if __name__ == "__main__":
    main()
