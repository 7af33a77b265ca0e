#!/usr/bin/env python3
"""A planner's sampling loop using relreward's GradientStream, from Python.

One bidirectional stream per planner episode: at every denoising step the planner sends its
current plan x_t with the step's t and gets grad_x rho(x_t, t) back, matched by request_id.
Here the "planner" is only the guidance part of Diffuser's guided sampling (x += omega *
grad, n_guide_steps times per step, t from T-1 down to 0), so the example needs nothing but
the reward model; a real planner puts its own denoiser step between two requests.

Stubs are generated at start from the repository's proto files with grpcio-tools (into a
temporary directory), so the example depends on nothing relreward-specific but the .proto.

    .venv/bin/python examples/planner_gradient_stream.py --endpoint 127.0.0.1:50051 --model maze-reward

A server with access control wants a token with scope `read` (--token, or RELREWARD_TOKEN);
one with TLS wants --ca-cert (and --client-cert/--client-key for mutual TLS).

Prints one JSON object: rho at the first and the last step, how much each guide step raised
rho at its own t (positive: the gradient points uphill), and the round-trip latency of the
stream's requests.
"""

import argparse
import json
import os
import pathlib
import queue
import sys
import tempfile
import time

import numpy as np


def load_stubs(proto_dir: pathlib.Path, out: pathlib.Path):
    from grpc_tools import protoc

    files = sorted(str(p.relative_to(proto_dir)) for p in (proto_dir / "relreward" / "v1").glob("*.proto"))
    include = pathlib.Path(protoc.__file__).parent / "_proto"
    args = ["protoc", f"-I{proto_dir}", f"-I{include}", f"--python_out={out}", f"--grpc_python_out={out}", *files]
    if protoc.main(args) != 0:
        sys.exit("could not generate the Python stubs from " + str(proto_dir))
    sys.path.insert(0, str(out))
    from relreward.v1 import models_pb2, models_pb2_grpc, reward_pb2, reward_pb2_grpc, tensor_pb2

    return models_pb2, models_pb2_grpc, reward_pb2, reward_pb2_grpc, tensor_pb2


def open_channel(grpc, args):
    """A plaintext channel, or a TLS one when a CA or client certificate is given."""
    if args.ca_cert is None and args.client_cert is None:
        return grpc.insecure_channel(args.endpoint)

    def read(path):
        return pathlib.Path(path).read_bytes() if path else None

    credentials = grpc.ssl_channel_credentials(
        root_certificates=read(args.ca_cert),
        private_key=read(args.client_key),
        certificate_chain=read(args.client_cert),
    )
    return grpc.secure_channel(args.endpoint, credentials)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--endpoint", default="127.0.0.1:50051")
    ap.add_argument("--model", required=True, help="a reward model")
    ap.add_argument("--omega", type=float, default=0.1, help="guidance scale")
    ap.add_argument("--n-guide-steps", type=int, default=2)
    ap.add_argument("--batch", type=int, default=4, help="plans per request")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--proto-dir", default=str(pathlib.Path(__file__).resolve().parent.parent / "proto"))
    ap.add_argument(
        "--token",
        default=os.environ.get("RELREWARD_TOKEN"),
        help="access token with scope read (default: $RELREWARD_TOKEN)",
    )
    ap.add_argument("--ca-cert", help="PEM CA certificate: connect with TLS, verifying the server against it")
    ap.add_argument("--client-cert", help="PEM client certificate, for servers that require mutual TLS")
    ap.add_argument("--client-key", help="PEM private key of --client-cert")
    args = ap.parse_args()
    if (args.client_cert is None) != (args.client_key is None):
        ap.error("--client-cert and --client-key go together")

    import grpc

    with tempfile.TemporaryDirectory() as tmp:
        models_pb2, models_pb2_grpc, reward_pb2, reward_pb2_grpc, tensor_pb2 = load_stubs(
            pathlib.Path(args.proto_dir), pathlib.Path(tmp)
        )
        channel = open_channel(grpc, args)
        # Sent with every call; the server checks it before any handler runs.
        metadata = [("authorization", f"Bearer {args.token}")] if args.token else None
        model = models_pb2_grpc.ModelServiceStub(channel).GetModel(
            models_pb2.GetModelRequest(name=args.model), metadata=metadata
        )
        shape = [args.batch, *model.reward.input_shape]
        big_t = model.reward.n_timesteps

        def tensor(x: np.ndarray):
            x = np.ascontiguousarray(x, dtype="<f4")
            return tensor_pb2.Tensor(shape=list(x.shape), dtype=tensor_pb2.DTYPE_FLOAT32, data=x.tobytes())

        def array(t) -> np.ndarray:
            return np.frombuffer(t.data, dtype="<f4").reshape(t.shape)

        # The request iterator feeds the stream from a queue: the loop below puts the next
        # request only after the previous answer arrived, as a planner must.
        requests: "queue.Queue" = queue.Queue()
        responses = reward_pb2_grpc.RewardServiceStub(channel).GradientStream(
            iter(requests.get, None), metadata=metadata
        )

        rng = np.random.default_rng(args.seed)
        x = rng.standard_normal(shape).astype(np.float32)  # a plan in normalized units
        first_rho = last_rho = None
        latencies = []
        gains = []  # rho after minus before one guide step, at the same t
        request_id = 0
        for t in range(big_t - 1, -1, -1):
            previous = None
            for _ in range(args.n_guide_steps):
                request_id += 1
                started = time.perf_counter()
                requests.put(
                    reward_pb2.GradientRequest(
                        request_id=request_id,
                        model=args.model,
                        x=tensor(x),
                        t=[t],
                        input_units=reward_pb2.UNITS_NORMALIZED,
                        gradient_units=reward_pb2.UNITS_NORMALIZED,
                        omega=args.omega,
                    )
                )
                answer = next(responses)
                latencies.append(time.perf_counter() - started)
                if answer.request_id != request_id:
                    sys.exit(f"answer {answer.request_id} for request {request_id}")
                if answer.HasField("error"):
                    sys.exit(f"request {request_id} failed: {answer.error.code} {answer.error.message}")
                rho = array(answer.rewards)
                if previous is not None:
                    gains.append(float(np.mean(rho - previous)))
                previous = rho
                first_rho = rho if first_rho is None else first_rho
                last_rho = rho
                x = x + array(answer.gradient)  # omega is applied by the server
        requests.put(None)  # ends the stream
        lat = np.array(latencies) * 1e3
        print(
            json.dumps(
                {
                    "model": args.model,
                    "requests": request_id,
                    "rho_first_step": float(np.mean(first_rho)),
                    "rho_last_step": float(np.mean(last_rho)),
                    "mean_gain_per_guide_step": float(np.mean(gains)) if gains else None,
                    "latency_ms": {"p50": float(np.percentile(lat, 50)), "p99": float(np.percentile(lat, 99))},
                }
            )
        )


if __name__ == "__main__":
    main()
