"""Times the PyTorch references (reference.py) on the work relreward does in
tests/bench/training.sh, and prints one JSON line per run.

    bench.py alg1   --models-dir DIR --base B --expert E --dataset maze.npz [--steps S --warmup W ...]
    bench.py ddpm   --dataset maze.npz --manifest-of B --models-dir DIR [--steps S --warmup W ...]
    bench.py sample --models-dir DIR --base B --reward R --n N [--repeats K ...]
    bench.py reward-step --horizon H --transition-dim D --n-timesteps T [--pool P --steps S ...]
    bench.py frozen-precision --horizon H --transition-dim D [--dim-mults 1,4,8 --batch B]

Models are read as relreward's API hands them out: DIR/NAME per model, as
`relreward model download NAME --out DIR/NAME` writes it (weights.safetensors and
manifest.json), so the reference runs the same diffusion models, with the same weights,
manifests and normalizer, as relreward. Trained
networks start from PyTorch's default initialisation (relreward's tch initialisation follows
the same scheme); their values do not change the cost of a step.

Training: `--warmup` steps untimed, then `--steps` timed steps, each drawing its batch (x0
windows from the dataset, t, noise) like relreward's jobs do, logging the loss (`.item()`, as
a researcher's loop prints it), Adam and the EMA (decay 0.995 every 10 steps from step 2000,
relreward's defaults). Sampling: three untimed guided steps, then `--repeats` timed runs of
Diffuser's guided p_sample_loop over `--n` trajectories in one batch.

`reward-step`: the reward's training step alone, as relreward's models-free amortised recipe
runs it (`tests/bench/reward_step.sh`): a pool of `--pool` (point, t, target) triples made once
(their values do not change the cost), then per step a batch gathered from the pool, the
alignment loss through the double backward, backward, Adam, the EMA and `.item()`. The reward
is the windowed MLP (`--window`, `--hidden`), or Diffuser's ValueFunction with `--widths`.

`frozen-precision`: one TemporalUnet forward pass (no gradient, PyTorch's initialisation) at
`--horizon`, `--transition-dim`, `--batch`, in float32 and under bfloat16 autocast, best of
three rounds of ten, with the largest output difference relative to the largest output: what
bf16 would buy the frozen models' passes, and cost their outputs, on this CPU.

`--compile` (alg1, ddpm): the same reference under `torch.compile` (inductor, the default
backend; on the CPU it generates C++/OpenMP kernels). Algorithm 1 compiles the two frozen
diffusion networks (where the step's time goes); the reward's double backward
(`autograd.grad(create_graph=True)` then `.backward()`) is not supported by compiled
autograd, so rho stays eager. DDPM compiles the denoiser (forward and backward through
AOTAutograd). `compile_seconds` is the wall time of the first step, which triggers the
compilation (the other warm-up steps then run the compiled code).

Each line also carries the multiply-accumulates of one forward pass of every network (counted
with hooks on the real modules, see reference.count_macs), the threads used and this
process's peak RSS.
"""

import argparse
import json
import pathlib
import sys
import time

import torch

from reference import (
    Diffusion,
    Ema,
    Windows,
    alg1_step,
    alignment_loss,
    count_macs,
    ddpm_step,
    guided_sample,
    guided_step,
    peak_rss_mib,
)
from relreward_dev.nets import build as build_denoiser
from relreward_dev.nets import item_shape
from relreward_dev.reward_nets import build as build_reward
from relreward_dev.safetensors import read_safetensors


def stored_model(models_dir, name):
    """(manifest, weights path) of a model downloaded into models_dir/name."""
    d = pathlib.Path(models_dir) / name
    if not (d / "manifest.json").is_file():
        sys.exit(f"bench.py: no model '{name}' in {models_dir} (relreward model download {name} --out {d})")
    return json.loads((d / "manifest.json").read_text()), d / "weights.safetensors"


def load_diffusion(models_dir, name):
    manifest, weights = stored_model(models_dir, name)
    net = build_denoiser(manifest["architecture"], manifest["space"])
    net.load_state_dict(read_safetensors(weights), strict=True)
    for p in net.parameters():
        p.requires_grad_(False)
    return Diffusion(net, manifest)


def normalize_obs(manifest, obs):
    """A raw observation in the model's normalized units (Limits normalizer over [action | obs])."""
    space, norm = manifest["space"], manifest["normalizer"]
    a = space["action_dim"]
    lo = torch.tensor(norm["min"][a:], dtype=torch.float64)
    hi = torch.tensor(norm["max"][a:], dtype=torch.float64)
    x = torch.tensor(obs, dtype=torch.float64)
    scale = torch.where(hi - lo > 1e-12, 2.0 / (hi - lo).clamp_min(1e-12), torch.zeros_like(lo))
    return ((x - (lo + hi) / 2) * scale).float()


def timed_training(step_fn, warmup, steps):
    """(seconds of the timed steps, seconds of the first step: the compile time under --compile)."""
    first = None
    for k in range(1, warmup + 1):
        start = time.perf_counter()
        step_fn(k).item()
        first = time.perf_counter() - start if first is None else first
    start = time.perf_counter()
    for k in range(warmup + 1, warmup + steps + 1):
        step_fn(k).item()
    return time.perf_counter() - start, first


def maybe_compile(module, args):
    """`module` under torch.compile (inductor) with --compile, else itself."""
    return torch.compile(module) if args.compile else module


def run_alg1(args):
    base, expert = load_diffusion(args.models_dir, args.base), load_diffusion(args.models_dir, args.expert)
    eager_net = base.net
    base.net, expert.net = maybe_compile(base.net, args), maybe_compile(expert.net, args)
    shape = item_shape(base.manifest["space"])
    arch = {"kind": "windowed_mlp", "window": args.window, "hidden": [int(h) for h in args.hidden.split(",")]}
    torch.manual_seed(args.seed)
    reward = build_reward(arch, shape)
    optimizer = torch.optim.Adam(reward.parameters(), lr=args.lr)
    ema = Ema(reward)
    data = Windows(args.dataset, shape[0])
    big_t = base.n_timesteps

    def step(k):
        x0 = data.batch(args.batch)
        t = torch.randint(big_t, (args.batch,))
        noise = torch.randn_like(x0)
        return alg1_step(base, expert, reward, optimizer, ema, k, x0, t, noise)

    seconds, first = timed_training(step, args.warmup, args.steps)
    x, t = torch.zeros(args.batch, *shape), torch.zeros(args.batch, dtype=torch.long)
    return {"steps": args.steps, "seconds": seconds, "steps_per_second": args.steps / seconds,
            "compiled": args.compile, "compile_seconds": first if args.compile else None,
            "macs": {"diffusion": count_macs(eager_net, x, t), "reward": count_macs(reward, x, t)},
            "parameters": {"diffusion": sum(p.numel() for p in eager_net.parameters()),
                           "reward": sum(p.numel() for p in reward.parameters())}}


def run_reward_step(args):
    shape = [args.horizon, args.transition_dim]
    if args.widths:
        arch = {"kind": "value_function", "widths": [int(w) for w in args.widths.split(",")]}
    else:
        arch = {"kind": "windowed_mlp", "window": args.window, "hidden": [int(h) for h in args.hidden.split(",")]}
    torch.manual_seed(args.seed)
    reward = build_reward(arch, shape)
    optimizer = torch.optim.Adam(reward.parameters(), lr=args.lr)
    ema = Ema(reward)
    points = torch.rand(args.pool, *shape) * 2 - 1
    targets = torch.randn(args.pool, *shape) * 0.1
    times = torch.randint(args.n_timesteps, (args.pool,))

    def step(k):
        pick = torch.randint(args.pool, (args.batch,))
        point, t, target = points.index_select(0, pick), times.index_select(0, pick), targets.index_select(0, pick)
        loss = alignment_loss(reward, point, t, target)
        loss.backward()
        optimizer.step()
        optimizer.zero_grad(set_to_none=True)
        ema.after_step(reward, k)
        return loss.detach()

    seconds, _ = timed_training(step, args.warmup, args.steps)
    return {"steps": args.steps, "seconds": seconds, "steps_per_second": args.steps / seconds,
            "parameters": {"reward": sum(p.numel() for p in reward.parameters())}}


def run_ddpm(args):
    # The architecture, schedule, parametrization and normalizer of a relreward model trained
    # with the benchmark's config; fresh weights (this is the model being trained).
    manifest, _ = stored_model(args.models_dir, args.manifest_of)
    torch.manual_seed(args.seed)
    net = build_denoiser(manifest["architecture"], manifest["space"])
    # Diffusion reads the network through .net; the compiled wrapper shares its parameters.
    model = Diffusion(maybe_compile(net, args), manifest)
    optimizer = torch.optim.Adam(net.parameters(), lr=args.lr)
    ema = Ema(net)
    shape = item_shape(manifest["space"])
    data = Windows(args.dataset, shape[0])

    def step(k):
        x0 = data.batch(args.batch)
        t = torch.randint(model.n_timesteps, (args.batch,))
        noise = torch.randn_like(x0)
        return ddpm_step(model, optimizer, ema, k, x0, t, noise)

    seconds, first = timed_training(step, args.warmup, args.steps)
    x, t = torch.zeros(args.batch, *shape), torch.zeros(args.batch, dtype=torch.long)
    return {"steps": args.steps, "seconds": seconds, "steps_per_second": args.steps / seconds,
            "compiled": args.compile, "compile_seconds": first if args.compile else None,
            "macs": {"diffusion": count_macs(net, x, t)},
            "parameters": {"diffusion": sum(p.numel() for p in net.parameters())}}


def run_sample(args):
    model = load_diffusion(args.models_dir, args.base)
    manifest, weights = stored_model(args.models_dir, args.reward)
    shape = item_shape(manifest["space"])
    reward = build_reward(manifest["architecture"], shape)
    reward.load_state_dict(read_safetensors(weights), strict=True)
    for p in reward.parameters():
        p.requires_grad_(False)
    conditions = []
    for spec in args.condition:
        index, values = spec.split("=")
        conditions.append((int(index), normalize_obs(model.manifest, [float(v) for v in values.split(",")])))
    guide = dict(omega=args.omega, n_guide_steps=args.n_guide_steps, t_stopgrad=args.t_stopgrad,
                 scale_grad_by_std=args.scale_grad_by_std)
    torch.manual_seed(args.seed)
    # Warm-up: a few guided steps at the timed batch size (oneDNN builds its kernels per shape).
    with torch.no_grad():
        x = torch.randn(args.n, *shape)
        for i in (model.n_timesteps - 1, 1, 0):
            x, _ = guided_step(model, reward, x, torch.full((args.n,), i), conditions, torch.randn_like(x), **guide)
    times = []
    for _ in range(args.repeats):
        start = time.perf_counter()
        x, y = guided_sample(model, reward, args.n, conditions, **guide)
        # relreward reports rho(x, 0) of each final sample; so does a planner ranking its plans.
        with torch.no_grad():
            reward(x, torch.zeros(args.n, dtype=torch.long))
        times.append(time.perf_counter() - start)
    times.sort()
    median = times[len(times) // 2]
    x, t = torch.zeros(args.n, *shape), torch.zeros(args.n, dtype=torch.long)
    return {"n": args.n, "seconds": median, "seconds_per_trajectory": median / args.n, "all_seconds": times,
            "macs": {"diffusion": count_macs(model.net, x, t), "reward": count_macs(reward, x, t)},
            "n_timesteps": model.n_timesteps}


def run_frozen_precision(args):
    from relreward_dev.nets import TemporalUnet
    torch.manual_seed(args.seed)
    mults = tuple(int(m) for m in args.dim_mults.split(","))
    net = TemporalUnet(args.transition_dim, dim=args.dim, dim_mults=mults).eval()
    x = torch.randn(args.batch, args.horizon, args.transition_dim)
    t = torch.randint(0, 20, (args.batch,))

    def best_ms():
        net(x, t)
        best = float("inf")
        for _ in range(3):
            start = time.perf_counter()
            for _ in range(10):
                net(x, t)
            best = min(best, (time.perf_counter() - start) / 10)
        return 1e3 * best

    with torch.no_grad():
        exact, float32_ms = net(x, t), best_ms()
        with torch.autocast("cpu", dtype=torch.bfloat16):
            bf16, bf16_ms = net(x, t).float(), best_ms()
    error = ((bf16 - exact).abs().max() / exact.abs().max()).item()
    return {"horizon": args.horizon, "batch": args.batch, "float32_ms": float32_ms, "bf16_autocast_ms": bf16_ms,
            "speedup": float32_ms / bf16_ms, "max_error_relative_to_max_output": error}


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest="benchmark", required=True)
    common = argparse.ArgumentParser(add_help=False)
    common.add_argument("--models-dir", required=True,
                        help="the models, downloaded: DIR/NAME each (relreward model download NAME --out DIR/NAME)")
    common.add_argument("--threads", type=int, required=True, help="torch.set_num_threads (relreward's intra-op threads)")
    common.add_argument("--seed", type=int, default=0)
    training = argparse.ArgumentParser(add_help=False)
    training.add_argument("--dataset", required=True, help="the .npz relreward was given")
    training.add_argument("--batch", type=int, default=64)
    training.add_argument("--steps", type=int, default=50)
    training.add_argument("--warmup", type=int, default=10)
    training.add_argument("--compile", action="store_true", help="torch.compile (inductor) the networks; see above")
    alg1 = sub.add_parser("alg1", parents=[common, training])
    alg1.add_argument("--base", required=True)
    alg1.add_argument("--expert", required=True)
    alg1.add_argument("--window", type=int, default=4)
    alg1.add_argument("--hidden", default="128,64,32")
    alg1.add_argument("--lr", type=float, default=5e-5)
    ddpm = sub.add_parser("ddpm", parents=[common, training])
    ddpm.add_argument("--manifest-of", required=True, help="a relreward model with the architecture to train")
    ddpm.add_argument("--lr", type=float, default=2e-4)
    sample = sub.add_parser("sample", parents=[common])
    sample.add_argument("--base", required=True)
    sample.add_argument("--reward", required=True)
    sample.add_argument("--n", type=int, default=64)
    sample.add_argument("--repeats", type=int, default=1)
    sample.add_argument("--omega", type=float, default=0.1)
    sample.add_argument("--n-guide-steps", type=int, default=1)
    sample.add_argument("--t-stopgrad", type=int, default=0)
    sample.add_argument("--scale-grad-by-std", action="store_true")
    sample.add_argument("--condition", action="append", default=[], help="INDEX=v1,v2,.. in raw units")
    step = sub.add_parser("reward-step")
    step.add_argument("--threads", type=int, required=True)
    step.add_argument("--seed", type=int, default=0)
    step.add_argument("--horizon", type=int, required=True)
    step.add_argument("--transition-dim", type=int, required=True)
    step.add_argument("--n-timesteps", type=int, required=True)
    step.add_argument("--window", type=int, default=4)
    step.add_argument("--hidden", default="128,64,32")
    step.add_argument("--widths", default="", help="a ValueFunction reward with these widths instead of the windowed MLP")
    step.add_argument("--batch", type=int, default=64)
    step.add_argument("--pool", type=int, default=4096)
    step.add_argument("--lr", type=float, default=1e-3)
    step.add_argument("--steps", type=int, default=1000)
    step.add_argument("--warmup", type=int, default=100)
    precision = sub.add_parser("frozen-precision")
    precision.add_argument("--threads", type=int, required=True)
    precision.add_argument("--seed", type=int, default=0)
    precision.add_argument("--horizon", type=int, required=True)
    precision.add_argument("--transition-dim", type=int, required=True)
    precision.add_argument("--dim", type=int, default=32)
    precision.add_argument("--dim-mults", default="1,2,4,8")
    precision.add_argument("--batch", type=int, default=64)
    args = parser.parse_args()

    torch.set_num_threads(args.threads)
    result = {"alg1": run_alg1, "ddpm": run_ddpm, "sample": run_sample,
              "reward-step": run_reward_step, "frozen-precision": run_frozen_precision}[args.benchmark](args)
    result.update({"benchmark": args.benchmark, "threads": torch.get_num_threads(), "torch": torch.__version__,
                   "peak_rss_mib": peak_rss_mib()})
    print(json.dumps(result))


if __name__ == "__main__":
    main()
