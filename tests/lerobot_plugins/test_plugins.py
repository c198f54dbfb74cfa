"""The LeRobot plugins against a real phone2act server, with lerobot 0.6.1's own discovery and scripts.

Bounds on a loaded 2-core machine: the sim arm follows its target with a 50 ms first-order lag, so a target
is reached to 1 mm within ~0.35 s (7 time constants); waits allow 5 s because the server, the status stream
and this process can each be descheduled for hundreds of milliseconds under parallel builds. Positions are
compared at 2 mm: the sim has no noise, so a settled arm sits on its target to well under that.
"""

from __future__ import annotations

import math
import shutil
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest
from conftest import REPO, Server, wait_until
from phone2act import Client, FailedPrecondition
from phone2act.v1 import common_pb2, policy_pb2

sys.path.insert(0, str(REPO / "clients" / "replay"))
from phone2act_replay import load_episode, path_errors, target_path_errors

sys.path.insert(0, str(REPO / "benchmarks" / "closed_loop"))
from lerobot_async import PolicyServer, RobotClient, robot_client_command

SETTLE_S = 5.0
FPS = 20
PHONE0 = (0.0, 1.2, -0.3)
EE = ("ee_x", "ee_y", "ee_z", "ee_r00", "ee_r10", "ee_r20", "ee_r01", "ee_r11", "ee_r21", "gripper")


def robot_config(server: Server, **kw):
    from lerobot_robot_phone2act import Phone2ActRobotConfig

    return Phone2ActRobotConfig(server=server.target, fps=FPS, **kw)


def make_robot(server: Server, **kw):
    from lerobot.robots.utils import make_robot_from_config

    return make_robot_from_config(robot_config(server, **kw))


def hold_action(obs: dict) -> dict[str, float]:
    """The absolute action that holds the measured pose: the observation's end-effector columns."""
    from lerobot_robot_phone2act import ABSOLUTE_EE_NAMES

    return {a: float(obs[e]) for a, e in zip(ABSOLUTE_EE_NAMES, EE, strict=True)}


def position(obs: dict) -> np.ndarray:
    return np.array([obs["ee_x"], obs["ee_y"], obs["ee_z"]])


def test_lerobot_discovers_both_plugins(server: Server) -> None:
    """A fresh interpreter that never imports the plugins: lerobot's own discovery registers both types."""
    code = f"""
from lerobot.utils.import_utils import register_third_party_plugins
from lerobot.robots.config import RobotConfig
from lerobot.robots.utils import make_robot_from_config
from lerobot.teleoperators.config import TeleoperatorConfig
from lerobot.teleoperators.utils import make_teleoperator_from_config
register_third_party_plugins()
robot = make_robot_from_config(RobotConfig.get_choice_class("phone2act")(server="{server.target}"))
teleop = make_teleoperator_from_config(TeleoperatorConfig.get_choice_class("phone2act")(server="{server.target}"))
print(type(robot).__module__, type(robot).__name__, type(teleop).__module__, type(teleop).__name__)
print(sorted(robot.action_features), sorted(robot.observation_features["front"]))
"""
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120, check=False)
    assert out.returncode == 0, out.stderr
    first, second = out.stdout.splitlines()[-2:]
    robot_mod, robot_cls, teleop_mod, teleop_cls = first.split()
    assert (robot_mod.split(".")[0], robot_cls) == ("lerobot_robot_phone2act", "Phone2ActRobot"), first
    assert (teleop_mod.split(".")[0], teleop_cls) == ("lerobot_teleoperator_phone2act", "Phone2ActTeleop"), first
    assert "'gripper'" in second and "'r21'" in second and "[3, 48, 64]" in second, second


def test_observation_has_the_declared_features(server: Server) -> None:
    robot = make_robot(server)
    with Client(server.target) as c:
        reported = c.observe(arms=["main"]).arms[0]
    features = robot.observation_features
    # What the server reports, in its order: the state vector's names, then the camera at its configured size.
    assert list(features) == [*reported.state_names, "front"]
    assert features["front"] == (48, 64, 3)
    # The sim arm is in the default `relative` mode; LeRobot policies output the recorded absolute layout.
    assert reported.action_names[0] == "delta_x"
    assert list(robot.action_features) == ["x", "y", "z", "r00", "r10", "r20", "r01", "r11", "r21", "gripper"]
    assert robot.action_mode == policy_pb2.ACTION_MODE_ABSOLUTE_EE
    with robot:
        obs = robot.get_observation()
        assert set(obs) == set(features)
        for name in reported.state_names:
            assert isinstance(obs[name], float) and math.isfinite(obs[name]), name
        img = obs["front"]
        assert img.shape == (48, 64, 3) and img.dtype == np.uint8
        assert img.std() > 0, "the test pattern came back blank"
        with Client(server.target) as c:
            state = c.arm("main")
        assert np.allclose(position(obs), [state.robot_from_ee.position_m.x, state.robot_from_ee.position_m.y,
                                           state.robot_from_ee.position_m.z], atol=2e-3)
    assert not robot.is_connected


def test_unknown_camera_and_arm_are_refused(server: Server) -> None:
    with pytest.raises(ValueError, match="no camera"):
        _ = make_robot(server, camera_names=["nope"]).observation_features
    with pytest.raises(LookupError, match="nope"):
        _ = make_robot(server, arm="nope").action_features


def test_send_action_moves_the_arm_through_the_gate(server: Server) -> None:
    with make_robot(server) as robot:
        obs = robot.get_observation()
        start = position(obs)
        base = hold_action(obs)
        dy = 0.03 if start[1] < 0.2 else -0.03  # stays inside the default workspace (|y| <= 0.25 m)
        for k in range(1, 7):  # 5 mm per step at 20 Hz: far below the 6 cm jump threshold
            robot.send_action(base | {"y": base["y"] + dy * k / 6})
            time.sleep(1.0 / FPS)
        goal = start + [0.0, dy, 0.0]
        assert wait_until(lambda: np.linalg.norm(position(robot.get_observation()) - goal) < 2e-3, SETTLE_S), (
            goal, position(robot.get_observation()))
        assert robot.refusals == ()

        # An absurd jump (20 cm in one step) is refused by the server's gate, reported, and the arm holds.
        jump = base | {"y": base["y"] + dy, "x": base["x"] + (0.2 if start[0] < 0.2 else -0.2)}
        robot.send_action(jump)
        assert wait_until(lambda: len(robot.refusals) > 0, SETTLE_S), "the gate's refusal was not reported"
        assert "jump" in robot.refusals[-1].reason, robot.refusals[-1]
        # 6 time constants of the sim's lag: the arm has settled on the held goal, and a jump that got through
        # (20 cm away) would show by now.
        time.sleep(0.3)
        assert np.linalg.norm(position(robot.get_observation()) - goal) < 1e-3

        # Malformed actions are refused before anything is sent.
        with pytest.raises(KeyError, match="gripper"):
            robot.send_action({k: v for k, v in base.items() if k != "gripper"})


def test_silence_holds_and_operator_takeover_stands(server: Server) -> None:
    with make_robot(server, silence_timeout_s=0.2) as robot:
        obs = robot.get_observation()
        robot.send_action(hold_action(obs))
        # Silent past its timeout (the reset phase of lerobot-record): the server revokes control, the arm holds,
        # and the next action claims the arm again.
        time.sleep(0.6)
        robot.send_action(hold_action(robot.get_observation()))
        with Client(server.target) as c:
            assert wait_until(lambda: c.arm("main").owner == common_pb2.CONTROL_SOURCE_POLICY, SETTLE_S)
            # The operator takes over with the phone: the robot's next action is refused, not forced through.
            with c.teleop("main", take_over=True) as t:
                t.wait_feedback(t.clutch(True, PHONE0))
                assert wait_until(lambda: c.arm("main").owner == common_pb2.CONTROL_SOURCE_TELEOP, SETTLE_S)
                with pytest.raises(FailedPrecondition):
                    robot.send_action(hold_action(robot.get_observation()))
                assert c.arm("main").owner == common_pb2.CONTROL_SOURCE_TELEOP
                t.wait_feedback(t.clutch(False))


def test_teleoperator_returns_the_phone_target(server: Server) -> None:
    from lerobot.teleoperators.utils import make_teleoperator_from_config
    from lerobot_teleoperator_phone2act import Phone2ActTeleopConfig

    teleop = make_teleoperator_from_config(Phone2ActTeleopConfig(server=server.target))
    with Client(server.target) as c, teleop, c.teleop("main") as phone:
        # The clutch re-indexes the target to the measured pose; the feedback carries the state after it.
        engaged = phone.wait_feedback(phone.clutch(True, PHONE0)).arm_state.robot_from_target.position_m
        before = {"x": engaged.x, "y": engaged.y, "z": engaged.z}
        for k in range(1, 31):  # the phone moves 3 cm to its right over 0.6 s
            phone.send([PHONE0[0] + 0.001 * k, PHONE0[1], PHONE0[2]])
            time.sleep(0.02)
        phone.wait_feedback(phone.send([PHONE0[0] + 0.03, PHONE0[1], PHONE0[2]]))

        def moved_3cm() -> bool:
            a = teleop.get_action()
            return abs(math.dist([a["x"], a["y"], a["z"]], [before["x"], before["y"], before["z"]]) - 0.03) < 1e-3

        # The target moves by the phone's motion (the default mapping has scale 1) ...
        assert wait_until(moved_3cm, SETTLE_S), (before, teleop.get_action())
        # ... and it is the target the arm goes to: the sim settles on it.
        a = teleop.get_action()

        def arm_on_target() -> bool:
            p = c.arm("main").robot_from_ee.position_m
            return math.dist([p.x, p.y, p.z], [a["x"], a["y"], a["z"]]) < 2e-3

        assert wait_until(arm_on_target, SETTLE_S)
        r = np.array([[a["r00"], a["r01"]], [a["r10"], a["r11"]], [a["r20"], a["r21"]]])
        assert np.allclose(r.T @ r, np.eye(2), atol=1e-9), "the 6D rotation is not two orthonormal columns"
        phone.wait_feedback(phone.clutch(False))


def teleop_loop(c: Client, seconds: float) -> None:
    """A phone tracing a closed loop (~3 cm/s) with a small wrist turn; ends where it started."""
    from phone2act.poses import quat_from_rpy

    with c.teleop("main") as t:
        t.wait_feedback(t.clutch(True, PHONE0))
        w = 2 * math.pi / seconds
        t0 = time.monotonic()
        while (now := time.monotonic() - t0) < seconds:
            p = (PHONE0[0] + 0.02 * math.sin(w * now), PHONE0[1] + 0.01 * (1 - math.cos(w * now)), PHONE0[2])
            t.send(p, quat_from_rpy(0.0, 0.0, 0.1 * math.sin(w * now)))
            time.sleep(0.02)
        time.sleep(0.3)
        t.wait_feedback(t.clutch(False))


def test_lerobot_replay_retraces_a_recorded_episode(server: Server, tmp_path: Path) -> None:
    """Record a teleoperated episode, replay its actions with lerobot's own `lerobot-replay` through the robot
    plugin while phone2act records the replay, and compare the two paths."""
    with Client(server.target) as c:
        c.episodes.start("trace a loop")
        teleop_loop(c, 4.0)
        original_info = c.episodes.stop()
        original = load_episode(server.root, int(original_info.episode_index))
        # lerobot reads a copy: the server keeps writing its dataset while it records the replay.
        copy = tmp_path / "dataset"
        shutil.copytree(server.root, copy)
        c.episodes.start("lerobot-replay of trace a loop")
        cmd = [
            str(Path(sys.executable).parent / "lerobot-replay"),
            "--robot.type=phone2act", f"--robot.server={server.target}", f"--robot.fps={FPS}",
            "--dataset.repo_id=local/phone2act", f"--dataset.root={copy}",
            f"--dataset.episode={original_info.episode_index}", f"--dataset.fps={FPS}", "--play_sounds=false",
        ]
        t0 = time.monotonic()
        out = subprocess.run(cmd, capture_output=True, text=True, timeout=300, check=False)
        took_s = time.monotonic() - t0
        time.sleep(0.5)  # the last target settles (10 time constants) before the recording stops
        replay_info = c.episodes.stop()
    assert out.returncode == 0, out.stderr[-4000:]
    replayed = load_episode(server.root, int(replay_info.episode_index))
    ref, new = original.ee_pose(), replayed.ee_pose()
    assert np.ptp(ref[:, :3], axis=0).max() > 0.01, "the teleop episode barely moved"
    # Executed targets: every target the replay executed lies on the original's target path (float32 rounding).
    tpos, tang = target_path_errors(original.targets(), replayed.targets())
    # Measured path: the sim's 50 ms lag cuts the loop's curves by at most v·τ = 3 cm/s · 50 ms = 1.5 mm in both
    # recordings, at different instants (50 Hz phone samples vs 20 Hz replay steps); a step held 50 ms
    # adds at most v/fps = 1.5 mm of staircase; the wrist turn (0.1 rad over a 4 s loop: ω ≤ 0.16 rad/s) likewise
    # at most ω·τ + ω/fps = 0.9°. Geometric, so a late tick or a stalled replay loop on a loaded machine does not
    # count: a held step only lets the arm settle on a target that lies on the path.
    pos, ang = path_errors(ref, new)
    back_pos, _ = path_errors(new, ref)
    print(f"\nlerobot-replay of {len(original)} frames took {took_s:.1f} s: target path error max "
          f"{tpos.max() * 1e3:.4f} mm / {math.degrees(tang.max()):.4f}°; measured path error max "
          f"{max(pos.max(), back_pos.max()) * 1e3:.3f} mm / {math.degrees(ang.max()):.3f}°")
    assert tpos.max() < 5e-5 and math.degrees(tang.max()) < 0.05
    assert pos.max() < 3e-3 and back_pos.max() < 3e-3
    assert math.degrees(ang.max()) < 1.2


TWO_ARMS = """
[[arms]]
name = "main"
bridge = "sim"

[[arms]]
name = "follower"
bridge = "sim"
"""


def test_lerobot_record_with_both_plugins(tmp_path: Path) -> None:
    """`lerobot-record` unchanged: a phone drives sim arm `main` (the teleoperator plugin reads its target), the
    robot plugin makes sim arm `follower` follow, and lerobot writes its own dataset, read back with lerobot."""
    from conftest import CAMERA, py_conftest
    from lerobot.datasets import LeRobotDataset
    from lerobot_robot_phone2act import ABSOLUTE_EE_NAMES

    srv = py_conftest.start_server(tmp_path / "srv", py_conftest.config_text(tmp_path / "srv" / "ds", TWO_ARMS, CAMERA))
    stop = threading.Event()
    try:
        with Client(srv.target) as c:
            follower_state_names = list(c.observe(arms=["follower"]).arms[0].state_names)

            def phone() -> None:  # 1.5 cm back and forth, 3 s period (≤ 3.1 cm/s), until lerobot-record is done
                with c.teleop("main") as t:
                    t.wait_feedback(t.clutch(True, PHONE0))
                    t0 = time.monotonic()
                    while not stop.is_set():
                        s = 0.015 * math.sin(2 * math.pi * (time.monotonic() - t0) / 3.0)
                        t.send([PHONE0[0] + s, PHONE0[1], PHONE0[2]])
                        time.sleep(0.02)
                    t.wait_feedback(t.clutch(False))

            th = threading.Thread(target=phone, daemon=True)
            th.start()
            root = tmp_path / "lerobot_ds"
            cmd = [
                str(Path(sys.executable).parent / "lerobot-record"),
                "--robot.type=phone2act", f"--robot.server={srv.target}", "--robot.arm=follower", f"--robot.fps={FPS}",
                "--teleop.type=phone2act", f"--teleop.server={srv.target}", "--teleop.arm=main",
                "--dataset.repo_id=local/phone2act_record", f"--dataset.root={root}", "--dataset.single_task=follow",
                f"--dataset.fps={FPS}", "--dataset.episode_time_s=4", "--dataset.reset_time_s=0",
                "--dataset.num_episodes=1", "--dataset.push_to_hub=false", "--play_sounds=false",
                "--display_data=false",
            ]
            out = subprocess.run(cmd, capture_output=True, text=True, timeout=600, check=False)
            stop.set()
            th.join(timeout=10)
    finally:
        stop.set()
        srv.stop()
    assert out.returncode == 0, out.stderr[-4000:]
    ds = LeRobotDataset("local/phone2act_record", root=root)
    assert ds.meta.features["observation.state"]["names"] == follower_state_names
    assert list(ds.meta.features["action"]["names"]) == list(ABSOLUTE_EE_NAMES)
    assert tuple(ds.meta.features["observation.images.front"]["shape"]) == (48, 64, 3)
    # lerobot's loop runs for episode_time_s at 20 Hz; a loaded machine slips iterations, never adds them.
    assert 10 <= ds.num_frames <= 4 * FPS + 2, ds.num_frames
    frame = ds[ds.num_frames // 2]
    assert tuple(frame["observation.images.front"].shape) == (3, 48, 64)  # decoded from lerobot's own video
    ep = load_episode(root, 0)
    targets, follower = ep.targets(), ep.ee_pose()
    assert np.ptp(targets[:, :3], axis=0).max() > 0.005, "the phone's motion did not reach the actions"
    # The follower went where the phone sent `main`: its measured path lies along the recorded targets within
    # the sim's lag (v·τ ≤ 3.1 cm/s · 50 ms = 1.6 mm) plus one 20 Hz step (v/fps = 1.6 mm), load-independent.
    pos, _ = path_errors(follower[5:], targets)
    print(f"\nlerobot-record: {ds.num_frames} frames; follower path vs phone targets max {pos.max() * 1e3:.2f} mm")
    assert pos.max() < 4e-3
    # ... and covered it (a follower that stayed put would also lie on that back-and-forth path): its excursion
    # matches the targets' within the same lag and step.
    reach_f, reach_t = np.ptp(follower[5:, :3], axis=0), np.ptp(targets[:, :3], axis=0)
    assert np.abs(reach_f - reach_t).max() < 3.2e-3, (reach_f, reach_t)


def random_act_policy(out: Path, state_dim: int, camera: str, image_hw: tuple[int, int], action_mean: list[float],
                      action_std: float) -> None:
    """A tiny ACT with random weights (no training) for the plugin's features, saved as lerobot saves a trained
    one: the model, and lerobot's own pre/post-processors whose normalisation stats put the actions around
    `action_mean`, `action_std` per normalised unit."""
    import torch
    from lerobot.configs.types import FeatureType, PolicyFeature
    from lerobot.policies.act.configuration_act import ACTConfig
    from lerobot.policies.act.modeling_act import ACTPolicy
    from lerobot.policies.factory import make_pre_post_processors

    image_key = f"observation.images.{camera}"
    cfg = ACTConfig(
        input_features={"observation.state": PolicyFeature(FeatureType.STATE, (state_dim,)),
                        image_key: PolicyFeature(FeatureType.VISUAL, (3, *image_hw))},
        output_features={"action": PolicyFeature(FeatureType.ACTION, (len(action_mean),))},
        device="cpu", chunk_size=10, n_action_steps=10, dim_model=16, n_heads=2, dim_feedforward=32,
        n_encoder_layers=1, n_decoder_layers=1, use_vae=False, pretrained_backbone_weights=None,
    )
    torch.manual_seed(0)
    policy = ACTPolicy(cfg)
    stats = {
        "observation.state": {"mean": torch.zeros(state_dim), "std": torch.ones(state_dim)},
        image_key: {"mean": torch.full((3, 1, 1), 0.5), "std": torch.full((3, 1, 1), 0.25)},
        "action": {"mean": torch.tensor(action_mean), "std": torch.full((len(action_mean),), action_std)},
    }
    pre, post = make_pre_post_processors(cfg, dataset_stats=stats)
    for part in (policy, pre, post):
        part.save_pretrained(out)


def in_workspace(p: common_pb2.Vec3) -> bool:
    # The server's default workspace box (server/core/src/config.rs, GateConfig::default).
    lo, hi = (0.10, -0.25, 0.02), (0.40, 0.25, 0.35)
    return all(lo[i] <= v <= hi[i] for i, v in enumerate((p.x, p.y, p.z)))


class StateLog:
    """Every state of one arm that `System.WatchStatus` reports (every 20 ms), until `close`."""

    def __init__(self, c: Client, arm: str) -> None:
        self.states: list[common_pb2.ArmState] = []
        self._call = c.watch_status(interval_s=0.02)
        self._thread = threading.Thread(target=self._run, args=(arm,), daemon=True)
        self._thread.start()

    def _run(self, arm: str) -> None:
        # Ends when `close` cancels the stream.
        for status in self._call:
            self.states.extend(s for s in status.arms if s.arm == arm)

    def close(self) -> list[common_pb2.ArmState]:
        self._call.cancel()
        self._thread.join(timeout=5.0)
        return self.states


def test_async_inference_drives_the_arm_and_holds_after_ctrl_c(server: Server, tmp_path: Path) -> None:
    """lerobot's async inference unchanged: its policy server serves a (random, untrained) ACT, its robot client
    drives the arm through the `phone2act` plugin; Ctrl-C stops the client and the arm holds."""
    from lerobot_robot_phone2act import ABSOLUTE_EE_NAMES, ArmWatch
    from lerobot_robot_phone2act.arm_watch import absolute_target

    with Client(server.target) as c:
        state_dim = len(c.observe(arms=["main"]).arms[0].state_names)
        before = c.arm("main")
    # The policy's actions centre on a goal 2 cm (towards the workspace's middle) from the arm's current target,
    # so an arm that reaches it was driven by the policy and by nothing else.
    start = absolute_target(before)
    goal = list(start)
    goal[1] += 0.02 if goal[1] < 0.0 else -0.02
    # Around it, the random network's outputs spread by at most 1.6 mm: its action head sees LayerNorm'd features
    # (each |x| <= sqrt(15) over 16 dims) through a 16-wide row of weights initialised within ±1/4, so it outputs
    # at most ~16 normalised units, i.e. 1.6 mm at 0.1 mm per unit (and 1.6e-3 in the 6D rotation and gripper).
    model = tmp_path / "model"
    random_act_policy(model, state_dim, "front", (48, 64), goal, action_std=1e-4)
    assert ABSOLUTE_EE_NAMES[1] == "y"  # the goal's offset is in y

    with Client(server.target) as c, PolicyServer(Path(sys.executable), tmp_path / "async", FPS) as policy_server:
        watch, states = ArmWatch(c, "main"), StateLog(c, "main")
        client = RobotClient(
            robot_client_command(Path(sys.executable), robot_server=server.target, token=None, arm="main",
                                 cameras=["front"], fps=FPS, policy_server=policy_server.address, model=model,
                                 task="go to the goal", actions_per_chunk=10),
            tmp_path / "async", tmp_path / "async" / "robot_client.log",
        )
        try:
            def at_goal(s: common_pb2.ArmState) -> bool:
                p = s.robot_from_ee.position_m
                return math.dist((p.x, p.y, p.z), goal[:3]) < 3e-3 and s.owner == common_pb2.CONTROL_SOURCE_POLICY

            # Two Python processes import torch and lerobot (12 s each, measured on this machine under a full
            # training run), the server loads 45 MB of weights, then infers; 120 s is several times all of it.
            # Within 3 mm: the policy's 1.6 mm spread plus the sim's lag settling (well under 1 mm once there).
            driven = watch.wait(at_goal, 120.0)
            assert client.running(), client.log_path.read_text()[-4000:]
            # It keeps driving: commands still flow a second later (20 control periods).
            time.sleep(1.0)
            assert client.running(), client.log_path.read_text()[-4000:]
            assert c.arm("main").commands_sent > driven.commands_sent
        except BaseException:
            client.stop()  # never leave it driving
            raise
        # Ctrl-C: the client's `finally` disconnects the robot, which releases the arm at once (at worst the
        # server's 1 s silence timeout would); then the process ends by the SIGINT it did not handle, or, when
        # lerobot's own exit deadlocks (see `RobotClient.stop`), by a second Ctrl-C.
        client.ctrl_c()
        held = watch.wait(lambda s: s.owner == common_pb2.CONTROL_SOURCE_NONE, SETTLE_S)
        rc = client.stop()
        log = client.log_path.read_text()
        assert rc == -signal.SIGINT, log[-4000:]
        if client.ctrl_c_sent == 1:
            assert "Client stopped" in log, log[-4000:]
        # The arm holds: no command after the release moves it.
        time.sleep(1.0)  # 20 periods of the client's 20 Hz loop: a client still sending would show here
        after = c.arm("main")
        watch.close()
        seen = states.close()
    assert after.commands_sent == held.commands_sent, (held.commands_sent, after.commands_sent)
    assert absolute_target(after) == absolute_target(held)
    # ... and sits on the last target it was given: 1 s is 20 time constants of the sim's lag.
    p, q = after.robot_from_ee.position_m, after.robot_from_target.position_m
    assert math.dist((p.x, p.y, p.z), (q.x, q.y, q.z)) < 1e-3
    # Every command passed the safety gate: what reached the arm lies in its workspace (the gate's clamp) and
    # the gate counted it; refusals and clamps are allowed, a target outside the box is not.
    assert after.commands_sent > before.commands_sent
    # The status stream reports every 20 ms over the 2 s and more above: 20 states is a fifth of that.
    assert len(seen) > 20, len(seen)
    outside = [s.robot_from_target.position_m for s in seen if not in_workspace(s.robot_from_target.position_m)]
    assert not outside, outside[:3]
    print(f"\nasync inference: {after.commands_sent - before.commands_sent} commands, "
          f"{after.commands_rejected - before.commands_rejected} refused, "
          f"{after.commands_clamped - before.commands_clamped} clamped by the gate; stopped by {client.ctrl_c_sent} Ctrl-C")
