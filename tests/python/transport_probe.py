"""Transport checks against a running relreward-server with stock Python gRPC clients.

Used by tests/tests/transport.rs. Two commands, each printing one JSON document on stdout:

    transport_probe.py compression --url 127.0.0.1:PORT
        grpcio channels created with compression (gzip, then deflate) call grpc.health.v1
        Health/Check and the OIP ServerLive; tritonclient infers with compression_algorithm
        gzip and deflate on a model that does not exist (the answer must be NOT_FOUND, which
        needs the compressed request decoded: UNIMPLEMENTED means compression is refused).

    transport_probe.py reflection --url 127.0.0.1:PORT [--compression gzip]
        For grpc.reflection.v1 and v1alpha: one ServerReflectionInfo stream, asking in turn
        for an unknown symbol, list_services, the file containing relreward.v1.RewardService,
        an unknown file, an extension, extension numbers of an unknown and of a known type,
        and list_services again; records each answer (or how the stream ended).

The reflection messages are compiled at run time from the protocol's definition below with
grpcio-tools' protoc (grpcio ships no reflection stubs; grpcio-reflection is not installed).
"""

import argparse
import importlib.util
import json
import queue
import sys
import tempfile
from pathlib import Path

import grpc

# grpc/reflection/v1/reflection.proto, comments left out; v1alpha is the same under its package.
REFLECTION_PROTO = """
syntax = "proto3";
package grpc.reflection.VERSION;
message ServerReflectionRequest {
  string host = 1;
  oneof message_request {
    string file_by_filename = 3;
    string file_containing_symbol = 4;
    ExtensionRequest file_containing_extension = 5;
    string all_extension_numbers_of_type = 6;
    string list_services = 7;
  }
}
message ExtensionRequest {
  string containing_type = 1;
  int32 extension_number = 2;
}
message ServerReflectionResponse {
  string valid_host = 1;
  ServerReflectionRequest original_request = 2;
  oneof message_response {
    FileDescriptorResponse file_descriptor_response = 4;
    ExtensionNumberResponse all_extension_numbers_response = 5;
    ListServiceResponse list_services_response = 6;
    ErrorResponse error_response = 7;
  }
}
message FileDescriptorResponse { repeated bytes file_descriptor_proto = 1; }
message ExtensionNumberResponse {
  string base_type_name = 1;
  repeated int32 extension_number = 2;
}
message ListServiceResponse { repeated ServiceResponse service = 1; }
message ServiceResponse { string name = 1; }
message ErrorResponse {
  int32 error_code = 1;
  string error_message = 2;
}
service ServerReflection {
  rpc ServerReflectionInfo(stream ServerReflectionRequest) returns (stream ServerReflectionResponse);
}
"""

COMPRESSIONS = {"gzip": grpc.Compression.Gzip, "deflate": grpc.Compression.Deflate, "none": grpc.Compression.NoCompression}


def health_check(channel, service=""):
    """grpc.health.v1 Health/Check with raw bytes: HealthCheckRequest{service}; the answer's
    status (1 SERVING, 2 NOT_SERVING)."""
    request = b"" if not service else b"\x0a" + bytes([len(service)]) + service.encode()
    call = channel.unary_unary("/grpc.health.v1.Health/Check", request_serializer=None, response_deserializer=None)
    answer = call(request, timeout=10)
    # HealthCheckResponse{status = 1}: field 1, varint.
    return answer[1] if len(answer) == 2 and answer[0] == 0x08 else 0


def compression(url):
    from tritonclient.grpc import service_pb2, service_pb2_grpc
    import numpy as np
    import tritonclient.grpc as grpcclient
    from tritonclient.utils import InferenceServerException

    out = {}
    for name in ("gzip", "deflate"):
        with grpc.insecure_channel(url, compression=COMPRESSIONS[name]) as channel:
            entry = {}
            try:
                entry["health"] = health_check(channel)
                entry["health_reward_service"] = health_check(channel, "relreward.v1.RewardService")
            except grpc.RpcError as e:
                entry["health_error"] = f"{e.code().name}: {e.details()}"
            try:
                live = service_pb2_grpc.GRPCInferenceServiceStub(channel).ServerLive(
                    service_pb2.ServerLiveRequest(), timeout=10
                )
                entry["server_live"] = live.live
            except grpc.RpcError as e:
                entry["server_live_error"] = f"{e.code().name}: {e.details()}"
            out[name] = entry

        client = grpcclient.InferenceServerClient(url=url)
        x = grpcclient.InferInput("x", [2, 8, 4], "FP32")
        x.set_data_from_numpy(np.zeros((2, 8, 4), dtype=np.float32))
        try:
            client.infer("no-such-model", [x], compression_algorithm=name)
            out[name]["infer"] = "OK"
        except InferenceServerException as e:
            out[name]["infer"] = str(e.status())
            out[name]["infer_message"] = e.message()
        client.close()
    return out


def reflection_modules(workdir):
    """(v1 module, v1alpha module) with the reflection messages, compiled by protoc."""
    from grpc_tools import protoc

    modules = {}
    for version in ("v1", "v1alpha"):
        name = f"relreward_probe_reflection_{version}"
        (Path(workdir) / f"{name}.proto").write_text(REFLECTION_PROTO.replace("VERSION", version))
        status = protoc.main(["protoc", f"-I{workdir}", f"--python_out={workdir}", f"{workdir}/{name}.proto"])
        if status != 0:
            sys.exit(f"protoc failed on {name}.proto")
    for version in ("v1", "v1alpha"):
        # Loaded from its file: each generated module stands alone (it imports only protobuf).
        name = f"relreward_probe_reflection_{version}_pb2"
        spec = importlib.util.spec_from_file_location(name, Path(workdir) / f"{name}.py")
        modules[version] = importlib.util.module_from_spec(spec)
        spec.loader.exec_module(modules[version])
    return modules


def describe(response):
    kind = response.WhichOneof("message_response")
    entry = {"kind": kind, "valid_host": response.valid_host,
             "original": response.original_request.WhichOneof("message_request")}
    if kind == "error_response":
        entry["error_code"] = response.error_response.error_code
        entry["error_message"] = response.error_response.error_message
    elif kind == "list_services_response":
        entry["services"] = sorted(s.name for s in response.list_services_response.service)
    elif kind == "file_descriptor_response":
        from google.protobuf import descriptor_pb2

        files = []
        for raw in response.file_descriptor_response.file_descriptor_proto:
            fd = descriptor_pb2.FileDescriptorProto.FromString(raw)
            files.append({"name": fd.name, "package": fd.package, "services": [s.name for s in fd.service]})
        entry["files"] = files
    elif kind == "all_extension_numbers_response":
        entry["base_type_name"] = response.all_extension_numbers_response.base_type_name
        entry["numbers"] = list(response.all_extension_numbers_response.extension_number)
    return entry


def reflection(url, compression_name):
    with tempfile.TemporaryDirectory() as workdir:
        modules = reflection_modules(workdir)
        out = {}
        for version, pb in modules.items():
            requests = [
                pb.ServerReflectionRequest(host="probe", file_containing_symbol="no.such.Symbol"),
                pb.ServerReflectionRequest(host="probe", list_services=""),
                pb.ServerReflectionRequest(host="probe", file_containing_symbol="relreward.v1.RewardService"),
                pb.ServerReflectionRequest(host="probe", file_by_filename="no/such/file.proto"),
                pb.ServerReflectionRequest(
                    host="probe",
                    file_containing_extension=pb.ExtensionRequest(
                        containing_type="relreward.v1.GradientRequest", extension_number=100
                    ),
                ),
                pb.ServerReflectionRequest(host="probe", all_extension_numbers_of_type="no.such.Type"),
                pb.ServerReflectionRequest(host="probe", all_extension_numbers_of_type="relreward.v1.GradientRequest"),
                pb.ServerReflectionRequest(host="probe", list_services=""),
            ]
            with grpc.insecure_channel(url, compression=COMPRESSIONS[compression_name]) as channel:
                call = channel.stream_stream(
                    f"/grpc.reflection.{version}.ServerReflection/ServerReflectionInfo",
                    request_serializer=pb.ServerReflectionRequest.SerializeToString,
                    response_deserializer=pb.ServerReflectionResponse.FromString,
                )
                # One request at a time on the one stream: the next goes only after the answer.
                outbox = queue.Queue()

                def feed():
                    while True:
                        item = outbox.get()
                        if item is None:
                            return
                        yield item

                responses = call(feed(), timeout=30)
                answers = []
                ended = None
                for request in requests:
                    outbox.put(request)
                    try:
                        answers.append(describe(next(responses)))
                    except StopIteration:
                        ended = "stream ended with OK"
                        break
                    except grpc.RpcError as e:
                        ended = f"{e.code().name}: {e.details()}"
                        break
                outbox.put(None)
                if ended is None:
                    # Half-closed: the stream must then end cleanly.
                    try:
                        extra = list(responses)
                        ended = "OK" if not extra else f"OK after {len(extra)} unasked answers"
                    except grpc.RpcError as e:
                        ended = f"{e.code().name}: {e.details()}"
            out[version] = {"answers": answers, "ended": ended}
        return out


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("command", choices=["compression", "reflection"])
    parser.add_argument("--url", required=True)
    parser.add_argument("--compression", choices=sorted(COMPRESSIONS), default="none")
    args = parser.parse_args()
    if args.command == "compression":
        result = compression(args.url)
    else:
        result = reflection(args.url, args.compression)
    print(json.dumps(result))


if __name__ == "__main__":
    main()
