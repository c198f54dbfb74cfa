"""The GR00T inference wire: ZeroMQ REQ/REP, one msgpack map per message, in its two current dialects.

Both dialects share the transport and the codec (`MsgSerializer` since 2025-09-10): requests are
`{"endpoint": name, "data": {...}}` (plus `"api_token"` when the server wants one), numpy arrays travel as
`{"__ndarray_class__": True, "as_npy": <bytes of a .npy file>}`, and any server-side exception comes back as
`{"error": "..."}`. They differ in what `get_action` carries:

- N1.5 (`gr00t/eval/service.py`, checked at tag `n1.5-release`, 4af2b62): the server calls the policy with `data`
  itself, a flat map `{"video.<cam>": ..., "state.<group>": ..., "annotation...": [task]}`; the answer is a flat
  map `{"action.<group>": (horizon, D)}`. `ModalityConfig` objects carry `as_json` as a JSON *string*.
- N1.6 (`gr00t/policy/server_client.py`, checked at 4e62473): the server calls `policy.get_action(**data)`, so
  `data` is `{"observation": {"video": {...}, "state": {...}, "language": {...}}, "options": ...}` with batched
  arrays; the answer is the list `[action, info]` with `action = {"<group>": (B, horizon, D)}`. `ModalityConfig`
  objects carry `as_json` as a map. Sending an N1.5 map to N1.6 fails with "unexpected keyword argument
  'video.webcam'". A server started with `--use-sim-policy-wrapper` wants flat keys inside `observation` and
  answers `action.<group>` keys (`N16_SIM`); its modality config looks the same, so that one is chosen by flag.

Servers from 2025-06-11 to 2025-09-10 serialized with `torch.save` (a zip archive holding a pickle); their bytes
are recognised and refused with a readable error instead of being handed to msgpack (or, worse, to pickle). Such a
server cannot read a msgpack request at all: its except-branch answers the bare bytes `b"ERROR"` (the reply N1.6's
own client names "Make sure we are running the correct policy server"), which is recognised as that server too.
"""

from __future__ import annotations

import io
import json
import logging
import time
from dataclasses import dataclass, field
from typing import Any

import msgpack
import numpy as np
import zmq

log = logging.getLogger("phone2act_gr00t")

NDARRAY_TAG = "__ndarray_class__"
MODALITY_CONFIG_TAG = "__ModalityConfig_class__"
N15 = "n1.5"
N16 = "n1.6"
# N1.6 served with `--use-sim-policy-wrapper` (`Gr00tSimPolicyWrapper`, meant for GR00T's simulation envs): the
# same envelope, but `observation` holds flat `video.<k>`/`state.<k>` keys and the language key -> [text].
N16_SIM = "n1.6-sim"
WIRE_VERSIONS = (N15, N16, N16_SIM)
# What the README and errors tell users to run (the commits this adapter was checked against).
CHECKED_AGAINST = {N15: "tag n1.5-release, 4af2b62", N16: "release commit 4e62473"}


class Gr00tError(RuntimeError):
    """The GR00T server answered with an error map."""


class Gr00tTimeout(TimeoutError):
    """The GR00T server did not answer within the deadline."""


class Gr00tProtocolError(Gr00tError):
    """The GR00T server speaks a wire format this adapter does not (named in the message)."""


@dataclass(frozen=True)
class ModalityConfig:
    """One modality of a server's `get_modality_config` answer (the fields the adapter uses, plus the rest)."""

    delta_indices: tuple[int, ...]
    modality_keys: tuple[str, ...]
    # Which dialect encoded it: N1.5 sends `as_json` as a string, N1.6 as a map.
    wire: str = N15
    extra: dict[str, Any] = field(default_factory=dict)

    @staticmethod
    def from_wire(obj: dict[str, Any]) -> ModalityConfig:
        raw = obj.get("as_json")
        wire = N15 if isinstance(raw, str) else N16
        body = json.loads(raw) if isinstance(raw, str) else raw
        if not isinstance(body, dict) or "modality_keys" not in body:
            raise Gr00tProtocolError(f"a ModalityConfig without modality_keys: {raw!r:.200}")
        extra = {k: v for k, v in body.items() if k not in ("delta_indices", "modality_keys")}
        return ModalityConfig(tuple(body.get("delta_indices") or ()), tuple(body["modality_keys"]), wire, extra)

    def to_wire(self) -> dict[str, Any]:
        body = {"delta_indices": list(self.delta_indices), "modality_keys": list(self.modality_keys), **self.extra}
        return {MODALITY_CONFIG_TAG: True, "as_json": json.dumps(body) if self.wire == N15 else body}


def _encode_obj(obj: Any) -> Any:
    if isinstance(obj, np.ndarray):
        buf = io.BytesIO()
        np.save(buf, obj, allow_pickle=False)
        return {NDARRAY_TAG: True, "as_npy": buf.getvalue()}
    if isinstance(obj, ModalityConfig):
        return obj.to_wire()
    raise TypeError(f"cannot send {type(obj).__name__} to GR00T")


def _decode_obj(obj: Any) -> Any:
    if isinstance(obj, dict):
        if obj.get(NDARRAY_TAG):
            return np.load(io.BytesIO(obj["as_npy"]), allow_pickle=False)
        if obj.get(MODALITY_CONFIG_TAG):
            return ModalityConfig.from_wire(obj)
    return obj


def packb(obj: Any) -> bytes:
    """Serialize like GR00T's `MsgSerializer.to_bytes`."""
    return msgpack.packb(obj, default=_encode_obj)


def unpackb(data: bytes) -> Any:
    """Deserialize like GR00T's `MsgSerializer.from_bytes` (no pickle: `.npy` payloads load with allow_pickle off)."""
    return msgpack.unpackb(data, object_hook=_decode_obj)


def torch_era_format(data: bytes) -> str | None:
    """What `torch.save` wrote, if these bytes are a pre-2025-09-10 GR00T message; None otherwise.

    torch.save writes a zip archive (local file header `PK\\x03\\x04`) since torch 1.6, and a bare pickle stream
    (protocol opcode 0x80 then the protocol number) before. A msgpack reply from either dialect is a map or an
    array, whose first byte is never `P` (a positive fixint) nor 0x80 followed by a pickle protocol number.
    """
    if data[:4] == b"PK\x03\x04":
        return "torch.save zip archive"
    if len(data) >= 2 and data[0] == 0x80 and 2 <= data[1] <= 5:
        return "pickle stream"
    return None


# What a pickle-era server (2025-06-11 .. 2025-09-10) sends when it cannot load a request: a msgpack request
# never loads with `torch.load`, so this is its answer to everything the adapter asks.
PICKLE_ERA_ERROR_REPLY = b"ERROR"


def decode_reply(data: bytes, endpoint: str, where: str) -> Any:
    """A reply's object, or Gr00tProtocolError saying which wire format the server spoke instead."""
    kind = torch_era_format(data)
    if data == PICKLE_ERA_ERROR_REPLY:
        kind = 'bare b"ERROR" (its answer to a request it cannot unpickle)'
    if kind is not None:
        raise Gr00tProtocolError(
            f"GR00T server at {where} answered {endpoint!r} with a {kind}: this GR00T server uses the "
            f"pre-2025-09-10 pickle wire format (TorchSerializer). Upgrade it to GR00T N1.5 "
            f"({CHECKED_AGAINST[N15]}) or N1.6 ({CHECKED_AGAINST[N16]}); this adapter never unpickles what a "
            f"network peer sends"
        )
    try:
        return unpackb(data)
    except (ValueError, msgpack.UnpackException, TypeError, KeyError) as e:
        raise Gr00tProtocolError(
            f"GR00T server at {where} answered {endpoint!r} with {len(data)} bytes that are not a GR00T msgpack "
            f"message ({type(e).__name__}: {e}; first bytes {data[:16].hex(' ')}). This adapter speaks GR00T "
            f"N1.5 ({CHECKED_AGAINST[N15]}) and N1.6 ({CHECKED_AGAINST[N16]})"
        ) from None


def request(endpoint: str, data: dict[str, Any] | None = None, api_token: str | None = None) -> bytes:
    msg: dict[str, Any] = {"endpoint": endpoint}
    if data is not None:
        msg["data"] = data
    if api_token:
        msg["api_token"] = api_token
    return packb(msg)


def wire_of_modality_config(config: Any) -> str | None:
    """N1.5 or N1.6 from a `get_modality_config` answer (None when it tells nothing, e.g. an empty map)."""
    if not isinstance(config, dict):
        return None
    wires = {c.wire for c in config.values() if isinstance(c, ModalityConfig)}
    if len(wires) == 1:
        return wires.pop()
    # N1.5 keys carry their modality ("state.single_arm"); N1.6 keys do not ("single_arm").
    keys = [k for c in config.values() if isinstance(c, ModalityConfig) for k in c.modality_keys]
    if keys:
        return N15 if all(k.split(".", 1)[0] in ("video", "state", "action", "annotation") for k in keys) else N16
    return None


def _family(wire: str) -> str:
    # n1.6-sim has N1.6's modality config: the config tells N1.5 from N1.6, not the sim wrapper.
    return N15 if wire == N15 else N16


def check_forced_wire(forced: str, config: Any, where: str) -> None:
    """Gr00tProtocolError when a forced `--gr00t-version` contradicts the dialect of the server's modality config.

    Without this, the first symptom is the embodiment check naming prefixed keys (`state.arm` against `arm`), which
    reads as a wrong `--config` when the version is the mistake.
    """
    detected = wire_of_modality_config(config)
    if detected is None or _family(detected) == _family(forced):
        return
    advice = (f"--gr00t-version {N15}" if detected == N15
              else f"--gr00t-version {N16} (or {N16_SIM} for a server started with --use-sim-policy-wrapper)")
    raise Gr00tProtocolError(
        f"--gr00t-version {forced} does not match the GR00T server at {where}: its get_modality_config is "
        f"{'N1.5' if detected == N15 else 'N1.6'}'s ({CHECKED_AGAINST[_family(detected)]}). The version is the "
        f"mistake, not the model or --config: run with {advice}, or leave --gr00t-version at auto"
    )


class Gr00tClient:
    """A REQ client for a GR00T inference server (N1.5 `inference_service.py --server`, N1.6 `PolicyServer`).

    Unlike the upstream clients, every call has a deadline: a REQ socket stuck waiting for a late reply is closed
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

    def call(self, endpoint: str, data: dict[str, Any] | None = None, timeout_s: float | None = None) -> Any:
        """One request and its decoded reply (a map for most endpoints; N1.6 `get_action` answers a list)."""
        timeout = self.timeout_s if timeout_s is None else timeout_s
        sock = self._socket()
        t0 = time.monotonic()
        sock.send(request(endpoint, data, self.api_token))
        if not sock.poll(int(timeout * 1000), zmq.POLLIN):
            self._reset()
            raise Gr00tTimeout(
                f"GR00T server at {self.endpoint} did not answer {endpoint!r} within {timeout * 1000:.0f} ms"
            )
        reply = decode_reply(sock.recv(), endpoint, self.endpoint)
        self.last_latency_s = time.monotonic() - t0
        if isinstance(reply, dict) and "error" in reply:
            raise Gr00tError(f"GR00T server at {self.endpoint} answered {endpoint!r} with an error: {reply['error']}")
        if not isinstance(reply, (dict, list)):
            raise Gr00tProtocolError(
                f"GR00T server at {self.endpoint} answered {endpoint!r} with a {type(reply).__name__}, not a map"
            )
        return reply

    def ping(self, timeout_s: float | None = None) -> bool:
        reply = self.call("ping", timeout_s=timeout_s)
        return isinstance(reply, dict) and reply.get("status") == "ok"

    def modality_config(self, timeout_s: float | None = None) -> dict[str, ModalityConfig] | None:
        """The server's modality config, or None if it has no such endpoint (or an empty one)."""
        try:
            reply = self.call("get_modality_config", timeout_s=timeout_s)
        except Gr00tProtocolError:
            raise
        except Gr00tError as e:
            log.info("GR00T server has no usable get_modality_config (%s)", e)
            return None
        if not isinstance(reply, dict) or not reply:
            return None
        return {k: v for k, v in reply.items() if isinstance(v, ModalityConfig)} or None

    def detect_wire(self, timeout_s: float | None = None) -> tuple[str, dict[str, ModalityConfig] | None]:
        """(N15 or N16, modality config) from `ping` and `get_modality_config`; Gr00tProtocolError if neither.

        A server that answers ping but no modality config is taken for N1.5 (whose servers may be started
        without one); its first `get_action` tells if that was wrong.
        """
        self.ping(timeout_s)
        config = self.modality_config(timeout_s)
        wire = wire_of_modality_config(config)
        return (wire or N15), config

    def get_action(self, data: dict[str, Any], timeout_s: float | None = None) -> Any:
        return self.call("get_action", data, timeout_s)

    def close(self) -> None:
        self._reset()
