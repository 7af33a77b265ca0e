"""Bring your own image model: export a diffusers UNet2DModel and its DDPMScheduler as a
relreward TorchScript model (module.pt) with its manifest (manifest.json).

    python export_diffusers.py OUT_DIR [--unet DIR] [--scheduler DIR] [--check]

--unet / --scheduler: directories saved by `UNet2DModel.save_pretrained` and
`DDPMScheduler.save_pretrained` (local files only; nothing is fetched). Without them a small,
seeded, randomly initialised UNet2DModel and a DDPMScheduler with a cosine schedule stand in
(what server/tests/diffusers_torchscript.rs uses; no hub is reachable here).

The manifest takes everything from the scheduler's config:
- schedule: the scheduler's own betas, listed explicitly (`{"kind": "betas"}`), so any
  beta_schedule (linear, scaled_linear, squaredcos_cap_v2, trained_betas) is reproduced exactly;
- n_timesteps: num_train_timesteps; parametrization: prediction_type "epsilon" -> epsilon,
  "sample" -> x0, "v_prediction" -> v;
- clip_denoised: clip_sample (clip_sample_range must be 1, thresholding off);
- space: the UNet's [in_channels, sample_size, sample_size]; normalizer: identity (diffusers
  models take their inputs already scaled).

The module is the UNet traced with torch.jit.trace as forward(x [B, C, H, W] float32,
t [B] int64) -> eps (or x0) [B, C, H, W]. Upload it with
`relreward model upload module.pt --manifest manifest.json --name NAME` (the server needs
models.allow_torchscript_upload: a TorchScript file is a program).

--check also writes check.safetensors: inputs x, t and diffusers' own eps = unet(x, t).sample and
posterior mean (DDPMScheduler.step's prev_sample with its noise set to zero), which the test
compares with relreward's eps_hat and model_mean.
"""

import argparse
import json
import pathlib
import sys

import torch
from diffusers import DDPMScheduler, UNet2DModel
from diffusers.schedulers import scheduling_ddpm


class Denoiser(torch.nn.Module):
    def __init__(self, unet):
        super().__init__()
        self.unet = unet

    def forward(self, x, t):
        return self.unet(x, t).sample


def manifest_of(unet, sched):
    cfg = sched.config
    prediction = {"epsilon": "epsilon", "sample": "x0", "v_prediction": "v"}.get(cfg.prediction_type)
    if prediction is None:
        sys.exit(f"prediction_type {cfg.prediction_type!r}: relreward takes epsilon, sample or v_prediction")
    if cfg.thresholding or (cfg.clip_sample and cfg.clip_sample_range != 1.0):
        sys.exit("thresholding and clip_sample_range != 1 have no relreward equivalent")
    size = unet.config.sample_size
    h, w = (size, size) if isinstance(size, int) else tuple(size)
    if unet.config.in_channels != unet.config.out_channels:
        sys.exit("in_channels and out_channels differ: not a denoiser of its own input")
    return {
        "parametrization": prediction,
        "schedule": {"kind": "betas", "betas": [float(b) for b in sched.betas.double()]},
        "n_timesteps": int(cfg.num_train_timesteps),
        "clip_denoised": bool(cfg.clip_sample),
        "space": {"kind": "sample", "shape": [int(unet.config.in_channels), int(h), int(w)]},
        "normalizer": {"kind": "identity"},
    }


def stand_ins():
    torch.manual_seed(0)
    unet = UNet2DModel(sample_size=8, in_channels=2, out_channels=2, block_out_channels=(16, 32),
                       layers_per_block=1, down_block_types=("DownBlock2D", "AttnDownBlock2D"),
                       up_block_types=("AttnUpBlock2D", "UpBlock2D"), norm_num_groups=8, attention_head_dim=8)
    # Move every weight off its initial value so that GroupNorm's ones and zeros take part.
    with torch.no_grad():
        for p in unet.parameters():
            p.add_(torch.randn_like(p) * 0.05)
    sched = DDPMScheduler(num_train_timesteps=100, beta_schedule="squaredcos_cap_v2", clip_sample=True)
    return unet, sched


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("out", type=pathlib.Path)
    ap.add_argument("--unet", type=pathlib.Path)
    ap.add_argument("--scheduler", type=pathlib.Path)
    ap.add_argument("--check", action="store_true")
    args = ap.parse_args()
    if (args.unet is None) != (args.scheduler is None):
        sys.exit("give both --unet and --scheduler, or neither")
    if args.unet is not None:
        unet = UNet2DModel.from_pretrained(args.unet, local_files_only=True)
        sched = DDPMScheduler.from_pretrained(args.scheduler, local_files_only=True)
    else:
        unet, sched = stand_ins()
    unet.eval()
    manifest = manifest_of(unet, sched)
    args.out.mkdir(parents=True, exist_ok=True)
    shape = manifest["space"]["shape"]
    example = (torch.randn(2, *shape), torch.tensor([0, manifest["n_timesteps"] - 1]))
    with torch.no_grad():
        traced = torch.jit.trace(Denoiser(unet), example, check_trace=False)
    traced.save(str(args.out / "module.pt"))
    (args.out / "manifest.json").write_text(json.dumps(manifest, indent=1) + "\n")

    if args.check:
        # The test's side only (the development package, dev/python): the recipe itself needs
        # torch and diffusers alone.
        from relreward_dev.safetensors import write_safetensors

        g = torch.Generator().manual_seed(1)
        n = 5
        x = torch.randn(n, *shape, generator=g) * 1.5
        t = torch.tensor([0, 1, 37, 80, manifest["n_timesteps"] - 1])
        # DDPMScheduler.step adds std * randn_tensor(...) for t > 0; zero noise leaves the mean.
        scheduling_ddpm.randn_tensor = lambda shape, **kw: torch.zeros(shape, dtype=kw.get("dtype"))
        with torch.no_grad():
            eps = unet(x, t).sample
            mean = torch.cat([sched.step(eps[i:i + 1], int(t[i]), x[i:i + 1]).prev_sample for i in range(n)])
            traced_eps = traced(x, t)
        assert torch.allclose(traced_eps, eps, atol=1e-6), "the traced module differs from the UNet"
        write_safetensors(args.out / "check.safetensors", {"x": x, "t": t, "eps": eps, "mean": mean})
    print(f"wrote {args.out / 'module.pt'} and manifest.json ({sum(p.numel() for p in unet.parameters())} "
          f"parameters, schedule of {manifest['n_timesteps']} steps)")


if __name__ == "__main__":
    main()
