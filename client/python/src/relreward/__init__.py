"""relreward: the Python client of the relreward service.

    import numpy as np, relreward
    with relreward.Client("127.0.0.1:50051") as client:
        grad, rho = client.gradient("maze-reward", np.zeros((1, 64, 6), np.float32), t=10)

See :class:`Client` (and :class:`AsyncClient` for asyncio), :mod:`relreward.guide` for a drop-in
value guide for Diffuser-style planners, and docs/python.md.
"""

from relreward._common import (GradientResult, JobEvent, Sample, SampleBatch, ScoreResult, TLS, DEFAULT_CHUNK_BYTES,
                               MAX_MESSAGE_BYTES)
from relreward._download import DownloadedModel
from relreward._proto import datasets_pb2, jobs_pb2, models_pb2, reward_pb2, tensor_pb2
from relreward.aio import AsyncClient, AsyncGradientStream
from relreward.client import Client, GradientStream, PendingGradient
from relreward.datasets import from_minari_episodes
from relreward.errors import (Aborted, AlreadyExists, Cancelled, DataLoss, DeadlineExceeded, FailedPrecondition,
                              Internal, InvalidArgument, InvalidInput, NotFound, OutOfRange, PermissionDenied, RelrewardError,
                              ResourceExhausted, Unauthenticated, Unavailable, Unimplemented, Unknown)
from relreward.specs import DiffusionJob, DiscriminatorJob, Optimization, RewardJob

__version__ = "0.1.0"


class pb:
    """The generated protobuf message modules (``pb.reward.GradientRequest``, ...), for callers
    that need a raw message."""

    datasets = datasets_pb2
    jobs = jobs_pb2
    models = models_pb2
    reward = reward_pb2
    tensor = tensor_pb2


__all__ = [
    "Client", "AsyncClient", "GradientStream", "AsyncGradientStream", "PendingGradient", "TLS",
    "ScoreResult", "GradientResult", "Sample", "SampleBatch", "JobEvent", "DownloadedModel",
    "DiffusionJob", "RewardJob", "DiscriminatorJob", "Optimization", "from_minari_episodes",
    "RelrewardError", "Cancelled", "Unknown", "InvalidArgument", "InvalidInput", "DeadlineExceeded", "NotFound", "AlreadyExists",
    "PermissionDenied", "ResourceExhausted", "FailedPrecondition", "Aborted", "OutOfRange", "Unimplemented",
    "Internal", "Unavailable", "DataLoss", "Unauthenticated", "pb", "DEFAULT_CHUNK_BYTES", "MAX_MESSAGE_BYTES",
]
