"""The Python example bridge over Bridge.Attach drives a `bridge = "remote"` arm; the server's arm state follows."""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field, replace

import grpc
import pytest
from conftest import Server, wait_until
from phone2act import Client, pose_tuple
from phone2act.joint_model import SO101_JOINTS, SO101_TOOL, chain_model, forward, so101_chain
from phone2act.poses import quat_angle
from phone2act.v1 import bridge_pb2, common_pb2
from phone2act_bridge_example import ExampleBridge, FirstOrderArm

JOINTS = ["j1", "j2", "j3", "j4", "j5", "j6"]
REMOTE_ARM = f"""
[[arms]]
name = "ext"
bridge = "remote"
[arms.remote]
joint_names = {JOINTS!r}
""".replace("'", '"')


@pytest.fixture(scope="module")
def rserver(make_server) -> Server:  # type: ignore[no-untyped-def]
    return make_server(arms=REMOTE_ARM)


def test_policy_target_followed_through_the_python_bridge(rserver: Server) -> None:
    robot = FirstOrderArm(joint_names=JOINTS, tau_s=0.05)
    bridge = ExampleBridge(rserver.target, "ext", robot)
    thread = bridge.start()
    try:
        assert bridge.attached.wait(10.0) and bridge.error is None, bridge.error
        assert bridge.welcome is not None and bridge.welcome.arm == "ext"
        with Client(rserver.target) as c:
            assert wait_until(lambda: c.arm("ext").health == common_pb2.BRIDGE_HEALTH_READY
                              and c.arm("ext").feedback_time_ns > 0, 5.0), c.arm("ext")
            state = c.arm("ext")
            assert state.bridge_kind == "remote" and list(state.joint_names) == JOINTS
            p_start, _q_start = pose_tuple(state.robot_from_ee)
            assert math.dist(p_start, robot.position_m) < 1e-3

            with c.policy_session(["ext"], observation_rate_hz=20) as s:
                assert s.layouts["ext"].state_names[:6] == tuple(JOINTS)
                obs = s.next_observation()
                # 2 cm +x, 1 cm -z and 0.2 rad of yaw, over 10 steps of 50 ms.
                steps = [[0.002 * k, 0, -0.001 * k, 0, 0, 0.02 * k, 1.0] for k in range(1, 11)]
                acc = s.push("ext", steps, 0.05, observation_id=obs.observation_id)
                assert acc.steps_scheduled >= 9
                p0, q0 = pose_tuple(obs.arms[0].robot_from_ee)
                goal_p = (p0[0] + 0.02, p0[1], p0[2] - 0.01)

                def followed() -> bool:
                    # Position and orientation converge at the same first-order rate from different
                    # distances: wait for both before judging either.
                    a = c.arm("ext")
                    ee_p, ee_q = pose_tuple(a.robot_from_ee)
                    _, target_q = pose_tuple(a.robot_from_target)
                    return math.dist(ee_p, goal_p) < 1e-3 and quat_angle(ee_q, target_q) < math.radians(0.5)

                assert wait_until(followed, 5.0), pose_tuple(c.arm("ext").robot_from_ee)
                a = c.arm("ext")
                target_p, target_q = pose_tuple(a.robot_from_target)
                ee_p, ee_q = pose_tuple(a.robot_from_ee)
                assert math.dist(target_p, goal_p) < 1e-9
                assert quat_angle(ee_q, target_q) < math.radians(0.5)
                assert quat_angle(q0, target_q) > math.radians(10)
                assert abs(a.gripper_position - 1.0) < 0.05
                assert bridge.commands > 0 and robot.applied_seq > 0
                assert list(a.joint_positions_rad)[:3] == pytest.approx(ee_p, abs=1e-6)
                print(f"\nremote arm follows the policy target: {math.dist(ee_p, target_p) * 1e3:.3f} mm, "
                      f"{math.degrees(quat_angle(ee_q, target_q)):.3f} deg after settling")
    finally:
        bridge.stop()
        thread.join(timeout=5)
    with Client(rserver.target) as c:
        assert wait_until(lambda: c.arm("ext").health == common_pb2.BRIDGE_HEALTH_DISCONNECTED, 5.0), c.arm("ext")


def test_bridge_with_wrong_joint_names_is_refused(rserver: Server) -> None:
    bridge = ExampleBridge(rserver.target, "ext", FirstOrderArm(joint_names=["a", "b"]))
    thread = bridge.start()
    thread.join(timeout=10)
    assert bridge.error is not None
    assert "joint" in bridge.error.details().lower(), bridge.error.details()


SO101_NAMES = [name for name, *_ in SO101_JOINTS]
SO101_REMOTE = f"""
[[arms]]
name = "so"
bridge = "remote"
[arms.remote]
joint_names = {SO101_NAMES!r}
""".replace("'", '"')
LIMIT_RAD_S = 2.0


@dataclass
class RecordingArm(FirstOrderArm):
    """The example robot, keeping every command's issue time and joint targets."""

    received: list[tuple[int, list[float]]] = field(default_factory=list)
    last_received_s: float = 0.0

    def command(self, cmd: bridge_pb2.BridgeCommand) -> None:
        super().command(cmd)
        self.received.append((cmd.issue_time_ns, list(cmd.joint_targets_rad)))
        self.last_received_s = time.monotonic()


@pytest.fixture(scope="module")
def so_server(make_server) -> Server:  # type: ignore[no-untyped-def]
    return make_server(arms=SO101_REMOTE)


def test_a_declared_chain_gets_joint_targets_within_its_limit(so_server: Server) -> None:
    """The example bridge declares the SO-101 chain at 2 rad/s; a policy's 0.45 rad yaw jump reaches it as joint
    targets that ramp, each step within the limit over the server's issue times (which every command carries, so
    the bound does not depend on scheduling)."""
    robot = RecordingArm(joint_names=SO101_NAMES, tau_s=0.02, chain=so101_chain(LIMIT_RAD_S), tool=SO101_TOOL,
                         joints=[0.0, -0.4, 0.6, 0.9, 0.0])
    bridge = ExampleBridge(so_server.target, "so", robot)
    thread = bridge.start()
    try:
        assert bridge.attached.wait(10.0) and bridge.error is None, bridge.error
        assert bridge.welcome is not None and bridge.welcome.joint_targets, bridge.welcome
        assert "2.00" in bridge.welcome.joint_limits, bridge.welcome.joint_limits
        with Client(so_server.target) as c:
            assert wait_until(lambda: c.arm("so").health == common_pb2.BRIDGE_HEALTH_READY
                              and len(c.arm("so").joint_positions_rad) == 5, 5.0), c.arm("so")
            with c.policy_session(["so"], observation_rate_hz=20, silence_timeout_s=5.0) as s:
                obs = s.next_observation()
                steps = [[0, 0, 0, 0, 0, 0.45, 0.0]] * 20
                acc = s.push("so", steps, 0.05, observation_id=obs.observation_id)
                assert acc.steps_scheduled >= 19
                pushed_s = time.monotonic()
                # The chunk's second (the ramp, 0.45 rad at 2 rad/s, takes 0.23 s of it), then no command for
                # 0.3 s: the arm has arrived. An event, not a guessed sleep: a loaded machine only makes it later.
                assert wait_until(lambda: time.monotonic() - pushed_s > 1.0 and robot.received
                                  and time.monotonic() - robot.last_received_s > 0.3, 10.0), len(robot.received)
            assert c.arm("so").commands_rejected == 0
    finally:
        bridge.stop()
        thread.join(timeout=5)
    received = [r for r in robot.received if r[1]]
    assert len(received) == len(robot.received), "a command without joint targets"
    largest, moving = 0.0, 0
    for (t0, q0), (t1, q1) in zip(received, received[1:]):
        step = max(abs(a - b) for a, b in zip(q0, q1))
        if step > 1e-9:
            moving += 1
            largest = max(largest, step / (LIMIT_RAD_S * (t1 - t0) * 1e-9))
    travel = max(abs(a - b) for a, b in zip(received[-1][1], received[0][1]))
    print(f"\ndeclared chain: {moving} moving commands, largest step {largest:.3f} of the limit, "
          f"largest joint travel {travel:.3f} rad")
    assert moving >= 5, moving
    assert largest <= 1.0 + 1e-6, largest
    assert travel > 0.2, travel


def test_a_malformed_chain_is_refused_with_the_reason(so_server: Server) -> None:
    chain = so101_chain(LIMIT_RAD_S)
    chain[2] = replace(chain[2], axis=(0.0, 0.0, 0.0))
    robot = FirstOrderArm(joint_names=SO101_NAMES, chain=so101_chain(LIMIT_RAD_S))
    robot.chain = chain  # declared as is: the SDK's own forward kinematics would refuse it first
    with pytest.raises(ValueError, match="not a direction"):
        forward(chain, [0.0] * 5)
    bridge = ExampleBridge(so_server.target, "so", robot)
    thread = bridge.start()
    thread.join(timeout=10)
    assert bridge.error is not None and bridge.error.code() == grpc.StatusCode.INVALID_ARGUMENT, bridge.error
    assert 'joint "elbow_flex": the axis is zero' in bridge.error.details(), bridge.error.details()


def test_forward_kinematics_matches_the_server(so_server: Server) -> None:
    """The SDK's forward kinematics of the SO-101 chain is the server's: the server checks the first feedback
    against its model of the declared chain, accepts the SDK's pose and refuses one from a wrong tool frame."""
    joints = [0.3, -0.2, 0.4, 0.7, -0.5]
    robot = FirstOrderArm(joint_names=SO101_NAMES, chain=so101_chain(), tool=SO101_TOOL, joints=list(joints))
    bridge = ExampleBridge(so_server.target, "so", robot)
    thread = bridge.start()
    try:
        assert bridge.attached.wait(10.0) and bridge.error is None, bridge.error
        with Client(so_server.target) as c:
            assert wait_until(lambda: c.arm("so").health == common_pb2.BRIDGE_HEALTH_READY, 5.0), c.arm("so")
            p, q = pose_tuple(c.arm("so").robot_from_ee)
        expected_p, expected_q = forward(so101_chain(), joints, *SO101_TOOL)
        assert math.dist(p, expected_p) < 1e-9 and quat_angle(q, expected_q) < 1e-9
        assert bridge.error is None
    finally:
        bridge.stop()
        thread.join(timeout=5)
    # The same chain declared with the tool at the last joint, while the robot reports the real tool's pose
    # (10 cm away): the model would drive the arm somewhere else than asked.
    wrong = FirstOrderArm(joint_names=SO101_NAMES, chain=so101_chain(), tool=SO101_TOOL, joints=list(joints))
    wrong.joint_model = lambda: chain_model(so101_chain())  # type: ignore[method-assign]
    bridge = ExampleBridge(so_server.target, "so", wrong)
    thread = bridge.start()
    thread.join(timeout=10)
    assert bridge.error is not None and "joint model" in bridge.error.details(), bridge.error
