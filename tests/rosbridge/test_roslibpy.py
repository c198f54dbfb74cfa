"""roslibpy against the phone2act gateway and the real server (two simulated arms, left and right).

Publishes phone poses and volume-key states the way a rosbridge client does (roslibpy advertises on first
publish and uses `pkg/msg/Type` names), and reads the result back through rosbridge subscriptions to the
gateway's feedback topics. Prints "N passed, M failed"; exits 1 on any failure.
"""

import argparse
import base64
import io
import json
import math
import threading
import time
import traceback

import roslibpy
from PIL import Image


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
        self.port = port
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

    def test_rosapi_lists_the_topics_ros_tools_expect(self):
        topics = self.ros.get_topics()
        for expected in (
            "/joint_states",
            "/tf",
            "/cameras/front/image/compressed",
            "/left/phone2act/robot_feedback",
            "/right/Phone2Act/ar_pose",
        ):
            assert expected in topics, f"{expected} not listed by /rosapi/topics: {topics}"
        assert self.ros.get_topic_type("/joint_states") == "sensor_msgs/msg/JointState"
        assert self.ros.get_topic_type("/tf") == "tf2_msgs/msg/TFMessage"
        # rosapi answers an unknown topic with an empty type, not a failure.
        assert self.ros.get_topic_type("/no/such/topic") == ""
        services = self.ros.get_services()
        assert "/rosapi/topics" in services, services

    def test_get_time_reads_the_gateways_wall_clock(self):
        """roslibpy's Ros.get_time() reads ROS 1's secs/nsecs; ROS 2 clients read sec/nanosec of the same answer."""
        before = time.time()
        t = self.ros.get_time()
        after = time.time()
        assert isinstance(t, roslibpy.Time), t
        assert 0 <= t.nsecs < 1_000_000_000, t
        # The gateway runs on this machine, so its wall clock is ours and it read it between our two readings;
        # 1 ms covers only float rounding (a quarter of a microsecond at today's epoch seconds), not a
        # monotonic or a millisecond clock.
        assert before - 0.001 <= t.to_sec() <= after + 0.001, f"get_time {t.to_sec()} not within [{before}, {after}]"
        answer = roslibpy.Service(self.ros, "/rosapi/get_time", "rosapi/GetTime").call(
            roslibpy.ServiceRequest(), timeout=10
        )
        stamp = answer["time"]
        assert (stamp["sec"], stamp["nanosec"]) == (stamp["secs"], stamp["nsecs"]), stamp
        # A moment after the first call: 10 s covers a stalled machine, not a monotonic clock's seconds since boot.
        assert abs(stamp["sec"] + stamp["nanosec"] * 1e-9 - time.time()) < 10.0, stamp

    def stamps(self, topic, msg_type, throttle_ms, count, key=lambda m: m["header"]["stamp"]):
        """Collects `count` messages of a throttled subscription; returns them and their stamps in seconds."""
        got = []
        done = threading.Event()

        def on(msg):
            if len(got) < count:
                got.append(msg)
            if len(got) >= count:
                done.set()

        sub = roslibpy.Topic(self.ros, topic, msg_type, throttle_rate=throttle_ms)
        sub.subscribe(on)
        # Generous: the status watch runs at 20 Hz and a camera poll takes milliseconds; a loaded 2-core
        # machine delays messages but does not stop them.
        ok = done.wait(20.0)
        sub.unsubscribe()
        assert ok, f"{topic}: {len(got)} of {count} messages in 20 s"
        return got, [key(m)["sec"] + key(m)["nanosec"] * 1e-9 for m in got]

    def check_stamps(self, stamps, throttle_s):
        # Stamps are the gateway's wall clock when it sent each message; the test runs on the same machine,
        # so a stamp lies between the subscription's start and now, give or take scheduling (10 s covers
        # any stall of a loaded machine but not a monotonic clock's seconds-since-boot).
        now = time.time()
        assert all(abs(s - now) < 10.0 for s in stamps), f"stamps are not wall-clock time: {stamps} vs {now}"
        # The throttle spaces the messages the gateway sends; load can only widen the gaps, never shorten
        # them (10 ms slack: the wall clock is read a few microseconds after the monotonic one it gates on).
        gaps = [b - a for a, b in zip(stamps, stamps[1:])]
        assert min(gaps) >= throttle_s - 0.01, f"throttle_rate {throttle_s} s not honoured: gaps {gaps}"

    def test_joint_states_for_each_arm_in_radians(self):
        msgs, stamps = self.stamps("/joint_states", "sensor_msgs/msg/JointState", 200, 4)
        self.check_stamps(stamps, 0.2)
        msg = msgs[-1]
        names = msg["name"]
        assert len(names) == len(msg["position"]), msg
        for arm in ("left", "right"):
            assert any(n.startswith(f"{arm}_") for n in names), f"no joints of {arm}: {names}"
        # Radians: an SO-101 joint never turns more than a full turn either way.
        assert all(math.isfinite(p) and abs(p) <= 2 * math.pi for p in msg["position"]), msg["position"]

    def test_tf_has_each_arms_end_effector_in_its_base_frame(self):
        _, stamps = self.stamps("/tf", "tf2_msgs/msg/TFMessage", 100, 3, key=lambda m: m["transforms"][0]["header"]["stamp"])
        self.check_stamps(stamps, 0.1)
        tf = Latest(self.ros, "/tf", "tf2_msgs/msg/TFMessage")

        def agrees(msg):
            frames = {(t["header"]["frame_id"], t["child_frame_id"]): t for t in msg["transforms"]}
            for arm in ("left", "right"):
                t = frames.get((f"{arm}_base_link", f"{arm}_tool0"))
                assert t is not None, f"no {arm}_base_link -> {arm}_tool0 in {list(frames)}"
                q = t["transform"]["rotation"]
                assert abs(math.sqrt(q["x"] ** 2 + q["y"] ** 2 + q["z"] ** 2 + q["w"] ** 2) - 1) < 1e-6, q
                tr = t["transform"]["translation"]
                fb = self.feedback[arm].get()
                # Two subscriptions see different snapshots while the sim arm still settles from the last
                # test; once it holds still they must agree to a millimetre.
                if fb is None or dist((tr["x"], tr["y"], tr["z"]), position(fb)) > 1e-3:
                    return False
            return True

        try:
            tf.wait(agrees, what="each arm's tool0 frame at its measured end effector")
        finally:
            tf.topic.unsubscribe()

    def test_camera_images_arrive_as_compressed_jpeg(self):
        msgs, stamps = self.stamps(
            "/cameras/front/image/compressed", "sensor_msgs/msg/CompressedImage", 500, 2
        )
        self.check_stamps(stamps, 0.5)
        msg = msgs[-1]
        assert msg["format"] == "jpeg", msg["format"]
        image = Image.open(io.BytesIO(base64.b64decode(msg["data"])))
        image.load()
        assert image.format == "JPEG" and image.size == (640, 480), (image.format, image.size)

    def test_an_image_subscription_does_not_hold_up_control(self):
        """With the camera topic subscribed on the same connection, poses still move the arm and service calls
        are answered, and the images keep coming meanwhile."""
        images = Latest(self.ros, "/cameras/front/image/compressed", "sensor_msgs/msg/CompressedImage")
        get_time = roslibpy.Service(self.ros, "/rosapi/get_time", "rosapi/GetTime")
        try:
            images.wait(lambda m: True, timeout=20.0, what="a first image")
            # After the pause since the last test the server re-indexes on the first pose (staleness): hold the
            # phone still first, then read where the target is.
            here = (0.0, 0.0, -0.07)
            self.stream({"left": here}, 0.3)
            start = position(self.target["left"].wait(lambda m: True, what="a target"))
            before = images.count
            # 4 cm up (+Y) at 2 mm per message (50 Hz), a service call every 10th message, then held.
            for i in range(1, 21):
                self.stream({"left": (here[0], here[1] + 0.002 * i, here[2])}, 0.0)
                if i % 10 == 0:
                    # Blocking, 10 s: one round trip on loopback, answered between the images.
                    answer = get_time.call(roslibpy.ServiceRequest(), timeout=10)
                    assert "time" in answer, answer
            goal_phone = (here[0], here[1] + 0.04, here[2])
            deadline = time.monotonic() + 10
            while abs(dist(position(self.target["left"].get()), start) - 0.04) >= 0.006:
                assert time.monotonic() < deadline, (
                    f"left target {position(self.target['left'].get())} not 4 cm from {start} with the camera subscribed"
                )
                self.stream({"left": goal_phone}, 0.02)
            # 3 more images: at the topic's 10 Hz a second or less; the wait's 20 s covers a loaded machine.
            images.wait(lambda m: images.count >= before + 3, timeout=20.0, what="images while driving")
            msg = images.get()
            image = Image.open(io.BytesIO(base64.b64decode(msg["data"])))
            image.load()
            assert image.format == "JPEG" and image.size == (640, 480), (image.format, image.size)
        finally:
            images.topic.unsubscribe()

    def test_unknown_topic_gets_an_error_status(self):
        """A client that asked for status messages (set_level) is told why a subscription gets nothing."""
        ros = roslibpy.Ros(host="127.0.0.1", port=self.port)
        statuses = []
        got = threading.Event()

        def install(proto):
            # roslibpy 2.1 has no public hook for the rosbridge `status` op (its handler table leaves it
            # empty); set it on the protocol object so the test can read what the gateway said.
            def on_status(message):
                statuses.append(dict(message))
                got.set()

            proto._message_handlers["status"] = on_status
            return proto

        ros.factory.on_ready(install)
        ros.run(timeout=10)
        try:
            ros.send_on_ready(roslibpy.Message({"op": "set_level", "level": "error"}))
            ros.send_on_ready(
                roslibpy.Message({"op": "subscribe", "id": "sub:nothing", "topic": "/no/such/topic", "type": "std_msgs/String"})
            )
            # One round trip on loopback; 10 s covers a loaded machine.
            assert got.wait(10.0), "no status for an unknown topic"
            st = statuses[0]
            assert st["level"] == "error" and st.get("id") == "sub:nothing", st
            assert "/no/such/topic" in st["msg"], st
            assert ros.is_connected, "the connection dropped"
        finally:
            # close, not terminate: terminate stops the Twisted reactor the suite's own connection runs on.
            ros.close()

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
        suite.test_rosapi_lists_the_topics_ros_tools_expect,
        suite.test_get_time_reads_the_gateways_wall_clock,
        suite.test_joint_states_for_each_arm_in_radians,
        suite.test_tf_has_each_arms_end_effector_in_its_base_frame,
        suite.test_camera_images_arrive_as_compressed_jpeg,
        suite.test_an_image_subscription_does_not_hold_up_control,
        suite.test_unknown_topic_gets_an_error_status,
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
