"""A phone2act arm, with its cameras, as a LeRobot `Robot`.

Observations come from `Policy.GetObservation` (the state vector and RGB frames the server reports); actions
go into a `Policy.Session` that owns the arm, as one-step chunks (or whole chunks with `send_action_chunk`),
so they pass the same chunk executor and safety gate as every other policy. Feature names and shapes are
what the server reports for the arm, so lerobot-record / lerobot-replay datasets line up with phone2act's own.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Mapping, Sequence
from functools import cached_property
from typing import Any

import numpy as np
from lerobot.robots.robot import Robot
from lerobot.utils.errors import DeviceAlreadyConnectedError, DeviceNotConnectedError
from phone2act import IMAGE_NONE, IMAGE_RGB8, Client, FailedPrecondition, PolicySession
from phone2act.v1 import policy_pb2

from lerobot_robot_phone2act.arm_watch import ABSOLUTE_EE_NAMES, ArmWatch, GateRefusal
from lerobot_robot_phone2act.config_phone2act_robot import Phone2ActRobotConfig

log = logging.getLogger(__name__)

RELATIVE_FIRST_NAME = "delta_x"


class _Layout:
    """What the server reports for the arm: state names, the absolute action layout and its mode, cameras."""

    def __init__(self, client: Client, cfg: Phone2ActRobotConfig) -> None:
        client.arm(cfg.arm)  # NotFound, with the arm's name, before anything else
        obs = client.observe(arms=[cfg.arm], image_encoding=IMAGE_NONE)
        arm = next(a for a in obs.arms if a.arm == cfg.arm)
        self.state_names: tuple[str, ...] = tuple(arm.state_names)
        reported = tuple(arm.action_names)
        if reported == ABSOLUTE_EE_NAMES or (reported and reported[0] == RELATIVE_FIRST_NAME):
            # LeRobot policies output what the dataset recorded: absolute targets, whatever the arm's mode.
            self.action_names, self.mode = ABSOLUTE_EE_NAMES, policy_pb2.ACTION_MODE_ABSOLUTE_EE
        else:
            self.action_names, self.mode = reported, policy_pb2.ACTION_MODE_JOINT
        cams = {c.camera: (int(c.height), int(c.width)) for c in client.list_cameras()}
        unknown = [c for c in cfg.camera_names if c not in cams]
        if unknown:
            raise ValueError(f"phone2act server {cfg.server} has no camera {unknown}; it has {sorted(cams)}")
        names = list(cfg.camera_names) or sorted(cams)
        self.cameras: dict[str, tuple[int, int]] = {c: cams[c] for c in names}
        clash = set(self.cameras) & set(self.state_names)
        if clash:
            raise ValueError(f"camera names {sorted(clash)} clash with state names of arm {cfg.arm!r}")


class Phone2ActRobot(Robot):
    """`--robot.type=phone2act --robot.server=HOST:PORT --robot.arm=main`."""

    config_class = Phone2ActRobotConfig
    name = "phone2act"

    def __init__(self, config: Phone2ActRobotConfig) -> None:
        super().__init__(config)
        self.config = config
        self._client: Client | None = None
        self._session: PolicySession | None = None
        self._watch: ArmWatch | None = None

    # --- what the server reports ----------------------------------------------------------------------

    def _connect_client(self) -> Client:
        return Client(self.config.server, token=self.config.token, connect_timeout_s=self.config.connect_timeout_s)

    @cached_property
    def layout(self) -> _Layout:
        # lerobot reads the features before `connect` (to create the dataset), so they are asked for on demand.
        if self._client is not None:
            return _Layout(self._client, self.config)
        with self._connect_client() as client:
            return _Layout(client, self.config)

    @property
    def observation_features(self) -> dict[str, Any]:
        state: dict[str, Any] = dict.fromkeys(self.layout.state_names, float)
        return state | {c: (h, w, 3) for c, (h, w) in self.layout.cameras.items()}

    @property
    def action_features(self) -> dict[str, type]:
        return dict.fromkeys(self.layout.action_names, float)

    @property
    def cameras(self) -> dict[str, tuple[int, int]]:
        """The server cameras this robot observes, name -> (height, width). lerobot-record sizes its image
        writer pools by `len(robot.cameras)`, as built-in robots hold their camera objects there."""
        return dict(self.layout.cameras)

    @property
    def action_mode(self) -> int:
        """`ACTION_MODE_ABSOLUTE_EE` or `ACTION_MODE_JOINT`: how `send_action` pushes its values."""
        return self.layout.mode

    @property
    def refusals(self) -> Sequence[GateRefusal]:
        """Commands the server's safety gate dropped since `connect` (also logged as warnings)."""
        return tuple(self._watch.refusals) if self._watch is not None else ()

    # --- lifecycle ------------------------------------------------------------------------------------

    @property
    def is_connected(self) -> bool:
        return self._session is not None and not self._session.closed

    def connect(self, calibrate: bool = True) -> None:
        if self.is_connected:
            raise DeviceAlreadyConnectedError(f"{self} is already connected")
        client = self._connect_client()
        try:
            self._client = client
            _ = self.layout
            self._watch = ArmWatch(client, self.config.arm)
            self._session = self._open_session()
        except BaseException:
            self.disconnect()
            raise
        log.info("%s connected to arm %r on %s", self, self.config.arm, self.config.server)

    def _open_session(self) -> PolicySession:
        assert self._client is not None
        # Observations are fetched on demand (GetObservation), so the session streams none (rate 0).
        return self._client.policy_session(
            [self.config.arm],
            observation_rate_hz=0.0,
            request_control=True,
            policy_name=f"lerobot:{self.id or self.name}",
            silence_timeout_s=self.config.silence_timeout_s,
        )

    @property
    def is_calibrated(self) -> bool:
        return True  # the server's bridge owns calibration

    def calibrate(self) -> None:
        pass

    def configure(self) -> None:
        pass

    def disconnect(self) -> None:
        # The arm holds: closing the session releases control, it does not stop or home the arm.
        if self._session is not None:
            self._session.close()
            self._session = None
        if self._watch is not None:
            self._watch.close()
            self._watch = None
        if self._client is not None:
            self._client.close()
            self._client = None

    # --- observations and actions ---------------------------------------------------------------------

    def _require(self) -> tuple[Client, PolicySession]:
        if self._client is None or self._session is None:
            raise DeviceNotConnectedError(f"{self} is not connected")
        return self._client, self._session

    def get_observation(self) -> dict[str, Any]:
        client, _ = self._require()
        cams = self.layout.cameras
        obs = client.observe(arms=[self.config.arm], image_encoding=IMAGE_RGB8, cameras=list(cams))
        arm = next(a for a in obs.arms if a.arm == self.config.arm)
        out: dict[str, Any] = dict(zip(self.layout.state_names, (float(v) for v in arm.state), strict=True))
        for frame in obs.frames:
            if frame.camera not in cams:
                continue
            h, w = cams[frame.camera]
            if (frame.height, frame.width) != (h, w):
                raise RuntimeError(
                    f"camera {frame.camera!r} now delivers {frame.width}x{frame.height}, declared {w}x{h}: reconnect"
                )
            out[frame.camera] = np.frombuffer(frame.data, dtype=np.uint8).reshape(h, w, 3)
        missing = [c for c in cams if c not in out]
        if missing:
            raise RuntimeError(f"phone2act observation has no frame from camera(s) {missing}")
        return out

    def _vector(self, action: Mapping[str, Any]) -> list[float]:
        missing = [n for n in self.layout.action_names if n not in action]
        if missing:
            raise KeyError(f"action lacks {missing}; arm {self.config.arm!r} takes {list(self.layout.action_names)}")
        return [float(action[n]) for n in self.layout.action_names]

    def send_action(self, action: Mapping[str, Any]) -> dict[str, float]:
        """Pushes one absolute step (end-effector target or joint targets) through the safety gate.

        Returns the action as pushed. The gate may still clamp it, or refuse a jump: refusals show up in
        `refusals` and as warnings, and the arm holds.
        """
        values = self._vector(action)
        self.send_action_chunk([values], step_period_s=1.0 / self.config.fps)
        return dict(zip(self.layout.action_names, values, strict=True))

    def send_action_chunk(
        self,
        steps: Sequence[Sequence[float] | Mapping[str, Any]],
        step_period_s: float,
        observation_id: int = 0,
        blend_steps: int = 0,
    ) -> policy_pb2.ChunkAccepted:
        """Pushes a whole chunk of absolute steps (rows in `action_features` order, or dicts)."""
        _, session = self._require()
        rows = [self._vector(s) if isinstance(s, Mapping) else [float(v) for v in s] for s in steps]
        kwargs = {"observation_id": observation_id, "mode": self.layout.mode, "blend_steps": blend_steps}
        try:
            return session.push(self.config.arm, rows, step_period_s, **kwargs)
        except FailedPrecondition:
            # The server sent ControlRevoked before it refused this push, on the session's own stream; give
            # the reader thread a moment to have handled it.
            deadline = time.monotonic() + 1.0
            while session.revoked is None and time.monotonic() < deadline:
                time.sleep(0.01)
            revoked = session.revoked
            # Only a session that lost the arm by its own silence (the reset phase of lerobot-record, a slow
            # policy) claims it back; an operator's take-over stands until this robot is reconnected.
            if revoked is None or not revoked.reason.startswith("silent"):
                raise
            log.info("%s lost arm %r (%s); claiming it again", self, self.config.arm, revoked.reason)
            session.close()
            self._session = None
            self._session = self._open_session()
            return self._session.push(self.config.arm, rows, step_period_s, **kwargs)
