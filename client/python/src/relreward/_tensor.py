"""numpy <-> relreward.v1.Tensor, with at most one copy each way (any array-like in; a torch
tensor is detached and brought to the CPU first, ``host``).

Encoding: ``np.ascontiguousarray(x, dtype='<f4').tobytes()`` copies the array once into the
message (no copy happens for the conversion when ``x`` is already C-contiguous little-endian
float32). Decoding: ``np.frombuffer(t.data, ...)`` is a view of the message's bytes, so the
arrays the client returns are read-only; call ``.copy()`` on one to modify it.
"""

from __future__ import annotations

import math
from typing import Any, cast

import numpy as np

from relreward.v1 import tensor_pb2

# numpy dtype (little-endian) for each wire dtype.
_NUMPY_OF: dict[int, np.dtype] = {
    tensor_pb2.DTYPE_FLOAT32: np.dtype("<f4"),
    tensor_pb2.DTYPE_FLOAT64: np.dtype("<f8"),
    tensor_pb2.DTYPE_INT32: np.dtype("<i4"),
    tensor_pb2.DTYPE_INT64: np.dtype("<i8"),
    tensor_pb2.DTYPE_UINT8: np.dtype("u1"),
    tensor_pb2.DTYPE_BOOL: np.dtype("?"),
}
_WIRE_OF: dict[tuple[str, int], tensor_pb2.Dtype] = {
    (v.kind, v.itemsize): cast("tensor_pb2.Dtype", k) for k, v in _NUMPY_OF.items()
}


def wire_dtype(dtype: Any) -> tensor_pb2.Dtype:
    """The wire ``Dtype`` of a numpy dtype (either byte order); ValueError when none fits."""
    d = np.dtype(dtype)
    try:
        return _WIRE_OF[(d.kind, d.itemsize)]
    except KeyError:
        raise ValueError(f"dtype {d} has no wire type (float32, float64, int32, int64, uint8, bool)") from None


def numpy_dtype(wire: int) -> np.dtype:
    """The little-endian numpy dtype of a wire ``Dtype``."""
    try:
        return _NUMPY_OF[wire]
    except KeyError:
        raise ValueError(f"unknown wire dtype {wire}") from None


_F32 = np.dtype("<f4")
_FLOAT32 = tensor_pb2.DTYPE_FLOAT32
_Tensor = tensor_pb2.Tensor


def is_torch(x: Any) -> bool:
    """Whether ``x`` is a torch tensor, told by its type's module: torch is never imported here."""
    return type(x) is not np.ndarray and type(x).__module__.startswith("torch") and hasattr(x, "detach")


def host(x: Any) -> Any:
    """``x``, or a torch tensor detached from autograd and brought to the CPU: numpy cannot read
    one that requires grad or lives on a GPU."""
    return x.detach().cpu() if is_torch(x) else x


def as_f32(x: Any) -> np.ndarray:
    """``x`` as a C-contiguous little-endian float32 array (no copy when it already is one)."""
    return np.ascontiguousarray(host(x), dtype=_F32)


def encode(x: Any, dtype: Any = None) -> tensor_pb2.Tensor:
    """A Tensor holding ``x`` (float32 unless ``dtype`` or ``x``'s own float64 says otherwise).

    Float inputs other than float64 become float32; float64 stays float64 only when ``dtype``
    asks for it. One copy: the array's bytes into the message.
    """
    x = host(x)
    if dtype is None:
        arr = np.ascontiguousarray(x, dtype=_F32)
        return _Tensor(shape=arr.shape, dtype=_FLOAT32, data=arr.tobytes())
    arr = np.ascontiguousarray(x, dtype=numpy_dtype(wire_dtype(dtype)))
    return _Tensor(shape=arr.shape, dtype=wire_dtype(arr.dtype), data=arr.tobytes())


def decode(t: tensor_pb2.Tensor) -> np.ndarray:
    """A read-only numpy view of a Tensor's bytes, shaped ``t.shape``.

    Raises ValueError when the byte count does not match the shape.
    """
    dtype = _F32 if t.dtype == _FLOAT32 else numpy_dtype(t.dtype)
    shape = tuple(t.shape)
    arr = np.frombuffer(t.data, dtype=dtype)
    if arr.size != math.prod(shape):
        raise ValueError(f"tensor of shape {list(shape)} carries {arr.size} values")
    return arr.reshape(shape)
