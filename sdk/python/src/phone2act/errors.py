"""Exceptions of the phone2act client: gRPC statuses turned into Python exceptions that say what went wrong."""

from __future__ import annotations

import grpc


class Phone2ActError(Exception):
    """A call to the phone2act server failed. `code` is the gRPC status code, `details` the server's text."""

    def __init__(self, message: str, code: grpc.StatusCode | None = None, details: str = "") -> None:
        super().__init__(message)
        self.code = code
        self.details = details


class ServerUnavailable(Phone2ActError, ConnectionError):
    """The server cannot be reached (not running, wrong address, connection lost)."""


class InvalidArgument(Phone2ActError, ValueError):
    """The server refused a request as malformed (e.g. a chunk of the wrong width)."""


class NotFound(Phone2ActError, LookupError):
    """Unknown arm, camera or session."""


class FailedPrecondition(Phone2ActError):
    """The request is valid but not now (e.g. an episode is already recording, a phone owns the arm)."""


class Unimplemented(Phone2ActError, NotImplementedError):
    """The arm or server cannot do this (e.g. a scene reset on a hardware arm)."""


class Unauthenticated(Phone2ActError, PermissionError):
    """Missing or wrong bearer token."""


class SessionClosed(Phone2ActError):
    """A streaming session ended (the server closed it, or the client did)."""


class DeadlineExceeded(Phone2ActError, TimeoutError):
    """A call or a wait took longer than allowed."""


_BY_CODE: dict[grpc.StatusCode, type[Phone2ActError]] = {
    grpc.StatusCode.UNAVAILABLE: ServerUnavailable,
    grpc.StatusCode.INVALID_ARGUMENT: InvalidArgument,
    grpc.StatusCode.NOT_FOUND: NotFound,
    grpc.StatusCode.FAILED_PRECONDITION: FailedPrecondition,
    grpc.StatusCode.ALREADY_EXISTS: FailedPrecondition,
    grpc.StatusCode.UNIMPLEMENTED: Unimplemented,
    grpc.StatusCode.UNAUTHENTICATED: Unauthenticated,
    grpc.StatusCode.PERMISSION_DENIED: Unauthenticated,
    grpc.StatusCode.DEADLINE_EXCEEDED: DeadlineExceeded,
}


def from_rpc_error(err: grpc.RpcError, what: str, target: str) -> Phone2ActError:
    """Translate a grpc error into the matching Phone2ActError, naming the call and the server."""
    code = err.code() if hasattr(err, "code") else None
    details = (err.details() if hasattr(err, "details") else "") or ""
    cls = _BY_CODE.get(code, Phone2ActError) if code is not None else Phone2ActError
    name = code.name if code is not None else "UNKNOWN"
    if cls is ServerUnavailable:
        message = f"{what}: phone2act server at {target} is unavailable ({details or name}); is `phone2act serve` running?"
    else:
        message = f"{what} failed: {name}: {details}"
    return cls(message, code, details)
