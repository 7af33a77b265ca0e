"""diffusers' own UNet2DModel as the independent reference for relreward's native Unet2d
(server/src/engine/nets/unet2d.rs), driven by server/tests/unet2d_vs_diffusers.rs.

    python unet2d_reference.py CASES.json

Each case: {"config": {channels, height, width, block_out_channels, layers_per_block, attention,
norm_num_groups, attention_head_dim}, "parametrization": "epsilon" | "x0", "n_timesteps": T,
"weights": path (written by Rust), "inputs": path (tensors x, t, x0, noise, t_train),
"output": path (written here), "torch_weights": path (written here)}.

For each case this builds the UNet2DModel of that configuration, loads the Rust weights with
load_state_dict(strict=True) (so the parameter names and shapes are diffusers' exactly), and
writes:
- "y": the forward pass model(x, t).sample;
- "loss" and "grad.<name>" for every parameter: one DDPM training step, x_t from diffusers'
  DDPMScheduler.add_noise with relreward's linear schedule (betas 1e-4 to 0.02 scaled by
  1000 / T), the mean squared error against the noise (eps) or x0;
- "y_torch": the output of a freshly initialised UNet2DModel (seed 1234) whose state dict goes
  to "torch_weights", so the Rust side also loads diffusers' own files.
"""

import json
import sys

import torch
from diffusers import DDPMScheduler, UNet2DModel

from nets_reference import read_safetensors, write_safetensors


def build(config):
    levels = len(config["block_out_channels"])
    attention = config["attention"]
    down = ["DownBlock2D"] * (levels - 1) + ["AttnDownBlock2D" if attention else "DownBlock2D"]
    up = ["AttnUpBlock2D" if attention else "UpBlock2D"] + ["UpBlock2D"] * (levels - 1)
    return UNet2DModel(
        sample_size=(config["height"], config["width"]),
        in_channels=config["channels"],
        out_channels=config["channels"],
        block_out_channels=tuple(config["block_out_channels"]),
        layers_per_block=config["layers_per_block"],
        down_block_types=tuple(down),
        up_block_types=tuple(up),
        norm_num_groups=config["norm_num_groups"],
        attention_head_dim=config["attention_head_dim"],
        add_attention=attention,
    )


def scheduler(n_timesteps):
    scale = 1000.0 / n_timesteps
    return DDPMScheduler(num_train_timesteps=n_timesteps, beta_schedule="linear",
                         beta_start=1e-4 * scale, beta_end=0.02 * scale)


def main():
    with open(sys.argv[1]) as f:
        cases = json.load(f)
    for case in cases:
        model = build(case["config"])
        model.load_state_dict(read_safetensors(case["weights"]), strict=True)
        inputs = read_safetensors(case["inputs"])
        with torch.no_grad():
            y = model(inputs["x"], inputs["t"]).sample

        sched = scheduler(case["n_timesteps"])
        x0, noise, t = inputs["x0"], inputs["noise"], inputs["t_train"]
        x_t = sched.add_noise(x0, noise, t)
        target = noise if case["parametrization"] == "epsilon" else x0
        loss = torch.nn.functional.mse_loss(model(x_t, t).sample, target)
        loss.backward()
        out = {"y": y, "loss": loss.detach().reshape(1)}
        for name, p in model.named_parameters():
            out[f"grad.{name}"] = p.grad

        torch.manual_seed(1234)
        fresh = build(case["config"])
        write_safetensors(case["torch_weights"], fresh.state_dict())
        with torch.no_grad():
            out["y_torch"] = fresh(inputs["x"], inputs["t"]).sample
        write_safetensors(case["output"], {k: v.float() for k, v in out.items()})
        print(f"unet2d {case['config']}: {sum(p.numel() for p in model.parameters())} parameters, "
              f"loss {loss.item():.6f}")


if __name__ == "__main__":
    main()
