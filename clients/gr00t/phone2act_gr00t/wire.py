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

N1.7 keeps N1.6's request and answer shapes. Its tag `n1.7-release` (23ace64, 2026-04-17) is N1.6's wire byte for
byte; GR00T's main branch from 2026-05-26 on (626af89, and the untagged "GR00T N1.7 General Release" after it)
changed the codec: arrays travel in msgpack-numpy's form `{b"nd": True, b"type": dtype.str, b"kind": b"",
b"shape": [...], b"data": <raw bytes>}` (keys are msgpack bin) and a ModalityConfig is marked `__ModalityConfig__`.
Neither codec reads the other's arrays (they arrive as plain maps, and the policy's check refuses "a numpy array.
Got <class 'dict'>"), so the codec is a property of the connection (`Gr00tClient.codec`), told by the marker of
the server's `get_modality_config` answer or chosen with `--gr00t-codec`. Replies are decoded in either codec.

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
from collections.abc import Callable
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
# N1.7 speaks N1.6's shapes (the request and answer are built as for N1.6); the names exist so that a user can say
# what they run, and so that a detected msgpack-numpy server is reported as the N1.7 release it is.
N17 = "n1.7"
N17_SIM = "n1.7-sim"
WIRE_VERSIONS = (N15, N16, N16_SIM, N17, N17_SIM)
# What the README and errors tell users to run (the commits this adapter was checked against).
CHECKED_AGAINST = {
    N15: "tag n1.5-release, 4af2b62",
    N16: "release commit 4e62473",
    N17: "tag n1.7-release 23ace64, and main 626af89 (msgpack-numpy)",
}
# The two array codecs (see the module doc): `np.save` bytes under `__ndarray_class__` (N1.5, N1.6, the N1.7 tag),
# and msgpack-numpy's map (GR00T main since 2026-05-26, the N1.7 General Release).
NPY = "npy"
MSGPACK_NUMPY = "msgpack-numpy"
CODECS = (NPY, MSGPACK_NUMPY)
MODALITY_CONFIG_TAG_MNP = "__ModalityConfig__"


def shapes_of(wire: str) -> str:
    """The request/answer dialect a version speaks: N1.7 builds its messages as N1.6 does."""
    return {N17: N16, N17_SIM: N16_SIM}.get(wire, wire)


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
    # Which codec's marker carried it: `__ModalityConfig_class__` (npy) or `__ModalityConfig__` (msgpack-numpy).
    codec: str = NPY

    @staticmethod
    def from_wire(obj: dict[str, Any], codec: str = NPY) -> ModalityConfig:
        raw = obj.get("as_json")
        wire = N15 if isinstance(raw, str) else N16
        body = json.loads(raw) if isinstance(raw, str) else raw
        if not isinstance(body, dict) or "modality_keys" not in body:
            raise Gr00tProtocolError(f"a ModalityConfig without modality_keys: {raw!r:.200}")
        extra = {k: v for k, v in body.items() if k not in ("delta_indices", "modality_keys")}
        return ModalityConfig(tuple(body.get("delta_indices") or ()), tuple(body["modality_keys"]), wire, extra,
                              codec)

    def to_wire(self) -> dict[str, Any]:
        body = {"delta_indices": list(self.delta_indices), "modality_keys": list(self.modality_keys), **self.extra}
        tag = MODALITY_CONFIG_TAG_MNP if self.codec == MSGPACK_NUMPY else MODALITY_CONFIG_TAG
        return {tag: True, "as_json": json.dumps(body) if self.wire == N15 else body}


def _refuse_dtype(dtype: np.dtype) -> None:
    # Object arrays would need pickle on the other side (msgpack-numpy pickles them), structured ones are no
    # GR00T modality: neither is sent, and neither is accepted from a peer.
    if dtype.kind in ("O", "V"):
        raise TypeError(f"GR00T arrays are numeric; refusing a {dtype} array")


def _npy(arr: np.ndarray) -> dict[str, Any]:
    buf = io.BytesIO()
    np.save(buf, arr, allow_pickle=False)
    return {NDARRAY_TAG: True, "as_npy": buf.getvalue()}


def _msgpack_numpy(arr: np.ndarray) -> dict[bytes, Any]:
    """msgpack-numpy's map for an array (field order and bin keys as msgpack-numpy 0.4.8 writes them)."""
    _refuse_dtype(arr.dtype)
    return {b"nd": True, b"type": arr.dtype.str, b"kind": b"", b"shape": list(arr.shape),
            b"data": np.ascontiguousarray(arr).tobytes()}


def _encoder(codec: str) -> Callable[[Any], Any]:
    if codec not in CODECS:
        raise ValueError(f"unknown GR00T codec {codec!r} ({', '.join(CODECS)})")

    def encode(obj: Any) -> Any:
        if isinstance(obj, np.ndarray):
            return _msgpack_numpy(obj) if codec == MSGPACK_NUMPY else _npy(obj)
        if isinstance(obj, ModalityConfig):
            return obj.to_wire()
        raise TypeError(f"cannot send {type(obj).__name__} to GR00T")

    return encode


def _field(obj: dict[Any, Any], name: str) -> Any:
    # msgpack-numpy writes bin keys (bytes after unpacking); a peer packing str keys means the same.
    return obj[name.encode()] if name.encode() in obj else obj.get(name)


def _from_msgpack_numpy(obj: dict[Any, Any]) -> Any:
    dtype = np.dtype(_field(obj, "type"))
    _refuse_dtype(dtype)
    if _field(obj, "kind") not in (b"", "", None):
        raise TypeError(f"msgpack-numpy array of kind {_field(obj, 'kind')!r} refused (it would need pickle)")
    data = _field(obj, "data")
    if _field(obj, "nd") is True:
        return np.frombuffer(data, dtype=dtype).reshape(_field(obj, "shape")).copy()
    return np.frombuffer(data, dtype=dtype)[0]  # a numpy scalar


def _is_msgpack_numpy(obj: dict[Any, Any]) -> bool:
    return isinstance(_field(obj, "nd"), bool) and _field(obj, "data") is not None and _field(obj, "type") is not None


def _decoder(accept: tuple[str, ...]) -> Callable[[Any], Any]:
    def decode(obj: Any) -> Any:
        if not isinstance(obj, dict):
            return obj
        if NPY in accept:
            if obj.get(NDARRAY_TAG):
                return np.load(io.BytesIO(obj["as_npy"]), allow_pickle=False)
            if obj.get(MODALITY_CONFIG_TAG):
                return ModalityConfig.from_wire(obj, NPY)
        if MSGPACK_NUMPY in accept:
            if _is_msgpack_numpy(obj):
                return _from_msgpack_numpy(obj)
            if obj.get(MODALITY_CONFIG_TAG_MNP):
                return ModalityConfig.from_wire(obj, MSGPACK_NUMPY)
        return obj

    return decode


def packb(obj: Any, codec: str = NPY) -> bytes:
    """Serialize like GR00T's `MsgSerializer.to_bytes` in `codec` (npy: N1.5 to the N1.7 tag; msgpack-numpy: main)."""
    return msgpack.packb(obj, default=_encoder(codec))


def unpackb(data: bytes, accept: tuple[str, ...] = CODECS) -> Any:
    """Deserialize like GR00T's `MsgSerializer.from_bytes`, arrays in any codec of `accept` (never pickle: `.npy`
    payloads load with allow_pickle off, msgpack-numpy object arrays are refused)."""
    return msgpack.unpackb(data, object_hook=_decoder(accept))


def codec_of(obj: Any) -> str | None:
    """The codec a decoded reply shows (its ModalityConfig markers), or None when it shows none."""
    if isinstance(obj, dict):
        codecs = {c.codec for c in obj.values() if isinstance(c, ModalityConfig)}
        if len(codecs) == 1:
            return codecs.pop()
    return None


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
            f"({CHECKED_AGAINST[N15]}), N1.6 ({CHECKED_AGAINST[N16]}) or N1.7 ({CHECKED_AGAINST[N17]}); this "
            f"adapter never unpickles what a network peer sends"
        )
    try:
        return unpackb(data)
    except (ValueError, msgpack.UnpackException, TypeError, KeyError) as e:
        raise Gr00tProtocolError(
            f"GR00T server at {where} answered {endpoint!r} with {len(data)} bytes that are not a GR00T msgpack "
            f"message ({type(e).__name__}: {e}; first bytes {data[:16].hex(' ')}). This adapter speaks GR00T "
            f"N1.5 ({CHECKED_AGAINST[N15]}), N1.6 ({CHECKED_AGAINST[N16]}) and N1.7 ({CHECKED_AGAINST[N17]})"
        ) from None


def request(endpoint: str, data: dict[str, Any] | None = None, api_token: str | None = None,
            codec: str = NPY) -> bytes:
    msg: dict[str, Any] = {"endpoint": endpoint}
    if data is not None:
        msg["data"] = data
    if api_token:
        msg["api_token"] = api_token
    return packb(msg, codec)


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
    # n1.6-sim (and N1.7) have N1.6's modality config: the config tells N1.5 from N1.6, not the sim wrapper.
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
    """A REQ client for a GR00T inference server (N1.5 `inference_service.py --server`, N1.6/N1.7 `PolicyServer`).

    Unlike the upstream clients, every call has a deadline: a REQ socket stuck waiting for a late reply is closed
    and replaced, so the next call starts clean (the late reply is dropped).

    `codec` is how requests carry arrays: "auto" sends `np.save` bytes (N1.5 to the N1.7 tag) until the server's
    `get_modality_config` answer shows msgpack-numpy's marker (GR00T main since 2026-05-26), then msgpack-numpy.
    """

    def __init__(self, endpoint: str = "tcp://127.0.0.1:5555", *, timeout_s: float = 1.0,
                 api_token: str | None = None, codec: str = "auto") -> None:
        if codec not in ("auto", *CODECS):
            raise ValueError(f"unknown GR00T codec {codec!r} (auto, {', '.join(CODECS)})")
        self.endpoint = endpoint
        self.timeout_s = timeout_s
        self.api_token = api_token
        self.codec_forced = codec != "auto"
        self.codec = NPY if codec == "auto" else codec
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
        sock.send(request(endpoint, data, self.api_token, self.codec))
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
        seen = codec_of(reply)
        if seen is not None and not self.codec_forced and seen != self.codec:
            log.info("GR00T server at %s speaks the %s codec", self.endpoint, seen)
            self.codec = seen
        return {k: v for k, v in reply.items() if isinstance(v, ModalityConfig)} or None

    def detect_wire(self, timeout_s: float | None = None) -> tuple[str, dict[str, ModalityConfig] | None]:
        """(N15, N16 or N17, modality config) from `ping` and `get_modality_config`; Gr00tProtocolError if neither.

        N1.6 and the N1.7 tag are the same wire and detected as N16; a msgpack-numpy server is N1.7's later
        release (N17, same shapes, `self.codec` switched). A server that answers ping but no modality config is
        taken for N1.5 (whose servers may be started without one); its first `get_action` tells if that was wrong.
        """
        self.ping(timeout_s)
        config = self.modality_config(timeout_s)
        wire = wire_of_modality_config(config)
        if wire == N16 and self.codec == MSGPACK_NUMPY:
            wire = N17
        return (wire or N15), config

    def get_action(self, data: dict[str, Any], timeout_s: float | None = None) -> Any:
        return self.call("get_action", data, timeout_s)

    def close(self) -> None:
        self._reset()
