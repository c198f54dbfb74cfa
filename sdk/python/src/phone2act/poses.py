"""Pose helpers in the server's conventions (pure Python, no numpy).

Quaternions are (x, y, z, w). Roll/pitch/yaw are extrinsic XYZ: R = Rz(yaw)·Ry(pitch)·Rx(roll), exactly as the
server's `observation.state` and action vectors use them.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

Quat = tuple[float, float, float, float]


def quat_from_rpy(roll: float, pitch: float, yaw: float) -> Quat:
    sr, cr = math.sin(0.5 * roll), math.cos(0.5 * roll)
    sp, cp = math.sin(0.5 * pitch), math.cos(0.5 * pitch)
    sy, cy = math.sin(0.5 * yaw), math.cos(0.5 * yaw)
    w = cr * cp * cy + sr * sp * sy
    x = sr * cp * cy - cr * sp * sy
    y = cr * sp * cy + sr * cp * sy
    z = cr * cp * sy - sr * sp * cy
    return (x, y, z, w)


def _matrix(q: Sequence[float]) -> list[list[float]]:
    x, y, z, w = q
    n = math.sqrt(x * x + y * y + z * z + w * w)
    x, y, z, w = x / n, y / n, z / n, w / n
    return [
        [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
        [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
        [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
    ]


def rpy_from_quat(q: Sequence[float]) -> tuple[float, float, float]:
    """Inverse of quat_from_rpy, pitch in [-pi/2, pi/2] (same extraction as the server)."""
    m = _matrix(q)
    pitch = math.atan2(-m[2][0], math.hypot(m[0][0], m[1][0]))
    yaw = math.atan2(m[1][0], m[0][0])
    sp, cp = math.sin(pitch), math.cos(pitch)
    sy, cy = math.sin(yaw), math.cos(yaw)
    r11 = -sy * m[0][1] + cy * m[1][1]
    r21 = sp * (cy * m[0][1] + sy * m[1][1]) + cp * m[2][1]
    return (math.atan2(r21, r11), pitch, yaw)


def quat_multiply(a: Sequence[float], b: Sequence[float]) -> Quat:
    ax, ay, az, aw = a
    bx, by, bz, bw = b
    return (
        aw * bx + ax * bw + ay * bz - az * by,
        aw * by - ax * bz + ay * bw + az * bx,
        aw * bz + ax * by - ay * bx + az * bw,
        aw * bw - ax * bx - ay * by - az * bz,
    )


def quat_angle(a: Sequence[float], b: Sequence[float]) -> float:
    """Angle (rad, in [0, pi]) of the rotation taking orientation a to orientation b."""
    dot = abs(sum(x * y for x, y in zip(a, b))) / (
        math.sqrt(sum(x * x for x in a)) * math.sqrt(sum(y * y for y in b))
    )
    return 2.0 * math.acos(min(1.0, dot))


def slerp(a: Sequence[float], b: Sequence[float], t: float) -> Quat:
    dot = sum(x * y for x, y in zip(a, b))
    bb = list(b)
    if dot < 0:
        bb, dot = [-v for v in bb], -dot
    if dot > 0.9995:
        out = [x + t * (y - x) for x, y in zip(a, bb)]
    else:
        theta = math.acos(dot)
        s = math.sin(theta)
        ka, kb = math.sin((1 - t) * theta) / s, math.sin(t * theta) / s
        out = [ka * x + kb * y for x, y in zip(a, bb)]
    n = math.sqrt(sum(v * v for v in out))
    return (out[0] / n, out[1] / n, out[2] / n, out[3] / n)


def wrap_angle(a: float) -> float:
    """Wrap to (-pi, pi]."""
    w = math.remainder(a, 2.0 * math.pi)
    return math.pi if w == -math.pi else w
