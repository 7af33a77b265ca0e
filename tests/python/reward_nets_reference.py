"""Independent PyTorch reference for the relative reward networks (server/src/engine/nets/reward/),
driven by server/tests/reward_nets_vs_pytorch.rs.

The networks are relreward_dev.reward_nets (the development package, dev/python): the windowed
MLP, Diffuser's ValueFunction, the strided 2D conv encoder and the flat MLP in plain torch.nn,
whose state-dict names are the contract with the Rust side. Given a JSON list of cases, it
builds each network, loads the weights the Rust test wrote (safetensors, strictly), and writes
for the inputs the Rust test wrote:

- "rho" [B] and "per_window" [B, W] (W = H / h for the windowed MLP, else 1);
- "per_step" [B, H] (windowed MLP only: stride-1 windows, end padded with the last row);
- "grad_x": d sum(rho) / dx (torch.autograd.grad);
- "grad.<name>" for every parameter: d loss / d theta for the double-backward loss of
  Algorithm 1, loss = mean_b || grad_x rho(x_b, t_b) - target_b ||^2, with grad_x taken with
  create_graph=True (zeros where a parameter does not reach the loss, e.g. the output bias);
- "rho_torch": rho under a freshly initialised PyTorch model, whose state dict goes to
  "torch_weights" (the other direction: PyTorch's file must load strictly on the Rust side).

    python reward_nets_reference.py CASES.json

Each case: {"architecture": <reward architecture>, "item_shape": [...], "weights": path,
"inputs": path (tensors "x" float32, "t" int64, "target" float32), "output": path,
"torch_weights": path}.
"""

import json
import sys

import torch

from relreward_dev.reward_nets import WindowedMlp, build
from relreward_dev.safetensors import read_safetensors, write_safetensors


def main():
    with open(sys.argv[1]) as f:
        cases = json.load(f)
    for case in cases:
        model = build(case["architecture"], case["item_shape"])
        model.load_state_dict(read_safetensors(case["weights"]), strict=True)
        inputs = read_safetensors(case["inputs"])
        x, t, target = inputs["x"], inputs["t"], inputs["target"]
        out = {}
        with torch.no_grad():
            out["rho"] = model(x, t)
            if isinstance(model, WindowedMlp):
                out["per_window"] = model.per_window(x, t)
                out["per_step"] = model.per_step(x, t)
            else:
                out["per_window"] = out["rho"][:, None]

        x_req = x.clone().requires_grad_(True)
        rho = model(x_req, t)
        (grad_x,) = torch.autograd.grad(rho.sum(), x_req, create_graph=True)
        out["grad_x"] = grad_x.detach()
        loss = (grad_x - target).pow(2).flatten(1).sum(dim=1).mean()
        names, params = zip(*model.named_parameters())
        grads = torch.autograd.grad(loss, params, allow_unused=True)
        for name, param, grad in zip(names, params, grads):
            out[f"grad.{name}"] = torch.zeros_like(param) if grad is None else grad
        out["loss"] = loss.detach().reshape(1)

        torch.manual_seed(1234)
        fresh = build(case["architecture"], case["item_shape"])
        write_safetensors(case["torch_weights"], fresh.state_dict())
        with torch.no_grad():
            out["rho_torch"] = fresh(x, t)
        write_safetensors(case["output"], {k: v.detach().float().contiguous() for k, v in out.items()})
        print(
            f"{case['architecture']}: {sum(p.numel() for p in model.parameters())} parameters, "
            f"loss {loss.item():.6g}"
        )


if __name__ == "__main__":
    main()
