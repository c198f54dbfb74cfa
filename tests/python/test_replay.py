"""Replaying a recorded sim episode through the Policy API reproduces its end-effector trajectory.

The original episode is teleoperated (a phone tracing a loop with a wrist turn); the replay is recorded as a
second episode, and the two `observation.state` end-effector tracks are compared after aligning their start.
"""

from __future__ import annotations

import math
import time

import numpy as np
import pytest
from conftest import Server
from phone2act import Client
from phone2act.poses import quat_from_rpy
from phone2act_replay import align, load_episode, pose_errors, replay

PHONE0 = (0.0, 1.2, -0.3)


def teleop_loop(c: Client, seconds: float = 5.0) -> None:
    """A phone moving ~3 cm/s around a loop while turning its wrist by up to ±9°."""
    with c.teleop("main") as t:
        t.wait_feedback(t.clutch(True, PHONE0))
        w = 2 * math.pi / seconds
        t0 = time.monotonic()
        while (now := time.monotonic() - t0) < seconds:
            p = (PHONE0[0] + 0.025 * math.sin(w * now), PHONE0[1] + 0.015 * (1 - math.cos(w * now)),
                 PHONE0[2] - 0.01 * math.sin(2 * w * now))
            t.send(p, quat_from_rpy(0.0, 0.0, 0.15 * math.sin(w * now)))  # about the phone's +Z
            time.sleep(0.02)
        time.sleep(0.5)
        t.wait_feedback(t.clutch(False))


@pytest.fixture(scope="module")
def recorded(server: Server) -> int:
    with Client(server.target) as c:
        c.episodes.start("trace a loop")
        teleop_loop(c)
        return int(c.episodes.stop().episode_index)


def test_replay_reproduces_the_recorded_trajectory(server: Server, recorded: int) -> None:
    original = load_episode(server.root, recorded)
    assert original.task == "trace a loop" and len(original) >= 100
    ref = original.ee_pose()
    assert np.ptp(ref[:, 0]) > 0.01 or np.ptp(ref[:, 1]) > 0.01, "the teleop episode barely moved"
    with Client(server.target) as c:
        r = replay(c, original, upsample=4, on_start=lambda: c.episodes.start("replay of trace a loop"))
        saved = c.episodes.stop()
    assert r.accepted.steps_skipped <= 1, r.accepted
    replayed = load_episode(server.root, int(saved.episode_index))
    offset, aligned = align(ref, replayed.ee_pose())
    pos, ang = pose_errors(ref, aligned)
    moved = max(np.linalg.norm(ref[:, :3] - ref[0, :3], axis=1))
    print(f"\nreplay of {len(original)} frames ({moved * 1e3:.1f} mm excursion): offset {offset:.2f} frames, "
          f"max error {pos.max() * 1e3:.3f} mm / {math.degrees(ang.max()):.3f}°, "
          f"rms {math.sqrt(np.mean(pos ** 2)) * 1e3:.3f} mm")
    assert pos.max() < 1e-3, f"position error {pos.max() * 1e3:.3f} mm"
    assert math.degrees(ang.max()) < 1.0, f"orientation error {math.degrees(ang.max()):.3f}°"
    # The executed targets agree too (they are what the dataset's action column encodes).
    _, aligned_targets = align(original.targets(), replayed.targets())
    tpos, tang = pose_errors(original.targets(), aligned_targets)
    assert np.median(tpos) < 1e-3 and math.degrees(np.median(tang)) < 1.0


def test_targets_follow_the_delta_convention(server: Server, recorded: int) -> None:
    """action = target - measured (position) and wrapped rpy differences, gripper absolute (layout.rs)."""
    ep = load_episode(server.root, recorded)
    assert ep.action_names[:3] == ["delta_x", "delta_y", "delta_z"]
    t = ep.targets()
    np.testing.assert_allclose(t[:, :3] - ep.ee_pose()[:, :3], ep.action[:, :3], atol=1e-6)
    assert np.all(np.abs(ep.action[:, 3:6]) <= math.pi + 1e-6)
    # Targets are where the arm goes: the measured pose one frame later is closer to target i than pose i is.
    closer = np.linalg.norm(t[:-1, :3] - ep.ee_pose()[1:, :3], axis=1) <= np.linalg.norm(ep.action[:-1, :3], axis=1) + 1e-6
    assert closer.mean() > 0.9
