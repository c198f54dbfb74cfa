"""Stand-in GR00T inference servers, written from GR00T's wire facts (not from its code), for the adapter tests.

- `ReplayStandIn`: GR00T N1.6/N1.7's `PolicyServer` serving `ReplayPolicy` (see its doc), in either array codec.
- `StandIn`: an N1.5 server that answers with the golden messages' exact bytes (written by GR00T N1.5's own
  `MsgSerializer`, see tests/fixtures/gr00t_wire/NOTE.md).
- `PolicyStandIn(wire=...)`: a server that runs a test-supplied policy function, speaking
  - "n1.5" (tag n1.5-release, 4af2b62): the endpoint handler is called with the request's `data` map itself;
    `get_action` takes flat `video.<k>` (T, H, W, 3) uint8, `state.<k>` (T, D), the language key -> [text], and
    answers `{"action.<k>": float32 (horizon, D)}`; `ModalityConfig.as_json` is a JSON string;
  - "n1.6" (4e62473): the handler is called as `handler(**data)`, so `get_action(observation, options)` takes
    `{"video": {k: (B, T, H, W, 3) uint8}, "state": {k: (B, T, D) float32}, "language": {key: [[text]]}}`,
    checked as strictly as N1.6's Gr00tPolicy does, and answers `[{k: float32 (B, horizon, D)}, {}]`;
    `ModalityConfig.as_json` is a map; there is a `reset` endpoint;
  - "n1.6-sim": N1.6 started with `--use-sim-policy-wrapper`: the same, but `observation` holds flat
    `video.<k>`/`state.<k>` keys and the language key -> [text], and the answer's keys are `action.<k>`;
  - "pickle" (2025-06-11 .. 2025-09-10): every message is `torch.save` output; a msgpack request cannot be loaded,
    so every answer is `torch.save({"error": ...})`, a zip archive holding `archive/data.pkl`. Built here with
    zipfile + pickle in torch's archive layout (no torch needed); `stream=True` sends a bare pickle instead (the
    pre-1.6 torch.save format);
  - "pickle-june" (the June-2025 server, the one N1.6's own client warns about): the request cannot be loaded and
    the server's except-branch answers the bare bytes `b"ERROR"` to everything.
  Any handler exception becomes `{"error": str(e)}`, the token check and the unknown-endpoint error are as upstream.
"""

from __future__ import annotations

import io
import pickle
import threading
import time
import zipfile
from collections.abc import Callable
from typing import Any

import msgpack
import numpy as np
import zmq
from conftest import golden
from phone2act_gr00t.wire import N16, NPY, ModalityConfig, packb, unpackb


class _RepServer:
    def __init__(self) -> None:
        self._ctx = zmq.Context()
        self._sock = self._ctx.socket(zmq.REP)
        self._sock.setsockopt(zmq.LINGER, 0)
        port = self._sock.bind_to_random_port("tcp://127.0.0.1")
        self.endpoint = f"tcp://127.0.0.1:{port}"
        self.requests: list[bytes] = []
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._serve, daemon=True)
        self._thread.start()

    def answer(self, raw: bytes) -> bytes:
        raise NotImplementedError

    def _serve(self) -> None:
        while not self._stop.is_set():
            if not self._sock.poll(50, zmq.POLLIN):
                continue
            raw = self._sock.recv()
            self.requests.append(raw)
            self._sock.send(self.answer(raw))

    def close(self) -> None:
        self._stop.set()
        self._thread.join(timeout=2)
        self._sock.close(linger=0)
        self._ctx.term()

    def __enter__(self):  # type: ignore[no-untyped-def]
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


class StandIn(_RepServer):
    """Answers `ping` with response_ping, `get_action` with response_get_action (or `action_bytes`), anything
    else with response_error; can sleep `delay_s` before answering to play a late policy."""

    def __init__(self, delay_s: float = 0.0, action_bytes: bytes | None = None) -> None:
        self.delay_s = delay_s
        self.replies = {
            "ping": golden("response_ping.msgpack"),
            "get_action": action_bytes if action_bytes is not None else golden("response_get_action.msgpack"),
        }
        self.error_reply = golden("response_error.msgpack")
        super().__init__()

    def answer(self, raw: bytes) -> bytes:
        endpoint = msgpack.unpackb(raw).get("endpoint", "get_action")
        if self.delay_s and endpoint == "get_action":
            time.sleep(self.delay_s)
        return self.replies.get(endpoint, self.error_reply)


# A policy: (state by bare group key -> (D,) float64 of the newest step, task text) -> action by bare key (H, D).
Policy = Callable[[dict[str, np.ndarray], str], dict[str, np.ndarray]]


def torch_save_like(obj: Any, stream: bool = False) -> bytes:
    """Bytes shaped like `torch.save(obj)`: a zip archive `archive/{data.pkl,byteorder,version}`, or a bare pickle."""
    if stream:
        return pickle.dumps(obj, protocol=2)
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w", zipfile.ZIP_STORED) as z:
        z.writestr("archive/data.pkl", pickle.dumps(obj, protocol=2))
        z.writestr("archive/byteorder", "little")
        z.writestr("archive/version", "3\n")
    return buf.getvalue()


class PolicyStandIn(_RepServer):
    def __init__(
        self,
        wire: str,
        *,
        video: tuple[str, ...] = (),
        state: tuple[str, ...] = ("arm", "gripper"),
        action: tuple[str, ...] = ("arm", "gripper"),
        language_key: str = "annotation.human.task_description",
        horizon: int = 16,
        policy: Policy | None = None,
        api_token: str | None = None,
        modality_endpoint: bool = True,
        stream: bool = False,
    ) -> None:
        self.wire = wire
        self.horizon = horizon
        self.policy = policy
        self.api_token = api_token
        self.stream = stream
        self.keys = {"video": video, "state": state, "action": action, "language": (language_key,)}
        self.decoded: list[dict[str, Any]] = []
        self.observations: list[tuple[dict[str, np.ndarray], str]] = []
        self.endpoints: dict[str, tuple[Callable[..., Any], bool]] = {
            "ping": (lambda: {"status": "ok", "message": "Server is running"}, False),
            "kill": (lambda: {}, False),
        }
        if modality_endpoint:
            self.endpoints["get_modality_config"] = (self._modality_config, False)
        if wire in ("n1.6", "n1.6-sim"):
            self.endpoints["get_action"] = (self._get_action_n16 if wire == "n1.6" else self._get_action_sim, True)
            self.endpoints["reset"] = (lambda options=None: {}, True)
        else:
            self.endpoints["get_action"] = (self._get_action_n15, True)
        super().__init__()

    # --- transport and dispatch, as both dialects' servers do it ---------------------------------------------

    def answer(self, raw: bytes) -> bytes:
        if self.wire == "pickle-june":
            return b"ERROR"
        if self.wire == "pickle":
            # torch.load cannot read a msgpack request; the server's except-branch answers with its own format.
            return torch_save_like({"error": "invalid load key, '\\x82'."}, self.stream)
        try:
            req = unpackb(raw)
            self.decoded.append(req)
            if self.api_token is not None and req.get("api_token") != self.api_token:
                return packb({"error": "Unauthorized: Invalid API token"})
            endpoint = req.get("endpoint", "get_action")
            if endpoint not in self.endpoints:
                raise ValueError(f"Unknown endpoint: {endpoint}")
            handler, takes_input = self.endpoints[endpoint]
            if not takes_input:
                return packb(handler())
            data = req.get("data", {})
            # N1.5 hands the data map over as one argument; N1.6 spreads it into keyword arguments.
            return packb(handler(**data) if self.wire.startswith("n1.6") else handler(data))
        except Exception as e:  # noqa: BLE001 - as upstream: every failure becomes an error map
            return packb({"error": str(e)})

    def _modality_config(self) -> dict[str, ModalityConfig]:
        prefix = {"video": "video.", "state": "state.", "action": "action."} if self.wire == "n1.5" else {}
        delta = {"action": tuple(range(self.horizon))}
        wire = self.wire[:4]  # "n1.6-sim" encodes its config as n1.6 does
        configs = {}
        for m, keys in self.keys.items():
            extra: dict[str, Any] = {}
            if wire == "n1.6":
                # N1.6 sends every ModalityConfig field (dataclass -> dict, enums by name).
                extra = {"sin_cos_embedding_keys": None, "mean_std_embedding_keys": None, "action_configs": None}
                if m == "action":
                    extra["action_configs"] = [
                        {"rep": "ABSOLUTE", "type": "NON_EEF", "format": "DEFAULT", "state_key": None} for _ in keys
                    ]
            configs[m] = ModalityConfig(delta.get(m, (0,)), tuple(prefix.get(m, "") + k for k in keys), wire, extra)
        return configs

    def _run_policy(self, state: dict[str, np.ndarray], task: str) -> dict[str, np.ndarray]:
        self.observations.append((state, task))
        if self.policy is None:  # a model that says "stay": zero deltas (1 column for grippers, 5 for so100's arm)
            width = {k: 1 if k.endswith("gripper") else 5 if k == "single_arm" else 6 for k in self.keys["action"]}
            return {k: np.zeros((self.horizon, w), np.float32) for k, w in width.items()}
        out = self.policy(state, task)
        return {k: np.asarray(out[k], np.float32).reshape(self.horizon, -1) for k in self.keys["action"]}

    # --- N1.5: flat keys, unbatched ---------------------------------------------------------------------------

    def _get_action_n15(self, obs: dict[str, Any]) -> dict[str, np.ndarray]:
        for k in self.keys["video"]:
            v = obs[f"video.{k}"]
            if v.dtype != np.uint8 or v.ndim != 4 or v.shape[-1] != 3:
                raise ValueError(f"video.{k} must be (T, H, W, 3) uint8, got {v.shape} {v.dtype}")
        state = {}
        for k in self.keys["state"]:
            s = obs[f"state.{k}"]
            if s.ndim != 2:
                raise ValueError(f"state.{k} must be (T, D), got {s.shape}")
            state[k] = s[-1].astype(np.float64)
        (lang,) = self.keys["language"]
        text = obs[lang]
        if not isinstance(text, list) or not all(isinstance(t, str) for t in text):
            raise ValueError(f"{lang} must be a list of str")
        return {f"action.{k}": v for k, v in self._run_policy(state, text[0]).items()}

    # --- N1.6: nested, batched, float32 state ------------------------------------------------------------------

    def _get_action_n16(self, observation: dict[str, Any], options: dict[str, Any] | None = None) -> list[Any]:
        for modality in ("video", "state", "language"):
            assert isinstance(observation.get(modality), dict), f"Observation must contain a '{modality}' key"
        for k in self.keys["video"]:
            v = observation["video"][k]
            assert v.dtype == np.uint8 and v.ndim == 5 and v.shape[1] == 1 and v.shape[-1] == 3, (
                f"Video key '{k}' must be a numpy array of shape (B, T, H, W, C) uint8, got {v.shape} {v.dtype}")
        state = {}
        for k in self.keys["state"]:
            s = observation["state"][k]
            assert s.dtype == np.float32, f"State key '{k}' must be a numpy array of type np.float32. Got {s.dtype}"
            assert s.ndim == 3 and s.shape[1] == 1, f"State key '{k}' must be (B, T, D), got {s.shape}"
            state[k] = s[0, -1].astype(np.float64)
        (lang,) = self.keys["language"]
        text = observation["language"][lang]
        assert isinstance(text, list) and len(text) == 1 and isinstance(text[0], list) and len(text[0]) == 1, (
            f"Language key '{lang}' must be [[str]], got {text!r}")
        actions = self._run_policy(state, text[0][0])
        return [{k: v[None] for k, v in actions.items()}, {}]

    # --- N1.6 behind Gr00tSimPolicyWrapper: flat keys inside `observation` --------------------------------------

    def _get_action_sim(self, observation: dict[str, Any], options: dict[str, Any] | None = None) -> list[Any]:
        for k in self.keys["video"]:
            assert f"video.{k}" in observation, f"Video key 'video.{k}' must be in observation"
        state = {}
        for k in self.keys["state"]:
            assert f"state.{k}" in observation, f"State key 'state.{k}' must be in observation"
            s = observation[f"state.{k}"]
            assert s.dtype == np.float32 and s.ndim == 3, f"State key '{k}' must be (B, T, D) float32"
            state[k] = s[0, -1].astype(np.float64)
        (lang,) = self.keys["language"]
        assert lang in observation, f"Language key '{lang}' must be in observation"
        text = observation[lang]
        assert isinstance(text, list) and isinstance(text[0], str), "Language batch item must be a string"
        actions = self._run_policy(state, text[0])
        return [{f"action.{k}": v[None] for k, v in actions.items()}, {}]


class ReplayStandIn(_RepServer):
    """GR00T's `PolicyServer` serving `ReplayPolicy` (N1.6/N1.7, `run_gr00t_server.py --dataset-path`), written from
    the behaviour read in its source (tag n1.7-release 23ace64, and main 626af89 for the msgpack-numpy codec):

    - `get_action(observation, options)` validates the observation as `ReplayPolicy.check_observation` does (three
      dict modalities; per key the same batch size, a numpy array, uint8 (B, T, H, W, 3) video and float32
      (B, T, D) state with T the modality's number of delta indices, language a list of one-string lists), then
      answers `[action, info]`: each action key `(B, horizon, D)` float32 from the recorded episode starting at
      `current_step` (padded with the last action past the end, `horizon` from the action delta indices), the batch
      size taken from the first video key, and info `{current_step, episode_length, episode_index}`; then
      `current_step` advances by `execution_horizon`.
    - `reset(options)` goes to `options["episode_index"]` (if given) and `options["step_index"]` (else 0), and
      answers `{episode_index, episode_length, current_step}`.
    - `get_modality_config` answers the modality configs; `ping`, `kill`, the token check, unknown endpoints and
      `{"error": str(e)}` for any exception are as in `PolicyServer`.
    - `codec`: the server reads and writes arrays in one codec only (npy: the tag; msgpack-numpy: main); arrays in
      the other arrive as plain maps, which the observation check refuses as upstream does ("Got <class 'dict'>").
    """

    def __init__(
        self,
        episodes: list[dict[str, np.ndarray]],
        *,
        codec: str = NPY,
        video: tuple[str, ...] = ("webcam",),
        state: tuple[str, ...] = ("single_arm", "gripper"),
        language_key: str = "annotation.human.task_description",
        action_horizon: int = 16,
        execution_horizon: int = 16,
        api_token: str | None = None,
    ) -> None:
        assert execution_horizon <= action_horizon
        self.codec = codec
        self.episodes = episodes
        self.episode_index = 0
        self.current_step = 0
        self.action_horizon = action_horizon
        self.execution_horizon = execution_horizon
        self.api_token = api_token
        action_keys = tuple(episodes[0])
        # N1.6/N1.7 send every ModalityConfig field (dataclass -> dict).
        unset = {"sin_cos_embedding_keys": None, "mean_std_embedding_keys": None, "action_configs": None}
        wire_config = {"wire": N16, "codec": codec, "extra": unset}
        self.config = {
            "video": ModalityConfig((0,), video, **wire_config),
            "state": ModalityConfig((0,), state, **wire_config),
            "action": ModalityConfig(tuple(range(action_horizon)), action_keys, **wire_config),
            "language": ModalityConfig((0,), (language_key,), **wire_config),
        }
        self.observations: list[dict[str, Any]] = []
        self.infos: list[dict[str, int]] = []
        super().__init__()

    @property
    def episode_length(self) -> int:
        return len(next(iter(self.episodes[self.episode_index].values())))

    def answer(self, raw: bytes) -> bytes:
        try:
            req = unpackb(raw, accept=(self.codec,))
            if self.api_token is not None and req.get("api_token") != self.api_token:
                return packb({"error": "Unauthorized: Invalid API token"}, self.codec)
            endpoint = req.get("endpoint", "get_action")
            data = req.get("data", {})
            if endpoint == "ping":
                result: Any = {"status": "ok", "message": "Server is running"}
            elif endpoint == "kill":
                result = None
            elif endpoint == "get_modality_config":
                result = self.config
            elif endpoint == "get_action":
                result = self._get_action(**data)
            elif endpoint == "reset":
                result = self._reset(**data)
            else:
                raise ValueError(f"Unknown endpoint: {endpoint}")
            return packb(result, self.codec)
        except Exception as e:  # noqa: BLE001 - as upstream: every failure becomes an error map
            return packb({"error": str(e)}, self.codec)

    def _check_observation(self, observation: dict[str, Any]) -> None:
        for modality in ("video", "state", "language"):
            assert modality in observation, f"Observation must contain a '{modality}' key"
            assert isinstance(observation[modality], dict), (
                f"Observation '{modality}' must be a dictionary. Got {type(observation[modality])}")
        batch = -1
        for modality, dtype, ndim in (("video", np.uint8, 5), ("state", np.float32, 3)):
            horizon = len(self.config[modality].delta_indices)
            for key in self.config[modality].modality_keys:
                assert key in observation[modality], f"{modality.title()} key '{key}' must be in observation"
                value = observation[modality][key]
                if batch == -1:
                    batch = len(value)
                assert len(value) == batch, f"{modality.title()} key '{key}' must have batch size {batch}"
                assert isinstance(value, np.ndarray), (
                    f"{modality.title()} key '{key}' must be a numpy array. Got {type(value)}")
                assert value.dtype == dtype, f"{modality.title()} key '{key}' must be of type {dtype}"
                assert value.ndim == ndim, f"{modality.title()} key '{key}' must have {ndim} dimensions"
                assert value.shape[1] == horizon, f"{modality.title()} key '{key}'s horizon must be {horizon}"
                if modality == "video":
                    assert value.shape[-1] == 3, f"Video key '{key}'s channel 'C' must be 3"
        for key in self.config["language"].modality_keys:
            text = observation["language"].get(key)
            assert isinstance(text, list), f"Language key '{key}' must be a list. Got {type(text)}"
            assert len(text) == batch, f"Language key '{key}' must have batch size {batch}"
            for item in text:
                assert isinstance(item, list) and len(item) == 1 and isinstance(item[0], str), (
                    f"Language batch item must be a list of one string. Got {item!r}")

    def _get_action(self, observation: dict[str, Any] | None = None,
                    options: dict[str, Any] | None = None) -> tuple[dict[str, np.ndarray], dict[str, int]]:
        self._check_observation(observation or {})
        self.observations.append(observation or {})
        batch = observation["video"][self.config["video"].modality_keys[0]].shape[0]
        chunk = {}
        for key, actions in self.episodes[self.episode_index].items():
            rows = actions[self.current_step:self.current_step + self.action_horizon]
            if len(rows) < self.action_horizon:  # past the end: the last action, repeated
                pad = np.repeat(actions[-1:], self.action_horizon - len(rows), axis=0)
                rows = np.concatenate([rows, pad]) if len(rows) else pad
            chunk[key] = np.tile(rows.astype(np.float32)[None], (batch, 1, 1))
        info = {"current_step": self.current_step, "episode_length": self.episode_length,
                "episode_index": self.episode_index}
        self.infos.append(info)
        self.current_step += self.execution_horizon
        return chunk, info

    def _reset(self, options: dict[str, Any] | None = None) -> dict[str, int]:
        options = options or {}
        self.episode_index = options.get("episode_index", self.episode_index)
        self.current_step = options.get("step_index", 0)
        return {"episode_index": self.episode_index, "episode_length": self.episode_length,
                "current_step": self.current_step}
