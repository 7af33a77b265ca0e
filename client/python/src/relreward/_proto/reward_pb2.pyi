from relreward._proto import tensor_pb2 as _tensor_pb2
from google.protobuf.internal import containers as _containers
from google.protobuf.internal import enum_type_wrapper as _enum_type_wrapper
from google.protobuf import descriptor as _descriptor
from google.protobuf import message as _message
from collections.abc import Iterable as _Iterable, Mapping as _Mapping
from typing import ClassVar as _ClassVar, Optional as _Optional, Union as _Union

DESCRIPTOR: _descriptor.FileDescriptor

class Units(int, metaclass=_enum_type_wrapper.EnumTypeWrapper):
    __slots__ = ()
    UNITS_UNSPECIFIED: _ClassVar[Units]
    UNITS_RAW: _ClassVar[Units]
    UNITS_NORMALIZED: _ClassVar[Units]
UNITS_UNSPECIFIED: Units
UNITS_RAW: Units
UNITS_NORMALIZED: Units

class ScoreRequest(_message.Message):
    __slots__ = ("model", "x", "t", "input_units", "per_window", "per_step")
    MODEL_FIELD_NUMBER: _ClassVar[int]
    X_FIELD_NUMBER: _ClassVar[int]
    T_FIELD_NUMBER: _ClassVar[int]
    INPUT_UNITS_FIELD_NUMBER: _ClassVar[int]
    PER_WINDOW_FIELD_NUMBER: _ClassVar[int]
    PER_STEP_FIELD_NUMBER: _ClassVar[int]
    model: str
    x: _tensor_pb2.Tensor
    t: _containers.RepeatedScalarFieldContainer[int]
    input_units: Units
    per_window: bool
    per_step: bool
    def __init__(self, model: _Optional[str] = ..., x: _Optional[_Union[_tensor_pb2.Tensor, _Mapping]] = ..., t: _Optional[_Iterable[int]] = ..., input_units: _Optional[_Union[Units, str]] = ..., per_window: _Optional[bool] = ..., per_step: _Optional[bool] = ...) -> None: ...

class ScoreResponse(_message.Message):
    __slots__ = ("rewards", "per_window", "per_step")
    REWARDS_FIELD_NUMBER: _ClassVar[int]
    PER_WINDOW_FIELD_NUMBER: _ClassVar[int]
    PER_STEP_FIELD_NUMBER: _ClassVar[int]
    rewards: _tensor_pb2.Tensor
    per_window: _tensor_pb2.Tensor
    per_step: _tensor_pb2.Tensor
    def __init__(self, rewards: _Optional[_Union[_tensor_pb2.Tensor, _Mapping]] = ..., per_window: _Optional[_Union[_tensor_pb2.Tensor, _Mapping]] = ..., per_step: _Optional[_Union[_tensor_pb2.Tensor, _Mapping]] = ...) -> None: ...

class GradientRequest(_message.Message):
    __slots__ = ("request_id", "model", "x", "t", "input_units", "gradient_units", "omega", "scale_by_posterior_variance_of")
    REQUEST_ID_FIELD_NUMBER: _ClassVar[int]
    MODEL_FIELD_NUMBER: _ClassVar[int]
    X_FIELD_NUMBER: _ClassVar[int]
    T_FIELD_NUMBER: _ClassVar[int]
    INPUT_UNITS_FIELD_NUMBER: _ClassVar[int]
    GRADIENT_UNITS_FIELD_NUMBER: _ClassVar[int]
    OMEGA_FIELD_NUMBER: _ClassVar[int]
    SCALE_BY_POSTERIOR_VARIANCE_OF_FIELD_NUMBER: _ClassVar[int]
    request_id: int
    model: str
    x: _tensor_pb2.Tensor
    t: _containers.RepeatedScalarFieldContainer[int]
    input_units: Units
    gradient_units: Units
    omega: float
    scale_by_posterior_variance_of: str
    def __init__(self, request_id: _Optional[int] = ..., model: _Optional[str] = ..., x: _Optional[_Union[_tensor_pb2.Tensor, _Mapping]] = ..., t: _Optional[_Iterable[int]] = ..., input_units: _Optional[_Union[Units, str]] = ..., gradient_units: _Optional[_Union[Units, str]] = ..., omega: _Optional[float] = ..., scale_by_posterior_variance_of: _Optional[str] = ...) -> None: ...

class GradientResponse(_message.Message):
    __slots__ = ("request_id", "gradient", "rewards", "error")
    REQUEST_ID_FIELD_NUMBER: _ClassVar[int]
    GRADIENT_FIELD_NUMBER: _ClassVar[int]
    REWARDS_FIELD_NUMBER: _ClassVar[int]
    ERROR_FIELD_NUMBER: _ClassVar[int]
    request_id: int
    gradient: _tensor_pb2.Tensor
    rewards: _tensor_pb2.Tensor
    error: StreamError
    def __init__(self, request_id: _Optional[int] = ..., gradient: _Optional[_Union[_tensor_pb2.Tensor, _Mapping]] = ..., rewards: _Optional[_Union[_tensor_pb2.Tensor, _Mapping]] = ..., error: _Optional[_Union[StreamError, _Mapping]] = ...) -> None: ...

class StreamError(_message.Message):
    __slots__ = ("code", "message")
    CODE_FIELD_NUMBER: _ClassVar[int]
    MESSAGE_FIELD_NUMBER: _ClassVar[int]
    code: int
    message: str
    def __init__(self, code: _Optional[int] = ..., message: _Optional[str] = ...) -> None: ...

class Condition(_message.Message):
    __slots__ = ("index", "state")
    INDEX_FIELD_NUMBER: _ClassVar[int]
    STATE_FIELD_NUMBER: _ClassVar[int]
    index: int
    state: _tensor_pb2.Tensor
    def __init__(self, index: _Optional[int] = ..., state: _Optional[_Union[_tensor_pb2.Tensor, _Mapping]] = ...) -> None: ...

class SampleRequest(_message.Message):
    __slots__ = ("model", "reward_model", "omega", "n_guide_steps", "t_stopgrad", "scale_grad_by_std", "conditions", "input_units", "n", "seed", "batch_size")
    MODEL_FIELD_NUMBER: _ClassVar[int]
    REWARD_MODEL_FIELD_NUMBER: _ClassVar[int]
    OMEGA_FIELD_NUMBER: _ClassVar[int]
    N_GUIDE_STEPS_FIELD_NUMBER: _ClassVar[int]
    T_STOPGRAD_FIELD_NUMBER: _ClassVar[int]
    SCALE_GRAD_BY_STD_FIELD_NUMBER: _ClassVar[int]
    CONDITIONS_FIELD_NUMBER: _ClassVar[int]
    INPUT_UNITS_FIELD_NUMBER: _ClassVar[int]
    N_FIELD_NUMBER: _ClassVar[int]
    SEED_FIELD_NUMBER: _ClassVar[int]
    BATCH_SIZE_FIELD_NUMBER: _ClassVar[int]
    model: str
    reward_model: str
    omega: float
    n_guide_steps: int
    t_stopgrad: int
    scale_grad_by_std: bool
    conditions: _containers.RepeatedCompositeFieldContainer[Condition]
    input_units: Units
    n: int
    seed: int
    batch_size: int
    def __init__(self, model: _Optional[str] = ..., reward_model: _Optional[str] = ..., omega: _Optional[float] = ..., n_guide_steps: _Optional[int] = ..., t_stopgrad: _Optional[int] = ..., scale_grad_by_std: _Optional[bool] = ..., conditions: _Optional[_Iterable[_Union[Condition, _Mapping]]] = ..., input_units: _Optional[_Union[Units, str]] = ..., n: _Optional[int] = ..., seed: _Optional[int] = ..., batch_size: _Optional[int] = ...) -> None: ...

class SampleResponse(_message.Message):
    __slots__ = ("index", "x", "x_normalized", "reward")
    INDEX_FIELD_NUMBER: _ClassVar[int]
    X_FIELD_NUMBER: _ClassVar[int]
    X_NORMALIZED_FIELD_NUMBER: _ClassVar[int]
    REWARD_FIELD_NUMBER: _ClassVar[int]
    index: int
    x: _tensor_pb2.Tensor
    x_normalized: _tensor_pb2.Tensor
    reward: float
    def __init__(self, index: _Optional[int] = ..., x: _Optional[_Union[_tensor_pb2.Tensor, _Mapping]] = ..., x_normalized: _Optional[_Union[_tensor_pb2.Tensor, _Mapping]] = ..., reward: _Optional[float] = ...) -> None: ...
