"""UNet2D training-step benchmark: relreward's native Unet2d (a DDPM diffusion job on the
server) against PyTorch eager running diffusers' UNet2DModel of the same configuration on the
same weights and the same sizes.

    .venv/bin/python tests/bench/unet2d.py [--steps 60] [--warmup 20] [--reps 3] [--threads 1]
                                           [--no-attention]

Both sides: items [1, 8, 8] (the digits experiment's), batch 64, eps prediction, linear betas,
T = 50, Adam lr 1e-3, UNet2D block_out_channels (32, 64), layers_per_block 1, attention at the
lowest resolution (none with --no-attention, the digits experiment's default network since its
EMA/attention change, 0.63M parameters), GroupNorm(8) (0.70M parameters with attention);
one libtorch intra-op thread on both sides (the server's engine.intra_op_threads, PyTorch's
torch.set_num_threads).

relreward: steps per second from the job's own progress events (every 10 steps) between step
WARMUP and WARMUP + STEPS, so start-up and the final held-out evaluation are excluded.
Reference: torch eager, the same loss (DDPMScheduler.add_noise, mean squared error), backward,
torch.optim.Adam step and zero_grad, timed over STEPS steps after WARMUP untimed ones, starting
from the weights relreward's job ended with (downloaded through the API, DownloadModel, and
loaded with load_state_dict(strict=True)). The two alternate REPS times; medians are reported with the
ratio relreward / reference (> 1: relreward is faster).
"""

import argparse
import json
import os
import pathlib
import statistics
import sys
import tempfile
import time

import numpy as np
import torch

from relreward import Client
from relreward.specs import DiffusionJob, Optimization
from relreward_dev.digits import load_digits_split
from relreward_dev.launcher import Binaries, Server
from relreward_dev.safetensors import read_safetensors

REPO = pathlib.Path(__file__).resolve().parents[2]

CONFIG = dict(channels=1, height=8, width=8, block_out_channels=[32, 64], layers_per_block=1, attention=True,
              norm_num_groups=8, attention_head_dim=8)
BATCH, T, LR = 64, 50, 1e-3


def relreward_rate(client, steps, warmup, rep, data):
    name = f"bench-unet2d-{rep}"
    spec = DiffusionJob(output_model=name, dataset="bench-digits", seed=rep,
                        optimization=Optimization(steps=warmup + steps, batch_size=BATCH, learning_rate=LR,
                                                  log_every=10, eval_every=10**9, checkpoint_every=10**9),
                        parametrization="epsilon", schedule="linear", n_timesteps=T,
                        architecture=("unet2d", {k: CONFIG[k] for k in
                                                 ("block_out_channels", "layers_per_block", "attention",
                                                  "norm_num_groups", "attention_head_dim")}),
                        clip_denoised=False, pooled_normalizer=True)
    job = client.submit_job(spec)
    seen = {}
    for ev in client.watch_job(job.id):
        if ev.type == "progress" and ev.step in (warmup, warmup + steps):
            seen[ev.step] = time.monotonic()
    done = client.get_job(job.id)
    if done.error:
        sys.exit(f"job failed: {done.error}")
    return steps / (seen[warmup + steps] - seen[warmup]), name


def reference_rate(steps, warmup, data, weights=None):
    from diffusers import DDPMScheduler
    from relreward_dev.unet2d import build, scheduler

    model = build(CONFIG)
    if weights is not None:
        model.load_state_dict(weights, strict=True)
    model.train()
    sched: DDPMScheduler = scheduler(T)
    opt = torch.optim.Adam(model.parameters(), lr=LR)
    x = torch.from_numpy(data)
    g = torch.Generator().manual_seed(0)

    def step():
        idx = torch.randint(0, len(x), (BATCH,), generator=g)
        x0 = x[idx]
        t = torch.randint(0, T, (BATCH,), generator=g)
        noise = torch.randn(x0.shape, generator=g)
        loss = torch.nn.functional.mse_loss(model(sched.add_noise(x0, noise, t), t).sample, noise)
        loss.backward()
        opt.step()
        opt.zero_grad(set_to_none=True)

    for _ in range(warmup):
        step()
    t0 = time.perf_counter()
    for _ in range(steps):
        step()
    return steps / (time.perf_counter() - t0)


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--steps", type=int, default=60)
    ap.add_argument("--warmup", type=int, default=20)
    ap.add_argument("--reps", type=int, default=3)
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--no-attention", action="store_true", help="no attention block (digits.py's default)")
    args = ap.parse_args()
    CONFIG["attention"] = not args.no_attention
    if args.steps % 10 or args.warmup % 10:
        sys.exit("--steps and --warmup must be multiples of 10 (the job's progress interval)")
    torch.set_num_threads(args.threads)
    os.environ["RELREWARD__ENGINE__INTRA_OP_THREADS"] = str(args.threads)

    def trained_weights(client, name, tmp):
        return read_safetensors(client.download_model(name, pathlib.Path(tmp) / "models" / name).path)

    x_train = load_digits_split(0)[0]
    # The job normalizes with the pooled mean and std; the reference trains on the same values.
    data = ((x_train - x_train.mean()) / x_train.std()).astype(np.float32)
    ours, theirs = [], []
    with tempfile.TemporaryDirectory(prefix="relreward-bench-unet2d-") as tmp:
        (pathlib.Path(tmp) / "data").mkdir()
        # As the digits experiment starts its server (experiments/images/digits.py).
        server = Server(Binaries.of_checkout(REPO), pathlib.Path(tmp) / "data",
                        env={"RELREWARD__JOBS__MAX_CONCURRENT": "2"}, log_path=pathlib.Path(tmp) / "server.log")
        try:
            client = Client(server.addr)
            client.upload_dataset("bench-digits", x_train, kind="samples")
            for rep in range(args.reps):
                rate, name = relreward_rate(client, args.steps, args.warmup, rep, data)
                ours.append(rate)
                weights = trained_weights(client, name, tmp)
                theirs.append(reference_rate(args.steps, args.warmup, data, weights))
                print(f"rep {rep}: relreward {ours[-1]:.2f} steps/s, PyTorch eager {theirs[-1]:.2f} steps/s",
                      flush=True)
        finally:
            server.stop(grace=20)
    a, b = statistics.median(ours), statistics.median(theirs)
    from relreward_dev.unet2d import build

    parameters = sum(p.numel() for p in build(CONFIG).parameters())
    print(json.dumps({"config": CONFIG, "batch": BATCH, "threads": args.threads, "steps": args.steps,
                      "warmup": args.warmup, "reps": args.reps, "relreward_steps_per_s": ours,
                      "pytorch_eager_steps_per_s": theirs, "median_relreward": a, "median_pytorch": b,
                      "ratio": a / b, "parameters": parameters},
                     indent=2))


if __name__ == "__main__":
    main()
