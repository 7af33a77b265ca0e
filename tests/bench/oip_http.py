"""Latency of one item through the Open Inference Protocol over gRPC and over HTTP/JSON, with
the stock Triton clients (what a KServe user runs), against one relreward server.

    oip_http.py --grpc HOST:PORT --http http://HOST:PORT --model NAME --data NPZ [--seconds 4] [--reps 3]

Sides, each a closed loop of one client sending one item (x FP32 [1, H, D] from the model's
metadata, t = 10; outputs `reward` and `grad_x`, i.e. a gradient query) for SECONDS:
- grpc: tritonclient.grpc infer;
- http-binary: tritonclient.http infer with binary tensors both ways (its default);
- http-json: tritonclient.http infer with JSON tensors both ways.
x is the first window of the dataset the model was trained on (NPZ with observations and
actions), in relreward's item layout [actions, observations] (Diffuser's), so that it is in the
units the model accepts.
Rotated A B C over REPS repetitions after a warm-up; every answer of every side is checked
against the first gRPC answer bit for bit (a mismatch exits 1). Prints one JSON object:
per side and repetition the p50, p99 and mean in ms and the call count.
"""

import argparse
import json
import sys
import time

import numpy as np
import tritonclient.grpc as grpcclient
import tritonclient.http as httpclient


def main():
    p = argparse.ArgumentParser()
    p.add_argument("--grpc", required=True)
    p.add_argument("--http", required=True)
    p.add_argument("--model", required=True)
    p.add_argument("--seconds", type=float, default=4.0)
    p.add_argument("--reps", type=int, default=3)
    p.add_argument("--data", required=True, help="the training dataset (.npz: observations, actions)")
    p.add_argument("--t", type=int, default=10)
    args = p.parse_args()
    grpc = grpcclient.InferenceServerClient(args.grpc)
    http = httpclient.InferenceServerClient(args.http.split("://", 1)[1])
    item = grpc.get_model_metadata(args.model, as_json=True)["inputs"][0]["shape"][1:]
    horizon = int(item[0])
    data = np.load(args.data)
    window = np.concatenate([data["actions"][:horizon], data["observations"][:horizon]], axis=1)
    x = window[None].astype(np.float32)
    t = np.array([args.t], dtype=np.int64)

    def grpc_call():
        xi = grpcclient.InferInput("x", list(x.shape), "FP32")
        xi.set_data_from_numpy(x)
        ti = grpcclient.InferInput("t", [1], "INT64")
        ti.set_data_from_numpy(t)
        outs = [grpcclient.InferRequestedOutput("reward"), grpcclient.InferRequestedOutput("grad_x")]
        r = grpc.infer(args.model, [xi, ti], outputs=outs)
        return r.as_numpy("reward"), r.as_numpy("grad_x")

    def http_call(binary):
        def call():
            xi = httpclient.InferInput("x", list(x.shape), "FP32")
            xi.set_data_from_numpy(x, binary_data=binary)
            ti = httpclient.InferInput("t", [1], "INT64")
            ti.set_data_from_numpy(t, binary_data=binary)
            outs = [httpclient.InferRequestedOutput(n, binary_data=binary) for n in ("reward", "grad_x")]
            r = http.infer(args.model, [xi, ti], outputs=outs)
            return r.as_numpy("reward"), r.as_numpy("grad_x")
        return call

    sides = {"grpc": grpc_call, "http-binary": http_call(True), "http-json": http_call(False)}
    want = [a.tobytes() for a in grpc_call()]

    def run(call, seconds):
        lat = []
        end = time.perf_counter() + seconds
        while time.perf_counter() < end:
            t0 = time.perf_counter()
            got = call()
            lat.append(time.perf_counter() - t0)
            if [a.tobytes() for a in got] != want:
                sys.exit("oip_http.py: an answer differs from gRPC's first answer")
        ms = np.array(lat) * 1e3
        return {"p50_ms": float(np.percentile(ms, 50)), "p99_ms": float(np.percentile(ms, 99)),
                "mean_ms": float(ms.mean()), "calls": len(lat)}

    for call in sides.values():
        run(call, 1.0)
    results = {name: [] for name in sides}
    for _ in range(args.reps):
        for name, call in sides.items():
            results[name].append(run(call, args.seconds))
    json.dump({"item_shape": [int(d) for d in item], "t": args.t, "results": results}, sys.stdout)


if __name__ == "__main__":
    main()
