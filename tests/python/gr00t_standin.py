"""A stand-in GR00T N1.5 inference server: a ZeroMQ REP socket answering with the golden messages' exact bytes."""

from __future__ import annotations

import threading
import time

import msgpack
import zmq
from conftest import golden


class StandIn:
    """Answers `ping` with response_ping, `get_action` with response_get_action (or `action_bytes`), anything
    else with response_error; can sleep `delay_s` before answering to play a late policy."""

    def __init__(self, delay_s: float = 0.0, action_bytes: bytes | None = None) -> None:
        self.delay_s = delay_s
        self.replies = {
            "ping": golden("response_ping.msgpack"),
            "get_action": action_bytes if action_bytes is not None else golden("response_get_action.msgpack"),
        }
        self.error_reply = golden("response_error.msgpack")
        self.requests: list[bytes] = []
        self._ctx = zmq.Context()
        self._sock = self._ctx.socket(zmq.REP)
        self._sock.setsockopt(zmq.LINGER, 0)
        port = self._sock.bind_to_random_port("tcp://127.0.0.1")
        self.endpoint = f"tcp://127.0.0.1:{port}"
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._serve, daemon=True)
        self._thread.start()

    def _serve(self) -> None:
        while not self._stop.is_set():
            if not self._sock.poll(50, zmq.POLLIN):
                continue
            raw = self._sock.recv()
            self.requests.append(raw)
            endpoint = msgpack.unpackb(raw).get("endpoint", "get_action")
            if self.delay_s and endpoint == "get_action":
                time.sleep(self.delay_s)
            self._sock.send(self.replies.get(endpoint, self.error_reply))

    def close(self) -> None:
        self._stop.set()
        self._thread.join(timeout=2)
        self._sock.close(linger=0)
        self._ctx.term()

    def __enter__(self) -> "StandIn":
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
