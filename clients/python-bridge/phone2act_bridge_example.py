"""Example out-of-process bridge in Python: a trivial simulated robot attached over `Bridge.Attach`.

The "robot" follows the newest target pose with a first-order lag (time constant `tau_s`) and reports its
pose, a made-up joint vector and the gripper as `RobotFeedback` at the rate the server asks for. Replace
`FirstOrderArm` with calls into a real robot SDK to make a real bridge.

    python phone2act_bridge_example.py --server 127.0.0.1:50051 --arm ext \
        --joint-names j1,j2,j3,j4,j5,j6

Given a joint chain (`--so101-chain`: the SO-101's, with `--max-velocity` rad/s), the bridge declares it in its
hello: the server then solves every target and limits every joint step, and the robot follows the commands'
`joint_targets_rad` instead of the pose, reporting the chain's forward kinematics as its pose:

    python phone2act_bridge_example.py --arm so101 --so101-chain --max-velocity 2.0 \
        --joint-names shoulder_pan,shoulder_lift,elbow_flex,wrist_flex,wrist_roll

The arm must be configured with `bridge = "remote"` and the same joint names:

    [[arms]]
    name = "ext"
    bridge = "remote"
    [arms.remote]
    joint_names = ["j1", "j2", "j3", "j4", "j5", "j6"]
"""

from __future__ import annotations

import argparse
import math
import threading
import time
from collections.abc import Sequence
from dataclasses import dataclass, field

import grpc
from phone2act import make_pose
from phone2act.bridge import BridgeHandler, BridgeLink
from phone2act.joint_model import SO101_TOOL, ChainJoint, chain_model, forward, so101_chain
from phone2act.poses import rpy_from_quat, slerp
from phone2act.v1 import bridge_pb2 as pb


@dataclass
class FirstOrderArm:
    """Pose, gripper and joints relaxing towards the target: x += (1 - exp(-dt/tau)) * (target - x)."""

    joint_names: Sequence[str]
    position_m: list[float] = field(default_factory=lambda: [0.25, 0.0, 0.20])
    # Tool pointing down (180° about x), inside the default workspace box.
    orientation_xyzw: tuple[float, float, float, float] = (1.0, 0.0, 0.0, 0.0)
    gripper: float = 0.0
    tau_s: float = 0.05
    target_position_m: list[float] | None = None
    target_orientation_xyzw: tuple[float, float, float, float] | None = None
    target_gripper: float | None = None
    applied_seq: int = 0
    # A declared joint chain: the robot then follows the server's joint targets (see the module docstring).
    chain: Sequence[ChainJoint] | None = None
    # The tool's origin on the chain's last link (xyz m, rpy rad).
    tool: tuple[tuple[float, float, float], tuple[float, float, float]] = ((0.0, 0.0, 0.0), (0.0, 0.0, 0.0))
    joints: list[float] = field(default_factory=list)
    target_joints: list[float] | None = None

    def __post_init__(self) -> None:
        if self.chain is not None:
            if not self.joints:
                self.joints = [0.5 * (j.lower_rad + j.upper_rad) for j in self.chain]
            self._pose_from_joints()

    def joint_model(self) -> pb.JointModel | None:
        return None if self.chain is None else chain_model(self.chain, *self.tool)

    def _pose_from_joints(self) -> None:
        assert self.chain is not None
        p, q = forward(self.chain, self.joints, *self.tool)
        self.position_m, self.orientation_xyzw = list(p), q

    def command(self, cmd: pb.BridgeCommand) -> None:
        p, q = cmd.robot_from_target.position_m, cmd.robot_from_target.orientation
        self.target_position_m = [p.x, p.y, p.z]
        self.target_orientation_xyzw = (q.x, q.y, q.z, q.w)
        if self.chain is not None and len(cmd.joint_targets_rad) == len(self.chain):
            self.target_joints = list(cmd.joint_targets_rad)
        self.target_gripper = cmd.gripper_target
        self.applied_seq = cmd.seq

    def step(self, dt_s: float) -> None:
        alpha = 1.0 - math.exp(-dt_s / self.tau_s)
        if self.chain is not None:
            # Joints, not the pose: the server already kept every step within the joints' speed limits.
            if self.target_joints is not None:
                self.joints = [x + alpha * (t - x) for x, t in zip(self.joints, self.target_joints)]
                self._pose_from_joints()
            if self.target_gripper is not None:
                self.gripper += alpha * (self.target_gripper - self.gripper)
            return
        if self.target_position_m is not None:
            self.position_m = [x + alpha * (t - x) for x, t in zip(self.position_m, self.target_position_m)]
        if self.target_orientation_xyzw is not None:
            self.orientation_xyzw = slerp(self.orientation_xyzw, self.target_orientation_xyzw, alpha)
        if self.target_gripper is not None:
            self.gripper += alpha * (self.target_gripper - self.gripper)

    def joints_rad(self) -> list[float]:
        if self.chain is not None:
            return list(self.joints)
        # A stand-in joint vector (position and rpy), enough for the dataset's joint columns to move.
        values = [*self.position_m, *rpy_from_quat(self.orientation_xyzw)]
        return [values[i % len(values)] for i in range(len(self.joint_names))]

    def feedback(self) -> pb.RobotFeedback:
        return pb.RobotFeedback(
            capture_time_ns=time.monotonic_ns(),
            joint_positions_rad=self.joints_rad(),
            robot_from_ee=make_pose(self.position_m, self.orientation_xyzw),
            gripper_position=self.gripper,
            applied_seq=self.applied_seq,
        )


class ExampleBridge(BridgeHandler):
    """Attach `robot` to `arm` on the server and run until `stop()` or the stream ends."""

    def __init__(self, target: str, arm: str, robot: FirstOrderArm, token: str | None = None) -> None:
        self.arm, self.robot = arm, robot
        self._lock = threading.Lock()
        hello = pb.BridgeHello(arm=arm, bridge_name="python-example", joint_names=list(robot.joint_names),
                               supports_orientation=True)
        model = robot.joint_model()
        if model is not None:
            hello.joint_model.CopyFrom(model)
        self.link = BridgeLink(target, hello, self, token)

    def on_welcome(self, link: BridgeLink, welcome: pb.BridgeWelcome) -> None:
        # Whether the server limits this robot's joints, or only watches them.
        print(f"phone2act bridge attached to {self.arm}: {welcome.joint_limits}", flush=True)
        link.ready()
        rate = welcome.expected_feedback_hz or 50.0
        threading.Thread(target=self._feedback_loop, args=(link, rate), daemon=True).start()

    def on_command(self, link: BridgeLink, command: pb.BridgeCommand) -> None:
        with self._lock:
            self.robot.command(command)

    def _feedback_loop(self, link: BridgeLink, rate_hz: float) -> None:
        period = 1.0 / rate_hz
        last = time.monotonic()
        while not link.stopped.wait(period):
            now = time.monotonic()
            with self._lock:
                self.robot.step(now - last)
                fb = self.robot.feedback()
            last = now
            link.feedback(fb)

    # The link's state, as the tests and `main` read it.
    @property
    def attached(self) -> threading.Event:
        return self.link.attached

    @property
    def welcome(self) -> pb.BridgeWelcome | None:
        return self.link.welcome

    @property
    def commands(self) -> int:
        return self.link.commands

    @property
    def error(self) -> grpc.RpcError | None:
        return self.link.error

    def run(self) -> None:
        self.link.run()

    def start(self) -> threading.Thread:
        return self.link.start()

    def stop(self) -> None:
        self.link.stop()


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--server", default="127.0.0.1:50051")
    p.add_argument("--token", default=None)
    p.add_argument("--arm", required=True)
    p.add_argument("--joint-names", required=True, help="comma-separated, as in [arms.remote] joint_names")
    p.add_argument("--tau", type=float, default=0.05, help="first-order time constant, seconds")
    p.add_argument("--so101-chain", action="store_true",
                   help="declare the SO-101's joint chain (five joints, the SO-101's names)")
    p.add_argument("--max-velocity", type=float, default=4.7, help="declared joint speed limit, rad/s")
    args = p.parse_args()
    chain = so101_chain(args.max_velocity) if args.so101_chain else None
    robot = FirstOrderArm(joint_names=args.joint_names.split(","), tau_s=args.tau, chain=chain, tool=SO101_TOOL)
    bridge = ExampleBridge(args.server, args.arm, robot, args.token)
    try:
        bridge.run()
    except KeyboardInterrupt:
        bridge.stop()
    if bridge.error is not None:
        raise SystemExit(f"bridge ended: {bridge.error.code().name}: {bridge.error.details()}")


if __name__ == "__main__":
    main()
