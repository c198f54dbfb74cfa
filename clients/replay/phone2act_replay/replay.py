"""Replay a recorded episode's actions through the Policy API.

The recorded actions are turned into the absolute end-effector targets they stood for (see dataset.py) and
pushed as one ABSOLUTE_EE chunk at the dataset rate (optionally resampled finer). Absolute targets make the
replay independent of where the arm happens to be between frames; the arm is first brought, in small steps
the safety gate accepts, to the pose it had at the episode's first frame.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from phone2act import ABSOLUTE_EE, Client, PolicySession, pose_tuple
from phone2act.poses import quat_angle, quat_from_rpy, rpy_from_quat
from phone2act.v1 import policy_pb2

from phone2act_replay.dataset import Episode, resample

# The server's default chunk length limit.
MAX_CHUNK_STEPS = 10_000


@dataclass
class ReplayResult:
    steps: int
    step_period_s: float
    duration_s: float
    approach_steps: int
    accepted: policy_pb2.ChunkAccepted


def measured_xyzrpy(obs: policy_pb2.Observation, arm: str) -> np.ndarray:
    a = next(a for a in obs.arms if a.arm == arm)
    p, q = pose_tuple(a.robot_from_ee)
    return np.array([*p, *rpy_from_quat(q), a.state[-1]])


def _pose_gap(a: np.ndarray, b: np.ndarray) -> tuple[float, float]:
    return float(np.linalg.norm(a[:3] - b[:3])), quat_angle(quat_from_rpy(*a[3:6]), quat_from_rpy(*b[3:6]))


def move_to(
    session: PolicySession,
    arm: str,
    goal: np.ndarray,
    *,
    step_period_s: float = 0.02,
    max_step_m: float = 0.004,
    max_step_rad: float = 0.035,
    tolerance_m: float = 3e-4,
    tolerance_rad: float = math.radians(0.3),
    timeout_s: float = 10.0,
) -> int:
    """Bring the arm to `goal` (x y z roll pitch yaw gripper) in gate-sized steps; wait until it is there."""
    start = measured_xyzrpy(session.next_observation(), arm)
    dist, angle = _pose_gap(start, goal)
    n = max(1, math.ceil(dist / max_step_m), math.ceil(angle / max_step_rad))
    qa, qb = np.array(quat_from_rpy(*start[3:6])), np.array(quat_from_rpy(*goal[3:6]))
    if np.dot(qa, qb) < 0:
        qb = -qb
    steps = []
    for k in range(1, n + 1):
        t = k / n
        row = start + t * (goal - start)
        q = (1 - t) * qa + t * qb
        row[3:6] = rpy_from_quat(tuple(q / np.linalg.norm(q)))
        steps.append(row)
    steps.append(goal)  # hold the goal one more period while the arm settles
    session.push(arm, steps, step_period_s, mode=ABSOLUTE_EE)
    deadline = time.monotonic() + n * step_period_s + timeout_s
    while time.monotonic() < deadline:
        d, a = _pose_gap(measured_xyzrpy(session.next_observation(), arm), goal)
        if d <= tolerance_m and a <= tolerance_rad:
            return n
    d, a = _pose_gap(measured_xyzrpy(session.next_observation(), arm), goal)
    raise TimeoutError(f"arm {arm!r} did not reach the episode's start pose: {d * 1e3:.2f} mm, {math.degrees(a):.2f}° away")


def replay(
    client: Client,
    episode: Episode,
    *,
    arm: str = "main",
    dataset_arm: str = "",
    upsample: int = 4,
    on_start: Callable[[], None] | None = None,
    settle_s: float = 0.5,
) -> ReplayResult:
    """Replay `episode` on `arm`; `on_start` runs right before the chunk is pushed (e.g. start recording)."""
    targets = episode.targets(dataset_arm)
    start_pose = episode.ee_pose(dataset_arm)[0]
    factor = max(1, min(upsample, (MAX_CHUNK_STEPS - 1) // max(1, len(targets) - 1)))
    steps = resample(targets, factor)
    period = 1.0 / (episode.fps * factor)
    duration = len(steps) * period
    with client.policy_session(
        [arm], observation_rate_hz=50.0, policy_name="replay", silence_timeout_s=duration + 30.0
    ) as session:
        n = move_to(session, arm, start_pose)
        if on_start is not None:
            on_start()
        accepted = session.push(arm, steps, period, mode=ABSOLUTE_EE)
        end = time.monotonic() + duration + settle_s
        while time.monotonic() < end:
            if session.revoked is not None:
                raise RuntimeError(f"replay interrupted: {session.revoked.reason}")
            time.sleep(0.02)
    return ReplayResult(len(steps), period, duration, n, accepted)
