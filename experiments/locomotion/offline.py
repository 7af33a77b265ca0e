"""Offline RL on relabelled locomotion data (issue 35 item 4): IQL trained on the extracted reward.

The medium-replay set of data.py is relabelled with relreward.relabel by the steering
experiment's own relative reward and discriminator (steer.prepare trains both on the server, or
finds them there by name), and d3rlpy's IQL is trained on the same transitions under four
rewards, every other input identical:

  true           the environment's rewards as data.py recorded them (the ceiling)
  rho            the relative reward: Score of the window ending at each row (docs/relabel.md)
  discriminator  the discriminator's Score of the same windows: its logit of expert against
                 base, log D - log(1 - D) (AIRL's reward form; the server trains it with
                 binary cross-entropy on logits)
  constant       zero everywhere (Li et al. 2023's "zero reward"): no information. In
                 HalfCheetah, which never terminates, this is a floor; in Hopper or Walker2d
                 episodes that end on a fall make any constant a survival signal (docs/offline_rl.md)

Module map: `arm_rewards` (relabel the file for each model, the four reward arrays),
`train_iql` (d3rlpy IQL with its D4RL locomotion settings), `evaluate` (deterministic episodes
of a trained policy), `run_arms` (every arm and seed on the same evaluation seeds), `summarize`
(D4RL-normalised means, Welch's t-tests against the constant arm), `table`, `experiment`
(server, reward, relabelling, arms, results JSON and markdown), `main` (CLI).

    python experiments/locomotion/data.py --env halfcheetah --out /tmp/loco-data
    python experiments/locomotion/offline.py --env halfcheetah --data /tmp/loco-data --work /tmp/offline-hc

d3rlpy is imported only when an agent is trained, so the module imports without it.
"""

from __future__ import annotations

import argparse
import json
import logging
import math
import os
import signal
import sys
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import gymnasium as gym
import numpy as np
import torch

import relreward
from common import ENVS, PLANNERS, episodes, normalized_score, welch
import steer  # the steering experiment whose reward and discriminator are relabelled

ARMS = ("true", "rho", "discriminator", "constant")
# IQL's D4RL locomotion recipe (Kostrikov et al. 2021, appendix; d3rlpy's reproductions/offline/iql.py):
# rewards scaled so that the dataset's episode returns span 1000, expectile 0.7, temperature 3,
# advantage weights clipped at 100, Adam 3e-4, batch 256, two 256-unit hidden layers, and a
# cosine schedule on the actor's learning rate over the run.
IQL = dict(expectile=0.7, weight_temp=3.0, max_weight=100.0, learning_rate=3e-4, return_span=1000.0)
# Evaluation episodes start from env seeds EVAL_SEED + k: data.py draws its reset seeds from
# its generator (values below 2^31 spread over the whole range), and no training run seeds an env.
EVAL_SEED = 2_000_000_000


@dataclass
class Config:
    env: str
    data: Path
    work: Path
    planners: Path = PLANNERS
    endpoint: str | None = None
    steps: int = 10_000
    batch_size: int = 256
    hidden: tuple = (256, 256)
    seeds: int = 2
    eval_episodes: int = 10
    max_steps: int = 1000
    t: int = 0
    # The reward's and the discriminator's training: steer.Config's own defaults, so that a
    # steering run's trained models, found by name on the same server data, are the ones relabelled.
    reward_steps: int = steer.Config.reward_steps
    disc_steps: int = steer.Config.disc_steps
    widths: tuple = steer.Config.widths
    arms: tuple = ARMS
    log: Callable = field(default=print)


def arm_rewards(client: relreward.Client, src: Path, models: dict, work: Path, t: int = 0,
                progress=None) -> dict[str, np.ndarray]:
    """The four reward arrays [N] for the rows of src (a D4RL-style npz with rewards): `true`
    from the file, one per entry of `models` (arm -> reward or discriminator model name) by
    relreward.relabel (the relabelled file is written to work/<src stem>-<arm>.npz and kept),
    and `constant`. Relabelled rewards are in the file's row order, as the file's own."""
    with np.load(src) as z:
        if "rewards" not in z:
            raise ValueError(f"src: {src} has no `rewards` (the true arm needs the environment's rewards)")
        true = z["rewards"].astype(np.float32)
    out = {"true": true}
    for arm, model in models.items():
        done = relreward.relabel(client, model, src, work / f"{src.stem}-{arm}.npz", t=t, overwrite=True,
                                 progress=progress)
        out[arm] = done.rewards
    out["constant"] = np.zeros_like(true)
    return out


def _d3rlpy():
    """d3rlpy, imported on first use, its info logging (a dozen lines per fit) turned down to
    warnings: structlog is configured process-wide by d3rlpy's import, so this is the one place."""
    import d3rlpy
    import structlog

    structlog.configure(wrapper_class=structlog.make_filtering_bound_logger(logging.WARNING))
    return d3rlpy


def train_iql(data: dict, rewards: np.ndarray, seed: int, steps: int, batch_size: int = 256,
              hidden: tuple = (256, 256)):
    """d3rlpy's IQL on data's transitions with `rewards`, IQL's D4RL settings (IQL above). The
    return-based reward scaling is skipped when every episode has the same return (the constant
    arm: scaling by a zero span is undefined, and any constant carries the same information)."""
    d3rlpy = _d3rlpy()
    d3rlpy.seed(seed)
    rewards = np.asarray(rewards, np.float32)
    ds = d3rlpy.dataset.MDPDataset(np.asarray(data["observations"], np.float32),
                                   np.asarray(data["actions"], np.float32), rewards,
                                   np.asarray(data["terminals"], bool), timeouts=np.asarray(data["timeouts"], bool))
    returns = np.array([rewards[s:e].sum() for s, e in episodes(data)])
    scaler = (d3rlpy.preprocessing.ReturnBasedRewardScaler(multiplier=IQL["return_span"])
              if returns.max() > returns.min() else None)
    enc = d3rlpy.models.VectorEncoderFactory(hidden_units=list(hidden))
    lr = IQL["learning_rate"]
    algo = d3rlpy.algos.IQLConfig(
        batch_size=batch_size, actor_learning_rate=lr, critic_learning_rate=lr,
        actor_optim_factory=d3rlpy.optimizers.AdamFactory(
            lr_scheduler_factory=d3rlpy.optimizers.CosineAnnealingLRFactory(T_max=steps)),
        actor_encoder_factory=enc, critic_encoder_factory=enc, value_encoder_factory=enc,
        expectile=IQL["expectile"], weight_temp=IQL["weight_temp"], max_weight=IQL["max_weight"],
        reward_scaler=scaler).create(device="cpu:0")
    # NoopAdapterFactory: no d3rlpy_logs folder, no checkpoints; the results are what evaluate returns.
    algo.fit(ds, n_steps=steps, n_steps_per_epoch=steps, show_progress=False, save_interval=steps + 1,
             logger_adapter=d3rlpy.logging.NoopAdapterFactory())
    return algo


def evaluate(algo, make_env: Callable[[], gym.Env], n: int, seed: int = EVAL_SEED) -> np.ndarray:
    """Returns of n episodes of algo's deterministic policy, episode k from env seed seed + k.
    The episodes run in lockstep, one batched `predict` per step for those still running: a
    call's overhead, not the network, dominates a single observation's action (4 ms a step)."""
    envs = [make_env() for _ in range(n)]
    try:
        obs = [env.reset(seed=seed + k)[0] for k, env in enumerate(envs)]
        ret, running = np.zeros(n), list(range(n))
        while running:
            acts = algo.predict(np.stack([np.asarray(obs[k], np.float32) for k in running]))
            still = []
            for k, act in zip(running, acts):
                obs[k], r, term, trunc, _ = envs[k].step(act)
                ret[k] += float(r)
                if not (term or trunc):
                    still.append(k)
            running = still
    finally:
        for env in envs:
            env.close()
    return ret


def run_arms(data: dict, rewards: dict[str, np.ndarray], make_env: Callable[[], gym.Env], *, seeds: int,
             steps: int, eval_episodes: int, batch_size: int = 256, hidden: tuple = (256, 256),
             eval_seed: int = EVAL_SEED, log: Callable = print) -> list[dict]:
    """One IQL agent per arm and training seed (0 .. seeds-1), each evaluated on the same
    eval_episodes env seeds; one row per agent: arm, seed, returns, train/eval seconds."""
    rows = []
    for arm, r in rewards.items():
        if len(r) != len(data["actions"]):
            raise ValueError(f"rewards[{arm!r}]: {len(r)} values for {len(data['actions'])} rows")
        for seed in range(seeds):
            t0 = time.time()
            algo = train_iql(data, r, seed, steps, batch_size, hidden)
            t1 = time.time()
            ret = evaluate(algo, make_env, eval_episodes, eval_seed)
            rows.append(dict(arm=arm, seed=seed, returns=ret.tolist(), train_seconds=t1 - t0,
                             eval_seconds=time.time() - t1))
            log(f"{arm} seed {seed}: mean return {ret.mean():.1f} ({t1 - t0:.0f}s training)")
    return rows


def summarize(rows: list[dict], env: str | None) -> dict:
    """Per arm: mean and standard error of the D4RL-normalised return over every evaluation
    episode pooled across seeds (raw returns when env has no reference scores), the per-seed
    means, and Welch's t-test of each arm against `constant` over the pooled episodes."""
    norm = (lambda r: normalized_score(env, r)) if env in ENVS else (lambda r: np.asarray(r, float))
    arms = list(dict.fromkeys(r["arm"] for r in rows))
    pooled = {a: np.concatenate([norm(r["returns"]) for r in rows if r["arm"] == a]) for a in arms}
    out = {}
    for a in arms:
        v = pooled[a]
        out[a] = dict(n=len(v), mean=float(v.mean()),
                      se=float(v.std(ddof=1) / math.sqrt(len(v))) if len(v) > 1 else math.nan,
                      seed_means=[float(norm(r["returns"]).mean()) for r in rows if r["arm"] == a])
        if a != "constant" and "constant" in pooled and len(v) > 1 and len(pooled["constant"]) > 1:
            w = welch(v, pooled["constant"])
            out[a]["vs_constant"] = {k: float(x) for k, x in w.items()}
    return dict(normalized=env in ENVS, arms=out)


def table(env: str, summary: dict) -> str:
    unit = "D4RL-normalised return" if summary["normalized"] else "return"
    lines = [f"{env}: {unit}, mean +- s.e. over evaluation episodes pooled across seeds", "",
             "| arm | episodes | mean +- s.e. | per-seed means | minus constant | Welch p |",
             "|---|---|---|---|---|---|"]
    for a, s in summary["arms"].items():
        w = s.get("vs_constant")
        lines.append(f"| {a} | {s['n']} | {s['mean']:.2f} +- {s['se']:.2f} | "
                     + ", ".join(f"{m:.2f}" for m in s["seed_means"])
                     + (f" | {w['diff']:+.2f} | {w['p']:.3g} |" if w else " | | |"))
    return "\n".join(lines) + "\n"


def experiment(cfg: Config) -> dict:
    # One thread: on a shared 2-core machine torch's default pool contends with the server.
    torch.set_num_threads(1)
    cfg.work.mkdir(parents=True, exist_ok=True)
    src = cfg.data / f"{cfg.env}-medium-replay.npz"
    if not src.is_file():
        raise FileNotFoundError(f"data: {src} does not exist (make it with experiments/locomotion/data.py)")
    data_dir = cfg.work / "server-data"
    data_dir.mkdir(exist_ok=True)
    server = None if cfg.endpoint else steer.start_server(data_dir)
    try:
        with relreward.Client(cfg.endpoint or server.addr) as client:
            t0 = time.time()
            names = steer.prepare(steer.Config(env=cfg.env, data=cfg.data, planners=cfg.planners, work=cfg.work,
                                               reward_steps=cfg.reward_steps, disc_steps=cfg.disc_steps,
                                               widths=cfg.widths, log=cfg.log), client)
            models = {a: names["reward" if a == "rho" else a] for a in ("rho", "discriminator") if a in cfg.arms}
            rewards = arm_rewards(client, src, models, cfg.work, cfg.t)
        rewards = {a: rewards[a] for a in cfg.arms}
        relabel_seconds = time.time() - t0
        with np.load(src) as z:
            data = {k: z[k] for k in ("observations", "actions", "terminals", "timeouts")}
        env_id = ENVS[cfg.env]["id"]
        rows = run_arms(data, rewards, lambda: gym.make(env_id, max_episode_steps=cfg.max_steps),
                        seeds=cfg.seeds, steps=cfg.steps, eval_episodes=cfg.eval_episodes,
                        batch_size=cfg.batch_size, hidden=cfg.hidden, log=cfg.log)
        summary = summarize(rows, cfg.env)
        result = dict(env=cfg.env, names=names, summary=summary, agents=rows,
                      reward_stats={a: dict(mean=float(r.mean()), std=float(r.std()),
                                            corr_true=float(np.corrcoef(r, rewards["true"])[0, 1])
                                            if r.std() > 0 and "true" in rewards else None)
                                    for a, r in rewards.items()},
                      prepare_and_relabel_seconds=relabel_seconds, seconds=time.time() - t0,
                      config={k: (str(v) if isinstance(v, Path) else v) for k, v in cfg.__dict__.items()
                              if k != "log"})
        (cfg.work / f"{cfg.env}-offline.json").write_text(json.dumps(result, indent=1, default=float) + "\n")
        (cfg.work / f"{cfg.env}-offline.md").write_text(table(cfg.env, summary))
        cfg.log(table(cfg.env, summary))
        return result
    finally:
        if server is not None:
            server.stop(grace=30)


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--env", default="halfcheetah", choices=sorted(ENVS))
    p.add_argument("--data", type=Path, required=True, help="directory of data.py's npz files")
    p.add_argument("--work", type=Path, default=None,
                   help="results, relabelled files and server data (default: a temp dir); a steering run's "
                        "--work reuses its trained reward and discriminator")
    p.add_argument("--planners", type=Path, default=PLANNERS)
    p.add_argument("--endpoint", default=os.environ.get("RELREWARD_ENDPOINT"),
                   help="a running server instead of starting one")
    p.add_argument("--steps", type=int, default=10_000, help="IQL gradient steps per agent")
    p.add_argument("--batch-size", type=int, default=256)
    p.add_argument("--seeds", type=int, default=2, help="training seeds per arm")
    p.add_argument("--eval-episodes", type=int, default=10, help="evaluation episodes per agent")
    p.add_argument("--max-steps", type=int, default=1000)
    p.add_argument("--t", type=int, default=0, help="diffusion step the rewards are read at")
    p.add_argument("--reward-steps", type=int, default=1500)
    p.add_argument("--disc-steps", type=int, default=1500)
    p.add_argument("--arms", default=",".join(ARMS))
    p.add_argument("--paper-scale", action="store_true",
                   help="1M IQL steps per agent (the IQL paper's), 10 seeds per arm, 10 episodes per agent; the "
                        "reward and discriminator as steer.py --full (widths 64,64,128,128, 50k steps)")
    a = p.parse_args()
    arms = tuple(a.arms.split(","))
    if bad := [x for x in arms if x not in ARMS]:
        p.error(f"--arms: {bad} not among {ARMS}")
    cfg = Config(env=a.env, data=a.data, work=a.work or Path(tempfile.mkdtemp(prefix=f"offline-{a.env}-")),
                 planners=a.planners, endpoint=a.endpoint, steps=a.steps, batch_size=a.batch_size, seeds=a.seeds,
                 eval_episodes=a.eval_episodes, max_steps=a.max_steps, t=a.t, reward_steps=a.reward_steps,
                 disc_steps=a.disc_steps, arms=arms, log=lambda s: print(s, flush=True))
    if a.paper_scale:
        cfg.steps, cfg.seeds, cfg.eval_episodes = 1_000_000, 10, 10
        cfg.widths, cfg.reward_steps, cfg.disc_steps = (64, 64, 128, 128), 50_000, 50_000
    # A terminated run stops the server it started (the `finally` in experiment).
    signal.signal(signal.SIGTERM, lambda *_: sys.exit(128 + signal.SIGTERM))
    experiment(cfg)


if __name__ == "__main__":
    main()
