"""Replay a recorded episode's actions through the Policy API.

A recorded action is the absolute end-effector target commanded at its frame (see dataset.py), which is what
an ABSOLUTE_EE chunk step means, so the action column is pushed as it is: one chunk at the dataset rate
(optionally resampled finer). Absolute targets make the replay independent of where the arm happens to be
between frames; the arm is first brought, in small steps the safety gate accepts, to the pose it had at the
episode's first frame. A take-over by the operator pauses the replay; after the hand-back it goes on from the
step that was due when the arm was taken.
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
    # Times the operator took the arm and handed it back, after which the replay went on.
    resumed: int = 0


def measured_pose(obs: policy_pb2.Observation, arm: str) -> np.ndarray:
    """The arm's measured x y z, 6D rotation and gripper from an observation's state."""
    a = next(a for a in obs.arms if a.arm == arm)
    names = list(a.state_names)
    return np.array([a.state[names.index(n)] for n in EE_NAMES])


def _pose_gap(a: np.ndarray, b: np.ndarray) -> tuple[float, float]:
    return float(np.linalg.norm(a[:3] - b[:3])), rotation_angle(a[3:9], b[3:9])


def approach(start: np.ndarray, goal: np.ndarray, *, max_step_m: float = 0.004,
             max_step_rad: float = 0.035) -> list[np.ndarray]:
    """Steps from `start` to `goal` (x y z, 6D rotation, gripper), each at most `max_step_m` and `max_step_rad`
    from the previous, ending at `goal`."""
    dist, angle = _pose_gap(start, goal)
    n = max(1, math.ceil(dist / max_step_m), math.ceil(angle / max_step_rad))
    # Linear in every column, projected onto rotations: steps of at most ~2° each, nowhere near a 180° turn
    # where the straight 6D line would leave the rotations.
    return list(_project(np.array([start + (k / n) * (goal - start) for k in range(1, n + 1)])))


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
    steps = approach(start, goal, max_step_m=max_step_m, max_step_rad=max_step_rad)
    n = len(steps)
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
    hand_back_timeout_s: float = 300.0,
) -> ReplayResult:
    """Replay `episode` on `arm`; `on_start` runs right before the chunk is pushed (e.g. start recording).

    If the operator takes the arm with a phone's clutch (`ControlPaused`), the replay waits for the hand-back
    (at most `hand_back_timeout_s`), brings the arm in gate-sized steps from where the operator left it to the
    step that was due when it was taken, and plays the rest of the episode from there."""
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
        started = time.monotonic()
        first = 0  # the episode step the current chunk's first step stands for
        resume_from = 0
        resumed = 0
        end = started + duration + settle_s
        while time.monotonic() < end:
            if session.revoked is not None:
                raise RuntimeError(f"replay interrupted: {session.revoked.reason}")
            if arm in session.waiting:
                # The step due when the arm was taken (never earlier than where the last resume started).
                due = min(len(steps) - 1, max(resume_from, first + math.floor((time.monotonic() - started) / period)))
                _wait_for_hand_back(session, arm, hand_back_timeout_s)
                # One chunk: steps from where the operator left the arm to the step that was due, at move_to's pace
                # (4 mm and 2° per 20 ms), then the rest of the episode from it.
                pace = period / 0.02
                lead = approach(measured_pose(session.next_observation(), arm), steps[due],
                                max_step_m=0.004 * pace, max_step_rad=0.035 * pace)
                n += len(lead)
                first, resume_from = due - len(lead), due
                session.push(arm, [*lead, *steps[due:]], period, mode=ABSOLUTE_EE)
                started = time.monotonic()
                end = started + (len(lead) + len(steps) - due) * period + settle_s
                resumed += 1
                continue
            time.sleep(0.02)
    return ReplayResult(len(steps), period, duration, n, accepted, resumed)


def _wait_for_hand_back(session: PolicySession, arm: str, timeout_s: float) -> None:
    deadline = time.monotonic() + timeout_s
    while arm in session.waiting:
        if session.revoked is not None:
            raise RuntimeError(f"replay interrupted: {session.revoked.reason}")
        if time.monotonic() > deadline:
            raise TimeoutError(f"arm {arm!r} was not handed back within {timeout_s:.0f} s")
        time.sleep(0.02)
