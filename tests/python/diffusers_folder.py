"""Folders written by diffusers' own save_pretrained, for `relreward model import DIR|ORG/NAME`,
and diffusers' outputs on them (server/tests/diffusers_folder.rs compares relreward's).

    python diffusers_folder.py OUT_DIR

Writes, each model small, seeded and randomly initialised (every weight moved off its
initial value, GroupNorm affines included):

- `unet1d/`: a UNet1DModel in the configuration diffusers' convert_models_diffuser_to_diffusers.py
  gives Diffuser's TemporalUnet (flip_sin_to_cos false, freq_shift 1), saved on its own with its
  DDPMScheduler in `scheduler/` (squaredcos_cap_v2, T = 20, epsilon, clip_sample);
- `hub/models--relreward-test--planner/`: a Hugging Face cache (HF_HOME=OUT_DIR, hub id
  relreward-test/planner, refs/main, snapshot files linked to blobs as huggingface_hub lays them
  out) holding a pipeline folder: `model_index.json`, `unet/` (a UNet1DModel with diffusers'
  default flip_sin_to_cos true), `scheduler/` (linear, T = 20, prediction_type sample,
  clip_sample);
- `unet2d/`: a UNet2DModel with attention at the lowest resolution (flip_sin_to_cos true),
  saved on its own with `scheduler/` (squaredcos_cap_v2, T = 100, epsilon, clip_sample);
- `pipeline2d/`: a DDPMPipeline's save_pretrained (`model_index.json`, `unet/`, `scheduler/`)
  of a UNet2DModel without attention (three levels, two layers per block, flip_sin_to_cos false,
  sample_size [8, 12]) and a scaled_linear schedule (T = 100, epsilon, no clipping,
  fixed_small_log);
- `missing_tensor/`: `unet1d/` with one tensor dropped from its weights;

and for each model `check-<name>.safetensors`: inputs `x` (relreward's layout: [B, H, D] for
trajectories, [B, C, H, W] for images) and `t` (int64: 0, 1, inside, T - 1), diffusers' raw
output `pred` = model(x, t).sample (eps, or x0 for prediction_type sample) and `mean`, the
posterior mean, DDPMScheduler.step's prev_sample with its noise set to zero; `mean64` is the same
step on the same output with the scheduler's tables and arithmetic in float64. diffusers forms
1 - alphas_cumprod and 1 - alphas_cumprod[t] / alphas_cumprod[t - 1] in float32, which for small
betas loses digits (about 4e-5 of the mean at t = 1 of a linear schedule from 1e-4 with T = 20);
relreward derives its tables in float64, so its mean is compared with `mean64` to 1e-5, and with
`mean` to 1e-5 plus diffusers' own float32 error.

It also checks numerically what the import relies on for time embeddings: diffusers'
sinusoid with flip_sin_to_cos false and freq_shift 1 is Diffuser's SinusoidalPosEmb, and
flip_sin_to_cos true only swaps its two halves.
"""

import hashlib
import json
import os
import pathlib
import shutil
import sys

import torch
from diffusers import DDPMPipeline, DDPMScheduler, UNet1DModel, UNet2DModel
from diffusers.models.embeddings import get_timestep_embedding
from diffusers.schedulers import scheduling_ddpm
from safetensors.torch import load_file, save_file

from relreward_dev.nets import SinusoidalPosEmb
from relreward_dev.safetensors import write_safetensors

HORIZON = 8
TRANSITION = 5


def temporal_unet(flip_sin_to_cos):
    """Diffuser's TemporalUnet(transition_dim 5, dim 8, dim_mults (1, 2, 4)) as diffusers has it."""
    return UNet1DModel(
        in_channels=TRANSITION, out_channels=TRANSITION, block_out_channels=(8, 16, 32),
        down_block_types=("DownResnetBlock1D",) * 3, up_block_types=("UpResnetBlock1D",) * 2,
        mid_block_type="MidResTemporalBlock1D", out_block_type="OutConv1DBlock", act_fn="mish",
        norm_num_groups=8, layers_per_block=1, use_timestep_embedding=True, time_embedding_type="positional",
        flip_sin_to_cos=flip_sin_to_cos, freq_shift=1)


def perturb(model, seed):
    g = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        for p in model.parameters():
            p.add_(torch.randn(p.shape, generator=g) * 0.2)
    return model.eval()


def check_embeddings():
    t = torch.tensor([0.0, 1.0, 7.0, 19.0, 99.0])
    for dim in (8, 32):
        diffuser = SinusoidalPosEmb(dim)(t)
        shifted = get_timestep_embedding(t, dim, flip_sin_to_cos=False, downscale_freq_shift=1)
        assert torch.allclose(diffuser, shifted, atol=1e-5), (dim, (diffuser - shifted).abs().max())
        flipped = get_timestep_embedding(t, dim, flip_sin_to_cos=True, downscale_freq_shift=1)
        assert torch.equal(flipped, torch.cat([shifted[:, dim // 2:], shifted[:, :dim // 2]], 1))


def in_float64(sched):
    """The same scheduler with its tables in float64 (from the same float32 betas)."""
    s = DDPMScheduler.from_config(sched.config)
    s.betas = sched.betas.double()
    s.alphas = 1.0 - s.betas
    s.alphas_cumprod = torch.cumprod(s.alphas, 0)
    s.one = torch.tensor(1.0, dtype=torch.float64)
    return s


def outputs(model, sched, x, t):
    """diffusers' raw output and posterior mean (zero noise) at (x, t), in diffusers' layout:
    the mean as diffusers computes it (float32), and its own step in float64 on the same output."""
    sched64 = in_float64(sched)
    with torch.no_grad():
        pred = model(x, t).sample
        mean = torch.cat([sched.step(pred[i:i + 1], int(t[i]), x[i:i + 1]).prev_sample for i in range(len(t))])
        mean64 = torch.cat([sched64.step(pred[i:i + 1].double(), int(t[i]), x[i:i + 1].double()).prev_sample
                            for i in range(len(t))])
    return pred, mean, mean64


def write_check(out, name, x, t, pred, mean, mean64, transpose=False):
    if transpose:
        pred, mean, mean64 = (a.transpose(1, 2) for a in (pred, mean, mean64))
    write_safetensors(out / f"check-{name}.safetensors",
                      {"x": x, "t": t, "pred": pred, "mean": mean, "mean64": mean64})


def steps(T):
    return torch.tensor([0, 1, T // 3, T - 1])


def trajectories(seed, n):
    return torch.randn(n, HORIZON, TRANSITION, generator=torch.Generator().manual_seed(seed)) * 1.5


def as_hub_cache(folder, cache, repo_id):
    """Moves `folder` into a Hugging Face hub cache as huggingface_hub lays one out: blobs named
    by digest, a snapshot of links to them, refs/main naming the snapshot."""
    repo = cache / ("models--" + repo_id.replace("/", "--"))
    commit = "0123456789abcdef0123456789abcdef01234567"
    snapshot = repo / "snapshots" / commit
    (repo / "blobs").mkdir(parents=True)
    (repo / "refs").mkdir()
    (repo / "refs" / "main").write_text(commit)
    for path in sorted(p for p in folder.rglob("*") if p.is_file()):
        data = path.read_bytes()
        blob = repo / "blobs" / hashlib.sha256(data).hexdigest()
        blob.write_bytes(data)
        link = snapshot / path.relative_to(folder)
        link.parent.mkdir(parents=True, exist_ok=True)
        os.symlink(os.path.relpath(blob, link.parent), link)
    shutil.rmtree(folder)


def main():
    out = pathlib.Path(sys.argv[1])
    out.mkdir(parents=True, exist_ok=True)
    check_embeddings()
    torch.manual_seed(0)
    # DDPMScheduler.step adds std * randn_tensor(...) for t > 0; zero noise leaves the mean.
    scheduling_ddpm.randn_tensor = lambda shape, **kw: torch.zeros(shape, dtype=kw.get("dtype"))

    # The converter's UNet1DModel, saved on its own with its scheduler beside it.
    unet = perturb(temporal_unet(flip_sin_to_cos=False), 1)
    sched = DDPMScheduler(num_train_timesteps=20, beta_schedule="squaredcos_cap_v2", clip_sample=True)
    unet.save_pretrained(out / "unet1d")
    sched.save_pretrained(out / "unet1d" / "scheduler")
    x, t = trajectories(2, 4), steps(20)
    write_check(out, "unet1d", x, t, *outputs(unet, sched, x.transpose(1, 2), t), transpose=True)

    # The same with one tensor missing.
    shutil.copytree(out / "unet1d", out / "missing_tensor")
    weights = out / "missing_tensor" / "diffusion_pytorch_model.safetensors"
    tensors = load_file(weights)
    del tensors["mid_block.resnets.1.time_emb.weight"]
    save_file(tensors, weights)

    # A pipeline folder of an x0 planner, in a local hub cache.
    unet = perturb(temporal_unet(flip_sin_to_cos=True), 3)
    sched = DDPMScheduler(num_train_timesteps=20, beta_schedule="linear", prediction_type="sample", clip_sample=True)
    staging = out / "planner"
    unet.save_pretrained(staging / "unet")
    sched.save_pretrained(staging / "scheduler")
    (staging / "model_index.json").write_text(json.dumps({
        "_class_name": "ValueGuidedRLPipeline", "unet": ["diffusers", "UNet1DModel"],
        "scheduler": ["diffusers", "DDPMScheduler"]}))
    as_hub_cache(staging, out / "hub", "relreward-test/planner")
    x, t = trajectories(4, 4), steps(20)
    write_check(out, "planner", x, t, *outputs(unet, sched, x.transpose(1, 2), t), transpose=True)

    # A UNet2DModel with attention, saved on its own.
    torch.manual_seed(5)
    unet = perturb(UNet2DModel(
        sample_size=8, in_channels=2, out_channels=2, block_out_channels=(16, 32), layers_per_block=1,
        down_block_types=("DownBlock2D", "AttnDownBlock2D"), up_block_types=("AttnUpBlock2D", "UpBlock2D"),
        norm_num_groups=8, attention_head_dim=8), 6)
    sched = DDPMScheduler(num_train_timesteps=100, beta_schedule="squaredcos_cap_v2", clip_sample=True)
    unet.save_pretrained(out / "unet2d")
    sched.save_pretrained(out / "unet2d" / "scheduler")
    x, t = torch.randn(4, 2, 8, 8, generator=torch.Generator().manual_seed(7)) * 1.5, steps(100)
    write_check(out, "unet2d", x, t, *outputs(unet, sched, x, t))

    # A DDPMPipeline without attention.
    torch.manual_seed(8)
    unet = perturb(UNet2DModel(
        sample_size=(8, 12), in_channels=3, out_channels=3, block_out_channels=(16, 16, 32), layers_per_block=2,
        down_block_types=("DownBlock2D",) * 3, up_block_types=("UpBlock2D",) * 3, add_attention=False,
        norm_num_groups=4, flip_sin_to_cos=False), 9)
    sched = DDPMScheduler(num_train_timesteps=100, beta_schedule="scaled_linear", beta_start=0.0001, beta_end=0.02,
                          clip_sample=False, variance_type="fixed_small_log")
    DDPMPipeline(unet=unet, scheduler=sched).save_pretrained(out / "pipeline2d")
    x, t = torch.randn(4, 3, 8, 12, generator=torch.Generator().manual_seed(10)), steps(100)
    write_check(out, "pipeline2d", x, t, *outputs(unet, sched, x, t))
    print(f"wrote unet1d, hub (relreward-test/planner), unet2d, pipeline2d and missing_tensor into {out}")


if __name__ == "__main__":
    main()
