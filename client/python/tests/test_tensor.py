"""numpy <-> Tensor: one copy on the way out, none on the way in (views of the message)."""

from __future__ import annotations

import numpy as np
import pytest

from relreward import _tensor
from relreward.v1 import tensor_pb2


def test_float32_input_is_not_converted_and_copied_once():
    x = np.arange(24, dtype=np.float32).reshape(2, 3, 4)
    assert _tensor.as_f32(x) is x  # no conversion copy
    t = _tensor.encode(x)
    assert list(t.shape) == [2, 3, 4] and t.dtype == tensor_pb2.DTYPE_FLOAT32 and t.data == x.tobytes()


def test_other_inputs_become_float32_little_endian():
    x = np.arange(6, dtype=">f8").reshape(2, 3)
    t = _tensor.encode(x)
    np.testing.assert_array_equal(np.frombuffer(t.data, "<f4").reshape(2, 3), x)
    t = _tensor.encode([[1, 2]], dtype="bool")
    assert t.dtype == tensor_pb2.DTYPE_BOOL and t.data == b"\x01\x01"


def test_decoding_is_a_read_only_view():
    t = tensor_pb2.Tensor(shape=[2, 2], dtype=tensor_pb2.DTYPE_FLOAT32, data=np.ones(4, "<f4").tobytes())
    y = _tensor.decode(t)
    assert y.shape == (2, 2) and not y.flags.writeable and not y.flags.owndata
    with pytest.raises(ValueError, match="carries"):
        _tensor.decode(tensor_pb2.Tensor(shape=[3], dtype=tensor_pb2.DTYPE_FLOAT32, data=b"\0" * 8))
