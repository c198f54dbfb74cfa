"""The GR00T adapter end to end: real phone2act server (sim arms) <-> adapter <-> stand-in GR00T servers.

N1.5 (golden bytes and a live stand-in), N1.6, N1.7 (GR00T's ReplayPolicy server, both codecs), absolute and delta arms, a bimanual embodiment, the task
instruction, and the errors a user sees from the command line (late policy, pickle-era server, wrong dialect).
"""

from __future__ import annotations

import math
import os
import subprocess
import sys
import time

import numpy as np
import pytest
from conftest import REPO, SIM_ARM, Server, free_port, wait_until
from gr00t_standin import PolicyStandIn, ReplayStandIn, StandIn
from phone2act import ABSOLUTE_EE, DELTA_EE, IMAGE_RGB8, Client, Phone2ActError, pose_tuple
from phone2act.v1 import common_pb2
from phone2act_gr00t import (
    MSGPACK_NUMPY,
    N15,
    N16,
    N17,
    NPY,
    ChunkShapeError,
    Embodiment,
    Gr00tAdapter,
    Gr00tClient,
    Gr00tProtocolError,
    Gr00tTimeout,
    MissingTaskError,
    packb,
)
from phone2act_gr00t.wire import unpackb

WEBCAM = """
[[cameras]]
name = "webcam"
kind = "test_pattern"
width = 64
height = 48
fps = 20
"""
ABSOLUTE_ARM = """
[[arms]]
name = "main"
bridge = "sim"
action_mode = "absolute"
"""
TWO_ARMS = """
[[arms]]
name = "left"
bridge = "sim"

[[arms]]
name = "right"
bridge = "sim"
"""
SCALE = 0.0005  # golden single_arm values 0..79 -> at most 4 cm / 0.04 rad deltas
# Long enough that the chunk's first step is still current when it arrives, even on a loaded machine: inference
# on a loopback stand-in takes a few ms, a loaded 2-core machine adds tens of ms, and 150 ms leaves room.
PERIOD = 0.15
STEP_M = 0.001  # the stand-in policies move 1 mm per step: 16 mm per chunk, far below the jump threshold
TASK = "pick the red cube"


@pytest.fixture(scope="module")
def gserver(make_server) -> Server:  # type: ignore[no-untyped-def]
    return make_server(arms=SIM_ARM, cameras=WEBCAM)


def open_adapter(c: Client, standin: StandIn, timeout_s: float = 2.0, silence_s: float = 1.0):  # type: ignore[no-untyped-def]
    session = c.policy_session(["main"], observation_rate_hz=20, image_encoding=IMAGE_RGB8, cameras=["webcam"],
                               policy_name="gr00t-n1.5", silence_timeout_s=silence_s)
    emb = Embodiment.so100(session.layouts["main"], camera="webcam", action_scale=SCALE)
    adapter = Gr00tAdapter(session, Gr00tClient(standin.endpoint, timeout_s=timeout_s), emb, task=TASK,
                           step_period_s=PERIOD)
    return session, adapter


def position(c: Client, arm: str) -> np.ndarray:
    return np.array(pose_tuple(c.arm(arm).robot_from_ee)[0])


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
            assert req["data"]["annotation.human.task_description"] == [TASK]
            np.testing.assert_allclose(req["data"]["state.single_arm"][0], obs.arms[0].state[:5])
            assert r.modes == {"main": DELTA_EE}  # the server's default arm takes deltas
            assert r.steps["main"].shape == (16, 7)
            acc = r.accepted["main"]
            assert acc.steps_scheduled + acc.steps_skipped == 16
            # Steps are anchored at the observation's time: an answer that comes back after step k's time (a loaded
            # machine) skips steps 0..k, never plays them late. How many is timing; that none of them runs is not.
            assert acc.steps_scheduled >= 1, acc

            expected = p0 + SCALE * np.array([[5 * k, 5 * k + 1, 5 * k + 2] for k in range(16)])
            seen: set[int] = set()
            # 16 steps of PERIOD plus 1 s: the executor plays on the server's clock, the poll only watches.
            deadline = time.monotonic() + 16 * PERIOD + 1.0
            while time.monotonic() < deadline:
                target = np.array(pose_tuple(c.arm("main").robot_from_target)[0])
                err = np.linalg.norm(expected - target, axis=1)
                k = int(np.argmin(err))
                if err[k] < 1e-6:
                    seen.add(k)
                time.sleep(0.02)
            # The poll samples the target every 20 ms and may miss a step on a stalled machine, so it checks what
            # cannot depend on timing: the last step is commanded and no skipped step ever is.
            assert 15 in seen and min(seen) >= acc.steps_skipped, (f"targets seen for steps {sorted(seen)}, "
                                                                   f"{acc.steps_skipped} skipped")
            final = expected[15]
            # 3 s for the sim arm to settle within 2 mm of its last target (it tracks in well under a second).
            assert wait_until(lambda: math.dist(position(c, "main"), final) < 2e-3, 3.0), (position(c, "main"), final)
            print(f"\nGR00T chunk: 16 steps, inference round trip {r.inference_s * 1e3:.1f} ms, final position "
                  f"error {math.dist(position(c, 'main'), final) * 1e3:.2f} mm")


def test_absolute_arm_follows_n16_absolute_targets(make_server) -> None:  # type: ignore[no-untyped-def]
    """An arm configured for absolute actions gets its chunk in absolute mode (delta mode would be refused)."""
    server = make_server(arms=ABSOLUTE_ARM, cameras=WEBCAM)
    with PolicyStandIn(N16, video=("webcam",)) as standin, Client(server.target) as c:
        with c.policy_session(["main"], observation_rate_hz=20, image_encoding=IMAGE_RGB8, cameras=["webcam"],
                              policy_name="gr00t-n1.6") as session:
            layout = session.layouts["main"]
            client = Gr00tClient(standin.endpoint, timeout_s=2.0)
            wire, config = client.detect_wire()
            assert wire == N16
            emb = Embodiment.phone2act(layout, ["webcam"]).check_against(config, wire)
            arm_state = layout.state_names[:-1]

            def policy(state: dict[str, np.ndarray], task: str) -> dict[str, np.ndarray]:
                # A model trained on absolute targets: hold the pose it sees, walk +x 1 mm per step.
                now = {n: state["arm"][i] for i, n in enumerate(arm_state)}
                pose = np.array([now[f"ee_{n}"] for n in layout.action_names[:-1]])
                steps = np.repeat(pose[None], 16, axis=0)
                steps[:, 0] += STEP_M * np.arange(1, 17)
                return {"arm": steps, "gripper": np.zeros((16, 1))}

            standin.policy = policy
            adapter = Gr00tAdapter(session, client, emb, wire=N16, task=TASK, step_period_s=PERIOD)
            obs = session.next_observation()
            p0 = np.array(pose_tuple(obs.arms[0].robot_from_ee)[0])
            r = adapter.step(obs)
            assert r.modes == {"main": ABSOLUTE_EE}
            assert r.accepted["main"].steps_scheduled + r.accepted["main"].steps_skipped == 16
            np.testing.assert_allclose(r.steps["main"][-1, 0], p0[0] + 16 * STEP_M, atol=1e-5)
            final = p0 + [16 * STEP_M, 0, 0]
            # 16 steps of PERIOD, then 3 s for the sim arm to settle within 2 mm (it tracks in well under 1 s).
            assert wait_until(lambda: math.dist(position(c, "main"), final) < 2e-3, 16 * PERIOD + 3.0), (
                position(c, "main"), final)
            assert c.arm("main").commands_rejected == 0
            assert standin.observations[-1][1] == TASK


def test_bimanual_embodiment_drives_each_arm_with_its_own_groups(make_server) -> None:  # type: ignore[no-untyped-def]
    server = make_server(arms=TWO_ARMS)
    keys = ("left_arm", "left_gripper", "right_arm", "right_gripper")
    ramp = STEP_M * np.arange(1, 17)[:, None]

    def policy(state: dict[str, np.ndarray], task: str) -> dict[str, np.ndarray]:
        # Deltas: left walks +x, right walks +y, so a swapped mapping shows.
        left, right = np.zeros((16, 6)), np.zeros((16, 6))
        left[:, 0:1], right[:, 1:2] = ramp, ramp
        return {"left_arm": left, "right_arm": right, "left_gripper": np.zeros((16, 1)),
                "right_gripper": np.zeros((16, 1))}

    with PolicyStandIn(N15, state=keys, action=keys, policy=policy) as standin, \
            Client(server.target) as c:
        with c.policy_session(["left", "right"], observation_rate_hz=20, policy_name="gr00t-n1.5") as session:
            client = Gr00tClient(standin.endpoint, timeout_s=2.0)
            wire, config = client.detect_wire()
            assert wire == N15
            emb = Embodiment.phone2act([session.layouts["left"], session.layouts["right"]]).check_against(config, wire)
            adapter = Gr00tAdapter(session, client, emb, wire=wire, task="hand over", step_period_s=PERIOD)
            obs = session.next_observation()
            start = {a.arm: np.array(pose_tuple(a.robot_from_ee)[0]) for a in obs.arms}
            r = adapter.step(obs)
            assert set(r.accepted) == {"left", "right"} and r.modes == {"left": DELTA_EE, "right": DELTA_EE}
            req = standin.decoded[-1]["data"]
            assert list(req) == [f"state.{k}" for k in keys] + ["annotation.human.task_description"]
            left_state = {a.arm: a for a in obs.arms}["left"].state
            np.testing.assert_allclose(req["state.left_arm"][0], left_state[:-1])
            targets = {"left": start["left"] + [16 * STEP_M, 0, 0], "right": start["right"] + [0, 16 * STEP_M, 0]}
            # 16 steps of PERIOD, then 3 s for the sim arms to settle within 2 mm.
            for arm, final in targets.items():
                assert wait_until(lambda a=arm, f=final: math.dist(position(c, a), f) < 2e-3, 16 * PERIOD + 3.0), (
                    arm, position(c, arm), final)


def test_operator_taking_one_arm_stops_the_other_arm_too(make_server) -> None:  # type: ignore[no-untyped-def]
    """A bimanual chunk refused for one arm (the operator took it from a phone) releases the other arm as well."""
    server = make_server(arms=TWO_ARMS)
    keys = ("left_arm", "left_gripper", "right_arm", "right_gripper")

    def policy(state: dict[str, np.ndarray], task: str) -> dict[str, np.ndarray]:
        walk = np.zeros((16, 6))
        walk[:, 0] = STEP_M * np.arange(1, 17)
        return {"left_arm": walk, "right_arm": walk, "left_gripper": np.zeros((16, 1)),
                "right_gripper": np.zeros((16, 1))}

    with PolicyStandIn(N15, state=keys, action=keys, policy=policy) as standin, Client(server.target) as c:
        with c.policy_session(["left", "right"], observation_rate_hz=20, policy_name="gr00t-n1.5") as session:
            emb = Embodiment.phone2act([session.layouts["left"], session.layouts["right"]])
            adapter = Gr00tAdapter(session, Gr00tClient(standin.endpoint, timeout_s=2.0), emb, task="hand over",
                                   step_period_s=PERIOD)
            with c.teleop("right", take_over=True) as phone:
                phone.wait_feedback(phone.clutch(True, (0.0, 0.0, 0.0)))
                # The policy waits for a hand-back on the right arm (it is not revoked).
                assert wait_until(lambda: c.arm("right").waiting_policy_id.startswith("gr00t-n1.5:"), 3.0)
                obs = session.next_observation()
                left0 = np.array(pose_tuple({a.arm: a for a in obs.arms}["left"].robot_from_ee)[0])
                with pytest.raises(Phone2ActError):
                    adapter.step(obs)
                # Left was given its chunk just before right's was refused; the release follows within one gRPC
                # round trip (ms, under 100 ms loaded), so at most the first 1 mm step of 150 ms can have played.
                time.sleep(16 * PERIOD + 0.5)
                moved_mm = math.dist(position(c, "left"), left0) * 1e3
                assert moved_mm < 2.5, f"left arm moved {moved_mm:.1f} mm of its 16 mm chunk"
                assert c.arm("left").owner != common_pb2.CONTROL_SOURCE_POLICY


def test_instruction_is_the_task_flag_else_the_episode_task(gserver: Server) -> None:
    with PolicyStandIn(N16, video=("webcam",)) as standin, Client(gserver.target) as c:
        with c.policy_session(["main"], observation_rate_hz=20, image_encoding=IMAGE_RGB8, cameras=["webcam"],
                              policy_name="gr00t") as session:
            emb = Embodiment.phone2act(session.layouts["main"], ["webcam"])
            adapter = Gr00tAdapter(session, Gr00tClient(standin.endpoint, timeout_s=2.0), emb, wire=N16,
                                   step_period_s=PERIOD)
            # Outside a recording there is no task: nothing is asked, nothing is pushed.
            before = c.arm("main").commands_sent
            with pytest.raises(MissingTaskError, match="no task instruction: pass --task"):
                adapter.step()
            assert standin.observations == []
            assert c.arm("main").commands_sent == before
            c.episodes.start("stack the cubes")
            try:
                assert wait_until(lambda: session.next_observation().task == "stack the cubes", 3.0)
                adapter.step()
                assert standin.observations[-1][1] == "stack the cubes"
                adapter.task = "open the drawer"  # --task wins over the episode's task
                adapter.step()
                assert standin.observations[-1][1] == "open the drawer"
            finally:
                c.episodes.discard()


def test_the_loop_waits_through_a_take_over_and_drives_again_after_the_hand_back(gserver: Server) -> None:
    import threading

    with StandIn() as standin, Client(gserver.target) as c:
        session, adapter = open_adapter(c, standin, silence_s=5.0)
        with session:
            stop = threading.Event()
            loop = threading.Thread(target=adapter.run, kwargs={"should_stop": stop.is_set})
            loop.start()
            try:
                # The adapter's first chunk within an inference and a push; 10 s covers a stalled machine.
                assert wait_until(lambda: adapter.stats.chunks >= 1, 10.0)
                with c.teleop("main", take_over=True) as phone:
                    phone.wait_feedback(phone.clutch(True, (0.0, 0.0, 0.0)))
                    # Refused while the operator drives: the loop keeps asking instead of ending.
                    assert wait_until(lambda: adapter.stats.waiting >= 2, 10.0)
                    assert loop.is_alive() and session.revoked is None
                    chunks = adapter.stats.chunks
                    fb = phone.wait_feedback(phone.hand_back())
                    assert not fb.error and fb.arm_state.owner == common_pb2.CONTROL_SOURCE_POLICY
                    # The next chunk answers a fresh observation and drives.
                    assert wait_until(lambda: adapter.stats.chunks > chunks, 10.0)
                    assert c.arm("main").owner == common_pb2.CONTROL_SOURCE_POLICY
            finally:
                stop.set()
                loop.join(10.0)
            assert adapter.stats.errors == 0, adapter.stats.last_error
        # The server is shared: leave its arm at rest (the released arm reaches its last target within a few
        # bridge periods; 10 s covers a stalled machine).
        last = [position(c, "main")]

        def at_rest() -> bool:
            time.sleep(0.1)
            now = position(c, "main")
            still = math.dist(now, last[0]) < 1e-5
            last[0] = now
            return still

        assert wait_until(at_rest, 10.0)


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
            with pytest.raises(ChunkShapeError, match=r"action single_arm has shape \(16, 4\); expected \(horizon, 5\)"):
                adapter.step()
            time.sleep(0.2)
            assert c.arm("main").commands_sent == before


def test_a_shape_refusal_stops_the_loop_at_once(gserver: Server) -> None:
    """The model's shape is the same at every step: asking again until the failure limit only repeats the error."""
    bad = packb({"action.single_arm": np.zeros((16, 4), np.float32),
                 "action.gripper": np.zeros((16, 1), np.float32)})
    with StandIn(action_bytes=bad) as standin, Client(gserver.target) as c:
        session, adapter = open_adapter(c, standin)
        with session, pytest.raises(ChunkShapeError, match=r"expected \(horizon, 5\)"):
            adapter.run(max_chunks=3)
        assert adapter.stats.chunks == 0 and adapter.stats.errors == 1
        assert sum(b"get_action" in r for r in standin.requests) == 1


def test_wrong_dialect_stops_with_advice_and_nothing_moves(gserver: Server) -> None:
    with PolicyStandIn(N16, video=("webcam",), state=("single_arm", "gripper"),
                       action=("single_arm", "gripper")) as standin, Client(gserver.target) as c:
        session, adapter = open_adapter(c, standin)  # adapter speaks N1.5 to an N1.6 server
        with session:
            before = c.arm("main").commands_sent
            with pytest.raises(Gr00tProtocolError, match=r"unexpected keyword argument 'video.webcam'.*speaks N1.6"):
                adapter.run(max_chunks=3)
            assert adapter.stats.chunks == 0 and adapter.stats.errors == 1  # one try, no retry loop
            assert c.arm("main").commands_sent == before


def test_n16_sim_wrapper_server_gets_advice(gserver: Server) -> None:
    with PolicyStandIn("n1.6-sim", video=("webcam",), state=("single_arm", "gripper"),
                       action=("single_arm", "gripper")) as standin, Client(gserver.target) as c:
        session, adapter = open_adapter(c, standin)
        adapter.wire = N16
        with session, pytest.raises(Gr00tProtocolError, match="run with --gr00t-version n1.6-sim"):
            adapter.step()
        out = run_cli("--server", gserver.target, "--gr00t", standin.endpoint, "--gr00t-version", "n1.6-sim",
                      "--config", "so100", "--camera", "webcam", "--so100-action-scale", "0.0002",
                      "--step-period", "0.15", "--chunks", "1", "--task", TASK)
        assert out.returncode == 0 and "chunks 1, timeouts 0, errors 0" in out.stdout, out.stdout + out.stderr


def run_cli(*args: str) -> subprocess.CompletedProcess[str]:
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(REPO / "clients" / "gr00t"), os.environ.get("PYTHONPATH", "")]))
    return subprocess.run([sys.executable, "-m", "phone2act_gr00t", *args], capture_output=True, text=True,
                          timeout=60, env=env, check=False)


def test_command_line_adapter(gserver: Server) -> None:
    with StandIn() as standin:
        out = run_cli("--server", gserver.target, "--gr00t", standin.endpoint, "--config", "so100",
                      "--camera", "webcam", "--so100-action-scale", "0.0002", "--step-period", "0.15", "--chunks", "2",
                      "--task", TASK)
        assert out.returncode == 0, out.stderr
        assert "chunks 2, timeouts 0, errors 0" in out.stdout, out.stdout + out.stderr
        assert "speaks n1.5" in out.stderr  # detected: ping answers, get_modality_config does not exist
        actions = [unpackb(r) for r in standin.requests if b"get_action" in r]
        assert len(actions) == 2 and all(a["data"]["annotation.human.task_description"] == [TASK] for a in actions)
    dead = f"tcp://127.0.0.1:{free_port()}"
    out = run_cli("--server", gserver.target, "--gr00t", dead, "--timeout", "0.3")
    assert out.returncode == 2 and f"GR00T server at {dead} did not answer 'ping' within 300 ms" in out.stderr


def test_command_line_n16_detected(gserver: Server) -> None:
    with PolicyStandIn(N16, video=("webcam",)) as standin:
        out = run_cli("--server", gserver.target, "--gr00t", standin.endpoint, "--camera", "webcam",
                      "--step-period", "0.15", "--chunks", "2", "--task", "wave")
        assert out.returncode == 0, out.stderr
        assert "chunks 2, timeouts 0, errors 0" in out.stdout and "speaks n1.6" in out.stderr
        assert [t for _, t in standin.observations] == ["wave", "wave"]


@pytest.mark.parametrize("stream", [False, True])
def test_command_line_names_a_pickle_era_server(gserver: Server, stream: bool) -> None:
    with PolicyStandIn("pickle", stream=stream) as standin:
        out = run_cli("--server", gserver.target, "--gr00t", standin.endpoint, "--task", TASK)
    assert out.returncode == 2, out.stdout + out.stderr
    assert "this GR00T server uses the pre-2025-09-10 pickle wire format" in out.stderr
    assert ("Upgrade it to GR00T N1.5 (tag n1.5-release, 4af2b62), N1.6 (release commit 4e62473) or N1.7 (tag "
            "n1.7-release 23ace64, and main 626af89 (msgpack-numpy))") in out.stderr
    assert "Traceback" not in out.stderr and "ExtraData" not in out.stderr


def test_command_line_names_a_june_2025_server(gserver: Server) -> None:
    with PolicyStandIn("pickle-june") as standin:
        out = run_cli("--server", gserver.target, "--gr00t", standin.endpoint, "--task", TASK)
    assert out.returncode == 2, out.stdout + out.stderr
    assert 'bare b"ERROR"' in out.stderr and "pre-2025-09-10 pickle wire format" in out.stderr, out.stderr
    assert "Traceback" not in out.stderr and "not a GR00T msgpack message" not in out.stderr


def test_command_line_forced_version_the_server_contradicts(gserver: Server) -> None:
    with PolicyStandIn(N15, video=("webcam",)) as standin:
        out = run_cli("--server", gserver.target, "--gr00t", standin.endpoint, "--gr00t-version", "n1.6",
                      "--camera", "webcam", "--task", TASK, "--chunks", "1")
    assert out.returncode == 2, out.stdout + out.stderr
    assert "--gr00t-version n1.6 does not match" in out.stderr and "The version is the mistake" in out.stderr
    # Not the embodiment check's prefixed keys, which read as a wrong --config.
    assert "the adapter sends" not in out.stderr and standin.observations == []


def test_command_line_errors_are_sentences(gserver: Server) -> None:
    with PolicyStandIn(N16, video=("webcam",), state=("single_arm", "gripper"),
                       action=("single_arm", "gripper")) as standin:
        # Forced to N1.5 against an N1.6 server: the server's own complaint, and what to do.
        out = run_cli("--server", gserver.target, "--gr00t", standin.endpoint, "--gr00t-version", "n1.5",
                      "--config", "so100", "--camera", "webcam", "--task", TASK, "--chunks", "1")
        assert out.returncode == 2 and "run with --gr00t-version n1.6" in out.stderr, out.stderr
        # The model's keys differ from the phone2act embodiment's: named before anything is asked.
        out = run_cli("--server", gserver.target, "--gr00t", standin.endpoint, "--camera", "webcam", "--task", TASK)
        assert out.returncode == 2 and "state keys ['gripper', 'single_arm'] (the adapter sends" in out.stderr
    with PolicyStandIn(N15, video=("webcam",)) as standin:
        out = run_cli("--server", gserver.target, "--gr00t", standin.endpoint, "--camera", "webcam", "--chunks", "1")
        assert out.returncode == 1 and "no task instruction: pass --task" in out.stderr, out.stderr
        assert standin.observations == []
        assert "Traceback" not in out.stderr


# --- N1.7: GR00T's PolicyServer serving ReplayPolicy, the tag's codec and main's ------------------------------------

# A recorded 40-step so100 episode of relative actions as ReplayPolicy would load it: within each 16-step chunk the
# arm moves 1 mm a step from the observation (2 * SCALE), and each chunk is offset by its index (0.5 mm), so that
# which chunk arrived shows in the values while no step jumps past the gate's jump filter.
REPLAYED = {
    "single_arm": np.array([[2 * (k % 16) + k // 16 + 0.1 * j for j in range(5)] for k in range(40)], np.float32),
    "gripper": np.zeros((40, 1), np.float32),
}


@pytest.mark.parametrize("codec", [NPY, MSGPACK_NUMPY])
def test_n17_replay_server_drives_the_sim_arm_chunk_after_chunk(gserver: Server, codec: str) -> None:
    """Both N1.7 builds (the n1.7-release tag: N1.6's wire; main: msgpack-numpy) replay a recorded episode
    into the sim arm through the real phone2act server: detected, then two chunks, each the episode's next 16
    steps, the second one played to its last target."""
    with ReplayStandIn([REPLAYED], codec=codec) as standin, Client(gserver.target) as c:
        client = Gr00tClient(standin.endpoint, timeout_s=2.0)
        wire, config = client.detect_wire()
        assert (wire, client.codec) == ((N16, NPY) if codec == NPY else (N17, MSGPACK_NUMPY))
        with c.policy_session(["main"], observation_rate_hz=20, image_encoding=IMAGE_RGB8, cameras=["webcam"],
                              policy_name=f"gr00t-{wire}") as session:
            emb = Embodiment.so100(session.layouts["main"], camera="webcam", action_scale=SCALE)
            adapter = Gr00tAdapter(session, client, emb.check_against(config, wire), wire=wire, task=TASK,
                                   step_period_s=PERIOD)
            first = adapter.step()
            np.testing.assert_allclose(first.steps["main"][:, :5], REPLAYED["single_arm"][:16] * SCALE, atol=1e-9)
            obs = session.next_observation()
            p0 = np.array(pose_tuple(obs.arms[0].robot_from_ee)[0])
            second = adapter.step(obs)
            np.testing.assert_allclose(second.steps["main"][:, :5], REPLAYED["single_arm"][16:32] * SCALE,
                                       atol=1e-9)
            assert [i["current_step"] for i in standin.infos] == [0, 16]
            # What the server validated is the observation phone2act sent: batched, float32, one frame.
            sent = standin.observations[-1]
            assert sent["video"]["webcam"].shape == (1, 1, 48, 64, 3)
            np.testing.assert_allclose(sent["state"]["single_arm"][0, 0], obs.arms[0].state[:5], rtol=1e-6)
            assert sent["language"] == {"annotation.human.task_description": [[TASK]]}
            final = p0 + SCALE * REPLAYED["single_arm"][31, :3]
            # The chunk's 16 steps of PERIOD, then 3 s for the sim arm to settle within 2 mm of its last target (it
            # tracks in well under a second; the margin is for a loaded 2-core machine).
            assert wait_until(lambda: math.dist(position(c, "main"), final) < 2e-3, 16 * PERIOD + 3.0), (
                position(c, "main"), final)
        client.close()


def test_n17_command_line_detects_the_msgpack_numpy_build(gserver: Server) -> None:
    with ReplayStandIn([REPLAYED], codec=MSGPACK_NUMPY) as standin:
        out = run_cli("--server", gserver.target, "--gr00t", standin.endpoint, "--config", "so100",
                      "--camera", "webcam", "--step-period", "0.15", "--chunks", "2", "--task", TASK)
        assert out.returncode == 0, out.stderr
        assert "chunks 2, timeouts 0, errors 0" in out.stdout
        assert "speaks n1.7 (msgpack-numpy arrays)" in out.stderr, out.stderr
        assert [i["current_step"] for i in standin.infos] == [0, 16]
        # Forced to the other codec: the server's own refusal, and what to run instead.
        out = run_cli("--server", gserver.target, "--gr00t", standin.endpoint, "--config", "so100",
                      "--gr00t-codec", "npy", "--camera", "webcam", "--chunks", "1", "--task", TASK)
        assert out.returncode == 2, out.stdout + out.stderr
        assert "Got <class 'dict'>" in out.stderr and "run with --gr00t-codec msgpack-numpy" in out.stderr
