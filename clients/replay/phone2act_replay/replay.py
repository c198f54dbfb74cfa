"""Replay a recorded episode's actions through the Policy API.

A recorded action is the absolute end-effector target commanded at its frame (see dataset.py), which is what
an ABSOLUTE_EE chunk step means, so the action column is pushed as it is: one chunk at the dataset rate
(optionally resampled finer). Absolute targets make the replay independent of where the arm happens to be
between frames; the arm is first brought, in small steps the safety gate accepts, to the pose it had at the
episode's first frame.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from phone2act import ABSOLUTE_EE, Client, PolicySession
from phone2act.v1 import policy_pb2

from phone2act_replay.dataset import EE_NAMES, Episode, _project, rotation_angle, resample

# The server's default chunk length limit.
MAX_CHUNK_STEPS = 10_000


@dataclass
class ReplayResult:
    steps: int
    step_period_s: float
    duration_s: float
    approach_steps: int
    accepted: policy_pb2.ChunkAccepted


def measured_pose(obs: policy_pb2.Observation, arm: str) -> np.ndarray:
    """The arm's measured x y z, 6D rotation and gripper from an observation's state."""
    a = next(a for a in obs.arms if a.arm == arm)
    names = list(a.state_names)
    return np.array([a.state[names.index(n)] for n in EE_NAMES])


def _pose_gap(a: np.ndarray, b: np.ndarray) -> tuple[float, float]:
    return float(np.linalg.norm(a[:3] - b[:3])), rotation_angle(a[3:9], b[3:9])


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
    arrive: np.ndarray | None = None,
) -> int:
    """Command `goal` (x y z, 6D rotation, gripper) in gate-sized steps and wait until the measured pose is at
    `arrive` (default: the goal itself; a 5-DoF arm may settle short of a goal orientation it cannot reach)."""
    arrive = goal if arrive is None else arrive
    start = measured_pose(session.next_observation(), arm)
    dist, angle = _pose_gap(start, goal)
    n = max(1, math.ceil(dist / max_step_m), math.ceil(angle / max_step_rad))
    # Linear in every column, projected onto rotations: steps of at most ~2° each, nowhere near a 180° turn
    # where the straight 6D line would leave the rotations.
    steps = list(_project(np.array([start + (k / n) * (goal - start) for k in range(1, n + 1)])))
    steps.append(goal)  # hold the goal one more period while the arm settles
    session.push(arm, steps, step_period_s, mode=ABSOLUTE_EE)
    deadline = time.monotonic() + n * step_period_s + timeout_s
    while time.monotonic() < deadline:
        d, a = _pose_gap(measured_pose(session.next_observation(), arm), arrive)
        if d <= tolerance_m and a <= tolerance_rad:
            return n
    d, a = _pose_gap(measured_pose(session.next_observation(), arm), arrive)
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
        # The same start: where the arm measured at the first frame. (Not the first target: a 5-DoF arm settles
        # short of an orientation it cannot reach, by an amount that depends on how it got there.)
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
