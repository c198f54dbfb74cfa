"""One arm's state from the server's `System.WatchStatus` stream, and the absolute action layout.

Shared by the robot plugin (which reports what the safety gate refused) and the teleoperator plugin (which
reads the target the phone commands).
"""

from __future__ import annotations

import logging
import threading
import time
from collections import deque
from collections.abc import Callable, Sequence
from dataclasses import dataclass

from phone2act import Client
from phone2act.v1 import common_pb2

log = logging.getLogger(__name__)

# The recorded `action` of an end-effector arm (server/core/src/layout.rs, ABSOLUTE_ACTION_NAMES): target
# position (m, robot base frame), the first two columns of its rotation matrix, gripper (0 open, 1 closed).
# The server reports these names for arms in `absolute` mode; an arm in `relative` mode reports its chunk
# layout (`delta_x` ...) instead, while datasets still record these.
ABSOLUTE_EE_NAMES: tuple[str, ...] = ("x", "y", "z", "r00", "r10", "r20", "r01", "r11", "r21", "gripper")


def rotation_6d(q_xyzw: Sequence[float]) -> tuple[float, float, float, float, float, float]:
    """r00 r10 r20 r01 r11 r21: the first two columns of the rotation matrix of a unit quaternion."""
    x, y, z, w = q_xyzw
    return (
        1 - 2 * (y * y + z * z),
        2 * (x * y + z * w),
        2 * (x * z - y * w),
        2 * (x * y - z * w),
        1 - 2 * (x * x + z * z),
        2 * (y * z + x * w),
    )


def absolute_target(state: common_pb2.ArmState) -> list[float]:
    """The arm's current target (`robot_from_target`, `gripper_target`) in the `ABSOLUTE_EE_NAMES` layout."""
    p, q = state.robot_from_target.position_m, state.robot_from_target.orientation
    return [p.x, p.y, p.z, *rotation_6d((q.x, q.y, q.z, q.w)), state.gripper_target]


@dataclass(frozen=True)
class GateRefusal:
    """A command to the arm that the server's safety gate dropped (a jump, an invalid target)."""

    arm: str
    reason: str
    # Monotonic time (this process) the refusal was seen.
    seen_s: float


class ArmWatch:
    """Keeps the newest `ArmState` of one arm from `System.WatchStatus` on a background thread.

    Every increase of the arm's `commands_rejected` counter is logged as a warning and kept in `refusals`
    (bounded), so a caller learns that a command it sent did not move the arm.
    """

    def __init__(self, client: Client, arm: str, interval_s: float = 0.02, max_refusals: int = 1000) -> None:
        self.arm = arm
        self.refusals: deque[GateRefusal] = deque(maxlen=max_refusals)
        self._cond = threading.Condition()
        self._state: common_pb2.ArmState | None = None
        self._rejected: int | None = None
        self._error: Exception | None = None
        self._call = client.watch_status(interval_s=interval_s)
        self._thread = threading.Thread(target=self._run, name=f"phone2act-watch-{arm}", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        try:
            for status in self._call:
                for state in status.arms:
                    if state.arm == self.arm:
                        self._update(state)
        except Exception as e:  # noqa: BLE001 - kept for the waiting caller, which raises it
            log.warning("phone2act status stream for arm %r ended: %s", self.arm, e)
            self._error = e
        with self._cond:
            self._cond.notify_all()

    def _update(self, state: common_pb2.ArmState) -> None:
        with self._cond:
            if self._rejected is not None and state.commands_rejected > self._rejected:
                reason = state.last_decision.reason or "refused by the safety gate"
                n = state.commands_rejected - self._rejected
                log.warning("phone2act arm %r: safety gate refused %d command(s): %s", self.arm, n, reason)
                self.refusals.append(GateRefusal(self.arm, reason, time.monotonic()))
            self._rejected = state.commands_rejected
            self._state = state
            self._cond.notify_all()

    def latest(self, timeout_s: float = 5.0) -> common_pb2.ArmState:
        """The newest state; waits for the first one up to `timeout_s`."""
        return self.wait(lambda _s: True, timeout_s)

    def wait(self, pred: Callable[[common_pb2.ArmState], bool], timeout_s: float) -> common_pb2.ArmState:
        """The first newest state satisfying `pred`, waiting up to `timeout_s` (then `TimeoutError`)."""
        deadline = time.monotonic() + timeout_s
        with self._cond:
            while self._state is None or not pred(self._state):
                left = deadline - time.monotonic()
                if self._error is not None:
                    raise ConnectionError(f"phone2act status stream ended: {self._error}")
                if left <= 0:
                    if self._state is None:
                        raise TimeoutError(f"no state of arm {self.arm!r} within {timeout_s:.1f} s")
                    raise TimeoutError(f"arm {self.arm!r} did not reach the awaited state within {timeout_s:.1f} s")
                self._cond.wait(timeout=left)
            return self._state

    def close(self) -> None:
        self._call.cancel()
        self._thread.join(timeout=2.0)
