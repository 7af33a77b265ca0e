"""relreward: the Python client of the relreward service.

    import numpy as np, relreward
    with relreward.Client("127.0.0.1:50051") as client:
        model = client.get_model("maze-reward")
        x = np.zeros((1, *model.item_shape), np.float32)
        grad, rho = client.gradient(model.name, x, t=model.n_timesteps - 1)

See :class:`Client` (and :class:`AsyncClient` for asyncio), :mod:`relreward.results` for what
they return, :mod:`relreward.guide` for a drop-in value guide for Diffuser-style planners,
:mod:`relreward.tracking` for a training job's events as TensorBoard event files and a W&B
offline run (imported on its own, ``from relreward.tracking import follow``, so that
``python -m relreward.tracking`` runs it as a script; it needs the ``tensorboard`` extra), and
docs/python.md.
"""

from relreward._common import TLS, DEFAULT_CHUNK_BYTES, MAX_MESSAGE_BYTES
from relreward._download import DownloadedModel
from relreward.v1 import autoencoder_pb2, datasets_pb2, jobs_pb2, models_pb2, reward_pb2, tensor_pb2
from relreward.aio import AsyncClient, AsyncGradientStream
from relreward.client import Client, GradientStream, PendingGradient
from relreward.datasets import from_minari_episodes
from relreward.relabel import Relabelled, relabel
from relreward.errors import (Aborted, AlreadyExists, Cancelled, DataLoss, DeadlineExceeded, FailedPrecondition,
                              Internal, InvalidArgument, InvalidInput, NotFound, OutOfRange, PermissionDenied, RelrewardError,
                              ResourceExhausted, Unauthenticated, Unavailable, Unimplemented, Unknown)
from relreward.results import (ArrayInfo, ArrayStats, AutoencoderInfo, Dataset, EpisodeInfo, GradientResult, Job, JobEvent, JobState,
                               Manifest, Model, Normalizer, Provenance, RecipeInfo, RewardInfo, Sample, SampleBatch, Schedule,
                               ScoreResult, Space)
from relreward.specs import DiffusionJob, DiscriminatorJob, Optimization, RewardJob, SafetyGuidance, SamplingRecipe
from relreward.rl import RewardVectorWrapper, RewardWindows, pointmaze_mapping

__version__ = "0.1.0"


class pb:
    """The generated protobuf message modules (``pb.reward.GradientRequest``, ...), for callers
    that need a raw message (every result also keeps the one it was read from as ``.proto``)."""

    autoencoder = autoencoder_pb2
    datasets = datasets_pb2
    jobs = jobs_pb2
    models = models_pb2
    reward = reward_pb2
    tensor = tensor_pb2


__all__ = [
    "Client", "AsyncClient", "GradientStream", "AsyncGradientStream", "PendingGradient", "TLS",
    "ScoreResult", "GradientResult", "Sample", "SampleBatch", "DownloadedModel",
    "Dataset", "ArrayInfo", "ArrayStats", "EpisodeInfo", "Model", "Manifest", "Schedule", "Space", "Normalizer",
    "RewardInfo", "AutoencoderInfo", "RecipeInfo", "Provenance", "Job", "JobState", "JobEvent",
    "DiffusionJob", "RewardJob", "DiscriminatorJob", "Optimization", "SafetyGuidance", "SamplingRecipe",
    "from_minari_episodes", "relabel", "Relabelled",
    "RewardVectorWrapper", "RewardWindows", "pointmaze_mapping",
    "RelrewardError", "Cancelled", "Unknown", "InvalidArgument", "InvalidInput", "DeadlineExceeded", "NotFound", "AlreadyExists",
    "PermissionDenied", "ResourceExhausted", "FailedPrecondition", "Aborted", "OutOfRange", "Unimplemented",
    "Internal", "Unavailable", "DataLoss", "Unauthenticated", "pb", "DEFAULT_CHUNK_BYTES", "MAX_MESSAGE_BYTES",
]
