"""Exceptions: one class per gRPC status code, each carrying the code and the server's message.

Every failed call raises a subclass of :class:`RelrewardError`::

    try:
        client.get_model("nope")
    except relreward.NotFound as e:
        print(e.code, e.message)   # grpc.StatusCode.NOT_FOUND, 'model "nope" not found'
"""

from __future__ import annotations

import grpc


class RelrewardError(Exception):
    """A failed relreward call: ``code`` (a ``grpc.StatusCode``) and the server's ``message``."""

    code: grpc.StatusCode = grpc.StatusCode.UNKNOWN

    def __init__(self, message: str, code: grpc.StatusCode | None = None) -> None:
        super().__init__(message)
        self.message = message
        if code is not None:
            self.code = code

    def __str__(self) -> str:
        return f"{self.code.name}: {self.message}"


class Cancelled(RelrewardError):
    code = grpc.StatusCode.CANCELLED


class Unknown(RelrewardError):
    code = grpc.StatusCode.UNKNOWN


class InvalidArgument(RelrewardError):
    code = grpc.StatusCode.INVALID_ARGUMENT


class InvalidInput(InvalidArgument, ValueError):
    """An argument refused by the client before anything was sent (a negative or fractional
    ``t``, a count past its field's range, ...); the message names the argument. Code
    INVALID_ARGUMENT, as the server answers for a value it refuses, and a ``ValueError``, as
    every local input problem is: ``except relreward.InvalidArgument`` and ``except
    ValueError`` both catch it."""


class DeadlineExceeded(RelrewardError):
    code = grpc.StatusCode.DEADLINE_EXCEEDED


class NotFound(RelrewardError):
    code = grpc.StatusCode.NOT_FOUND


class AlreadyExists(RelrewardError):
    code = grpc.StatusCode.ALREADY_EXISTS


class PermissionDenied(RelrewardError):
    code = grpc.StatusCode.PERMISSION_DENIED


class ResourceExhausted(RelrewardError):
    code = grpc.StatusCode.RESOURCE_EXHAUSTED


class FailedPrecondition(RelrewardError):
    code = grpc.StatusCode.FAILED_PRECONDITION


class Aborted(RelrewardError):
    code = grpc.StatusCode.ABORTED


class OutOfRange(RelrewardError):
    code = grpc.StatusCode.OUT_OF_RANGE


class Unimplemented(RelrewardError):
    code = grpc.StatusCode.UNIMPLEMENTED


class Internal(RelrewardError):
    code = grpc.StatusCode.INTERNAL


class Unavailable(RelrewardError):
    code = grpc.StatusCode.UNAVAILABLE


class DataLoss(RelrewardError):
    code = grpc.StatusCode.DATA_LOSS


class Unauthenticated(RelrewardError):
    code = grpc.StatusCode.UNAUTHENTICATED


_BY_CODE: dict[grpc.StatusCode, type[RelrewardError]] = {
    cls.code: cls
    for cls in (Cancelled, Unknown, InvalidArgument, DeadlineExceeded, NotFound, AlreadyExists, PermissionDenied,
                ResourceExhausted, FailedPrecondition, Aborted, OutOfRange, Unimplemented, Internal, Unavailable,
                DataLoss, Unauthenticated)
}
_BY_NUMBER: dict[int, grpc.StatusCode] = {c.value[0]: c for c in grpc.StatusCode}


def error_for(code: grpc.StatusCode | int, message: str) -> RelrewardError:
    """The exception for a status ``code`` (a ``grpc.StatusCode`` or its number) and message."""
    if isinstance(code, int):
        code = _BY_NUMBER.get(code, grpc.StatusCode.UNKNOWN)
    cls = _BY_CODE.get(code, RelrewardError)
    return cls(message, code)


def from_rpc_error(e: grpc.RpcError) -> RelrewardError:
    """The exception for a failed grpcio call (``grpc.RpcError`` or ``grpc.aio.AioRpcError``)."""
    code = e.code() if hasattr(e, "code") else grpc.StatusCode.UNKNOWN  # type: ignore[attr-defined]
    details = e.details() if hasattr(e, "details") else str(e)  # type: ignore[attr-defined]
    return error_for(code or grpc.StatusCode.UNKNOWN, details or "")


def is_retryable(e: grpc.RpcError | RelrewardError) -> bool:
    """Whether a failure lies in the connection rather than the request (as the Rust client's
    ``is_retryable``): UNAVAILABLE, or UNKNOWN/INTERNAL/CANCELLED naming a transport failure.
    Errors the server chose (NOT_FOUND, INVALID_ARGUMENT, ...) are final."""
    if isinstance(e, RelrewardError):
        code, message = e.code, e.message
    else:
        code = e.code()  # type: ignore[attr-defined]
        message = e.details() or ""  # type: ignore[attr-defined]
    if code == grpc.StatusCode.UNAVAILABLE:
        return True
    if code in (grpc.StatusCode.UNKNOWN, grpc.StatusCode.INTERNAL, grpc.StatusCode.CANCELLED):
        m = message.lower()
        return any(s in m for s in ("transport", "connection", "socket closed", "stream removed", "goaway"))
    return False
