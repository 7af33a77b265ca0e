"""Algorithm 1 at the paper's maze size on one device, PyTorch eager and torch.compile.

    gpu_alg1.py [--device cuda] [--batch 256] [--horizon 256] [--steps 50] [--warmup 10]
                [--compile] [--tf32]

The paper's Maze2D sizes (Diffuser's maze2d config): TemporalUnet(dim 32, dim_mults (1, 4, 8))
over state-action windows [horizon 256, 6] (Maze2D: 4 observation + 2 action coordinates),
Diffuser's cosine schedule, T = 256, x0 parametrization; the reward is Diffuser's
ValueFunction encoder (widths 32, 128, 256; relreward's `value_function` default); batch 256.
Same networks and step as bench.py alg1 (reference.py's alg1_step: x_t from the forward
process, target mu_expert - mu_base under no-grad, loss ||grad_x rho - target||^2 with the
double backward, Adam, EMA); weights are PyTorch's default initialisation (a step's cost does
not depend on them).

Why this script and not bench.py: bench.py reads the models from a relreward data directory
and runs on the CPU; this one builds them from the manifest and runs wherever `--device`
points, so it can be carried to a GPU machine that has PyTorch but no relreward build
(BENCHMARKS.md, "Algorithm 1 on a GPU"). Prints one JSON line.
"""

import argparse
import json
import time

import torch

from reference import Diffusion, Ema, alg1_step
from relreward_dev.nets import build as build_denoiser
from relreward_dev.reward_nets import build as build_reward


def on_device(diffusion, device):
    diffusion.net.to(device)
    diffusion.buffers = {k: v.to(device) for k, v in diffusion.buffers.items()}
    return diffusion


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    ap.add_argument("--batch", type=int, default=256)
    ap.add_argument("--horizon", type=int, default=256)
    ap.add_argument("--n-timesteps", type=int, default=256)
    ap.add_argument("--steps", type=int, default=50)
    ap.add_argument("--warmup", type=int, default=10)
    ap.add_argument("--compile", action="store_true", help="torch.compile the two frozen denoisers")
    ap.add_argument("--tf32", action="store_true", help="allow TF32 matmuls and convolutions")
    args = ap.parse_args()
    if args.warmup < 1 or args.steps < 1:
        ap.error("--warmup and --steps must be at least 1")
    device = torch.device(args.device)
    torch.manual_seed(0)
    if args.tf32:
        torch.backends.cuda.matmul.allow_tf32 = True
        torch.backends.cudnn.allow_tf32 = True

    space = {"kind": "trajectory", "horizon": args.horizon, "obs_dim": 4, "action_dim": 2}
    manifest = {
        "parametrization": "x0",
        "clip_denoised": True,
        "n_timesteps": args.n_timesteps,
        "schedule": {"kind": "diffuser_cosine"},
        "space": space,
    }
    arch = {"kind": "temporal_unet", "dim": 32, "dim_mults": [1, 4, 8]}
    base = on_device(Diffusion(build_denoiser(arch, space).eval(), manifest), device)
    expert = on_device(Diffusion(build_denoiser(arch, space).eval(), manifest), device)
    for net in (base.net, expert.net):
        for p in net.parameters():
            p.requires_grad_(False)
    reward = build_reward({"kind": "value_function", "widths": [32, 128, 256]}, [args.horizon, 6]).to(device)
    optimizer = torch.optim.Adam(reward.parameters(), lr=5e-5)
    ema = Ema(reward)

    compile_seconds = None
    if args.compile:
        base.net = torch.compile(base.net)
        expert.net = torch.compile(expert.net)

    def sync():
        if device.type == "cuda":
            torch.cuda.synchronize(device)

    x0_all = torch.rand(4096, args.horizon, 6, device=device) * 2 - 1

    def step(i):
        idx = torch.randint(0, x0_all.shape[0], (args.batch,), device=device)
        x0 = x0_all[idx]
        t = torch.randint(0, args.n_timesteps, (args.batch,), device=device)
        noise = torch.randn_like(x0)
        return alg1_step(base, expert, reward, optimizer, ema, i, x0, t, noise)

    start = time.perf_counter()
    loss = step(0)
    sync()
    first = time.perf_counter() - start
    if args.compile:
        compile_seconds = first
    for i in range(1, args.warmup):
        loss = step(i)
    sync()
    start = time.perf_counter()
    for i in range(args.warmup, args.warmup + args.steps):
        loss = step(i)
    sync()
    elapsed = time.perf_counter() - start
    out = {
        "benchmark": "alg1_paper_maze",
        "device": str(device),
        "device_name": torch.cuda.get_device_name(device) if device.type == "cuda" else "cpu",
        "torch": torch.__version__,
        "compile": args.compile,
        "tf32": args.tf32,
        "batch": args.batch,
        "horizon": args.horizon,
        "n_timesteps": args.n_timesteps,
        "steps": args.steps,
        "steps_per_s": args.steps / elapsed,
        "ms_per_step": 1000 * elapsed / args.steps,
        "first_step_s": first,
        "compile_seconds": compile_seconds,
        "loss": float(loss),
        "peak_mem_mib": torch.cuda.max_memory_allocated(device) / 2**20 if device.type == "cuda" else None,
    }
    print(json.dumps(out), flush=True)


if __name__ == "__main__":
    main()
