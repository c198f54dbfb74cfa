"""Joint models an out-of-process bridge declares in `BridgeHello.joint_model`.

With a model, the server solves every target for the bridge's joints and limits each joint's step to its speed
limit; every `BridgeCommand` then carries `joint_targets_rad` (in the hello's joint order) and the bridge drives
to those. Without one, the bridge solves the pose itself and the server can only watch the measured joint
speeds. The server compares the model's pose of the first reported joints with the reported tool pose and
ends the stream if they differ by more than 5 mm or 0.05 rad, so a bridge without its own forward kinematics
can report `forward(...)` of its joints.

    hello = BridgeHello(arm="ext", joint_names=[j.name for j in joints], supports_orientation=True,
                        joint_model=chain_model(joints, tool_xyz_m=(0, 0, 0.1)))
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

from phone2act.poses import Quat, quat_from_rpy, quat_multiply
from phone2act.v1 import bridge_pb2 as pb

Vec3 = tuple[float, float, float]


@dataclass(frozen=True)
class ChainJoint:
    """One revolute joint in URDF terms: origin on the parent link, axis in its own frame, range, speed."""

    name: str
    origin_xyz_m: Vec3
    origin_rpy_rad: Vec3
    axis: Vec3
    lower_rad: float
    upper_rad: float
    max_velocity_rad_s: float
    max_acceleration_rad_s2: float | None = None

    def to_proto(self) -> pb.ChainJoint:
        j = pb.ChainJoint(name=self.name, origin_xyz_m=list(self.origin_xyz_m),
                          origin_rpy_rad=list(self.origin_rpy_rad), axis=list(self.axis),
                          lower_rad=self.lower_rad, upper_rad=self.upper_rad,
                          max_velocity_rad_s=self.max_velocity_rad_s)
        if self.max_acceleration_rad_s2 is not None:
            j.max_acceleration_rad_s2 = self.max_acceleration_rad_s2
        return j


def known_model(name: str) -> pb.JointModel:
    """A model the server knows by name: "so101" (five arm joints) or "cr5" (six)."""
    return pb.JointModel(known=name)


def chain_model(joints: Sequence[ChainJoint], tool_xyz_m: Vec3 = (0.0, 0.0, 0.0),
                tool_rpy_rad: Vec3 = (0.0, 0.0, 0.0)) -> pb.JointModel:
    """An explicit chain, base to last link (three to seven joints), and the tool's origin on the last link."""
    return pb.JointModel(chain=pb.JointChain(joints=[j.to_proto() for j in joints],
                                             tool_xyz_m=list(tool_xyz_m), tool_rpy_rad=list(tool_rpy_rad)))


def _rotate(q: Sequence[float], v: Sequence[float]) -> Vec3:
    x, y, z, w = q
    # v + 2w(u × v) + 2u × (u × v), u the vector part.
    cx, cy, cz = y * v[2] - z * v[1], z * v[0] - x * v[2], x * v[1] - y * v[0]
    ccx, ccy, ccz = y * cz - z * cy, z * cx - x * cz, x * cy - y * cx
    return (v[0] + 2 * (w * cx + ccx), v[1] + 2 * (w * cy + ccy), v[2] + 2 * (w * cz + ccz))


def _axis_angle(axis: Sequence[float], angle: float) -> Quat:
    n = math.sqrt(sum(a * a for a in axis))
    if not n > 0.0:
        raise ValueError(f"axis {tuple(axis)} is not a direction")
    s = math.sin(angle / 2) / n
    return (axis[0] * s, axis[1] * s, axis[2] * s, math.cos(angle / 2))


def forward(joints: Sequence[ChainJoint], joints_rad: Sequence[float], tool_xyz_m: Vec3 = (0.0, 0.0, 0.0),
            tool_rpy_rad: Vec3 = (0.0, 0.0, 0.0)) -> tuple[Vec3, Quat]:
    """The tool pose (position m, quaternion x, y, z, w) of a chain at these joints, as the server computes it."""
    if len(joints_rad) != len(joints):
        raise ValueError(f"{len(joints_rad)} joint values for {len(joints)} joints")
    p: Vec3 = (0.0, 0.0, 0.0)
    q: Quat = (0.0, 0.0, 0.0, 1.0)

    def then(xyz: Sequence[float], rot: Quat) -> None:
        nonlocal p, q
        d = _rotate(q, xyz)
        p = (p[0] + d[0], p[1] + d[1], p[2] + d[2])
        q = quat_multiply(q, rot)

    for j, angle in zip(joints, joints_rad):
        then(j.origin_xyz_m, quat_from_rpy(*j.origin_rpy_rad))
        then((0.0, 0.0, 0.0), _axis_angle(j.axis, angle))
    then(tool_xyz_m, quat_from_rpy(*tool_rpy_rad))
    return p, q


# The SO-101 (TheRobotStudio SO-ARM100 "new calib" URDF, base_link to gripper_frame_link): what
# `known_model("so101")` means on the server, for a bridge that wants the same model with its own speeds.
SO101_JOINTS: tuple[tuple[str, Vec3, Vec3, tuple[float, float]], ...] = (
    ("shoulder_pan", (0.0388353, -8.97657e-09, 0.0624), (3.14159, 4.18253e-17, -3.14159), (-1.91986, 1.91986)),
    ("shoulder_lift", (-0.0303992, -0.0182778, -0.0542), (-1.5708, -1.5708, 0.0), (-1.74533, 1.74533)),
    ("elbow_flex", (-0.11257, -0.028, 1.73763e-16), (-3.63608e-16, 8.74301e-16, 1.5708), (-1.69, 1.69)),
    ("wrist_flex", (-0.1349, 0.0052, 3.62355e-17), (4.02456e-15, 8.67362e-16, -1.5708), (-1.65806, 1.65806)),
    ("wrist_roll", (5.55112e-17, -0.0611, 0.0181), (1.5708, 0.0486795, 3.14159), (-2.74385, 2.84121)),
)
SO101_TOOL: tuple[Vec3, Vec3] = ((-0.0079, -0.000218121, -0.0981274), (0.0, 3.14159, 0.0))


def so101_chain(max_velocity_rad_s: float = 4.7) -> list[ChainJoint]:
    """The SO-101's five arm joints as a chain, every joint limited to `max_velocity_rad_s`."""
    return [ChainJoint(name, xyz, rpy, (0.0, 0.0, 1.0), lo, hi, max_velocity_rad_s)
            for name, xyz, rpy, (lo, hi) in SO101_JOINTS]
