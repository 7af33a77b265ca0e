#!/usr/bin/env python3
"""A Python gRPC server for relreward.v1 RewardService.Gradient and GradientStream, written the
way a researcher would wrap the paper's PyTorch code: grpcio's thread-pool server, stubs
from relreward's own .proto files (the relreward package's), the reward network from the
PyTorch reference (relreward_dev.reward_nets, the development package's, which loads
relreward's safetensors weights strictly), and one forward/backward pass per request. It is
the baseline of the serving benchmark (tests/bench/serving.sh) and is cross-checked against
relreward by tests/tests/reference_server.rs, so both compute the same numbers on the same
weights.

    .venv/bin/python bench/reference/grpc_server.py --models-dir MODELS --model maze-reward
    .venv/bin/python bench/reference/grpc_server.py --weights W.safetensors --manifest M.json --model NAME

Models come from relreward's API: each `--model NAME` from `MODELS/NAME`, as
`relreward model download NAME --out MODELS/NAME` (or the Python client's `download_model`)
writes it (weights.safetensors, manifest.json, and an Algorithm 2 reward's
step_norm.safetensors); or from a weights file and a reward manifest (JSON, as relreward
stores it) given on the command line. Prints
`reference grpc_server listening on HOST:PORT` as its first stdout line once serving.

What it answers, as relreward does (proto/relreward/v1/reward.proto):
- `x` float32 or float64 `[B, *item_shape]`; `t` empty (0), one value (broadcast) or B values;
- `input_units` and `gradient_units` raw (the default) or normalized; rho takes normalized
  inputs, and a raw-unit gradient is the normalized one times the normalizer's Jacobian
  (it is affine: d x_norm / d x_raw = scale per coordinate);
- `omega` multiplies the gradient (unset: 1);
- Algorithm 2 rewards (`step_normalization`): rho sees (x - input_mean[t]) / input_std[t],
  differentiated through by autograd.
`scale_by_posterior_variance_of` needs a diffusion model's schedule and is answered
UNIMPLEMENTED. Errors are INVALID_ARGUMENT / NOT_FOUND naming the field; on GradientStream
they go into the response's `error` and the stream goes on.

grpcio's synchronous server runs each RPC on a pool thread, and a GradientStream holds its
thread for the whole stream: `--workers` must be at least the number of concurrent streams
(default 128), or further streams wait for a free thread.
"""

import argparse
import json
import pathlib
import signal
import sys
import threading
from concurrent import futures

import numpy as np
import torch

from relreward_dev.served import RewardModel


def load_stubs():
    """The relreward.v1 Python stubs: the `relreward` package's (client/python, which `make
    setup` installs, built from the same proto/)."""
    from relreward.v1 import reward_pb2, reward_pb2_grpc, tensor_pb2

    return reward_pb2, reward_pb2_grpc, tensor_pb2


class BadRequest(Exception):
    """A request error: a gRPC status code name and a message naming the field."""

    def __init__(self, code: str, message: str):
        super().__init__(message)
        self.code = code


def models_from_downloads(models_dir: pathlib.Path, names):
    """Each reward model NAME from MODELS/NAME, as relreward's download writes it."""
    models = {}
    for name in names:
        d = models_dir / name
        if not (d / "manifest.json").is_file():
            sys.exit(f"grpc_server.py: no model '{name}' in {models_dir} "
                     f"(download it first: relreward model download {name} --out {d})")
        manifest = json.loads((d / "manifest.json").read_text())
        if "objective" not in manifest:
            sys.exit(f"grpc_server.py: model '{name}' is not a reward or discriminator model (its manifest has no "
                     "objective)")
        models[name] = RewardModel(name, manifest, d / "weights.safetensors")
    return models


def make_request_handling(models, reward_pb2, tensor_pb2):
    """(prepare, compute, tensor): the request checks and the pass both reference servers share.

    prepare(request) -> (model, x normalized [B, *item] float32, t [B] int64, omega or None,
    raw-unit gradient?) or raises BadRequest; compute(model, x, t) -> (rho [B], grad_x rho)."""
    units_raw = (reward_pb2.UNITS_UNSPECIFIED, reward_pb2.UNITS_RAW)

    def decode_x(request):
        if not request.HasField("x"):
            raise BadRequest("INVALID_ARGUMENT", "x: missing")
        x = request.x
        dtype = {tensor_pb2.DTYPE_FLOAT32: "<f4", tensor_pb2.DTYPE_FLOAT64: "<f8"}.get(x.dtype)
        if dtype is None:
            raise BadRequest("INVALID_ARGUMENT", "x: dtype must be float32 or float64")
        shape = list(x.shape)
        if len(x.data) != int(np.prod(shape)) * np.dtype(dtype).itemsize:
            raise BadRequest("INVALID_ARGUMENT", f"x: {len(x.data)} bytes do not fill the shape {shape}")
        array = np.frombuffer(x.data, dtype=dtype).reshape(shape)
        if not np.isfinite(array).all():
            raise BadRequest("INVALID_ARGUMENT", "x: not every element is finite")
        return torch.from_numpy(array.astype(np.float32))  # a copy: frombuffer is read-only

    def tensor(t: torch.Tensor):
        array = np.ascontiguousarray(t.detach().numpy(), dtype="<f4")
        return tensor_pb2.Tensor(shape=list(array.shape), dtype=tensor_pb2.DTYPE_FLOAT32, data=array.tobytes())

    def prepare(request):
        model = models.get(request.model)
        if model is None:
            raise BadRequest("NOT_FOUND", f"model: no reward model '{request.model}'")
        if request.scale_by_posterior_variance_of:
            raise BadRequest("UNIMPLEMENTED", "scale_by_posterior_variance_of: not supported by the reference server")
        x = decode_x(request)
        if x.dim() != len(model.item_shape) + 1 or list(x.shape[1:]) != model.item_shape or x.shape[0] < 1:
            want = ", ".join(["B", *map(str, model.item_shape)])
            raise BadRequest("INVALID_ARGUMENT", f"x: expected shape [{want}] for this model, got {list(x.shape)}")
        b = x.shape[0]
        t = list(request.t)
        if len(t) not in (0, 1, b):
            raise BadRequest("INVALID_ARGUMENT", f"t: {len(t)} values for {b} items")
        t = torch.tensor(t if len(t) == b else (t or [0]) * b, dtype=torch.int64)
        if (t >= model.n_timesteps).any():
            raise BadRequest("INVALID_ARGUMENT", f"t: values must lie in [0, {model.n_timesteps})")
        if model.scale is not None and request.input_units in units_raw:
            x = (x - model.offset) * model.scale
        omega = request.omega if request.HasField("omega") else None
        raw_grad = model.scale is not None and request.gradient_units in units_raw
        return model, x, t, omega, raw_grad

    def compute(model, x, t):
        x = x.detach().requires_grad_(True)
        rho = model.rho(x, t)
        (grad,) = torch.autograd.grad(rho.sum(), x)
        return rho.detach(), grad

    def finish(request, model, rho, grad, omega, raw_grad):
        if omega is not None:
            grad = grad * omega
        if raw_grad:
            grad = grad * model.scale
        return reward_pb2.GradientResponse(request_id=request.request_id, gradient=tensor(grad), rewards=tensor(rho))

    return prepare, compute, finish


def make_servicer(models, reward_pb2, reward_pb2_grpc, tensor_pb2):
    import grpc

    prepare, compute, finish = make_request_handling(models, reward_pb2, tensor_pb2)

    def answer(request):
        model, x, t, omega, raw_grad = prepare(request)
        rho, grad = compute(model, x, t)
        return finish(request, model, rho, grad, omega, raw_grad)

    class Servicer(reward_pb2_grpc.RewardServiceServicer):
        def Gradient(self, request, context):
            try:
                return answer(request)
            except BadRequest as e:
                context.abort(getattr(grpc.StatusCode, e.code), str(e))

        def GradientStream(self, request_iterator, context):
            # One request at a time, in order: forward, backward, answer, next.
            for request in request_iterator:
                try:
                    yield answer(request)
                except BadRequest as e:
                    code = getattr(grpc.StatusCode, e.code).value[0]
                    yield reward_pb2.GradientResponse(
                        request_id=request.request_id, error=reward_pb2.StreamError(code=code, message=str(e))
                    )

    return Servicer()


def add_model_flags(ap: argparse.ArgumentParser) -> None:
    """The flags both reference servers take: where to listen, which reward models to serve
    and where to read them, torch's intra-op threads (checked by `models_from_flags`)."""
    ap.add_argument("--listen", default="127.0.0.1:0", help="HOST:PORT (port 0: any free port)")
    ap.add_argument("--models-dir", type=pathlib.Path,
                    help="downloaded models: MODELS/NAME per --model (relreward model download NAME --out MODELS/NAME)")
    ap.add_argument("--model", action="append", required=True, help="reward model name (repeatable)")
    ap.add_argument("--weights", type=pathlib.Path, help="safetensors weights (with --manifest, one --model)")
    ap.add_argument("--manifest", type=pathlib.Path, help="reward manifest JSON (with --weights)")
    ap.add_argument("--threads", type=int, default=0, help="torch intra-op threads (0: torch's default)")


def models_from_flags(ap: argparse.ArgumentParser, args: argparse.Namespace) -> dict:
    """Checks `add_model_flags`' flags (ap.error on a bad combination), sets torch's threads,
    and loads the models they name: {name: RewardModel}."""
    if (args.weights is None) != (args.manifest is None) or (args.weights is None) == (args.models_dir is None):
        ap.error("give either --models-dir, or --weights with --manifest")
    if args.weights is not None and len(args.model) != 1:
        ap.error("--weights serves exactly one --model")
    if args.threads > 0:
        torch.set_num_threads(args.threads)
    if args.models_dir is not None:
        return models_from_downloads(args.models_dir, args.model)
    manifest = json.loads(args.manifest.read_text())
    return {args.model[0]: RewardModel(args.model[0], manifest, args.weights)}


def announce(name: str, listen: str, port: int, models: dict, detail: str) -> None:
    """The first stdout line, `reference NAME listening on HOST:PORT`, which tests/bench/serving.sh
    and tests/tests/reference_server.rs wait for; then what is served, on stderr."""
    host = listen.rsplit(":", 1)[0]
    print(f"reference {name} listening on {host}:{port}", flush=True)
    print(f"reference {name}: {len(models)} model(s), torch intra-op threads {torch.get_num_threads()}, {detail}",
          file=sys.stderr, flush=True)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    add_model_flags(ap)
    ap.add_argument("--workers", type=int, default=128, help="grpcio thread-pool size")
    args = ap.parse_args()
    models = models_from_flags(ap, args)

    import grpc

    reward_pb2, reward_pb2_grpc, tensor_pb2 = load_stubs()
    server = grpc.server(
        futures.ThreadPoolExecutor(max_workers=args.workers),
        options=[("grpc.max_receive_message_length", 16 << 20), ("grpc.max_send_message_length", 16 << 20)],
    )
    reward_pb2_grpc.add_RewardServiceServicer_to_server(
        make_servicer(models, reward_pb2, reward_pb2_grpc, tensor_pb2), server
    )
    port = server.add_insecure_port(args.listen)
    if port == 0:
        sys.exit(f"grpc_server.py: cannot listen on {args.listen}")
    server.start()
    announce("grpc_server", args.listen, port, models, f"{args.workers} pool threads")
    stop = threading.Event()
    for sig in (signal.SIGTERM, signal.SIGINT):
        signal.signal(sig, lambda *_: stop.set())
    stop.wait()
    server.stop(grace=1).wait()


if __name__ == "__main__":
    main()
