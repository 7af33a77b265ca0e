"""The generated gRPC stubs of relreward.v1 (``jobs_pb2``, ``reward_pb2_grpc``, ...), built from
proto/relreward/v1 when the package is built: protoc's own output, with the module and file
names a user's ``grpc_tools.protoc -I proto`` run gives, so code written against such stubs runs
with the package's. The public API is ``relreward``; ``relreward.pb`` reaches the messages.
"""
