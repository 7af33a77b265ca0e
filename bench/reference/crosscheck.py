"""The PyTorch side of server/tests/training_vs_pytorch.rs: the same training steps and the
same guided sampling as relreward, on the weights and inputs the Rust test wrote, with the
functions the benchmarks time (bench/reference/reference.py).

    python crosscheck.py CASES.json

Each case is a JSON object with "kind" and "output" (a safetensors file written here):

- "alg1": {"base": M, "expert": M, "reward": R, "batches": [path, ...] (tensors x0, t, noise),
  "target", "eval_point", "rho_l2", "entry_weights": [action_weight, condition_weight], "lr",
  "ema": [decay, every, start]}, with M = {"manifest",
  "weights"} and R = {"architecture", "item_shape", "weights"}. One Algorithm 1 step per batch
  with torch.optim.Adam and the EMA. Writes "loss" [steps], "grad<k>.<name>" (the parameter
  gradients of step k = 1, 2, ...), "param.<name>" (weights after the last step), "ema.<name>".
- "ddpm": {"model": M, "batches": [...], "action_weight", "lr", "ema"}: DDPM steps, same outputs.
- "sample": {"model": M, "reward": R, "inputs": path (x_T [n, H, D], noises [T-1, n, H, D],
  states [T, n, H, D]: relreward's x after each step), "conditions": [[index, [obs...]], ...],
  "omega", "n_guide_steps", "t_stopgrad", "scale_grad_by_std"}. Writes "step_x" [T, n, H, D]
  and "step_y" [T, n]: the guided step at each t taken from relreward's state before it (x_T
  conditioned, then relreward's previous output), so float32 rounding does not accumulate;
  and "chain_x", "chain_y": the whole loop from x_T with the same noise.
"""

import json
import sys

import torch

from reference import (
    Diffusion,
    Ema,
    alg1_step,
    apply_conditioning,
    entry_weights,
    ddpm_step,
    guided_sample,
    guided_step,
)
from relreward_dev.nets import build as build_denoiser
from relreward_dev.reward_nets import build as build_reward
from relreward_dev.safetensors import read_safetensors, write_safetensors


def load_diffusion(spec):
    manifest = spec["manifest"]
    net = build_denoiser(manifest["architecture"], manifest["space"])
    net.load_state_dict(read_safetensors(spec["weights"]), strict=True)
    return Diffusion(net, manifest)


def load_reward(spec):
    net = build_reward(spec["architecture"], spec["item_shape"])
    net.load_state_dict(read_safetensors(spec["weights"]), strict=True)
    return net


def train(case, net, step_fn):
    """Runs step_fn(optimizer, ema, step, batch) per batch with torch.optim.Adam and the EMA;
    records every step's parameter gradients (by wrapping optimizer.step, which consumes them)."""
    optimizer = torch.optim.Adam(net.parameters(), lr=case["lr"])
    decay, every, start = case["ema"]
    ema = Ema(net, decay, every, start)
    out, adam_step = {}, optimizer.step
    losses = []

    def record_then_step(*args, **kwargs):
        for name, p in net.named_parameters():
            out[f"grad{len(losses) + 1}.{name}"] = torch.zeros_like(p) if p.grad is None else p.grad.detach().clone()
        return adam_step(*args, **kwargs)

    optimizer.step = record_then_step
    for step, path in enumerate(case["batches"], start=1):
        losses.append(step_fn(optimizer, ema, step, read_safetensors(path)))
    out["loss"] = torch.stack(losses).reshape(-1)
    out.update({f"param.{name}": p.detach() for name, p in net.named_parameters()})
    out.update({f"ema.{name}": p.detach() for name, p in ema.model.named_parameters()})
    return out


def run_alg1(case):
    base, expert, reward = load_diffusion(case["base"]), load_diffusion(case["expert"]), load_reward(case["reward"])
    for p in list(base.net.parameters()) + list(expert.net.parameters()):
        p.requires_grad_(False)  # frozen, as in the paper

    space = case["base"]["manifest"]["space"]
    aw, cw = case.get("entry_weights", (1.0, 1.0))
    weights = entry_weights(space["horizon"], space["action_dim"], space["obs_dim"], aw, cw)

    def step(optimizer, ema, k, b):
        return alg1_step(base, expert, reward, optimizer, ema, k, b["x0"], b["t"], b["noise"], case["target"],
                         case["eval_point"], case["rho_l2"], weights)

    return train(case, reward, step)


def run_ddpm(case):
    model = load_diffusion(case["model"])

    def step(optimizer, ema, k, b):
        return ddpm_step(model, optimizer, ema, k, b["x0"], b["t"], b["noise"], case["action_weight"])

    return train(case, model.net, step)


def run_sample(case):
    model, reward = load_diffusion(case["model"]), load_reward(case["reward"])
    for p in list(model.net.parameters()) + list(reward.parameters()):
        p.requires_grad_(False)
    inputs = read_safetensors(case["inputs"])
    x_T, noises, states = inputs["x_T"], inputs["noises"], inputs["states"]
    conditions = [(index, torch.tensor(state, dtype=torch.float32)) for index, state in case["conditions"]]
    n, big_t = x_T.shape[0], model.n_timesteps
    guide = dict(omega=case["omega"], n_guide_steps=case["n_guide_steps"], t_stopgrad=case["t_stopgrad"],
                 scale_grad_by_std=case["scale_grad_by_std"])
    step_x, step_y = [], []
    with torch.no_grad():
        x = apply_conditioning(x_T.clone(), conditions, model.action_dim)
        for k, i in enumerate(reversed(range(big_t))):
            t = torch.full((n,), i, dtype=torch.long)
            z = noises[k] if i > 0 else torch.zeros_like(x)
            x_next, y = guided_step(model, reward, x, t, conditions, z, **guide)
            step_x.append(x_next)
            step_y.append(y)
            x = states[k].clone()  # continue from relreward's state
    chain_x, chain_y = guided_sample(model, reward, n, conditions, noises=[x_T, *noises], **guide)
    return {"step_x": torch.stack(step_x), "step_y": torch.stack(step_y), "chain_x": chain_x, "chain_y": chain_y}


def main():
    with open(sys.argv[1]) as f:
        cases = json.load(f)
    torch.manual_seed(0)
    for case in cases:
        out = {"alg1": run_alg1, "ddpm": run_ddpm, "sample": run_sample}[case["kind"]](case)
        write_safetensors(case["output"], {k: v.detach().float().contiguous() for k, v in out.items()})
        print(f"{case['kind']}: wrote {len(out)} tensors")


if __name__ == "__main__":
    main()
