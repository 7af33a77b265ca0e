"""Independent PyTorch reference for the native denoisers (server/src/engine/nets/), driven by
server/tests/nets_vs_pytorch.rs.

The networks are relreward_dev.nets (the development package, dev/python): Diffuser's
TemporalUnet without attention and the service's MLP denoiser in plain torch.nn, whose
state-dict names are the contract with the Rust side. Given a JSON list of cases, it builds
each network, loads the weights the Rust test wrote (safetensors, strictly), runs the forward
pass on the inputs the Rust test wrote, and writes the outputs.

    python nets_reference.py CASES.json

Each case: {"architecture": <manifest architecture>, "space": <manifest space>,
"weights": path, "inputs": path (tensors "x" float32, "t" int64), "output": path (written:
tensor "y" float32), "torch_weights": path (written: the state dict of a freshly initialised
PyTorch model, whose outputs on the same inputs go to "output" as "y_torch")}. The second half
checks the other direction: a file written by PyTorch loads strictly on the Rust side.

safetensors is read and written by hand (relreward_dev.safetensors), so that the script needs
only torch and numpy.
"""

import json
import sys

import torch

from relreward_dev.nets import build
from relreward_dev.safetensors import read_safetensors, write_safetensors


def main():
    with open(sys.argv[1]) as f:
        cases = json.load(f)
    torch.set_grad_enabled(False)
    for case in cases:
        model = build(case["architecture"], case["space"])
        model.load_state_dict(read_safetensors(case["weights"]), strict=True)
        model.eval()
        inputs = read_safetensors(case["inputs"])
        # Diffuser feeds the integer step to the embedding; do the same (promotion to float
        # happens inside SinusoidalPosEmb).
        y = model(inputs["x"], inputs["t"])

        torch.manual_seed(1234)
        fresh = build(case["architecture"], case["space"]).eval()
        write_safetensors(case["torch_weights"], fresh.state_dict())
        y_torch = fresh(inputs["x"], inputs["t"])
        write_safetensors(case["output"], {"y": y.float(), "y_torch": y_torch.float()})
        print(f"{case['architecture']['kind']}: {sum(p.numel() for p in model.parameters())} parameters, "
              f"output {list(y.shape)}")


if __name__ == "__main__":
    main()
