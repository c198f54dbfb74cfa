"""Replaying a recorded sim episode through the Policy API reproduces its targets and its trajectory.

The original episode is teleoperated (a phone tracing a loop with a wrist turn); the replay is recorded as a
second episode. Compared, both geometrically (each frame against the other recording's path, so a recorder
tick that wakes late on a loaded machine, which samples the same path a little further along, does not count):
- the executed targets (the `action` columns): the replay pushes the recorded targets themselves, so they must
  lie on the original's target path to float32 rounding;
- the measured end-effector paths (`observation.state`): the sim's 50 ms first-order joint lag follows the same
  target path in both, but driven at different instants (50 Hz phone samples vs 80 Hz chunk steps), which
  changes how it cuts the loop's curves by at most the lag's reach, v·τ ≤ 3.5 cm/s · 50 ms = 1.75 mm (and
  0.19 rad/s · 50 ms = 0.5° of wrist turn), whatever the machine's load.
"""

from __future__ import annotations

import math
import os
import re
import subprocess
import sys
import threading
import time

import numpy as np
import pytest
from conftest import REPO, Server
from phone2act import Client
from phone2act.poses import quat_from_rpy
from phone2act_replay import align, load_episode, path_errors, pose_errors, replay, target_path_errors

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


FPS = 20.0
ATTEMPTS = 4


def lost_ticks(frames: int, elapsed_s: float) -> int:
    """Recorder ticks missing from an episode: a starved recorder thread drops late ticks and writes the next
    frame at the next index, which compresses the dataset's time axis (frame i is no longer at i/fps)."""
    return max(0, round(elapsed_s * FPS) - frames - 2)  # 2 ticks of slack for start/stop latency


@pytest.fixture(scope="module")
def recorded(server: Server) -> int:
    with Client(server.target) as c:
        for _ in range(ATTEMPTS):
            c.episodes.start("trace a loop")
            t0 = time.monotonic()
            teleop_loop(c)
            ep, _ = c.episodes.stop_with_latency()
            elapsed = time.monotonic() - t0
            lost = lost_ticks(ep.length_frames, elapsed)
            print(f"\nrecorded {ep.length_frames} frames in {elapsed:.2f} s: ~{lost} ticks lost "
                  f"(held {ep.held_ticks}, paused {ep.paused_ticks})")
            if lost == 0:
                return int(ep.episode_index)
    pytest.fail(f"the recorder lost ticks in {ATTEMPTS} recordings in a row (machine overloaded?)")


def test_replay_reproduces_the_recorded_trajectory(server: Server, recorded: int) -> None:
    original = load_episode(server.root, recorded)
    assert original.task == "trace a loop" and len(original) >= 80
    ref = original.ee_pose()
    assert np.ptp(ref[:, 0]) > 0.01 or np.ptp(ref[:, 1]) > 0.01, "the teleop episode barely moved"
    with Client(server.target) as c:
        started: list[float] = []

        def start_recording() -> None:
            c.episodes.start("replay of trace a loop")
            started.append(time.monotonic())

        for _ in range(ATTEMPTS):
            r = replay(c, original, upsample=4, on_start=start_recording)
            saved = c.episodes.stop()
            lost = lost_ticks(saved.length_frames, time.monotonic() - started[-1])
            if lost == 0:
                break
            print(f"\nreplay recording: {saved.length_frames} frames, ~{lost} ticks lost (held {saved.held_ticks}, "
                  f"paused {saved.paused_ticks}); again")
        else:
            pytest.fail(f"the recorder lost ticks in {ATTEMPTS} replay recordings in a row")
    assert r.accepted.steps_skipped <= 1, r.accepted
    replayed = load_episode(server.root, int(saved.episode_index))
    new = replayed.ee_pose()
    moved = max(np.linalg.norm(ref[:, :3] - ref[0, :3], axis=1))
    # Along the path: every recorded pose lies on the replayed path and vice versa, orientation included.
    pos, ang = path_errors(ref, new)
    back_pos, back_ang = path_errors(new, ref)
    # In time: frame i against the replay's frame i + offset. Besides the motion this includes the jitter of
    # the recorder's tick (state sampled when the thread wakes, stamped i/fps), which grows with machine load.
    offset, aligned = align(ref, new)
    tpos, tang = pose_errors(ref, aligned)
    print(f"\nreplay of {len(original)} frames ({moved * 1e3:.1f} mm excursion): path error max "
          f"{max(pos.max(), back_pos.max()) * 1e3:.3f} mm / {math.degrees(max(ang.max(), back_ang.max())):.3f}°; "
          f"time-aligned (offset {offset:.2f} frames) max {tpos.max() * 1e3:.3f} mm / "
          f"{math.degrees(tang.max()):.3f}°, median {np.median(tpos) * 1e3:.3f} mm")
    # See the module docstring for why these bounds hold on a loaded 2-core machine.
    assert pos.max() < 2e-3 and back_pos.max() < 2e-3, f"path error {pos.max() * 1e3:.3f} / {back_pos.max() * 1e3:.3f} mm"
    assert math.degrees(max(ang.max(), back_ang.max())) < 1.0
    # The median frame's tick is on time to a few ms even under load: v·δ = 3.5 cm/s · 10 ms = 0.35 mm.
    assert np.median(tpos) < 1.5e-3 and math.degrees(np.median(tang)) < 1.0, "the replay's timing is off"
    # The executed targets are the recorded ones (the same action definition end to end): every target the
    # replay executed (its action column, once its chunk started) lies on the original's target path as the
    # replay resampled it, to float32 rounding. Timing does not enter: a late tick samples a later target.
    tpos, tang = target_path_errors(original.targets(), replayed.targets())
    print(f"executed targets: path error max {tpos.max() * 1e3:.4f} mm / {math.degrees(tang.max()):.4f}°")
    assert tpos.max() < 5e-5 and math.degrees(tang.max()) < 0.05


def test_command_line_replay(server: Server, recorded: int) -> None:
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(REPO / "clients" / "replay"), os.environ.get("PYTHONPATH", "")]))
    out = subprocess.run([sys.executable, "-m", "phone2act_replay", str(server.root), str(recorded), "--server",
                          server.target, "--record", "cli replay"], capture_output=True, text=True, timeout=120,
                         env=env, check=False)
    assert out.returncode == 0, out.stderr
    m = re.search(r"max target path error ([0-9.]+) mm, ([0-9.]+)°; max path error ([0-9.]+) mm, ([0-9.]+)°",
                  out.stdout)
    assert m, out.stdout
    # The bounds of test_replay_reproduces_the_recorded_trajectory, for the same reasons.
    assert float(m.group(1)) < 0.05 and float(m.group(2)) < 0.05, out.stdout
    assert float(m.group(3)) < 2.0 and float(m.group(4)) < 1.0, out.stdout


def test_a_replay_waits_while_the_operator_corrects_and_goes_on_after_the_hand_back(
    server: Server, recorded: int
) -> None:
    original = load_episode(server.root, recorded)
    chunk_started = threading.Event()
    operator_done: list[str] = []

    def operator() -> None:
        # A second client, as a phone is: it takes the arm 1 s into the replay's chunk, moves it 1 cm and hands
        # it back. 30 s covers a stalled machine's approach to the start pose.
        if not chunk_started.wait(30.0):
            return
        time.sleep(1.0)
        with Client(server.target) as phone, phone.teleop("main") as t:
            fb = t.wait_feedback(t.clutch(True, PHONE0))
            assert fb.arm_state.waiting_policy_id.startswith("replay:"), fb
            for i in range(1, 11):
                t.send((PHONE0[0], PHONE0[1] + 0.001 * i, PHONE0[2]), quat_from_rpy(0.0, 0.0, 0.0))
                time.sleep(0.02)
            t.wait_feedback(t.clutch(False))
            fb = t.wait_feedback(t.hand_back())
            operator_done.append(fb.error)

    helper = threading.Thread(target=operator, daemon=True)
    helper.start()
    with Client(server.target) as c:
        r = replay(c, original, upsample=4, on_start=chunk_started.set)
        helper.join(timeout=30.0)
        assert operator_done == [""], operator_done
        assert r.resumed == 1, r
        # The rest of the episode played after the hand-back: the arm ends where the original ended (its last
        # target, held 0.5 s; the sim's 50 ms lag settles within that), not where the operator left it.
        end = c.list_arms()[0].robot_from_ee
    last = original.ee_pose()[-1]
    gap_m = float(np.linalg.norm(np.array([end.position_m.x, end.position_m.y, end.position_m.z]) - last[:3]))
    print(f"\nreplay resumed after a correction; ends {gap_m * 1e3:.2f} mm from the original's end")
    assert gap_m < 2e-3, gap_m
