"""roslibpy against the phone2act gateway and the real server (two simulated arms, left and right).

Publishes phone poses and volume-key states the way a rosbridge client does (roslibpy advertises on first
publish and uses `pkg/msg/Type` names), and reads the result back through rosbridge subscriptions to the
gateway's feedback topics. Prints "N passed, M failed"; exits 1 on any failure.
"""

import argparse
import json
import math
import threading
import time
import traceback

import roslibpy


class Latest:
    """Keeps the newest message of a subscription."""

    def __init__(self, ros, topic, msg_type):
        self.lock = threading.Lock()
        self.msg = None
        self.count = 0
        self.topic = roslibpy.Topic(ros, topic, msg_type)
        self.topic.subscribe(self._on)

    def _on(self, msg):
        with self.lock:
            self.msg = msg
            self.count += 1

    def get(self):
        with self.lock:
            return self.msg

    def wait(self, pred, timeout=10.0, what="condition"):
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            msg = self.get()
            if msg is not None and pred(msg):
                return msg
            time.sleep(0.02)
        raise AssertionError(f"{self.topic.name}: timed out waiting for {what}; last {self.get()}")


def position(msg):
    p = msg["pose"]["position"]
    return (p["x"], p["y"], p["z"])


def dist(a, b):
    return math.sqrt(sum((x - y) ** 2 for x, y in zip(a, b)))


def pose_msg(x, y, z, stamp=None):
    now = time.time() if stamp is None else stamp
    return roslibpy.Message(
        {
            "header": {"stamp": {"sec": int(now), "nanosec": int((now % 1) * 1e9)}, "frame_id": "phone"},
            "pose": {
                "position": {"x": x, "y": y, "z": z},
                "orientation": {"x": 0.0, "y": 0.0, "z": 0.0, "w": 1.0},
            },
        }
    )


class Suite:
    def __init__(self, port):
        self.ros = roslibpy.Ros(host="127.0.0.1", port=port)
        self.ros.run(timeout=10)
        assert self.ros.is_connected, "roslibpy did not connect"
        self.pose = {
            arm: roslibpy.Topic(self.ros, f"/{arm}/Phone2Act/ar_pose", "geometry_msgs/msg/PoseStamped")
            for arm in ("left", "right")
        }
        self.volume = {
            arm: roslibpy.Topic(self.ros, f"/{arm}/Phone2Act/volume", "std_msgs/msg/Int32MultiArray")
            for arm in ("left", "right")
        }
        self.target = {
            arm: Latest(self.ros, f"/{arm}/phone2act/target_pose", "geometry_msgs/msg/PoseStamped")
            for arm in ("left", "right")
        }
        self.feedback = {
            arm: Latest(self.ros, f"/{arm}/phone2act/robot_feedback", "geometry_msgs/msg/PoseStamped")
            for arm in ("left", "right")
        }
        self.status = {
            arm: Latest(self.ros, f"/{arm}/phone2act/status", "std_msgs/msg/String") for arm in ("left", "right")
        }
        self.toggles = {"left": [0, 0], "right": [0, 0]}

    def state(self, arm):
        msg = self.status[arm].wait(lambda m: True, what="a status message")
        return json.loads(msg["data"])

    def press(self, arm, key):
        """Flips a volume-key toggle like the Phone2Act app does (0 = up/gripper, 1 = down/clutch)."""
        self.toggles[arm][key] ^= 1
        self.report(arm)

    def report(self, arm):
        """Publishes the toggle state, as the app does when its volume monitor starts. The gateway reads it as
        the original planner does: down 0 follows, 1 holds; up 0 closes the gripper, 1 opens it."""
        self.volume[arm].publish(
            roslibpy.Message({"layout": {"dim": [], "data_offset": 0}, "data": list(self.toggles[arm])})
        )

    def test_feedback_subscriptions_answer(self):
        for arm in ("left", "right"):
            self.feedback[arm].wait(lambda m: m["header"]["frame_id"] == "robot_base", what="robot feedback")
            st = self.state(arm)
            assert st["arm"] == arm, st
            assert st["recording"]["phase"] in ("idle", "recording"), st

    def stream(self, poses, seconds):
        """Publishes fixed poses for both phones at the app's 50 Hz; a phone that goes quiet lets the server
        treat its next pose as a fresh start (staleness), as a real phone would never do mid-motion."""
        end = time.monotonic() + seconds
        while True:
            for arm, p in poses.items():
                self.pose[arm].publish(pose_msg(*p))
            time.sleep(0.02)
            if time.monotonic() >= end:
                return

    def test_left_and_right_publish_drive_their_own_arms(self):
        origin = {"left": (0.0, 0.0, 0.0), "right": (0.0, 0.0, 0.0)}
        self.stream(origin, 0.1)
        for arm in ("left", "right"):
            self.report(arm)
        deadline = time.monotonic() + 10
        while not (self.state("left")["engaged"] and self.state("right")["engaged"]):
            assert time.monotonic() < deadline, "the app's [0, 0] (follow) did not engage both arms"
            self.stream(origin, 0.05)
        self.stream(origin, 0.2)
        start = {arm: position(self.target[arm].wait(lambda m: True, what="a target")) for arm in ("left", "right")}
        # Left phone 5 cm forward (-Z), right phone 5 cm up (+Y), 2 mm per message at 50 Hz, then held.
        for i in range(1, 26):
            d = 0.002 * i
            self.stream({"left": (0.0, 0.0, -d), "right": (0.0, d, 0.0)}, 0.0)
        self.stream({"left": (0.0, 0.0, -0.05), "right": (0.0, 0.05, 0.0)}, 0.3)
        moved = {}
        for arm in ("left", "right"):
            msg = self.target[arm].wait(
                lambda m, a=arm: abs(dist(position(m), start[a]) - 0.05) < 0.006,
                what=f"{arm} target 5 cm away from {start[arm]} (server state {self.state(arm)})",
            )
            moved[arm] = [b - a for a, b in zip(start[arm], position(msg))]
        dl, dr = moved["left"], moved["right"]
        cos = sum(a * b for a, b in zip(dl, dr)) / (math.sqrt(sum(a * a for a in dl)) * math.sqrt(sum(b * b for b in dr)))
        assert abs(cos) < 0.2, f"left and right moved alike: {dl} {dr}"
        # The measured end effector (sim) follows the target.
        for arm in ("left", "right"):
            goal = position(self.target[arm].get())
            self.feedback[arm].wait(lambda m, g=goal: dist(position(m), g) < 0.01, what=f"{arm} sim arm to follow")

    def test_volume_up_toggles_the_gripper(self):
        before = self.state("right")["gripper_target"]
        self.press("right", 0)
        deadline = time.monotonic() + 10
        while abs(self.state("right")["gripper_target"] - before) < 0.5:
            assert time.monotonic() < deadline, "gripper did not toggle"
            time.sleep(0.05)
        left = self.state("left")["gripper_target"]
        time.sleep(0.2)
        assert self.state("left")["gripper_target"] == left, "the left gripper moved too"

    def test_nan_pose_is_refused_and_the_connection_survives(self):
        held = position(self.target["left"].wait(lambda m: True))
        # Python's json writes a bare NaN; the gateway must refuse it without moving the arm or dropping us.
        self.pose["left"].publish(pose_msg(float("nan"), 0.0, -0.05))
        time.sleep(0.3)
        assert dist(position(self.target["left"].get()), held) < 1e-6, "a NaN pose moved the arm"
        assert self.ros.is_connected, "the connection dropped"
        # After a pause the server may re-index on the first pose (staleness), so walk a few steps on.
        for i in range(1, 6):
            self.pose["left"].publish(pose_msg(0.0, 0.0, -0.05 - 0.004 * i))
            time.sleep(0.02)
        self.target["left"].wait(lambda m: dist(position(m), held) > 0.005, what="a valid pose after the NaN")

    def close(self):
        self.ros.terminate()


def main():
    parser = argparse.ArgumentParser()
    parser.add_argument("--port", type=int, required=True)
    args = parser.parse_args()
    suite = Suite(args.port)
    tests = [
        suite.test_feedback_subscriptions_answer,
        suite.test_left_and_right_publish_drive_their_own_arms,
        suite.test_volume_up_toggles_the_gripper,
        suite.test_nan_pose_is_refused_and_the_connection_survives,
    ]
    passed = failed = 0
    for test in tests:
        try:
            test()
            passed += 1
            print(f"PASS {test.__name__}", flush=True)
        except Exception:  # noqa: BLE001 - report every failure and go on
            failed += 1
            print(f"FAIL {test.__name__}", flush=True)
            traceback.print_exc()
    suite.close()
    print(f"rosbridge: {passed} passed, {failed} failed", flush=True)
    raise SystemExit(1 if failed else 0)


if __name__ == "__main__":
    main()
