"""Agents trained on the extracted reward alone: Stable-Baselines3 SAC in gymnasium-robotics
PointMaze (MuJoCo), umaze, one run per goal, arm and training seed (issue 35, item 3).

For each goal (default: the four umaze goals of docs/results.md), experiments/pointmaze/generate.py
makes base data (random goals) and expert data (the goal held, the D4RL way); one
`relreward extract --discriminator` call turns them into a reward per goal and the discriminator
baseline; then SAC trains, per arm and seed, on:

  rho            the extracted reward alone, through relreward.rl.SB3RewardWrapper (the score g
                 of the h rows ending at each step; docs/rl.md)
  discriminator  the discriminator baseline's reward from the same data, through the same
                 wrapper: its logit, log D - log(1 - D) (AIRL's form; the server's Score serves a
                 discriminator's raw logit, the value its BCE-with-logits training loss takes)
  env            PointMaze's own dense reward for that goal, exp(-distance) (the ceiling)
  constant       0 every step (the floor: no information; episodes never terminate, so any
                 constant is the same)

Every arm sees the same environment: the goal cell fixed (marked "g" in the maze map, so every
reset draws it, with gymnasium-robotics' position noise), continuing_task with reset_target off
(the agent must hold the goal, as the experts do), 300-step episodes (generate.py's cap), the
policy observing PointMaze's dict. Rewards are normalised by SB3's VecNormalize (reward only,
every arm alike; --no-normalize turns it off).

Evaluation (deterministic policy): --eval-episodes episodes per trained agent from reset seeds
EVAL_SEED + k, a range no training environment or learning-curve evaluation ever uses; success =
the final position within 0.5 cells of the goal cell's centre, plus the fraction of steps within
0.5 and the mean final distance (cells). Learning curves: success on --curve-episodes episodes
(seeds CURVE_SEED + k) every --eval-every environment steps.

Writes WORK/results.json (every episode with its final position in relreward's maze frame,
summaries, curves, rewards seen in training, timings), WORK/curves.json, WORK/curves.png,
WORK/results.md (the table) and the trained agents, WORK/agents/ROW-COL-ARM-SEED.zip (SB3's
SAC.load).

    python experiments/pointmaze/rl.py --work rl-pointmaze-out                 # defaults
    python experiments/pointmaze/rl.py --work out --goals 3,1 1,3 --arms rho,env --seeds 1

Defaults are sized for the issue's bar (one goal's four arms in under 30 minutes on a 2-core
CPU); the paper-scale options are flags: --extract-size full, --base-transitions 1000000,
--expert-transitions 100000, --steps 300000, --seeds 5, --eval-episodes 100.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import subprocess
import sys
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, Callable

import numpy as np

HERE = Path(__file__).resolve().parent
REPO = HERE.parents[1]
# generate.py is this script's sibling: on sys.path when it runs by path (the tests' conftest
# adds the folder).

import generate  # noqa: E402  (gymnasium-robotics registered on import)

ARMS = ("rho", "discriminator", "env", "constant")
UMAZE_GOALS = ((1, 1), (3, 3), (1, 3), (3, 1))
# Reset seeds: training environments use seed * 1000 + i (i < n_envs, SB3's make_vec_env);
# the curves and the final evaluation have ranges of their own that training never reaches.
CURVE_SEED = 10_000_000
EVAL_SEED = 20_000_000


@dataclass
class Config:
    work: Path
    goals: tuple[tuple[int, int], ...] = UMAZE_GOALS
    arms: tuple[str, ...] = ARMS
    seeds: int = 2
    steps: int = 100_000
    n_envs: int = 4
    gradient_steps: int = 2
    learning_starts: int = 1_000
    batch_size: int = 256
    net: tuple[int, ...] = (64, 64)
    normalize: bool = True
    cap: int = generate.CAPS["umaze"]
    eval_episodes: int = 20
    curve_episodes: int = 5
    eval_every: int = 4_000
    base_transitions: int = 100_000
    expert_transitions: int = 30_000
    extract_size: str = "default"
    data_seed: int = 0
    torch_threads: int = 1
    workers: int = 2
    log: Callable[[str], None] = field(default=print, repr=False)


def maze_map(goal: tuple[int, int]) -> list[list[Any]]:
    """The umaze of generate.py with the goal cell marked "g": every reset draws that goal, and
    the agent starts in another free cell (gymnasium-robotics' reset locations)."""
    walls = [[ch == "#" for ch in row] for row in generate.LAYOUTS["umaze"]]
    if not (0 <= goal[0] < len(walls) and 0 <= goal[1] < len(walls[0])) or walls[goal[0]][goal[1]]:
        raise ValueError(f"goals: {goal} is not a free cell of the umaze {generate.LAYOUTS['umaze']}")
    m: list[list[Any]] = [[int(w) for w in row] for row in walls]
    m[goal[0]][goal[1]] = "g"
    return m


def make_env(goal: tuple[int, int], cap: int):
    import gymnasium as gym
    return gym.make("PointMaze_UMaze-v3", maze_map=maze_map(goal), continuing_task=True, reset_target=False,
                    reward_type="dense", max_episode_steps=cap)


def prepare(cfg: Config, server) -> dict[tuple[int, int], dict[str, Any]]:
    """Data by generate.py and one `relreward extract --discriminator` over every goal's expert:
    {goal: {"rho": reward model, "discriminator": model, "sha256": {model: digest}, "extract": ...}}.

    A finished extract is reused (WORK/prepare.json) when it was made from the same data settings
    and goals and the server still holds its models unchanged (same sha256), so a run split across
    sessions, or rerun for more seeds, trains every agent on the same rewards."""
    import relreward
    key = {k: getattr(cfg, k) for k in ("base_transitions", "expert_transitions", "extract_size", "data_seed")}
    key["goals"] = [list(g) for g in cfg.goals]
    done = cfg.work / "prepare.json"
    with relreward.Client(server.addr) as client:
        return _prepare(cfg, server, client, key, done)


def _prepare(cfg: Config, server, client, key: dict, done: Path) -> dict[tuple[int, int], dict[str, Any]]:
    import relreward
    if done.exists():
        prev = json.loads(done.read_text())
        try:
            same = prev["key"] == key and all(
                client.get_model(name).sha256 == sha for m in prev["models"].values() for name, sha in m["sha256"].items())
        except relreward.NotFound:  # a model is gone
            same = False
        if same:
            cfg.log("extract: reusing WORK/prepare.json (same data settings and goals, models unchanged)")
            return {tuple(int(v) for v in g.split(",")): m for g, m in prev["models"].items()}
    data = cfg.work / "data"
    data.mkdir(parents=True, exist_ok=True)
    gen = [sys.executable, str(HERE / "generate.py"), "--maze", "umaze", "--variant", "d4rl"]
    # Each file's seed depends on its goal only (not on which other goals run), and its name on
    # everything that makes it, so a rerun in the same WORK reuses exactly the files it would make.
    seed0 = cfg.data_seed * 1000
    base = data / f"base-{cfg.base_transitions}-s{seed0}.npz"
    if not base.exists():
        subprocess.run([*gen, "--mode", "base", "--transitions", str(cfg.base_transitions), "--seed", str(seed0),
                        "--out", str(base)], check=True, stdout=subprocess.DEVNULL)
    experts = []
    for r, c in cfg.goals:
        seed = seed0 + 10 * r + c + 1
        e = data / f"expert-{r}-{c}-{cfg.expert_transitions}-s{seed}.npz"
        if not e.exists():
            subprocess.run([*gen, "--mode", "expert", "--goal", f"{r},{c}", "--transitions",
                            str(cfg.expert_transitions), "--seed", str(seed), "--out", str(e)],
                           check=True, stdout=subprocess.DEVNULL)
        experts.append(e)
    args = ["--json", "extract", "--base", str(base), "--discriminator", "--size", cfg.extract_size,
            "--seed", str(cfg.data_seed), "--name", "rl-pm", "--out", str(cfg.work / "extract")]
    for e in experts:
        args += ["--expert", str(e)]
    t0 = time.time()
    report = json.loads(server.cli(*args).stdout)
    (cfg.work / "extract.json").write_text(json.dumps(report, indent=1) + "\n")
    cfg.log(f"extract: {time.time() - t0:.0f} s")
    models = {}
    for goal, rw in zip(cfg.goals, report["rewards"]):
        if tuple(int(round(v)) for v in rw["goal"]) != goal:  # the expert files' constant goals
            raise RuntimeError(f"extract reported goal {rw['goal']} for the expert of {goal}")
        models[goal] = {"rho": rw["model"], "discriminator": rw["discriminator"]["model"],
                        "extract": {k: rw.get(k) for k in ("balanced_accuracy", "auc", "argmax_cell", "goal_recovered")}
                        | {"discriminator_auc": rw["discriminator"]["auc"],
                           "discriminator_balanced_accuracy": rw["discriminator"]["balanced_accuracy"]}}
    for m in models.values():
        m["sha256"] = {m[arm]: client.get_model(m[arm]).sha256 for arm in ("rho", "discriminator")}
    done.write_text(json.dumps({"key": key, "models": {f"{g[0]},{g[1]}": m for g, m in models.items()}}, indent=1)
                    + "\n")
    return models


def _constant_reward_wrapper():
    from stable_baselines3.common.vec_env import VecEnvWrapper

    class ConstantReward(VecEnvWrapper):
        """The floor arm: reward 0 every step; infos[i]["env_reward"] keeps PointMaze's."""

        def reset(self):
            return self.venv.reset()

        def step_wait(self):
            obs, env_reward, dones, infos = self.venv.step_wait()
            for i, info in enumerate(infos):
                info["env_reward"] = float(env_reward[i])
            return obs, np.zeros_like(env_reward, dtype=np.float32), dones, infos

    return ConstantReward


def episode_metrics(model, goal: tuple[int, int], cap: int, seeds: list[int]) -> list[dict[str, float]]:
    """Each episode from reset(seed=s), deterministic actions: final distance to the goal cell's
    centre (cells), success (final distance <= 0.5), fraction of steps within 0.5."""
    from relreward.rl import pointmaze_mapping

    env = make_env(goal, cap)
    maze = env.unwrapped.maze
    to_maze_frame = pointmaze_mapping(maze.maze_map, maze.maze_size_scaling)
    centre = maze.cell_rowcol_to_xy(np.array(goal))
    out = []
    for s in seeds:
        o, _ = env.reset(seed=int(s))
        dists = []
        for _ in range(cap):
            a, _ = model.predict(o, deterministic=True)
            o, _, terminated, truncated, _ = env.step(a)
            dists.append(float(np.linalg.norm(o["achieved_goal"] - centre)) / maze.maze_size_scaling)
            if terminated or truncated:
                break
        d = np.array(dists)
        _, final = to_maze_frame({"observation": o["observation"][None]}, np.zeros((1, 2)))
        out.append({"seed": int(s), "final_position": [round(float(v), 3) for v in final[0, :2]],
                    "final_distance": float(d[-1]), "success": bool(d[-1] <= generate.GOAL_RADIUS),
                    "time_within": float(np.mean(d <= generate.GOAL_RADIUS)), "steps": len(d)})
    env.close()
    return out


def train(cfg: Config, client, goal: tuple[int, int], arm: str, seed: int, models: dict[str, str]) -> dict:
    import torch
    from stable_baselines3 import SAC
    from stable_baselines3.common.callbacks import BaseCallback
    from stable_baselines3.common.env_util import make_vec_env
    from stable_baselines3.common.vec_env import VecNormalize

    from relreward.rl import SB3RewardWrapper, pointmaze_mapping

    torch.set_num_threads(cfg.torch_threads)
    venv = make_vec_env(lambda: make_env(goal, cfg.cap), n_envs=cfg.n_envs, seed=seed * 1000)
    if arm in ("rho", "discriminator"):
        maze = venv.envs[0].unwrapped.maze
        venv = SB3RewardWrapper(venv, client, models[arm], mapping=pointmaze_mapping(maze.maze_map,
                                                                                     maze.maze_size_scaling))
    elif arm == "constant":
        venv = _constant_reward_wrapper()(venv)
    elif arm != "env":
        raise ValueError(f"arms: unknown arm {arm!r} (one of {', '.join(ARMS)})")
    if cfg.normalize:
        venv = VecNormalize(venv, norm_obs=False, norm_reward=True)

    curve: list[dict[str, float]] = []
    seen = {"n": 0, "sum": 0.0, "sumsq": 0.0, "min": math.inf, "max": -math.inf}
    curve_seeds = [CURVE_SEED + k for k in range(cfg.curve_episodes)]

    class Track(BaseCallback):
        """Records the rewards SAC trains on (before normalisation) and the learning curve."""

        def __init__(self):
            super().__init__()
            self.next_eval = cfg.eval_every

        def _on_step(self) -> bool:
            env = self.training_env
            r = env.get_original_reward() if isinstance(env, VecNormalize) else self.locals["rewards"]
            r = np.asarray(r, np.float64)
            seen["n"] += r.size
            seen["sum"] += float(r.sum())
            seen["sumsq"] += float((r * r).sum())
            seen["min"], seen["max"] = min(seen["min"], float(r.min())), max(seen["max"], float(r.max()))
            if self.num_timesteps >= self.next_eval:
                self.next_eval += cfg.eval_every
                curve.append(point(self.model, self.num_timesteps))
            return True

    def point(model, steps: int) -> dict[str, float]:
        eps = episode_metrics(model, goal, cfg.cap, curve_seeds)
        return {"steps": steps, "success": float(np.mean([e["success"] for e in eps])),
                "final_distance": float(np.mean([e["final_distance"] for e in eps]))}

    model = SAC("MultiInputPolicy", venv, seed=seed, learning_starts=cfg.learning_starts, batch_size=cfg.batch_size,
                gradient_steps=cfg.gradient_steps, policy_kwargs={"net_arch": list(cfg.net)}, verbose=0,
                device="cpu")
    t0 = time.time()
    model.learn(total_timesteps=cfg.steps, callback=Track())
    train_s = time.time() - t0
    if not curve or curve[-1]["steps"] != model.num_timesteps:
        curve.append(point(model, model.num_timesteps))
    episodes = episode_metrics(model, goal, cfg.cap, [EVAL_SEED + k for k in range(cfg.eval_episodes)])
    (cfg.work / "agents").mkdir(exist_ok=True)
    model.save(cfg.work / "agents" / f"{goal[0]}-{goal[1]}-{arm}-{seed}.zip")
    venv.close()
    n = max(seen["n"], 1)
    mean = seen["sum"] / n
    return {"goal": list(goal), "arm": arm, "seed": seed, "env_steps": int(model.num_timesteps),
            "train_seconds": train_s, "curve": curve, "episodes": episodes,
            "success": float(np.mean([e["success"] for e in episodes])),
            "time_within": float(np.mean([e["time_within"] for e in episodes])),
            "final_distance": float(np.mean([e["final_distance"] for e in episodes])),
            "train_rewards": {"mean": mean, "std": math.sqrt(max(seen["sumsq"] / n - mean * mean, 0.0)),
                              "min": seen["min"], "max": seen["max"], "count": seen["n"]}}


def table(cfg: Config, runs: list[dict]) -> str:
    lines = [f"SAC, {cfg.steps} environment steps per agent ({cfg.n_envs} environments, {cfg.gradient_steps} "
             f"gradient steps per vector step), {cfg.eval_episodes} evaluation episodes of {cfg.cap} steps per agent "
             f"(seeds {EVAL_SEED}+k); mean over training seeds, each seed's value in brackets.", "",
             "| goal | arm | success | time within 0.5 | final distance (cells) | training s per agent |",
             "|---|---|---|---|---|---|"]
    for goal in cfg.goals:
        for arm in cfg.arms:
            rs = [r for r in runs if tuple(r["goal"]) == goal and r["arm"] == arm]
            if not rs:
                continue

            def cell(k: str, fmt: str = "{:.2f}") -> str:
                return f"{fmt.format(np.mean([r[k] for r in rs]))} ({', '.join(fmt.format(r[k]) for r in rs)})"

            lines.append(f"| {goal[0]},{goal[1]} | {arm} | {cell('success')} | {cell('time_within')} | "
                         f"{cell('final_distance')} | {np.mean([r['train_seconds'] for r in rs]):.0f} |")
    return "\n".join(lines) + "\n"


def plot(cfg: Config, runs: list[dict], path: Path) -> None:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    fig, axes = plt.subplots(1, len(cfg.goals), figsize=(4 * len(cfg.goals), 3.2), squeeze=False, sharey=True)
    for ax, goal in zip(axes[0], cfg.goals):
        for i, arm in enumerate(cfg.arms):
            for j, r in enumerate(r for r in runs if tuple(r["goal"]) == goal and r["arm"] == arm):
                ax.plot([p["steps"] for p in r["curve"]], [p["success"] for p in r["curve"]], color=f"C{i}",
                        marker=".", alpha=0.8, label=arm if j == 0 else None)
        ax.set_title(f"goal {goal[0]},{goal[1]}")
        ax.set_xlabel("environment steps")
        ax.set_ylim(-0.05, 1.05)
    axes[0][0].set_ylabel(f"success ({cfg.curve_episodes} episodes)")
    axes[0][0].legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def run_file(cfg: Config, goal: tuple[int, int], arm: str, seed: int) -> Path:
    return cfg.work / "runs" / f"{goal[0]}-{goal[1]}-{arm}-{seed}.json"


def run_key(cfg: Config, goal: tuple[int, int], arm: str, seed: int, models: dict[str, Any]) -> dict:
    """What makes one agent: the training and evaluation settings and the reward's exact weights."""
    key = {k: getattr(cfg, k) for k in ("steps", "n_envs", "gradient_steps", "learning_starts", "batch_size", "net",
                                        "normalize", "cap", "eval_episodes", "curve_episodes", "eval_every")}
    key.update(goal=list(goal), arm=arm, seed=seed, net=list(cfg.net))
    if arm in ("rho", "discriminator"):
        key["reward_sha256"] = models["sha256"][models[arm]]
    return key


def run_agent(cfg: Config, addr: str, goal: tuple[int, int], arm: str, seed: int, models: dict[str, Any]) -> dict:
    """Trains and evaluates one agent and records it in WORK/runs/ (written whole or not at all)."""
    import relreward
    client = relreward.Client(addr)
    try:
        run = train(cfg, client, goal, arm, seed, models)
    finally:
        client.close()
    path = run_file(cfg, goal, arm, seed)
    path.parent.mkdir(exist_ok=True)
    tmp = path.with_suffix(".tmp")
    tmp.write_text(json.dumps({"key": run_key(cfg, goal, arm, seed, models), "run": run}, indent=1) + "\n")
    tmp.replace(path)
    return run


def finished_run(cfg: Config, goal: tuple[int, int], arm: str, seed: int, models: dict[str, Any]) -> dict | None:
    path = run_file(cfg, goal, arm, seed)
    if not path.exists():
        return None
    rec = json.loads(path.read_text())
    return rec["run"] if rec["key"] == run_key(cfg, goal, arm, seed, models) else None


def run_agents(cfg: Config, addr: str, models: dict, todo: list[tuple[tuple[int, int], str, int]]) -> None:
    """Every agent of `todo`, cfg.workers at a time. With one worker they train in this process;
    with more, each in a process of its own (`rl.py --worker SPEC`; its log in WORK/logs/), since
    SAC's updates run on one core each and the machine's cores are otherwise idle."""
    def report(goal, arm, seed, r):
        cfg.log(f"goal {goal} {arm} seed {seed}: success {r['success']:.2f}, within {r['time_within']:.2f}, "
                f"final distance {r['final_distance']:.2f} ({r['train_seconds']:.0f} s)")

    if cfg.workers == 1:
        for goal, arm, seed in todo:
            report(goal, arm, seed, run_agent(cfg, addr, goal, arm, seed, models[goal]))
        return
    (cfg.work / "logs").mkdir(exist_ok=True)
    spec_cfg = {k: (str(v) if isinstance(v, Path) else v) for k, v in asdict(cfg).items() if k != "log"}
    pending, running = list(todo), {}
    try:
        while pending or running:
            while pending and len(running) < cfg.workers:
                goal, arm, seed = task = pending.pop(0)
                name = f"{goal[0]}-{goal[1]}-{arm}-{seed}"
                spec = cfg.work / "logs" / f"{name}.spec.json"
                spec.write_text(json.dumps({"config": spec_cfg, "addr": addr, "goal": list(goal), "arm": arm,
                                            "seed": seed, "models": models[goal]}))
                log = open(cfg.work / "logs" / f"{name}.log", "w")
                running[task] = (subprocess.Popen([sys.executable, str(Path(__file__).resolve()), "--worker",
                                                   str(spec)], stdout=log, stderr=subprocess.STDOUT), log)
            time.sleep(0.5)
            for task, (proc, log) in list(running.items()):
                if proc.poll() is None:
                    continue
                log.close()
                del running[task]
                goal, arm, seed = task
                if proc.returncode != 0:
                    tail = Path(log.name).read_text()[-3000:]
                    raise RuntimeError(f"agent {task} failed (exit {proc.returncode}); {log.name}:\n{tail}")
                report(goal, arm, seed, finished_run(cfg, goal, arm, seed, models[goal]))
    finally:
        for proc, log in running.values():
            proc.kill()
            proc.wait()
            log.close()


def experiment(cfg: Config, server) -> dict:
    """Every goal, arm and seed against `server` (a relreward_dev.launcher.Server: the CLI's
    extract runs through it); writes and returns the results. Agents already recorded in
    WORK/runs/ with the same settings and rewards are reused, not retrained."""
    cfg.work.mkdir(parents=True, exist_ok=True)
    t0 = time.time()
    models = prepare(cfg, server)
    prep_s = time.time() - t0
    tasks = [(goal, arm, seed) for goal in cfg.goals for seed in range(cfg.seeds) for arm in cfg.arms]
    todo = [t for t in tasks if finished_run(cfg, *t, models[t[0]]) is None]
    if len(todo) < len(tasks):
        cfg.log(f"reusing {len(tasks) - len(todo)} agents recorded in WORK/runs/")
    run_agents(cfg, server.addr, models, todo)
    runs = [finished_run(cfg, goal, arm, seed, models[goal])
            for goal in cfg.goals for arm in cfg.arms for seed in range(cfg.seeds)]
    result = {"config": {k: (str(v) if isinstance(v, Path) else v) for k, v in asdict(cfg).items() if k != "log"},
              "models": {f"{g[0]},{g[1]}": m for g, m in models.items()}, "prepare_seconds": prep_s,
              "trained_now": len(todo), "total_seconds": time.time() - t0, "runs": runs}
    (cfg.work / "results.json").write_text(json.dumps(result, indent=1) + "\n")
    (cfg.work / "curves.json").write_text(json.dumps(
        [{k: r[k] for k in ("goal", "arm", "seed", "curve")} for r in runs], indent=1) + "\n")
    plot(cfg, runs, cfg.work / "curves.png")
    (cfg.work / "results.md").write_text(table(cfg, runs))
    return result


def worker(spec_path: Path) -> None:
    """One agent, as run_agents' child process: the spec names the settings, server and reward."""
    spec = json.loads(spec_path.read_text())
    c = spec["config"]
    c.update(work=Path(c["work"]), goals=tuple(tuple(g) for g in c["goals"]), arms=tuple(c["arms"]),
             net=tuple(c["net"]))
    cfg = Config(**c)
    goal = tuple(spec["goal"])
    run_agent(cfg, spec["addr"], goal, spec["arm"], spec["seed"], spec["models"])


def parse_goal(s: str) -> tuple[int, int]:
    try:
        r, c = (int(v) for v in s.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(f"goals: {s!r} is not ROW,COL") from None
    try:
        maze_map((r, c))
    except ValueError as e:
        raise argparse.ArgumentTypeError(str(e)) from None
    return r, c


def main() -> None:
    if len(sys.argv) == 3 and sys.argv[1] == "--worker":
        worker(Path(sys.argv[2]))
        return
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    d = Config(work=Path("rl-pointmaze-out"))
    p.add_argument("--work", type=Path, default=d.work)
    p.add_argument("--goals", type=parse_goal, nargs="+", default=d.goals,
                   help="ROW,COL ... (default: the four umaze goals)")
    p.add_argument("--arms", type=lambda s: tuple(s.split(",")), default=d.arms, help=",".join(ARMS))
    p.add_argument("--seeds", type=int, default=d.seeds, help="training seeds per arm and goal (0..N-1)")
    p.add_argument("--steps", type=int, default=d.steps, help="environment steps per agent")
    p.add_argument("--n-envs", type=int, default=d.n_envs)
    p.add_argument("--gradient-steps", type=int, default=d.gradient_steps, help="SAC updates per vector step")
    p.add_argument("--learning-starts", type=int, default=d.learning_starts)
    p.add_argument("--batch-size", type=int, default=d.batch_size)
    p.add_argument("--net", type=lambda s: tuple(int(v) for v in s.split(",")), default=d.net)
    p.add_argument("--no-normalize", dest="normalize", action="store_false")
    p.add_argument("--cap", type=int, default=d.cap, help="episode length (generate.py's umaze cap)")
    p.add_argument("--eval-episodes", type=int, default=d.eval_episodes)
    p.add_argument("--curve-episodes", type=int, default=d.curve_episodes)
    p.add_argument("--eval-every", type=int, default=d.eval_every)
    p.add_argument("--base-transitions", type=int, default=d.base_transitions)
    p.add_argument("--expert-transitions", type=int, default=d.expert_transitions)
    p.add_argument("--extract-size", choices=("tiny", "default", "full"), default=d.extract_size)
    p.add_argument("--data-seed", type=int, default=d.data_seed)
    p.add_argument("--torch-threads", type=int, default=d.torch_threads, help="SAC's torch threads per agent")
    p.add_argument("--workers", type=int, default=d.workers,
                   help="agents trained at once, each in its own process (1: in this process)")
    a = vars(p.parse_args())
    a["goals"] = tuple(a["goals"])
    for arm in a["arms"]:
        if arm not in ARMS:
            p.error(f"--arms: unknown arm {arm!r} (one of {', '.join(ARMS)})")
    if len(set(a["goals"])) < len(a["goals"]):
        p.error(f"--goals: a goal is named twice in {a['goals']}")
    for k in ("seeds", "steps", "n_envs", "gradient_steps", "batch_size", "cap", "eval_episodes", "curve_episodes",
              "eval_every", "base_transitions", "expert_transitions", "torch_threads", "workers"):
        if a[k] < 1:
            p.error(f"--{k.replace('_', '-')}: {a[k]} is not a positive integer")
    if a["learning_starts"] < 0 or min(a["net"]) < 1:
        p.error("--learning-starts must be >= 0 and every --net width >= 1")
    cfg = Config(**a)
    from relreward_dev.launcher import Binaries, Server, ServerStartError
    data_dir = cfg.work / "server-data"
    data_dir.parent.mkdir(parents=True, exist_ok=True)
    try:
        server = Server(Binaries.of_checkout(REPO), data_dir, log_path=cfg.work / "server.log",
                        env={"RELREWARD__ENGINE__INTRA_OP_THREADS":
                             os.environ.get("RELREWARD__ENGINE__INTRA_OP_THREADS", "1")})
    except ServerStartError as e:
        sys.exit(f"rl.py: the server did not start ({e}); run `make build`")
    try:
        experiment(cfg, server)
    finally:
        server.stop(grace=5)
    print((cfg.work / "results.md").read_text())


if __name__ == "__main__":
    main()
