"""A phone, through phone2act, as a LeRobot `Teleoperator`.

The phone streams to the server (the phone page through the gateway, or `Teleop.Stream`) and drives one
phone2act arm; the server's planner and safety gate turn its poses into that arm's target. `get_action`
returns that target, read from `System.WatchStatus`: the same absolute end-effector action phone2act records
(`x y z r00 r10 r20 r01 r11 r21 gripper`, robot base frame of that arm). A LeRobot robot that takes other
actions (joint positions) needs an action processor that maps end-effector targets onto it (inverse
kinematics), as lerobot's own phone teleoperator does.
"""

from __future__ import annotations

from typing import Any

from lerobot.teleoperators.teleoperator import Teleoperator
from lerobot.utils.errors import DeviceAlreadyConnectedError, DeviceNotConnectedError
from lerobot_robot_phone2act import ABSOLUTE_EE_NAMES, ArmWatch
from lerobot_robot_phone2act.arm_watch import absolute_target
from phone2act import Client

from lerobot_teleoperator_phone2act.config_phone2act_teleop import Phone2ActTeleopConfig


class Phone2ActTeleop(Teleoperator):
    """`--teleop.type=phone2act --teleop.server=HOST:PORT --teleop.arm=main`."""

    config_class = Phone2ActTeleopConfig
    name = "phone2act"

    def __init__(self, config: Phone2ActTeleopConfig) -> None:
        super().__init__(config)
        self.config = config
        self._client: Client | None = None
        self._watch: ArmWatch | None = None

    @property
    def action_features(self) -> dict[str, type]:
        return dict.fromkeys(ABSOLUTE_EE_NAMES, float)

    @property
    def feedback_features(self) -> dict[str, type]:
        return {}

    @property
    def is_connected(self) -> bool:
        return self._watch is not None

    def connect(self, calibrate: bool = True) -> None:
        if self.is_connected:
            raise DeviceAlreadyConnectedError(f"{self} is already connected")
        client = Client(self.config.server, token=self.config.token, connect_timeout_s=self.config.connect_timeout_s)
        try:
            client.arm(self.config.arm)  # NotFound with the arm's name
            self._watch = ArmWatch(client, self.config.arm, interval_s=self.config.status_interval_s)
            self._watch.latest(timeout_s=self.config.connect_timeout_s)
        except BaseException:
            if self._watch is not None:
                self._watch.close()
                self._watch = None
            client.close()
            raise
        self._client = client

    @property
    def is_calibrated(self) -> bool:
        return True  # the phone needs none; the server's mapping config says how it moves the arm

    def calibrate(self) -> None:
        pass

    def configure(self) -> None:
        pass

    def get_action(self) -> dict[str, float]:
        """The target the phone commands for the arm now (held while the phone is clutched or away)."""
        if self._watch is None:
            raise DeviceNotConnectedError(f"{self} is not connected")
        state = self._watch.latest()
        return dict(zip(ABSOLUTE_EE_NAMES, absolute_target(state), strict=True))

    def send_feedback(self, feedback: dict[str, Any]) -> None:
        pass  # the phone shows phone2act's own feedback (engaged, clamped, rejected jumps, latency)

    def disconnect(self) -> None:
        if self._watch is not None:
            self._watch.close()
            self._watch = None
        if self._client is not None:
            self._client.close()
            self._client = None
