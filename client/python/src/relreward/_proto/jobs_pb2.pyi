import datetime

from google.protobuf import timestamp_pb2 as _timestamp_pb2
from relreward._proto import models_pb2 as _models_pb2
from relreward._proto import tensor_pb2 as _tensor_pb2
from google.protobuf.internal import containers as _containers
from google.protobuf.internal import enum_type_wrapper as _enum_type_wrapper
from google.protobuf import descriptor as _descriptor
from google.protobuf import message as _message
from collections.abc import Iterable as _Iterable, Mapping as _Mapping
from typing import ClassVar as _ClassVar, Optional as _Optional, Union as _Union

DESCRIPTOR: _descriptor.FileDescriptor

class JobState(int, metaclass=_enum_type_wrapper.EnumTypeWrapper):
    __slots__ = ()
    JOB_STATE_UNSPECIFIED: _ClassVar[JobState]
    JOB_STATE_PENDING: _ClassVar[JobState]
    JOB_STATE_RUNNING: _ClassVar[JobState]
    JOB_STATE_SUCCEEDED: _ClassVar[JobState]
    JOB_STATE_FAILED: _ClassVar[JobState]
    JOB_STATE_CANCELLED: _ClassVar[JobState]

class RewardTarget(int, metaclass=_enum_type_wrapper.EnumTypeWrapper):
    __slots__ = ()
    REWARD_TARGET_UNSPECIFIED: _ClassVar[RewardTarget]
    REWARD_TARGET_MEAN: _ClassVar[RewardTarget]
    REWARD_TARGET_SCORE: _ClassVar[RewardTarget]

class EvalPoint(int, metaclass=_enum_type_wrapper.EnumTypeWrapper):
    __slots__ = ()
    EVAL_POINT_UNSPECIFIED: _ClassVar[EvalPoint]
    EVAL_POINT_X_T: _ClassVar[EvalPoint]
    EVAL_POINT_MU_BASE: _ClassVar[EvalPoint]
JOB_STATE_UNSPECIFIED: JobState
JOB_STATE_PENDING: JobState
JOB_STATE_RUNNING: JobState
JOB_STATE_SUCCEEDED: JobState
JOB_STATE_FAILED: JobState
JOB_STATE_CANCELLED: JobState
REWARD_TARGET_UNSPECIFIED: RewardTarget
REWARD_TARGET_MEAN: RewardTarget
REWARD_TARGET_SCORE: RewardTarget
EVAL_POINT_UNSPECIFIED: EvalPoint
EVAL_POINT_X_T: EvalPoint
EVAL_POINT_MU_BASE: EvalPoint

class JobSpec(_message.Message):
    __slots__ = ("output_model", "seed", "optimization", "diffusion", "reward", "discriminator")
    OUTPUT_MODEL_FIELD_NUMBER: _ClassVar[int]
    SEED_FIELD_NUMBER: _ClassVar[int]
    OPTIMIZATION_FIELD_NUMBER: _ClassVar[int]
    DIFFUSION_FIELD_NUMBER: _ClassVar[int]
    REWARD_FIELD_NUMBER: _ClassVar[int]
    DISCRIMINATOR_FIELD_NUMBER: _ClassVar[int]
    output_model: str
    seed: int
    optimization: Optimization
    diffusion: TrainDiffusion
    reward: TrainReward
    discriminator: TrainDiscriminator
    def __init__(self, output_model: _Optional[str] = ..., seed: _Optional[int] = ..., optimization: _Optional[_Union[Optimization, _Mapping]] = ..., diffusion: _Optional[_Union[TrainDiffusion, _Mapping]] = ..., reward: _Optional[_Union[TrainReward, _Mapping]] = ..., discriminator: _Optional[_Union[TrainDiscriminator, _Mapping]] = ...) -> None: ...

class Optimization(_message.Message):
    __slots__ = ("steps", "batch_size", "learning_rate", "grad_clip", "ema_decay", "ema_every", "ema_start", "checkpoint_every", "eval_every", "log_every")
    STEPS_FIELD_NUMBER: _ClassVar[int]
    BATCH_SIZE_FIELD_NUMBER: _ClassVar[int]
    LEARNING_RATE_FIELD_NUMBER: _ClassVar[int]
    GRAD_CLIP_FIELD_NUMBER: _ClassVar[int]
    EMA_DECAY_FIELD_NUMBER: _ClassVar[int]
    EMA_EVERY_FIELD_NUMBER: _ClassVar[int]
    EMA_START_FIELD_NUMBER: _ClassVar[int]
    CHECKPOINT_EVERY_FIELD_NUMBER: _ClassVar[int]
    EVAL_EVERY_FIELD_NUMBER: _ClassVar[int]
    LOG_EVERY_FIELD_NUMBER: _ClassVar[int]
    steps: int
    batch_size: int
    learning_rate: float
    grad_clip: float
    ema_decay: float
    ema_every: int
    ema_start: int
    checkpoint_every: int
    eval_every: int
    log_every: int
    def __init__(self, steps: _Optional[int] = ..., batch_size: _Optional[int] = ..., learning_rate: _Optional[float] = ..., grad_clip: _Optional[float] = ..., ema_decay: _Optional[float] = ..., ema_every: _Optional[int] = ..., ema_start: _Optional[int] = ..., checkpoint_every: _Optional[int] = ..., eval_every: _Optional[int] = ..., log_every: _Optional[int] = ...) -> None: ...

class TrainDiffusion(_message.Message):
    __slots__ = ("dataset", "parametrization", "schedule", "n_timesteps", "horizon", "temporal_unet", "mlp", "action_weight", "clip_denoised", "normalizer_datasets")
    DATASET_FIELD_NUMBER: _ClassVar[int]
    PARAMETRIZATION_FIELD_NUMBER: _ClassVar[int]
    SCHEDULE_FIELD_NUMBER: _ClassVar[int]
    N_TIMESTEPS_FIELD_NUMBER: _ClassVar[int]
    HORIZON_FIELD_NUMBER: _ClassVar[int]
    TEMPORAL_UNET_FIELD_NUMBER: _ClassVar[int]
    MLP_FIELD_NUMBER: _ClassVar[int]
    ACTION_WEIGHT_FIELD_NUMBER: _ClassVar[int]
    CLIP_DENOISED_FIELD_NUMBER: _ClassVar[int]
    NORMALIZER_DATASETS_FIELD_NUMBER: _ClassVar[int]
    dataset: str
    parametrization: _models_pb2.Parametrization
    schedule: _models_pb2.Schedule
    n_timesteps: int
    horizon: int
    temporal_unet: TemporalUnet
    mlp: Mlp
    action_weight: float
    clip_denoised: bool
    normalizer_datasets: _containers.RepeatedScalarFieldContainer[str]
    def __init__(self, dataset: _Optional[str] = ..., parametrization: _Optional[_Union[_models_pb2.Parametrization, str]] = ..., schedule: _Optional[_Union[_models_pb2.Schedule, _Mapping]] = ..., n_timesteps: _Optional[int] = ..., horizon: _Optional[int] = ..., temporal_unet: _Optional[_Union[TemporalUnet, _Mapping]] = ..., mlp: _Optional[_Union[Mlp, _Mapping]] = ..., action_weight: _Optional[float] = ..., clip_denoised: _Optional[bool] = ..., normalizer_datasets: _Optional[_Iterable[str]] = ...) -> None: ...

class TemporalUnet(_message.Message):
    __slots__ = ("dim", "dim_mults")
    DIM_FIELD_NUMBER: _ClassVar[int]
    DIM_MULTS_FIELD_NUMBER: _ClassVar[int]
    dim: int
    dim_mults: _containers.RepeatedScalarFieldContainer[int]
    def __init__(self, dim: _Optional[int] = ..., dim_mults: _Optional[_Iterable[int]] = ...) -> None: ...

class Mlp(_message.Message):
    __slots__ = ("hidden",)
    HIDDEN_FIELD_NUMBER: _ClassVar[int]
    hidden: _containers.RepeatedScalarFieldContainer[int]
    def __init__(self, hidden: _Optional[_Iterable[int]] = ...) -> None: ...

class RewardArchitecture(_message.Message):
    __slots__ = ("windowed_mlp", "value_function", "conv_encoder", "mlp")
    class WindowedMlp(_message.Message):
        __slots__ = ("window", "hidden")
        WINDOW_FIELD_NUMBER: _ClassVar[int]
        HIDDEN_FIELD_NUMBER: _ClassVar[int]
        window: int
        hidden: _containers.RepeatedScalarFieldContainer[int]
        def __init__(self, window: _Optional[int] = ..., hidden: _Optional[_Iterable[int]] = ...) -> None: ...
    class ValueFunction(_message.Message):
        __slots__ = ("widths",)
        WIDTHS_FIELD_NUMBER: _ClassVar[int]
        widths: _containers.RepeatedScalarFieldContainer[int]
        def __init__(self, widths: _Optional[_Iterable[int]] = ...) -> None: ...
    class ConvEncoder(_message.Message):
        __slots__ = ("widths",)
        WIDTHS_FIELD_NUMBER: _ClassVar[int]
        widths: _containers.RepeatedScalarFieldContainer[int]
        def __init__(self, widths: _Optional[_Iterable[int]] = ...) -> None: ...
    WINDOWED_MLP_FIELD_NUMBER: _ClassVar[int]
    VALUE_FUNCTION_FIELD_NUMBER: _ClassVar[int]
    CONV_ENCODER_FIELD_NUMBER: _ClassVar[int]
    MLP_FIELD_NUMBER: _ClassVar[int]
    windowed_mlp: RewardArchitecture.WindowedMlp
    value_function: RewardArchitecture.ValueFunction
    conv_encoder: RewardArchitecture.ConvEncoder
    mlp: Mlp
    def __init__(self, windowed_mlp: _Optional[_Union[RewardArchitecture.WindowedMlp, _Mapping]] = ..., value_function: _Optional[_Union[RewardArchitecture.ValueFunction, _Mapping]] = ..., conv_encoder: _Optional[_Union[RewardArchitecture.ConvEncoder, _Mapping]] = ..., mlp: _Optional[_Union[Mlp, _Mapping]] = ...) -> None: ...

class TrainReward(_message.Message):
    __slots__ = ("base_model", "expert_model", "architecture", "target", "eval_point", "with_dataset", "models_only", "rho_l2")
    class WithDataset(_message.Message):
        __slots__ = ("datasets",)
        DATASETS_FIELD_NUMBER: _ClassVar[int]
        datasets: _containers.RepeatedScalarFieldContainer[str]
        def __init__(self, datasets: _Optional[_Iterable[str]] = ...) -> None: ...
    class ModelsOnly(_message.Message):
        __slots__ = ("num_chains",)
        NUM_CHAINS_FIELD_NUMBER: _ClassVar[int]
        num_chains: int
        def __init__(self, num_chains: _Optional[int] = ...) -> None: ...
    BASE_MODEL_FIELD_NUMBER: _ClassVar[int]
    EXPERT_MODEL_FIELD_NUMBER: _ClassVar[int]
    ARCHITECTURE_FIELD_NUMBER: _ClassVar[int]
    TARGET_FIELD_NUMBER: _ClassVar[int]
    EVAL_POINT_FIELD_NUMBER: _ClassVar[int]
    WITH_DATASET_FIELD_NUMBER: _ClassVar[int]
    MODELS_ONLY_FIELD_NUMBER: _ClassVar[int]
    RHO_L2_FIELD_NUMBER: _ClassVar[int]
    base_model: str
    expert_model: str
    architecture: RewardArchitecture
    target: RewardTarget
    eval_point: EvalPoint
    with_dataset: TrainReward.WithDataset
    models_only: TrainReward.ModelsOnly
    rho_l2: float
    def __init__(self, base_model: _Optional[str] = ..., expert_model: _Optional[str] = ..., architecture: _Optional[_Union[RewardArchitecture, _Mapping]] = ..., target: _Optional[_Union[RewardTarget, str]] = ..., eval_point: _Optional[_Union[EvalPoint, str]] = ..., with_dataset: _Optional[_Union[TrainReward.WithDataset, _Mapping]] = ..., models_only: _Optional[_Union[TrainReward.ModelsOnly, _Mapping]] = ..., rho_l2: _Optional[float] = ...) -> None: ...

class TrainDiscriminator(_message.Message):
    __slots__ = ("base_dataset", "expert_dataset", "architecture", "diffusion_model")
    BASE_DATASET_FIELD_NUMBER: _ClassVar[int]
    EXPERT_DATASET_FIELD_NUMBER: _ClassVar[int]
    ARCHITECTURE_FIELD_NUMBER: _ClassVar[int]
    DIFFUSION_MODEL_FIELD_NUMBER: _ClassVar[int]
    base_dataset: str
    expert_dataset: str
    architecture: RewardArchitecture
    diffusion_model: str
    def __init__(self, base_dataset: _Optional[str] = ..., expert_dataset: _Optional[str] = ..., architecture: _Optional[_Union[RewardArchitecture, _Mapping]] = ..., diffusion_model: _Optional[str] = ...) -> None: ...

class Job(_message.Message):
    __slots__ = ("id", "spec", "state", "step", "total_steps", "loss", "error", "created_at", "started_at", "finished_at", "last_seq")
    ID_FIELD_NUMBER: _ClassVar[int]
    SPEC_FIELD_NUMBER: _ClassVar[int]
    STATE_FIELD_NUMBER: _ClassVar[int]
    STEP_FIELD_NUMBER: _ClassVar[int]
    TOTAL_STEPS_FIELD_NUMBER: _ClassVar[int]
    LOSS_FIELD_NUMBER: _ClassVar[int]
    ERROR_FIELD_NUMBER: _ClassVar[int]
    CREATED_AT_FIELD_NUMBER: _ClassVar[int]
    STARTED_AT_FIELD_NUMBER: _ClassVar[int]
    FINISHED_AT_FIELD_NUMBER: _ClassVar[int]
    LAST_SEQ_FIELD_NUMBER: _ClassVar[int]
    id: str
    spec: JobSpec
    state: JobState
    step: int
    total_steps: int
    loss: float
    error: str
    created_at: _timestamp_pb2.Timestamp
    started_at: _timestamp_pb2.Timestamp
    finished_at: _timestamp_pb2.Timestamp
    last_seq: int
    def __init__(self, id: _Optional[str] = ..., spec: _Optional[_Union[JobSpec, _Mapping]] = ..., state: _Optional[_Union[JobState, str]] = ..., step: _Optional[int] = ..., total_steps: _Optional[int] = ..., loss: _Optional[float] = ..., error: _Optional[str] = ..., created_at: _Optional[_Union[datetime.datetime, _timestamp_pb2.Timestamp, _Mapping]] = ..., started_at: _Optional[_Union[datetime.datetime, _timestamp_pb2.Timestamp, _Mapping]] = ..., finished_at: _Optional[_Union[datetime.datetime, _timestamp_pb2.Timestamp, _Mapping]] = ..., last_seq: _Optional[int] = ...) -> None: ...

class SubmitJobRequest(_message.Message):
    __slots__ = ("spec", "job_id")
    SPEC_FIELD_NUMBER: _ClassVar[int]
    JOB_ID_FIELD_NUMBER: _ClassVar[int]
    spec: JobSpec
    job_id: str
    def __init__(self, spec: _Optional[_Union[JobSpec, _Mapping]] = ..., job_id: _Optional[str] = ...) -> None: ...

class GetJobRequest(_message.Message):
    __slots__ = ("id",)
    ID_FIELD_NUMBER: _ClassVar[int]
    id: str
    def __init__(self, id: _Optional[str] = ...) -> None: ...

class ListJobsRequest(_message.Message):
    __slots__ = ("page", "state")
    PAGE_FIELD_NUMBER: _ClassVar[int]
    STATE_FIELD_NUMBER: _ClassVar[int]
    page: _tensor_pb2.PageRequest
    state: JobState
    def __init__(self, page: _Optional[_Union[_tensor_pb2.PageRequest, _Mapping]] = ..., state: _Optional[_Union[JobState, str]] = ...) -> None: ...

class ListJobsResponse(_message.Message):
    __slots__ = ("jobs", "next_page_token")
    JOBS_FIELD_NUMBER: _ClassVar[int]
    NEXT_PAGE_TOKEN_FIELD_NUMBER: _ClassVar[int]
    jobs: _containers.RepeatedCompositeFieldContainer[Job]
    next_page_token: str
    def __init__(self, jobs: _Optional[_Iterable[_Union[Job, _Mapping]]] = ..., next_page_token: _Optional[str] = ...) -> None: ...

class CancelJobRequest(_message.Message):
    __slots__ = ("id",)
    ID_FIELD_NUMBER: _ClassVar[int]
    id: str
    def __init__(self, id: _Optional[str] = ...) -> None: ...

class WatchJobRequest(_message.Message):
    __slots__ = ("id", "from_seq")
    ID_FIELD_NUMBER: _ClassVar[int]
    FROM_SEQ_FIELD_NUMBER: _ClassVar[int]
    id: str
    from_seq: int
    def __init__(self, id: _Optional[str] = ..., from_seq: _Optional[int] = ...) -> None: ...

class JobEvent(_message.Message):
    __slots__ = ("seq", "time", "state", "progress", "checkpoint", "log")
    class StateChange(_message.Message):
        __slots__ = ("state", "message")
        STATE_FIELD_NUMBER: _ClassVar[int]
        MESSAGE_FIELD_NUMBER: _ClassVar[int]
        state: JobState
        message: str
        def __init__(self, state: _Optional[_Union[JobState, str]] = ..., message: _Optional[str] = ...) -> None: ...
    class Progress(_message.Message):
        __slots__ = ("step", "total_steps", "loss", "grad_norm", "learning_rate", "steps_per_second", "eta_seconds", "eval_loss")
        STEP_FIELD_NUMBER: _ClassVar[int]
        TOTAL_STEPS_FIELD_NUMBER: _ClassVar[int]
        LOSS_FIELD_NUMBER: _ClassVar[int]
        GRAD_NORM_FIELD_NUMBER: _ClassVar[int]
        LEARNING_RATE_FIELD_NUMBER: _ClassVar[int]
        STEPS_PER_SECOND_FIELD_NUMBER: _ClassVar[int]
        ETA_SECONDS_FIELD_NUMBER: _ClassVar[int]
        EVAL_LOSS_FIELD_NUMBER: _ClassVar[int]
        step: int
        total_steps: int
        loss: float
        grad_norm: float
        learning_rate: float
        steps_per_second: float
        eta_seconds: float
        eval_loss: float
        def __init__(self, step: _Optional[int] = ..., total_steps: _Optional[int] = ..., loss: _Optional[float] = ..., grad_norm: _Optional[float] = ..., learning_rate: _Optional[float] = ..., steps_per_second: _Optional[float] = ..., eta_seconds: _Optional[float] = ..., eval_loss: _Optional[float] = ...) -> None: ...
    class Checkpoint(_message.Message):
        __slots__ = ("step",)
        STEP_FIELD_NUMBER: _ClassVar[int]
        step: int
        def __init__(self, step: _Optional[int] = ...) -> None: ...
    class LogLine(_message.Message):
        __slots__ = ("message",)
        MESSAGE_FIELD_NUMBER: _ClassVar[int]
        message: str
        def __init__(self, message: _Optional[str] = ...) -> None: ...
    SEQ_FIELD_NUMBER: _ClassVar[int]
    TIME_FIELD_NUMBER: _ClassVar[int]
    STATE_FIELD_NUMBER: _ClassVar[int]
    PROGRESS_FIELD_NUMBER: _ClassVar[int]
    CHECKPOINT_FIELD_NUMBER: _ClassVar[int]
    LOG_FIELD_NUMBER: _ClassVar[int]
    seq: int
    time: _timestamp_pb2.Timestamp
    state: JobEvent.StateChange
    progress: JobEvent.Progress
    checkpoint: JobEvent.Checkpoint
    log: JobEvent.LogLine
    def __init__(self, seq: _Optional[int] = ..., time: _Optional[_Union[datetime.datetime, _timestamp_pb2.Timestamp, _Mapping]] = ..., state: _Optional[_Union[JobEvent.StateChange, _Mapping]] = ..., progress: _Optional[_Union[JobEvent.Progress, _Mapping]] = ..., checkpoint: _Optional[_Union[JobEvent.Checkpoint, _Mapping]] = ..., log: _Optional[_Union[JobEvent.LogLine, _Mapping]] = ...) -> None: ...
