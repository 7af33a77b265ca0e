#!/usr/bin/env python3
"""Per-call overhead of the relreward Python client over the raw grpcio stub.

Starts relreward-server on a loopback port with a temporary data dir, trains a maze-shaped
reward for one step through the CLI (windowed MLP h = 4, hidden 128, 64, 32, items [64, 6], as
the serving benchmark's maze model; weights do not change the cost), then times, alternating
A B A B over REPS rounds of N calls each:

- unary Gradient at B = 1 and B = 64: the raw stub (request built from the same numpy array:
  `Tensor(data=x.tobytes())`, answer read with `np.frombuffer`) vs `relreward.Client.gradient`;
- GradientStream, one request in flight: the raw stub fed from a queue vs
  `Client.gradient_stream(...).gradient`;

raw and client calls alternating call by call (so drift and other load hit both alike).

Prints the markdown body of BENCHMARKS.md's `python-client` section; `--splice` writes it there
(tests/bench/splice.py). Binaries: $RELREWARD_SERVER_BIN, $RELREWARD_CLI_BIN (default
target/release/).

    .venv/bin/python tests/bench/python_client.py --calls 2000 --reps 3 --splice
"""

from __future__ import annotations

import argparse
import datetime
import os
import pathlib
import platform
import queue
import subprocess
import sys
import tempfile
import time

import numpy as np

import relreward
from relreward.v1 import reward_pb2, reward_pb2_grpc, tensor_pb2
from relreward_dev.launcher import Binaries, Server

REPO = pathlib.Path(__file__).resolve().parents[2]
BINARIES = Binaries.of_checkout(REPO)


def train(server: Server, d: pathlib.Path) -> str:
    data = d / "maze.npz"
    subprocess.run([str(BINARIES.cli), "maze", "generate", "--layout", "umaze", "--mode", "base", "--transitions", "5000",
                    "--seed", "1", "--out", str(data)], check=True, capture_output=True)
    server.cli("dataset", "upload", str(data), "--name", "maze")
    cfg = d / "d.toml"
    cfg.write_text("[optimization]\nsteps = 1\nbatch_size = 4\n[diffusion]\nhorizon = 64\nn_timesteps = 20\n"
                   "architecture = { kind = \"temporal_unet\", dim = 8, dim_mults = [1, 2] }\n")
    for name in ("base", "expert"):
        server.cli("train", "diffusion", "--name", name, "--dataset", "maze", "--config", str(cfg), "--watch")
    server.cli("train", "reward", "--name", "rw", "--base", "base", "--expert", "expert", "--dataset", "maze",
               "--arch", "windowed_mlp", "--window", "4", "--hidden", "128,64,32", "--steps", "1", "--batch-size", "4",
               "--watch")
    return "rw"


def timed(call, n: int) -> list[float]:
    out = []
    for _ in range(n):
        t0 = time.perf_counter()
        call()
        out.append(time.perf_counter() - t0)
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--calls", type=int, default=2000, help="calls per variant per round")
    ap.add_argument("--reps", type=int, default=3, help="rounds (A B A B)")
    ap.add_argument("--splice", action="store_true", help="write the section into BENCHMARKS.md")
    args = ap.parse_args()
    started = time.time()
    with tempfile.TemporaryDirectory() as tmp:
        d = pathlib.Path(tmp)
        # As the Python package's tests start it (client/python/tests/conftest.py).
        server = Server(BINARIES, d / "data", env={"RELREWARD__ENGINE__INTRA_OP_THREADS": "1"})
        try:
            model = train(server, d)
            rows = run(server.addr, model, args.calls, args.reps)
        finally:
            server.stop()
    body = report(rows, args, time.time() - started)
    print(body)
    if args.splice:
        f = d_body = pathlib.Path(tempfile.mkstemp(suffix=".md")[1])
        d_body.write_text(body)
        subprocess.run([sys.executable, str(REPO / "tests/bench/splice.py"), "python-client", str(f), "--file",
                        str(REPO / "BENCHMARKS.md")], check=True)
        f.unlink()


def run(addr: str, model: str, n: int, reps: int) -> list[tuple[str, str, list[float]]]:
    client = relreward.Client(addr)
    stub = reward_pb2_grpc.RewardServiceStub(client.channel)
    rng = np.random.default_rng(0)
    xs = {b: rng.uniform(-1, 1, (b, 64, 6)).astype(np.float32) for b in (1, 64)}

    def raw_gradient(x: np.ndarray):
        def call():
            req = reward_pb2.GradientRequest(model=model, t=[5], input_units=reward_pb2.UNITS_RAW,
                                             gradient_units=reward_pb2.UNITS_RAW,
                                             x=tensor_pb2.Tensor(shape=x.shape, dtype=tensor_pb2.DTYPE_FLOAT32,
                                                                 data=x.tobytes()))
            r = stub.Gradient(req)
            g = np.frombuffer(r.gradient.data, "<f4").reshape(r.gradient.shape)
            rho = np.frombuffer(r.rewards.data, "<f4")
            return g, rho
        return call

    def client_gradient(x: np.ndarray):
        return lambda: client.gradient(model, x, 5)

    samples: dict[tuple[str, str], list[float]] = {}
    q: queue.SimpleQueue = queue.SimpleQueue()
    end = object()
    raw_stream = stub.GradientStream(iter(q.get, end))
    counter = [0]

    def raw_stream_call():
        counter[0] += 1
        x = xs[1]
        q.put(reward_pb2.GradientRequest(request_id=counter[0], model=model, t=[5], input_units=reward_pb2.UNITS_RAW,
                                         gradient_units=reward_pb2.UNITS_RAW,
                                         x=tensor_pb2.Tensor(shape=x.shape, dtype=tensor_pb2.DTYPE_FLOAT32,
                                                             data=x.tobytes())))
        r = next(raw_stream)
        return np.frombuffer(r.gradient.data, "<f4").reshape(r.gradient.shape), np.frombuffer(r.rewards.data, "<f4")

    stream = client.gradient_stream(model)

    pairs = [("gradient B=1", raw_gradient(xs[1]), client_gradient(xs[1])),
             ("gradient B=64", raw_gradient(xs[64]), client_gradient(xs[64])),
             ("gradient_stream B=1", raw_stream_call, lambda: stream.gradient(xs[1], 5))]
    for _, raw_call, client_call in pairs:
        timed(raw_call, 100)  # warm-up
        timed(client_call, 100)
    # Per call, raw and client alternate (which goes first alternates too), so drift and other
    # load on the machine hit both alike.
    for _ in range(reps):
        for config, raw_call, client_call in pairs:
            raw_s = samples.setdefault((config, "raw grpcio"), [])
            client_s = samples.setdefault((config, "relreward"), [])
            for i in range(n):
                order = ((raw_call, raw_s), (client_call, client_s))
                for call, out in (order if i % 2 == 0 else order[::-1]):
                    t0 = time.perf_counter()
                    call()
                    out.append(time.perf_counter() - t0)
    q.put(end)
    raw_stream.cancel()
    stream.close()
    client.close()
    return [(config, who, samples[(config, who)]) for config, _, _ in pairs for who in ("raw grpcio", "relreward")]


def report(rows, args, wall: float) -> str:
    cpu = "unknown"
    try:
        cpu = next(line.split(":", 1)[1].strip() for line in open("/proc/cpuinfo") if line.startswith("model name"))
    except (OSError, StopIteration):
        pass
    lines = [
        "Per-call latency of `relreward.Client` (client/python) against the raw grpcio stub on the same channel and "
        "the same numpy input (the raw path builds `Tensor(data=x.tobytes())` and reads the answer with "
        "`np.frombuffer`, as the client does), maze-shaped reward (windowed MLP h = 4, hidden 128, 64, 32, items "
        "[64, 6], one training step), t = 5, raw units, one call in flight, loopback. Raw and client calls "
        f"alternate call by call, {args.reps} rounds of {args.calls} calls each per call kind (after 100 warm-up "
        "calls); p50 / p99 over all of them. "
        "Overhead = relreward p50 / raw p50 - 1.",
        "",
        f"Machine: {cpu}, {os.cpu_count()} CPUs (`nproc`), Python {platform.python_version()}, grpcio "
        f"{__import__('grpc').__version__}, protobuf {__import__('google.protobuf').protobuf.__version__}; server and "
        f"client on the same machine. {datetime.date.today().isoformat()}, {wall:.0f} s in all. Command: "
        f"`.venv/bin/python tests/bench/python_client.py --calls {args.calls} --reps {args.reps} --splice`.",
        "",
        "| call | client | p50 ms | p99 ms | overhead (p50) |",
        "|---|---|---|---|---|",
    ]
    raw_p50 = {}
    for config, who, s in rows:
        a = np.array(s) * 1e3
        p50, p99 = np.percentile(a, 50), np.percentile(a, 99)
        if who == "raw grpcio":
            raw_p50[config] = p50
            over = ""
        else:
            over = f"{100 * (p50 / raw_p50[config] - 1):+.1f}%"
        lines.append(f"| {config} | {who} | {p50:.3f} | {p99:.3f} | {over} |")
    lines += ["", "For comparison, the Rust client (`relreward-loadgen`, the `serving` section above): unary Gradient, "
              "maze model, B = 1, 1 client: p50 0.961 ms, p99 1.616 ms (2026-11-22, same kind of machine; not rerun "
              "here)."]
    return "\n".join(lines)


if __name__ == "__main__":
    main()
