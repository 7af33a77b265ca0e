"""Drives relreward's Open Inference Protocol over HTTP/JSON (KServe v2 REST) with the stock
`tritonclient.http`, `curl` and plain `urllib`, beside the same requests through
`tritonclient.grpc`.

Used by tests/tests/oip.rs (which checks the gRPC answers against the native API bit for bit):

    oip_http_client.py --http URL --grpc HOST:PORT --model NAME --diffusion-model NAME

What it does, with nothing relreward-specific in the client code:
- liveness, readiness, server and model metadata, config, statistics and the repository index
  through tritonclient.http (the JSON answers are printed for the Rust side);
- one batch x (FP32 [B, H, D], shape from the model's metadata) and t (INT64 [B]) inferred
  through tritonclient.grpc (the reference), then through tritonclient.http with binary inputs
  and outputs (its default), with JSON inputs and outputs, with no outputs named, with gzip
  request and response bodies, and through `curl` with a hand-written JSON body: every answer
  must equal gRPC's bit for bit (compared here; the summary says which differ);
- refusals: an unknown model, a diffusion model, x as FP64, t of the wrong shape, a malformed
  JSON body, a body with an unknown field, an unknown route, a wrong method: each answer's HTTP
  status and JSON error message are printed for the Rust side to check;
- and one more inference afterwards, to show the server still answers.

A JSON summary goes to stdout; float arrays as uint32 bit patterns.
"""

import argparse
import gzip
import json
import subprocess
import sys
import urllib.error
import urllib.request

import numpy as np
import tritonclient.grpc as grpcclient
import tritonclient.http as httpclient
from tritonclient.utils import InferenceServerException


def bits(a):
    return np.ascontiguousarray(a, dtype=np.float32).view(np.uint32).ravel().tolist()


def raw(url, method, path, body=None, headers=None):
    """(status, parsed JSON or text) of one plain HTTP request."""
    data = body if body is None or isinstance(body, bytes) else json.dumps(body).encode()
    req = urllib.request.Request(url + path, data=data, method=method, headers=headers or {})
    try:
        with urllib.request.urlopen(req, timeout=60) as r:
            status, text = r.status, r.read()
    except urllib.error.HTTPError as e:
        status, text = e.code, e.read()
    try:
        return status, json.loads(text) if text else None
    except ValueError:
        return status, text.decode(errors="replace")


def main():
    p = argparse.ArgumentParser()
    p.add_argument("--http", required=True, help="base URL of the OIP HTTP listener, http://HOST:PORT")
    p.add_argument("--grpc", required=True, help="HOST:PORT of the gRPC listener")
    p.add_argument("--model", required=True)
    p.add_argument("--diffusion-model", required=True)
    p.add_argument("--batch", type=int, default=3)
    args = p.parse_args()
    host = args.http.split("://", 1)[1]
    http = httpclient.InferenceServerClient(host)
    grpc = grpcclient.InferenceServerClient(args.grpc)
    out = {}

    out["server_live"] = http.is_server_live()
    out["server_ready"] = http.is_server_ready()
    out["server_metadata"] = http.get_server_metadata()
    out["model_ready"] = http.is_model_ready(args.model)
    out["model_ready_version_1"] = http.is_model_ready(args.model, "1")
    out["model_ready_version_2"] = http.is_model_ready(args.model, "2")
    out["unknown_model_ready"] = http.is_model_ready("no-such-model")
    out["diffusion_model_ready"] = http.is_model_ready(args.diffusion_model)
    meta = http.get_model_metadata(args.model)
    out["model_metadata"] = meta
    out["model_config"] = http.get_model_config(args.model)
    out["repository_index"] = http.get_model_repository_index()
    out["config_grpc_equal"] = (
        grpc.get_model_config(args.model, as_json=True)["config"]["max_batch_size"]
        == out["model_config"]["max_batch_size"]
    )

    item = [d for d in meta["inputs"][0]["shape"][1:]]
    rng = np.random.default_rng(7)
    x = rng.standard_normal((args.batch, *item)).astype(np.float32)
    t = np.array([0, 3, 7][: args.batch] + [1] * max(0, args.batch - 3), dtype=np.int64)

    def grpc_infer():
        xi = grpcclient.InferInput("x", list(x.shape), "FP32")
        xi.set_data_from_numpy(x)
        ti = grpcclient.InferInput("t", list(t.shape), "INT64")
        ti.set_data_from_numpy(t)
        r = grpc.infer(args.model, [xi, ti])
        return r.as_numpy("reward"), r.as_numpy("grad_x")

    def http_infer(binary_in, binary_out, named=True, **kw):
        xi = httpclient.InferInput("x", list(x.shape), "FP32")
        xi.set_data_from_numpy(x, binary_data=binary_in)
        ti = httpclient.InferInput("t", list(t.shape), "INT64")
        ti.set_data_from_numpy(t, binary_data=binary_in)
        outputs = None
        if named:
            outputs = [httpclient.InferRequestedOutput(n, binary_data=binary_out) for n in ("reward", "grad_x")]
        r = http.infer(args.model, [xi, ti], outputs=outputs, request_id="req-1", **kw)
        resp = r.get_response()
        return r.as_numpy("reward"), r.as_numpy("grad_x"), resp

    reward, grad = grpc_infer()
    out["x"], out["t"] = bits(x), t.tolist()
    out["reward"], out["grad_x"] = bits(reward), bits(grad)
    out["reward_shape"], out["grad_x_shape"] = list(reward.shape), list(grad.shape)
    same = {}
    for label, kw in [
        ("binary", dict(binary_in=True, binary_out=True)),
        ("json", dict(binary_in=False, binary_out=False)),
        ("mixed", dict(binary_in=True, binary_out=False)),
        ("unnamed", dict(binary_in=True, binary_out=True, named=False)),
        ("gzip", dict(binary_in=True, binary_out=True, request_compression_algorithm="gzip",
                      response_compression_algorithm="gzip")),
        ("deflate", dict(binary_in=False, binary_out=False, request_compression_algorithm="deflate",
                         response_compression_algorithm="deflate")),
    ]:
        r, g, resp = http_infer(**kw)
        same[label] = bits(r) == out["reward"] and bits(g) == out["grad_x"]
        if label == "json":
            out["json_response"] = {k: v for k, v in resp.items() if k != "outputs"}
            out["json_output_keys"] = sorted(resp["outputs"][0])
    out["same_as_grpc"] = same

    # curl with a hand-written JSON body: reward only, t once for every item.
    body = {
        "inputs": [
            {"name": "x", "shape": list(x.shape), "datatype": "FP32", "data": x.tolist()},
            {"name": "t", "shape": [len(t)], "datatype": "INT64", "data": t.tolist()},
        ],
        "outputs": [{"name": "reward"}],
    }
    curl = subprocess.run(
        ["curl", "-sS", "-X", "POST", "-H", "Content-Type: application/json", "--data-binary", "@-",
         f"{args.http}/v2/models/{args.model}/infer"],
        input=json.dumps(body).encode(), capture_output=True, check=True,
    )
    answer = json.loads(curl.stdout)
    out["curl_outputs"] = [o["name"] for o in answer["outputs"]]
    out["curl_same"] = bits(np.array(answer["outputs"][0]["data"], dtype=np.float32)) == out["reward"]

    # Refusals through tritonclient.http: the exception's status and message.
    def refused(call):
        try:
            call()
            return None
        except InferenceServerException as e:
            return {"status": str(e.status()), "message": e.message()}

    def infer_with(model, xdtype="FP32", tshape=None):
        xi = httpclient.InferInput("x", list(x.shape), xdtype)
        xi.set_data_from_numpy(x.astype(np.float64) if xdtype == "FP64" else x)
        tt = t if tshape is None else np.zeros(tshape, dtype=np.int64)
        ti = httpclient.InferInput("t", list(tt.shape), "INT64")
        ti.set_data_from_numpy(tt)
        return http.infer(model, [xi, ti])

    out["refusals"] = {
        "unknown_model": refused(lambda: infer_with("no-such-model")),
        "diffusion_model": refused(lambda: infer_with(args.diffusion_model)),
        "fp64": refused(lambda: infer_with(args.model, xdtype="FP64")),
        "t_shape": refused(lambda: infer_with(args.model, tshape=(2, 2))),
        "metadata_unknown_version": refused(lambda: http.get_model_metadata(args.model, "9")),
    }
    # Refusals through plain HTTP.
    infer_path = f"/v2/models/{args.model}/infer"
    out["raw"] = {
        "malformed_json": raw(args.http, "POST", infer_path, b"{not json", {"Content-Type": "application/json"}),
        "unknown_field": raw(args.http, "POST", infer_path, {"inputs": [], "outptus": []}),
        "short_data": raw(args.http, "POST", infer_path,
                          {"inputs": [{"name": "x", "shape": [1, *item], "datatype": "FP32", "data": [0.5]}]}),
        # Finite in JSON, beyond float32: refused as such, not as an infinity the client never sent.
        "beyond_f32": raw(args.http, "POST", infer_path,
                          {"inputs": [{"name": "x", "shape": [1, *item], "datatype": "FP32",
                                       "data": [1e39] + [0.0] * (int(np.prod(item)) - 1)}]}),
        "unknown_route": raw(args.http, "GET", "/v2/models/x/explain"),
        "wrong_method": raw(args.http, "GET", infer_path),
        "unsupported_encoding": raw(args.http, "POST", infer_path, b"{}", {"Content-Encoding": "br"}),
        "bad_gzip": raw(args.http, "POST", infer_path, b"not gzip", {"Content-Encoding": "gzip"}),
        "index_ready": raw(args.http, "POST", "/v2/repository/index", {"ready": True}),
        "live": raw(args.http, "GET", "/v2/health/live"),
    }
    # And it still answers, bit for bit.
    r, g, _ = http_infer(True, True)
    out["after_refusals_same"] = bits(r) == out["reward"] and bits(g) == out["grad_x"]
    out["statistics"] = http.get_inference_statistics(args.model)
    json.dump(out, sys.stdout)


if __name__ == "__main__":
    main()
