"""The GR00T adapter end to end: real phone2act server (sim arm) <-> adapter <-> stand-in GR00T server."""

from __future__ import annotations

import math
import os
import subprocess
import sys
import time

import numpy as np
import pytest
from conftest import REPO, SIM_ARM, Server, free_port, wait_until
from gr00t_standin import StandIn
from phone2act import IMAGE_RGB8, Client, pose_tuple
from phone2act_gr00t import ChunkShapeError, Embodiment, Gr00tAdapter, Gr00tClient, Gr00tTimeout, packb
from phone2act_gr00t.wire import unpackb

WEBCAM = """
[[cameras]]
name = "webcam"
kind = "test_pattern"
width = 64
height = 48
fps = 20
"""
SCALE = 0.0005  # golden single_arm values 0..79 -> at most 4 cm / 0.04 rad deltas
# Long enough that the chunk's first step is still current when it arrives, even on a loaded machine.
PERIOD = 0.15


@pytest.fixture(scope="module")
def gserver(make_server) -> Server:  # type: ignore[no-untyped-def]
    return make_server(arms=SIM_ARM, cameras=WEBCAM)


def open_adapter(c: Client, standin: StandIn, timeout_s: float = 2.0, silence_s: float = 1.0):  # type: ignore[no-untyped-def]
    session = c.policy_session(["main"], observation_rate_hz=20, image_encoding=IMAGE_RGB8, cameras=["webcam"],
                               policy_name="gr00t-n1.5", silence_timeout_s=silence_s)
    emb = Embodiment.so100(session.layouts["main"], camera="webcam", action_scale=SCALE)
    adapter = Gr00tAdapter(session, Gr00tClient(standin.endpoint, timeout_s=timeout_s), emb,
                           arm="main", step_period_s=PERIOD)
    return session, adapter


def test_adapter_drives_the_sim_arm_through_a_full_golden_chunk(gserver: Server) -> None:
    with StandIn() as standin, Client(gserver.target) as c:
        session, adapter = open_adapter(c, standin)
        with session:
            obs = session.next_observation()
            p0 = np.array(pose_tuple(obs.arms[0].robot_from_ee)[0])
            r = adapter.step(obs)
            # What GR00T received is a well-formed so100 request built from this observation.
            req = unpackb(standin.requests[-1])
            assert req["endpoint"] == "get_action"
            assert req["data"]["video.webcam"].shape == (1, 48, 64, 3)
            assert req["data"]["state.single_arm"].shape == (1, 5)
            np.testing.assert_allclose(req["data"]["state.single_arm"][0], obs.arms[0].state[:5])
            assert r.steps.shape == (16, 7)
            assert r.accepted.steps_scheduled + r.accepted.steps_skipped == 16
            assert r.accepted.steps_skipped == 0, r.accepted  # answered within the first step

            expected = p0 + SCALE * np.array([[5 * k, 5 * k + 1, 5 * k + 2] for k in range(16)])
            seen: set[int] = set()
            deadline = time.monotonic() + 16 * PERIOD + 1.0
            while time.monotonic() < deadline:
                target = np.array(pose_tuple(c.arm("main").robot_from_target)[0])
                err = np.linalg.norm(expected - target, axis=1)
                k = int(np.argmin(err))
                if err[k] < 1e-6:
                    seen.add(k)
                time.sleep(0.02)
            assert len(seen) >= 15 and 15 in seen, f"targets seen for steps {sorted(seen)}"
            final = expected[15]
            assert wait_until(lambda: math.dist(pose_tuple(c.arm("main").robot_from_ee)[0], final) < 2e-3, 3.0), (
                pose_tuple(c.arm("main").robot_from_ee)[0], final)
            arm = c.arm("main")
            assert arm.gripper_target == 0.0
            print(f"\nGR00T chunk: 16 steps, inference round trip {r.inference_s * 1e3:.1f} ms, final position "
                  f"error {math.dist(pose_tuple(arm.robot_from_ee)[0], final) * 1e3:.2f} mm")


def test_late_policy_is_reported_and_the_arm_holds(gserver: Server) -> None:
    with StandIn(delay_s=1.0) as standin, Client(gserver.target) as c:
        session, adapter = open_adapter(c, standin, timeout_s=0.3, silence_s=1.0)
        with session:
            before = c.arm("main")
            with pytest.raises(Gr00tTimeout, match=r"did not answer 'get_action' within 300 ms"):
                adapter.step()
            stats = adapter.run(max_consecutive_failures=2)
            assert stats.chunks == 0 and stats.timeouts + (1 if session.revoked else 0) >= 1
            assert "did not answer" in stats.last_error
            # The server's silence timeout takes the arm from the silent policy; it holds where it was.
            assert wait_until(lambda: session.revoked is not None, 3.0)
            assert "silent" in session.revoked.reason
            after = c.arm("main")
            assert after.commands_sent == before.commands_sent
            assert math.dist(pose_tuple(before.robot_from_ee)[0], pose_tuple(after.robot_from_ee)[0]) < 2e-4


def test_wrong_shape_answer_is_refused_before_anything_moves(gserver: Server) -> None:
    bad = packb({"action.single_arm": np.zeros((16, 4), np.float32),
                 "action.gripper": np.zeros((16, 1), np.float32)})
    with StandIn(action_bytes=bad) as standin, Client(gserver.target) as c:
        session, adapter = open_adapter(c, standin)
        with session:
            before = c.arm("main").commands_sent
            with pytest.raises(ChunkShapeError, match=r"action.single_arm has shape \(16, 4\); expected \(horizon, 5\)"):
                adapter.step()
            time.sleep(0.2)
            assert c.arm("main").commands_sent == before


def run_cli(*args: str) -> subprocess.CompletedProcess[str]:
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(REPO / "clients" / "gr00t"), os.environ.get("PYTHONPATH", "")]))
    return subprocess.run([sys.executable, "-m", "phone2act_gr00t", *args], capture_output=True, text=True,
                          timeout=60, env=env, check=False)


def test_command_line_adapter(gserver: Server) -> None:
    with StandIn() as standin:
        out = run_cli("--server", gserver.target, "--gr00t", standin.endpoint, "--config", "so100",
                      "--camera", "webcam", "--so100-action-scale", "0.0002", "--step-period", "0.15", "--chunks", "2")
        assert out.returncode == 0, out.stderr
        assert "chunks 2, timeouts 0, errors 0" in out.stdout, out.stdout + out.stderr
        assert sum(1 for r in standin.requests if b"get_action" in r) == 2
    dead = f"tcp://127.0.0.1:{free_port()}"
    out = run_cli("--server", gserver.target, "--gr00t", dead, "--timeout", "0.3")
    assert out.returncode == 2 and f"GR00T server at {dead} did not answer 'ping' within 300 ms" in out.stderr
