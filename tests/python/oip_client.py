"""Drives relreward's Open Inference Protocol endpoint with the stock `tritonclient.grpc`.

Used by tests/tests/oip.rs: everything here is generic KServe v2 / Triton client code, with
nothing relreward-specific, which is the point of the check.

    oip_client.py --url 127.0.0.1:PORT --model NAME --diffusion-model NAME --out results.npz
        [--descriptor inference_descriptor.bin]

Asks liveness, readiness and metadata; reads the input shape from the model's metadata;
draws a deterministic batch x (FP32 [B, H, D]) and t (INT64 [B]); infers `reward` and `grad_x`
together, `reward` alone, and with no outputs named; reads the model's config, statistics
(before and after those inferences) and the repository index through tritonclient's own
stubs, as protobuf messages and as JSON; then sends bad requests (x as FP64, an unknown model,
a diffusion model, config of an unknown model or version) and calls RPCs relreward does not
implement, recording the status of each InferenceServerException; and infers once more to
show the server still answers. Arrays go to the .npz (x, t, reward, grad_x, reward_only,
reward_default, grad_x_default); a JSON summary goes to stdout, with every array as the uint32
bit patterns of its float32 values (int64 for t) so that the Rust side can compare bit for bit.

With --descriptor (the encoded FileDescriptorSet relreward registers for reflection), also
compares every message, enum, field (name, number, type, label, message or enum type, oneof)
and method of relreward's `inference` package with the descriptors that ship inside
tritonclient (grpc_service.proto and model_config.proto), and reports the differences (none
expected: wire compatibility).

Only tritonclient's stubs are imported here: relreward's proto/inference must never be compiled
into the same process (both define `inference.*` in protobuf's default pool).
"""

import argparse
import json
import sys

import numpy as np
import tritonclient.grpc as grpcclient
from tritonclient.grpc import model_config_pb2 as mc
from tritonclient.utils import InferenceServerException

TYPE_NAMES = {
    1: "double", 2: "float", 3: "int64", 4: "uint64", 5: "int32", 8: "bool", 9: "string",
    11: "message", 12: "bytes", 13: "uint32",
}


def describe_file(fd):
    """Every message (nested ones included), enum value, field and method of a file descriptor,
    as text."""
    lines = {}

    def enum(e):
        for v in e.values:
            lines[f"{e.full_name}.{v.name}"] = f"enum value {v.number}"

    def message(m):
        for e in m.enum_types:
            enum(e)
        for f in m.fields:
            target = f.message_type.full_name if f.message_type else (f.enum_type.full_name if f.enum_type else "")
            oneof = f.containing_oneof.name if f.containing_oneof else ""
            repeated = f.is_repeated if hasattr(f, "is_repeated") else f.label == 3
            lines[f"{m.full_name}.{f.name}"] = (
                f"{f.number} {TYPE_NAMES.get(f.type, f.type)} {'repeated' if repeated else 'single'} "
                f"{target} {oneof}".strip()
            )
        for n in m.nested_types:
            message(n)

    for m in fd.message_types_by_name.values():
        message(m)
    for e in fd.enum_types_by_name.values():
        enum(e)
    for s in fd.services_by_name.values():
        for m in s.methods:
            lines[f"/{s.full_name}/{m.name}"] = f"{m.input_type.full_name} -> {m.output_type.full_name}"
    return lines


def compare_descriptors(path):
    """Differences between relreward's inference package and tritonclient's, for what relreward
    defines (tritonclient's has more messages and RPCs, which relreward leaves out). Messages of
    tritonclient's grpc_service.proto that relreward defines must be complete; those of its
    model_config.proto (ModelConfig and what it holds, which relreward only sends) may carry a
    subset of the fields, each with the same number and type."""
    from google.protobuf import descriptor_pb2, descriptor_pool
    from tritonclient.grpc import model_config_pb2, service_pb2

    fds = descriptor_pb2.FileDescriptorSet()
    with open(path, "rb") as f:
        fds.ParseFromString(f.read())
    pool = descriptor_pool.DescriptorPool()
    for file in fds.file:
        pool.Add(file)
    ours_file = pool.FindFileByName("inference/grpc_service.proto")
    ours, theirs = describe_file(ours_file), describe_file(service_pb2.DESCRIPTOR)
    config_only = describe_file(model_config_pb2.DESCRIPTOR)
    theirs_all = {**config_only, **theirs}
    problems = []
    if ours_file.package != service_pb2.DESCRIPTOR.package:
        problems.append(f"package {ours_file.package} vs {service_pb2.DESCRIPTOR.package}")
    for key, value in sorted(ours.items()):
        if key not in theirs_all:
            problems.append(f"{key}: ours only ({value})")
        elif theirs_all[key] != value:
            problems.append(f"{key}: ours {value!r}, tritonclient {theirs_all[key]!r}")
    # Every field of a message we define must be ours too (a field we lack would be dropped).
    our_messages = {k.rsplit(".", 1)[0] for k in ours if not k.startswith("/")}
    for key, value in sorted(theirs.items()):
        if not key.startswith("/") and key.rsplit(".", 1)[0] in our_messages and key not in ours:
            problems.append(f"{key}: tritonclient only ({value})")
    return {"fields_and_methods_compared": len(ours), "mismatches": problems}


def bits(a):
    a = np.ascontiguousarray(a)
    if a.dtype == np.float32:
        return a.view(np.uint32).ravel().tolist()
    return a.ravel().tolist()


def failure(call):
    """The gRPC status and message of the InferenceServerException `call` raises."""
    try:
        call()
    except InferenceServerException as e:
        return {"status": str(e.status()), "message": e.message()}
    return {"status": "no error", "message": ""}


def main():
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--url", required=True, help="host:port of the server")
    p.add_argument("--model", required=True, help="a reward model")
    p.add_argument("--diffusion-model", required=True, help="a diffusion model (not servable here)")
    p.add_argument("--out", required=True, help=".npz for the arrays")
    p.add_argument("--batch", type=int, default=5)
    p.add_argument("--seed", type=int, default=3)
    p.add_argument("--descriptor", help="relreward's encoded inference FileDescriptorSet")
    args = p.parse_args()

    client = grpcclient.InferenceServerClient(url=args.url)
    stats_before = client.get_inference_statistics(args.model)
    summary = {
        "server_live": client.is_server_live(),
        "server_ready": client.is_server_ready(),
        "model_ready": client.is_model_ready(args.model),
        "model_ready_version_1": client.is_model_ready(args.model, "1"),
        "unknown_model_ready": client.is_model_ready("no-such-model"),
        "diffusion_model_ready": client.is_model_ready(args.diffusion_model),
        "server_metadata": client.get_server_metadata(as_json=True),
        "model_metadata": client.get_model_metadata(args.model, as_json=True),
    }
    x_meta = next(i for i in summary["model_metadata"]["inputs"] if i["name"] == "x")
    item = [int(d) for d in x_meta["shape"][1:]]
    rng = np.random.default_rng(args.seed)
    x = rng.uniform(-1.0, 1.0, size=[args.batch, *item]).astype(np.float32)
    t = rng.integers(0, 3, size=[args.batch]).astype(np.int64)

    def inputs(x_array=x, x_type="FP32"):
        xi = grpcclient.InferInput("x", list(x_array.shape), x_type)
        xi.set_data_from_numpy(x_array)
        ti = grpcclient.InferInput("t", list(t.shape), "INT64")
        ti.set_data_from_numpy(t)
        return [xi, ti]

    def outputs(*names):
        return [grpcclient.InferRequestedOutput(n) for n in names]

    both = client.infer(args.model, inputs(), outputs=outputs("reward", "grad_x"), request_id="req-7")
    response = both.get_response()
    summary["response"] = {
        "id": response.id,
        "model_name": response.model_name,
        "model_version": response.model_version,
        "outputs": [{"name": o.name, "datatype": o.datatype, "shape": list(o.shape)} for o in response.outputs],
    }
    reward_only = client.infer(args.model, inputs(), outputs=outputs("reward"))
    summary["reward_only_outputs"] = [o.name for o in reward_only.get_response().outputs]
    default = client.infer(args.model, inputs(), model_version="1")
    summary["default_outputs"] = [o.name for o in default.get_response().outputs]
    arrays = {
        "x": x,
        "t": t,
        "reward": both.as_numpy("reward"),
        "grad_x": both.as_numpy("grad_x"),
        "reward_only": reward_only.as_numpy("reward"),
        "reward_default": default.as_numpy("reward"),
        "grad_x_default": default.as_numpy("grad_x"),
    }
    np.savez(args.out, **arrays)

    # Config, statistics and the repository index, parsed by tritonclient's own stubs.
    config = client.get_model_config(args.model).config
    summary["model_config"] = client.get_model_config(args.model, "1", as_json=True)["config"]
    summary["model_config_proto"] = {
        "name": config.name,
        "max_batch_size": config.max_batch_size,
        "inputs": [[i.name, mc.DataType.Name(i.data_type), list(i.dims), list(i.reshape.shape), i.optional]
                   for i in config.input],
        "outputs": [[o.name, mc.DataType.Name(o.data_type), list(o.dims), list(o.reshape.shape)] for o in config.output],
        "scheduling": config.WhichOneof("scheduling_choice"),
        "preferred_batch_size": list(config.dynamic_batching.preferred_batch_size),
        "version_policy": config.version_policy.WhichOneof("policy_choice"),
    }
    stats_after = client.get_inference_statistics(args.model)
    (before,), (after,) = stats_before.model_stats, stats_after.model_stats
    summary["statistics_delta"] = {
        "name": after.name,
        "version": after.version,
        "success": after.inference_stats.success.count - before.inference_stats.success.count,
        "fail": after.inference_stats.fail.count - before.inference_stats.fail.count,
        "inference_count": after.inference_count - before.inference_count,
        "success_ns_grew": after.inference_stats.success.ns > before.inference_stats.success.ns,
        "compute_infer": after.inference_stats.compute_infer.count - before.inference_stats.compute_infer.count,
        "last_inference_ms": after.last_inference,
    }
    summary["statistics_json"] = client.get_inference_statistics(args.model, as_json=True)
    summary["statistics_all_json"] = client.get_inference_statistics(as_json=True)
    summary["repository_index"] = [
        [m.name, m.version, m.state, m.reason] for m in client.get_model_repository_index().models
    ]
    summary["repository_index_json"] = client.get_model_repository_index(as_json=True)
    summary["arrays"] = {k: {"dtype": str(v.dtype), "shape": list(v.shape), "bits": bits(v)} for k, v in arrays.items()}

    summary["errors"] = {
        "x_fp64": failure(lambda: client.infer(args.model, inputs(x.astype(np.float64), "FP64"))),
        "unknown_model": failure(lambda: client.infer("no-such-model", inputs())),
        "diffusion_model": failure(lambda: client.infer(args.diffusion_model, inputs())),
        "unknown_output": failure(lambda: client.infer(args.model, inputs(), outputs=outputs("value"))),
        "config_unknown_model": failure(lambda: client.get_model_config("no-such-model")),
        "config_diffusion_model": failure(lambda: client.get_model_config(args.diffusion_model)),
        "config_unknown_version": failure(lambda: client.get_model_config(args.model, "2")),
        "statistics_unknown_model": failure(lambda: client.get_inference_statistics("no-such-model")),
        "statistics_diffusion_model": failure(lambda: client.get_inference_statistics(args.diffusion_model)),
        # Still left out: model control, shared memory, trace and log settings.
        "load_model": failure(lambda: client.load_model(args.model)),
        "shared_memory_status": failure(lambda: client.get_system_shared_memory_status()),
        "log_settings": failure(lambda: client.get_log_settings()),
    }
    again = client.infer(args.model, inputs(), outputs=outputs("reward"))
    summary["after_errors_equal"] = bool(np.array_equal(again.as_numpy("reward"), arrays["reward_only"]))
    if args.descriptor:
        summary["descriptor"] = compare_descriptors(args.descriptor)
    client.close()
    json.dump(summary, sys.stdout)


if __name__ == "__main__":
    main()
