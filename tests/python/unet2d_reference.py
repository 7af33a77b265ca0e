"""diffusers' own UNet2DModel as the independent reference for relreward's native Unet2d
(server/src/engine/nets/unet2d.rs), driven by server/tests/unet2d_vs_diffusers.rs; the model
and scheduler are configured by relreward_dev.unet2d (the development package, dev/python).

    python unet2d_reference.py CASES.json

Each case: {"config": {channels, height, width, block_out_channels, layers_per_block, attention,
norm_num_groups, attention_head_dim, conditioning (optional: relreward's manifest conditioning)},
"parametrization": "epsilon" | "x0" | "v", "n_timesteps": T, "weights": path (written by Rust),
"inputs": path (tensors x, t, x0, noise, t_train, and for a conditional model cond and
cond_train, the class_labels of both passes),
"output": path (written here), "torch_weights": path (written here)}.

For each case this builds the UNet2DModel of that configuration, loads the Rust weights with
load_state_dict(strict=True) (so the parameter names and shapes are diffusers' exactly), and
writes:
- "y": the forward pass model(x, t).sample;
- "loss" and "grad.<name>" for every parameter: one DDPM training step, x_t from diffusers'
  DDPMScheduler.add_noise with relreward's linear schedule (betas 1e-4 to 0.02 scaled by
  1000 / T), the mean squared error against the noise (eps), x0, or the velocity (v, diffusers'
  get_velocity);
- "y_torch": the output of a freshly initialised UNet2DModel (seed 1234) whose state dict goes
  to "torch_weights", so the Rust side also loads diffusers' own files.
"""

import json
import sys

import torch

from relreward_dev.safetensors import read_safetensors, write_safetensors
from relreward_dev.unet2d import build, scheduler


def main():
    with open(sys.argv[1]) as f:
        cases = json.load(f)
    for case in cases:
        model = build(case["config"])
        model.load_state_dict(read_safetensors(case["weights"]), strict=True)
        inputs = read_safetensors(case["inputs"])
        cond, cond_train = inputs.get("cond"), inputs.get("cond_train")
        with torch.no_grad():
            y = model(inputs["x"], inputs["t"], class_labels=cond).sample

        sched = scheduler(case["n_timesteps"])
        x0, noise, t = inputs["x0"], inputs["noise"], inputs["t_train"]
        x_t = sched.add_noise(x0, noise, t)
        target = {"epsilon": noise, "x0": x0, "v": sched.get_velocity(x0, noise, t)}[case["parametrization"]]
        loss = torch.nn.functional.mse_loss(model(x_t, t, class_labels=cond_train).sample, target)
        loss.backward()
        out = {"y": y, "loss": loss.detach().reshape(1)}
        for name, p in model.named_parameters():
            out[f"grad.{name}"] = p.grad

        torch.manual_seed(1234)
        fresh = build(case["config"])
        write_safetensors(case["torch_weights"], fresh.state_dict())
        with torch.no_grad():
            out["y_torch"] = fresh(inputs["x"], inputs["t"], class_labels=cond).sample
        write_safetensors(case["output"], {k: v.float() for k, v in out.items()})
        print(f"unet2d {case['config']}: {sum(p.numel() for p in model.parameters())} parameters, "
              f"loss {loss.item():.6f}")


if __name__ == "__main__":
    main()
