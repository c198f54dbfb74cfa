"""Which action representation an arm takes, as the phone2act server reports it.

The arm's configuration decides what its recorded `action` column means (end-effector deltas relative to the
chunk's observation, absolute end-effector targets, or joint targets), so a model trained on that dataset
answers in the same representation and the adapter pushes its chunks with that mode. The mode is read from the
server, never chosen here: an explicit `action_mode` on the arm's observation when the server sends one,
otherwise the arm's action names (`delta_*` for deltas, the state's joint names for joint targets, end-effector
axis names for absolute targets).
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

from phone2act.v1 import policy_pb2

DELTA = "delta"
ABSOLUTE = "absolute"
JOINT = "joint"
# Absolute end-effector axis names: phone2act's `x y z` and 6D rotation `r00 r10 r20 r01 r11 r21` (the recorded
# action layout, `server/core/src/layout.rs`), and other spellings (roll/pitch/yaw, rotation vector, quaternion).
# The absolute end-effector action axes a phone2act dataset records (`server/core/src/layout.rs`), gripper aside:
# an answer this wide for an arm that takes another representation comes from a model trained on absolute targets.
RECORDED_ABSOLUTE_AXES = ("x", "y", "z", "r00", "r10", "r20", "r01", "r11", "r21")
EE_AXES = {"x", "y", "z", "r00", "r10", "r20", "r01", "r11", "r21", "roll", "pitch", "yaw", "rx", "ry", "rz", "qx", "qy",
           "qz", "qw"}


class ActionModeError(ValueError):
    """The server reports an action representation this adapter cannot push."""


def _enum_value(kind: str) -> int:
    """The proto `ActionMode` value for a representation, matched by name so renamed or added modes still map."""
    names = dict(policy_pb2.ActionMode.items())
    wanted = {
        DELTA: ("ACTION_MODE_DELTA_EE", "DELTA", "RELATIVE"),
        ABSOLUTE: ("ACTION_MODE_ABSOLUTE_EE", "ABSOLUTE"),
        JOINT: ("ACTION_MODE_JOINT", "JOINT"),
    }[kind]
    if wanted[0] in names:
        return names[wanted[0]]
    for part in wanted[1:]:
        for name, value in names.items():
            if part in name and (kind == JOINT or "JOINT" not in name):
                return value
    raise ActionModeError(
        f"the server reports {kind} actions, but this phone2act SDK has no such ActionMode ({sorted(names)}); "
        f"update the phone2act Python package"
    )


def kind_of_mode(value: int) -> str:
    name = policy_pb2.ActionMode.Name(value)
    if "JOINT" in name:
        return JOINT
    if "ABSOLUTE" in name:
        return ABSOLUTE
    if "DELTA" in name or "RELATIVE" in name:
        return DELTA
    raise ActionModeError(f"unknown action mode {name}")


def is_gripper(name: str) -> bool:
    return name.split(".", 1)[0].endswith("gripper")


def kind_from_names(arm: str, action_names: Sequence[str], state_names: Sequence[str]) -> str:
    body = [n for n in action_names if not is_gripper(n)]
    if not body:
        raise ActionModeError(f"arm {arm!r} reports no action axes besides the gripper ({list(action_names)})")
    if all(n.startswith("delta_") for n in body):
        return DELTA
    joints = {n for n in state_names if not n.startswith("ee_") and not is_gripper(n)}
    if all(n in joints for n in body):
        return JOINT
    if all(n in EE_AXES or n.startswith(("ee_", "rot")) for n in body):
        return ABSOLUTE
    raise ActionModeError(
        f"cannot tell the action representation of arm {arm!r} from its action names {list(action_names)}; "
        f"the adapter knows delta_* (deltas), the arm's joint names (joint targets) and end-effector axes "
        f"(absolute)"
    )


def action_mode_of(arm_obs: Any, arm_state: Any = None) -> int:
    """The `ActionMode` to push for this arm, from what the server reports: an explicit mode on its
    `ArmObservation` or (from `System.ListArms`) its `ArmState`, else its action names."""
    for reported in (arm_obs, arm_state):
        explicit = int(getattr(reported, "action_mode", 0) or 0)
        if explicit:
            return explicit
    kind = kind_from_names(arm_obs.arm, tuple(arm_obs.action_names), tuple(arm_obs.state_names))
    return _enum_value(kind)
