import datetime

from google.protobuf import timestamp_pb2 as _timestamp_pb2
from relreward._proto import tensor_pb2 as _tensor_pb2
from relreward._proto import datasets_pb2 as _datasets_pb2
from google.protobuf.internal import containers as _containers
from google.protobuf.internal import enum_type_wrapper as _enum_type_wrapper
from google.protobuf import descriptor as _descriptor
from google.protobuf import message as _message
from collections.abc import Iterable as _Iterable, Mapping as _Mapping
from typing import ClassVar as _ClassVar, Optional as _Optional, Union as _Union

DESCRIPTOR: _descriptor.FileDescriptor

class ModelKind(int, metaclass=_enum_type_wrapper.EnumTypeWrapper):
    __slots__ = ()
    MODEL_KIND_UNSPECIFIED: _ClassVar[ModelKind]
    MODEL_KIND_DIFFUSION: _ClassVar[ModelKind]
    MODEL_KIND_REWARD: _ClassVar[ModelKind]
    MODEL_KIND_DISCRIMINATOR: _ClassVar[ModelKind]

class ModelFormat(int, metaclass=_enum_type_wrapper.EnumTypeWrapper):
    __slots__ = ()
    MODEL_FORMAT_UNSPECIFIED: _ClassVar[ModelFormat]
    MODEL_FORMAT_TORCHSCRIPT: _ClassVar[ModelFormat]
    MODEL_FORMAT_NATIVE: _ClassVar[ModelFormat]

class Parametrization(int, metaclass=_enum_type_wrapper.EnumTypeWrapper):
    __slots__ = ()
    PARAMETRIZATION_UNSPECIFIED: _ClassVar[Parametrization]
    PARAMETRIZATION_EPSILON: _ClassVar[Parametrization]
    PARAMETRIZATION_X0: _ClassVar[Parametrization]
MODEL_KIND_UNSPECIFIED: ModelKind
MODEL_KIND_DIFFUSION: ModelKind
MODEL_KIND_REWARD: ModelKind
MODEL_KIND_DISCRIMINATOR: ModelKind
MODEL_FORMAT_UNSPECIFIED: ModelFormat
MODEL_FORMAT_TORCHSCRIPT: ModelFormat
MODEL_FORMAT_NATIVE: ModelFormat
PARAMETRIZATION_UNSPECIFIED: Parametrization
PARAMETRIZATION_EPSILON: Parametrization
PARAMETRIZATION_X0: Parametrization

class Schedule(_message.Message):
    __slots__ = ("linear", "cosine", "diffuser_cosine", "betas")
    class Linear(_message.Message):
        __slots__ = ()
        def __init__(self) -> None: ...
    class Cosine(_message.Message):
        __slots__ = ("s",)
        S_FIELD_NUMBER: _ClassVar[int]
        s: float
        def __init__(self, s: _Optional[float] = ...) -> None: ...
    class ExplicitBetas(_message.Message):
        __slots__ = ("betas",)
        BETAS_FIELD_NUMBER: _ClassVar[int]
        betas: _containers.RepeatedScalarFieldContainer[float]
        def __init__(self, betas: _Optional[_Iterable[float]] = ...) -> None: ...
    LINEAR_FIELD_NUMBER: _ClassVar[int]
    COSINE_FIELD_NUMBER: _ClassVar[int]
    DIFFUSER_COSINE_FIELD_NUMBER: _ClassVar[int]
    BETAS_FIELD_NUMBER: _ClassVar[int]
    linear: Schedule.Linear
    cosine: Schedule.Cosine
    diffuser_cosine: Schedule.Cosine
    betas: Schedule.ExplicitBetas
    def __init__(self, linear: _Optional[_Union[Schedule.Linear, _Mapping]] = ..., cosine: _Optional[_Union[Schedule.Cosine, _Mapping]] = ..., diffuser_cosine: _Optional[_Union[Schedule.Cosine, _Mapping]] = ..., betas: _Optional[_Union[Schedule.ExplicitBetas, _Mapping]] = ...) -> None: ...

class DiffusionManifest(_message.Message):
    __slots__ = ("parametrization", "schedule", "n_timesteps", "clip_denoised", "trajectory", "sample", "normalizer")
    class Trajectory(_message.Message):
        __slots__ = ("horizon", "action_dim", "obs_dim")
        HORIZON_FIELD_NUMBER: _ClassVar[int]
        ACTION_DIM_FIELD_NUMBER: _ClassVar[int]
        OBS_DIM_FIELD_NUMBER: _ClassVar[int]
        horizon: int
        action_dim: int
        obs_dim: int
        def __init__(self, horizon: _Optional[int] = ..., action_dim: _Optional[int] = ..., obs_dim: _Optional[int] = ...) -> None: ...
    class Sample(_message.Message):
        __slots__ = ("shape",)
        SHAPE_FIELD_NUMBER: _ClassVar[int]
        shape: _containers.RepeatedScalarFieldContainer[int]
        def __init__(self, shape: _Optional[_Iterable[int]] = ...) -> None: ...
    PARAMETRIZATION_FIELD_NUMBER: _ClassVar[int]
    SCHEDULE_FIELD_NUMBER: _ClassVar[int]
    N_TIMESTEPS_FIELD_NUMBER: _ClassVar[int]
    CLIP_DENOISED_FIELD_NUMBER: _ClassVar[int]
    TRAJECTORY_FIELD_NUMBER: _ClassVar[int]
    SAMPLE_FIELD_NUMBER: _ClassVar[int]
    NORMALIZER_FIELD_NUMBER: _ClassVar[int]
    parametrization: Parametrization
    schedule: Schedule
    n_timesteps: int
    clip_denoised: bool
    trajectory: DiffusionManifest.Trajectory
    sample: DiffusionManifest.Sample
    normalizer: _tensor_pb2.Normalizer
    def __init__(self, parametrization: _Optional[_Union[Parametrization, str]] = ..., schedule: _Optional[_Union[Schedule, _Mapping]] = ..., n_timesteps: _Optional[int] = ..., clip_denoised: _Optional[bool] = ..., trajectory: _Optional[_Union[DiffusionManifest.Trajectory, _Mapping]] = ..., sample: _Optional[_Union[DiffusionManifest.Sample, _Mapping]] = ..., normalizer: _Optional[_Union[_tensor_pb2.Normalizer, _Mapping]] = ...) -> None: ...

class UploadModelRequest(_message.Message):
    __slots__ = ("header", "chunk", "commit")
    HEADER_FIELD_NUMBER: _ClassVar[int]
    CHUNK_FIELD_NUMBER: _ClassVar[int]
    COMMIT_FIELD_NUMBER: _ClassVar[int]
    header: UploadModelHeader
    chunk: bytes
    commit: _datasets_pb2.UploadCommit
    def __init__(self, header: _Optional[_Union[UploadModelHeader, _Mapping]] = ..., chunk: _Optional[bytes] = ..., commit: _Optional[_Union[_datasets_pb2.UploadCommit, _Mapping]] = ...) -> None: ...

class UploadModelHeader(_message.Message):
    __slots__ = ("name", "manifest", "description")
    NAME_FIELD_NUMBER: _ClassVar[int]
    MANIFEST_FIELD_NUMBER: _ClassVar[int]
    DESCRIPTION_FIELD_NUMBER: _ClassVar[int]
    name: str
    manifest: DiffusionManifest
    description: str
    def __init__(self, name: _Optional[str] = ..., manifest: _Optional[_Union[DiffusionManifest, _Mapping]] = ..., description: _Optional[str] = ...) -> None: ...

class Provenance(_message.Message):
    __slots__ = ("uploaded", "trained")
    class Uploaded(_message.Message):
        __slots__ = ()
        def __init__(self) -> None: ...
    class Trained(_message.Message):
        __slots__ = ("job_id", "datasets", "models", "final_loss")
        JOB_ID_FIELD_NUMBER: _ClassVar[int]
        DATASETS_FIELD_NUMBER: _ClassVar[int]
        MODELS_FIELD_NUMBER: _ClassVar[int]
        FINAL_LOSS_FIELD_NUMBER: _ClassVar[int]
        job_id: str
        datasets: _containers.RepeatedScalarFieldContainer[str]
        models: _containers.RepeatedScalarFieldContainer[str]
        final_loss: float
        def __init__(self, job_id: _Optional[str] = ..., datasets: _Optional[_Iterable[str]] = ..., models: _Optional[_Iterable[str]] = ..., final_loss: _Optional[float] = ...) -> None: ...
    UPLOADED_FIELD_NUMBER: _ClassVar[int]
    TRAINED_FIELD_NUMBER: _ClassVar[int]
    uploaded: Provenance.Uploaded
    trained: Provenance.Trained
    def __init__(self, uploaded: _Optional[_Union[Provenance.Uploaded, _Mapping]] = ..., trained: _Optional[_Union[Provenance.Trained, _Mapping]] = ...) -> None: ...

class RewardInfo(_message.Message):
    __slots__ = ("base_model", "expert_model", "architecture", "window", "input_shape", "normalizer", "n_timesteps")
    BASE_MODEL_FIELD_NUMBER: _ClassVar[int]
    EXPERT_MODEL_FIELD_NUMBER: _ClassVar[int]
    ARCHITECTURE_FIELD_NUMBER: _ClassVar[int]
    WINDOW_FIELD_NUMBER: _ClassVar[int]
    INPUT_SHAPE_FIELD_NUMBER: _ClassVar[int]
    NORMALIZER_FIELD_NUMBER: _ClassVar[int]
    N_TIMESTEPS_FIELD_NUMBER: _ClassVar[int]
    base_model: str
    expert_model: str
    architecture: str
    window: int
    input_shape: _containers.RepeatedScalarFieldContainer[int]
    normalizer: _tensor_pb2.Normalizer
    n_timesteps: int
    def __init__(self, base_model: _Optional[str] = ..., expert_model: _Optional[str] = ..., architecture: _Optional[str] = ..., window: _Optional[int] = ..., input_shape: _Optional[_Iterable[int]] = ..., normalizer: _Optional[_Union[_tensor_pb2.Normalizer, _Mapping]] = ..., n_timesteps: _Optional[int] = ...) -> None: ...

class Model(_message.Message):
    __slots__ = ("name", "kind", "format", "manifest", "reward", "parameter_count", "sha256", "size_bytes", "provenance", "created_at", "description")
    NAME_FIELD_NUMBER: _ClassVar[int]
    KIND_FIELD_NUMBER: _ClassVar[int]
    FORMAT_FIELD_NUMBER: _ClassVar[int]
    MANIFEST_FIELD_NUMBER: _ClassVar[int]
    REWARD_FIELD_NUMBER: _ClassVar[int]
    PARAMETER_COUNT_FIELD_NUMBER: _ClassVar[int]
    SHA256_FIELD_NUMBER: _ClassVar[int]
    SIZE_BYTES_FIELD_NUMBER: _ClassVar[int]
    PROVENANCE_FIELD_NUMBER: _ClassVar[int]
    CREATED_AT_FIELD_NUMBER: _ClassVar[int]
    DESCRIPTION_FIELD_NUMBER: _ClassVar[int]
    name: str
    kind: ModelKind
    format: ModelFormat
    manifest: DiffusionManifest
    reward: RewardInfo
    parameter_count: int
    sha256: str
    size_bytes: int
    provenance: Provenance
    created_at: _timestamp_pb2.Timestamp
    description: str
    def __init__(self, name: _Optional[str] = ..., kind: _Optional[_Union[ModelKind, str]] = ..., format: _Optional[_Union[ModelFormat, str]] = ..., manifest: _Optional[_Union[DiffusionManifest, _Mapping]] = ..., reward: _Optional[_Union[RewardInfo, _Mapping]] = ..., parameter_count: _Optional[int] = ..., sha256: _Optional[str] = ..., size_bytes: _Optional[int] = ..., provenance: _Optional[_Union[Provenance, _Mapping]] = ..., created_at: _Optional[_Union[datetime.datetime, _timestamp_pb2.Timestamp, _Mapping]] = ..., description: _Optional[str] = ...) -> None: ...

class GetModelRequest(_message.Message):
    __slots__ = ("name",)
    NAME_FIELD_NUMBER: _ClassVar[int]
    name: str
    def __init__(self, name: _Optional[str] = ...) -> None: ...

class ListModelsRequest(_message.Message):
    __slots__ = ("page", "kind")
    PAGE_FIELD_NUMBER: _ClassVar[int]
    KIND_FIELD_NUMBER: _ClassVar[int]
    page: _tensor_pb2.PageRequest
    kind: ModelKind
    def __init__(self, page: _Optional[_Union[_tensor_pb2.PageRequest, _Mapping]] = ..., kind: _Optional[_Union[ModelKind, str]] = ...) -> None: ...

class ListModelsResponse(_message.Message):
    __slots__ = ("models", "next_page_token")
    MODELS_FIELD_NUMBER: _ClassVar[int]
    NEXT_PAGE_TOKEN_FIELD_NUMBER: _ClassVar[int]
    models: _containers.RepeatedCompositeFieldContainer[Model]
    next_page_token: str
    def __init__(self, models: _Optional[_Iterable[_Union[Model, _Mapping]]] = ..., next_page_token: _Optional[str] = ...) -> None: ...

class DeleteModelRequest(_message.Message):
    __slots__ = ("name",)
    NAME_FIELD_NUMBER: _ClassVar[int]
    name: str
    def __init__(self, name: _Optional[str] = ...) -> None: ...

class DeleteModelResponse(_message.Message):
    __slots__ = ()
    def __init__(self) -> None: ...
