"""The Python example bridge over Bridge.Attach drives a `bridge = "remote"` arm; the server's arm state follows."""

from __future__ import annotations

import math

import pytest
from conftest import Server, wait_until
from phone2act import Client, pose_tuple
from phone2act.poses import quat_angle
from phone2act.v1 import common_pb2
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
