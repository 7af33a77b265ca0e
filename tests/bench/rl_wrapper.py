#!/usr/bin/env python3
"""The online reward wrapper (relreward.rl): what its reward should be, and what it costs.

`definitions`: the measurement behind docs/rl.md's choices, on a real reward and its data.
Replays recorded episodes (rows [a_n | s_n], as the wrapper builds them) through the reward and
compares, over base and expert steps: the per-step reward definitions (the score g of the h
rows ending at step n; rho of the H rows ending there; the difference of consecutive rho) by
their Spearman correlation with PointMaze's dense reward exp(-distance to the goal) and their
expert-vs-base AUC, per step and per episode; rho over longer items (H' = 4 .. 256 rows, from the
step values: rho of a windowed reward is the mean of its tiles); and the episode-start rules (rows
before the first: [0 | s_0] "rest", the first row repeated "first", the end padded with the
current row "end", or reward 0 until the window is full "zero") by how far their value at
pseudo-starts (a start placed mid-episode, where the real history is known) lies from the value
with the real history, relative to the values' spread. Numbers in docs/rl.md came from:

    python experiments/pointmaze/generate.py --maze umaze --mode base --transitions 100000 --seed 0 --out base.npz
    python experiments/pointmaze/generate.py --maze umaze --mode expert --goal 3,1 --variant d4rl \\
        --transitions 30000 --seed 1 --out expert.npz
    target/release/relreward-server --listen 127.0.0.1:50613 --data-dir /tmp/rl-data &
    target/release/relreward --endpoint http://127.0.0.1:50613 extract --base base.npz --expert expert.npz \\
        --goal 3,1 --name pm --out out --discriminator
    .venv/bin/python tests/bench/rl_wrapper.py definitions --endpoint 127.0.0.1:50613 \\
        --reward "$(target/release/relreward --endpoint http://127.0.0.1:50613 model list --kind reward \\
                    | awk 'NR==2{print $1}')" \\
        --base base.npz --expert expert.npz --goal 3,1

`cost`: the wrapper's cost per vector step at 1, 8 and 64 sub-environments (RewardWindows.rewards:
the rows, one Score call, the rewards) against the same reward computed in-process by PyTorch
from the same weights (fetched with `download_model`, run by the PyTorch reference network of
bench/reference/grpc_server.py on the same items), both on one thread (server intra-op threads 1,
torch.set_num_threads(1)), alternating step by step; beside them, a Score of the same items
without per_window (rho only: the server runs the network once, against twice with it).
Starts its own server and trains the serving benchmarks' maze-shaped reward for one step
(tests/bench/python_client.py's: windowed MLP h = 4, hidden 128, 64, 32, items [64, 6]; weights
do not change the cost). Checks that the wrapper and the in-process pass give the same rewards first.

    .venv/bin/python tests/bench/rl_wrapper.py cost --steps 300 --reps 3
"""

from __future__ import annotations

import argparse
import os
import pathlib
import platform
import sys
import tempfile
import time

import numpy as np

import relreward
from relreward.rl import RewardWindows
from relreward_dev.launcher import Binaries, Server

# The serving benchmarks' maze-shaped reward, trained for one step (beside this file).
from python_client import train

REPO = pathlib.Path(__file__).resolve().parents[2]
BINARIES = Binaries.of_checkout(REPO)


# --------------------------------------------------------------------------------------------
# definitions


def ranks(v: np.ndarray) -> np.ndarray:
    r = np.empty(len(v))
    r[np.argsort(v, kind="stable")] = np.arange(len(v))
    return r


def spearman(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.corrcoef(ranks(a), ranks(b))[0, 1])


def auc(pos: np.ndarray, neg: np.ndarray) -> float:
    r = ranks(np.concatenate([pos, neg]))
    return float((r[:len(pos)].sum() - len(pos) * (len(pos) - 1) / 2) / (len(pos) * len(neg)))


def episodes(path: str, action_dim: int) -> list[np.ndarray]:
    """The file's episodes as rows [action | observation]."""
    d = np.load(path)
    ends = np.flatnonzero(d["terminals"] | d["timeouts"])
    starts = np.concatenate([[0], ends[:-1] + 1])
    rows = np.concatenate([d["actions"].reshape(len(d["actions"]), action_dim), d["observations"]], 1)
    return [rows[s:e + 1].astype(np.float32) for s, e in zip(starts, ends)]


def definitions(args: argparse.Namespace) -> None:
    client = relreward.Client(args.endpoint)
    model = client.get_model(args.reward)
    H, D = model.item_shape
    h = model.reward.window
    A = client.get_model(model.reward.base_model).manifest.space.action_dim
    goal = np.array([float(v) for v in args.goal.split(",")])
    rng = np.random.default_rng(args.seed)
    sets = {}
    for label, path, k in (("base", args.base, args.episodes), ("expert", args.expert, args.episodes // 2)):
        eps = [e for e in episodes(path, A) if len(e) >= 4 * H]
        sets[label] = [eps[i] for i in rng.choice(len(eps), min(k, len(eps)), replace=False)]

    def score(items: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        w, s = [], []
        for i in range(0, len(items), 4096):
            r = client.score(model.name, items[i:i + 4096], 0, per_window=True)
            w.append(r.rewards)
            s.append(r.per_window[:, -1])
        return np.concatenate(w), np.concatenate(s)

    def steady(ep: np.ndarray) -> dict[str, np.ndarray]:
        idx = np.arange(H - 1, len(ep))
        w, s = score(np.stack([ep[n - H + 1:n + 1] for n in idx]))
        dense = np.exp(-np.linalg.norm(ep[idx, A:A + 2] - goal, axis=1))
        return dict(step=s[1:], window=w[1:], diff=np.diff(w), dense=dense[1:])

    res = {k: [steady(e) for e in v] for k, v in sets.items()}
    cat = lambda label, key: np.concatenate([r[key] for r in res[label]])  # noqa: E731
    print(f"reward {model.name}: H = {H}, h = {h}, D = {D}; {len(sets['base'])} base and "
          f"{len(sets['expert'])} expert episodes; goal {args.goal}\n")
    print("| definition | Spearman with exp(-distance), base steps | expert steps | per-step AUC expert vs base "
          "| per-episode AUC |\n|---|---|---|---|---|")
    for d in ("step", "window", "diff"):
        per_episode = auc(np.array([r[d].mean() for r in res["expert"]]), np.array([r[d].mean() for r in res["base"]]))
        print(f"| {d} | {spearman(cat('base', d), cat('base', 'dense')):.3f} | "
              f"{spearman(cat('expert', d), cat('expert', 'dense')):.3f} | "
              f"{auc(cat('expert', d), cat('base', d)):.3f} | {per_episode:.3f} |")
    print("\nrho over the last H' rows (the mean of its tiles' step values), Spearman with "
          "exp(-distance):\n")
    sizes = [h * 2 ** i for i in range(7)]
    print("| steps | " + " | ".join(f"H' = {s}" for s in sizes) + " |\n|---|" + "---|" * len(sizes))
    for label in ("base", "expert"):
        cells = []
        for Hp in sizes:
            a, b = [], []
            for r in res[label]:
                s = r["step"]
                if len(s) <= Hp:
                    continue
                a.append(np.mean([s[Hp - h - j * h:len(s) - j * h] for j in range(Hp // h)], axis=0))
                b.append(r["dense"][Hp - h:])
            cells.append(f"{spearman(np.concatenate(a), np.concatenate(b)):.3f}" if a else "-")
        print(f"| {label} | " + " | ".join(cells) + " |")

    def padded(ep: np.ndarray, m: int, n: int, rule: str, L: int) -> np.ndarray:
        real = ep[m:n + 1]
        k = L - len(real)
        if k <= 0:
            return real[-L:]
        if rule == "end":
            return np.concatenate([real, np.repeat(real[-1:], k, 0)])
        pad = np.repeat(real[:1], k, 0).copy()
        if rule == "rest":
            pad[:, :A] = 0
        return np.concatenate([pad, real])

    print("\nStart rules at pseudo-starts (the first L - 1 steps of a window of L rows): mean |value - value "
          "with the real history| / std of the latter (bias / std):\n")
    rules = ("rest", "first", "end", "zero")
    print("| steps, definition | " + " | ".join(rules) + " |\n|---|" + "---|" * len(rules))
    for label in ("base", "expert"):
        for definition, L in (("step", h), ("window", H)):
            truths, cands = [], {r: [] for r in rules[:3]}
            for ep in sets[label]:
                for m in rng.integers(H, len(ep) - H, 4):
                    for n in range(m, m + L - 1):
                        truths.append(ep[n - H + 1:n + 1])
                        for r in rules[:3]:
                            win = padded(ep, m, n, r, L)
                            cands[r].append(np.concatenate([np.repeat(win[:1], H - L, 0), win]) if L < H else win)
            tw, ts = score(np.stack(truths))
            truth = ts if definition == "step" else tw
            cells = []
            for r in rules:
                if r == "zero":
                    v = np.zeros_like(truth)
                else:
                    cw, cs = score(np.stack(cands[r]))
                    v = cs if definition == "step" else cw
                err = v - truth
                cells.append(f"{np.mean(np.abs(err)) / np.std(truth):.3f} ({np.mean(err) / np.std(truth):+.3f})")
            print(f"| {label}, {definition} (first {L - 1}) | " + " | ".join(cells) + " |")


# --------------------------------------------------------------------------------------------
# cost


def cost(args: argparse.Namespace) -> None:
    import torch

    from relreward_dev.served import RewardModel  # the PyTorch reference network on relreward's weights

    torch.set_num_threads(1)
    started = time.time()
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        d = pathlib.Path(tmp)
        server = Server(BINARIES, d / "data", env={"RELREWARD__ENGINE__INTRA_OP_THREADS": "1"})
        try:
            name = train(server, d)
            client = relreward.Client(server.addr)
            got = client.download_model(name, d / "download")
            local = RewardModel(name, got.manifest, got.path)
            rng = np.random.default_rng(0)
            for n in (1, 8, 64):
                windows = RewardWindows(client, name, n)
                windows.begin(rng.uniform(0, 3, (n, 4)).astype(np.float32))

                def in_process() -> np.ndarray:
                    with torch.no_grad():
                        x = (torch.from_numpy(np.array(windows.items)) - local.offset) * local.scale
                        return local.net.per_window(x, torch.zeros(n, dtype=torch.long))[:, -1].numpy()

                def wrapper() -> np.ndarray:
                    windows.begin(rng.uniform(0, 3, (n, 4)).astype(np.float32), np.zeros(n, bool))
                    return windows.rewards(rng.uniform(-1, 1, (n, 2)).astype(np.float32))

                def rho_only() -> np.ndarray:  # the same items, Score without per_window: one pass
                    return client.score(name, windows.items, 0).rewards

                served = wrapper()
                np.testing.assert_allclose(in_process(), served, rtol=1e-4, atol=1e-5)
                for _ in range(50):  # warm-up
                    wrapper(), in_process(), rho_only()
                samples = {"wrapper": [], "in-process": [], "rho only": []}
                for _ in range(args.reps):
                    for i in range(args.steps):
                        order = (("wrapper", wrapper), ("in-process", in_process), ("rho only", rho_only))
                        for who, call in (order if i % 2 == 0 else order[::-1]):
                            t0 = time.perf_counter()
                            call()
                            samples[who].append(time.perf_counter() - t0)
                rows.append((n, {k: np.array(v) * 1e3 for k, v in samples.items()}))
            client.close()
        finally:
            server.stop()
    cpu = "unknown"
    try:
        cpu = next(line.split(":", 1)[1].strip() for line in open("/proc/cpuinfo") if line.startswith("model name"))
    except (OSError, StopIteration):
        pass
    print(f"Machine: {cpu}, {os.cpu_count()} CPUs, Python {platform.python_version()}, torch {torch.__version__}; "
          f"{args.reps} rounds of {args.steps} steps per size, alternating; {time.time() - started:.0f} s in all.\n")
    print("| sub-environments | wrapper p50 ms | p99 ms | in-process PyTorch p50 ms | p99 ms | ratio (p50) "
          "| Score without per_window, p50 ms |")
    print("|---|---|---|---|---|---|---|")
    for n, s in rows:
        w, p = s["wrapper"], s["in-process"]
        print(f"| {n} | {np.percentile(w, 50):.3f} | {np.percentile(w, 99):.3f} | {np.percentile(p, 50):.3f} | "
              f"{np.percentile(p, 99):.3f} | {np.percentile(w, 50) / np.percentile(p, 50):.2f} | "
              f"{np.percentile(s['rho only'], 50):.3f} |")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = ap.add_subparsers(dest="command", required=True)
    m = sub.add_parser("definitions", help="the reward definitions and start rules, measured")
    m.add_argument("--endpoint", required=True)
    m.add_argument("--reward", required=True, help="a windowed reward model on the server")
    m.add_argument("--base", required=True, help="base data (.npz, relreward's maze frame)")
    m.add_argument("--expert", required=True, help="expert data (.npz)")
    m.add_argument("--goal", required=True, help="the expert's goal position ROW,COL")
    m.add_argument("--episodes", type=int, default=40, help="base episodes (half as many expert ones)")
    m.add_argument("--seed", type=int, default=0)
    c = sub.add_parser("cost", help="cost per vector step against in-process PyTorch")
    c.add_argument("--steps", type=int, default=300)
    c.add_argument("--reps", type=int, default=3)
    args = ap.parse_args()
    definitions(args) if args.command == "definitions" else cost(args)


if __name__ == "__main__":
    main()
