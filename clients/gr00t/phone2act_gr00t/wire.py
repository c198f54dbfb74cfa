"""The GR00T N1.5 inference wire protocol: ZeroMQ REQ/REP, one msgpack map per message.

Requests are `{"endpoint": name, "data": {...}}` (plus `"api_token"` when the server wants one); numpy arrays
travel as `{"__ndarray_class__": True, "as_npy": <bytes of a .npy file>}` (what `gr00t/eval/service.py` does
since the msgpack switch, Aug-Sep 2025). Any server-side exception comes back as `{"error": "..."}`.
"""

from __future__ import annotations

import io
import time
from typing import Any

import msgpack
import numpy as np
import zmq

NDARRAY_TAG = "__ndarray_class__"


class Gr00tError(RuntimeError):
    """The GR00T server answered with an error map."""


class Gr00tTimeout(TimeoutError):
    """The GR00T server did not answer within the deadline."""


def _encode_obj(obj: Any) -> Any:
    if isinstance(obj, np.ndarray):
        buf = io.BytesIO()
        np.save(buf, obj, allow_pickle=False)
        return {NDARRAY_TAG: True, "as_npy": buf.getvalue()}
    raise TypeError(f"cannot send {type(obj).__name__} to GR00T")


def _decode_obj(obj: Any) -> Any:
    if isinstance(obj, dict) and obj.get(NDARRAY_TAG):
        return np.load(io.BytesIO(obj["as_npy"]), allow_pickle=False)
    return obj


def packb(obj: Any) -> bytes:
    """Serialize like GR00T's `MsgSerializer.to_bytes`."""
    return msgpack.packb(obj, default=_encode_obj)


def unpackb(data: bytes) -> Any:
    """Deserialize like GR00T's `MsgSerializer.from_bytes`."""
    return msgpack.unpackb(data, object_hook=_decode_obj)


def request(endpoint: str, data: dict[str, Any] | None = None, api_token: str | None = None) -> bytes:
    msg: dict[str, Any] = {"endpoint": endpoint}
    if data is not None:
        msg["data"] = data
    if api_token:
        msg["api_token"] = api_token
    return packb(msg)


class Gr00tClient:
    """A REQ client for a GR00T N1.5 inference server (`scripts/inference_service.py --server`).

    Unlike the upstream client, every call has a deadline: a REQ socket stuck waiting for a late reply is closed
    and replaced, so the next call starts clean (the late reply is dropped).
    """

    def __init__(self, endpoint: str = "tcp://127.0.0.1:5555", *, timeout_s: float = 1.0,
                 api_token: str | None = None) -> None:
        self.endpoint = endpoint
        self.timeout_s = timeout_s
        self.api_token = api_token
        self._ctx = zmq.Context.instance()
        self._sock: zmq.Socket | None = None
        self.last_latency_s = 0.0

    def _socket(self) -> zmq.Socket:
        if self._sock is None:
            s = self._ctx.socket(zmq.REQ)
            s.setsockopt(zmq.LINGER, 0)
            s.connect(self.endpoint)
            self._sock = s
        return self._sock

    def _reset(self) -> None:
        if self._sock is not None:
            self._sock.close(linger=0)
            self._sock = None

    def call(self, endpoint: str, data: dict[str, Any] | None = None,
             timeout_s: float | None = None) -> dict[str, Any]:
        timeout = self.timeout_s if timeout_s is None else timeout_s
        sock = self._socket()
        t0 = time.monotonic()
        sock.send(request(endpoint, data, self.api_token))
        if not sock.poll(int(timeout * 1000), zmq.POLLIN):
            self._reset()
            raise Gr00tTimeout(
                f"GR00T server at {self.endpoint} did not answer {endpoint!r} within {timeout * 1000:.0f} ms"
            )
        reply = unpackb(sock.recv())
        self.last_latency_s = time.monotonic() - t0
        if not isinstance(reply, dict):
            raise Gr00tError(f"GR00T server at {self.endpoint} sent a {type(reply).__name__}, not a map")
        if "error" in reply:
            raise Gr00tError(f"GR00T server at {self.endpoint} answered {endpoint!r} with an error: {reply['error']}")
        return reply

    def ping(self, timeout_s: float | None = None) -> bool:
        return self.call("ping", timeout_s=timeout_s).get("status") == "ok"

    def get_action(self, observation: dict[str, Any], timeout_s: float | None = None) -> dict[str, np.ndarray]:
        return self.call("get_action", observation, timeout_s)

    def close(self) -> None:
        self._reset()
