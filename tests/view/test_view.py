"""The live view against a running server: record an episode while a teleop stream moves the simulated arm
(with a clutch cycle and a rejected jump), discard a second one, then read the .rrd files the view wrote
with rerun-sdk's reader and check they hold the camera frames, the poses and the events."""

from __future__ import annotations

import math
import os
import re
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from pathlib import Path

import pytest
from conftest import read_rrd, suite, texts
from phone2act import Client

# A rendered camera of the sim scene, small so three encoders' worth of work never loads the machine.
CAMERA = """
[[cameras]]
name = "front"
kind = "sim_render"
width = 160
height = 120
fps = 20
"""
# The arm's workspace in this test's config: the view draws it from --config (the API does not expose it).
ARM = """
[[arms]]
name = "main"
bridge = "sim"

[arms.teleop.gate]
workspace_min_m = [0.05, -0.3, 0.0]
workspace_max_m = [0.45, 0.3, 0.4]
"""
# Every wait below polls a condition; these are ceilings, reached only when something is broken. The
# longest real wait is the server committing an episode (milliseconds) and the view's next status snapshot
# (50 ms at 20 Hz); 30 s leaves room for a 2-core machine loaded by a training run.
TIMEOUT_S = 30.0


class ViewProcess:
    def __init__(self, args: list[str]) -> None:
        env = dict(os.environ, PYTHONUNBUFFERED="1")
        self.proc = subprocess.Popen([sys.executable, "-m", "phone2act_view", *args], stderr=subprocess.PIPE,
                                     stdout=subprocess.DEVNULL, text=True, env=env)
        self.lines: list[str] = []
        self.started = threading.Event()

        def drain() -> None:
            assert self.proc.stderr is not None
            for line in self.proc.stderr:
                self.lines.append(line.rstrip())
                if " Hz" in line:
                    self.started.set()
            self.started.set()

        threading.Thread(target=drain, daemon=True).start()

    def stop(self) -> int:
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGTERM)
        try:
            return self.proc.wait(timeout=TIMEOUT_S)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            self.proc.wait()
            pytest.fail("the view did not exit on SIGTERM:\n" + "\n".join(self.lines[-20:]))
        return -1


@pytest.fixture(scope="module")
def server(tmp_path_factory: pytest.TempPathFactory) -> Iterator[suite.Server]:
    tmp = tmp_path_factory.mktemp("server")
    s = suite.start_server(tmp, suite.config_text(tmp / "ds", arms=ARM, cameras=CAMERA))
    yield s
    s.stop()


def config_path(server: suite.Server) -> Path:
    return server.root.parent / "config.toml"


def stop_process_group(process: subprocess.Popen) -> None:
    """Ends a process started with `start_new_session=True` together with every child it started."""
    for sig in (signal.SIGTERM, signal.SIGKILL):
        try:
            os.killpg(process.pid, sig)
        except ProcessLookupError:
            return
        try:
            process.wait(timeout=TIMEOUT_S / 3)
            # The launcher is gone; its children may still be ending.
            os.killpg(process.pid, signal.SIGKILL)
        except subprocess.TimeoutExpired:
            continue
        except ProcessLookupError:
            return
        return


def hold(c: Client, arm: str, engaged: bool) -> None:
    """Wait until the server reports the clutch state, then keep it long enough for the view to sample it:
    the view's status stream runs at 20 Hz, and 1 s is 20 snapshots, of which it needs one."""
    assert suite.wait_until(lambda: c.arm(arm).engaged == engaged, TIMEOUT_S), f"engaged never became {engaged}"
    time.sleep(1.0)


def test_view_saves_cameras_poses_and_events_of_an_episode(server: suite.Server, tmp_path: Path) -> None:
    episodes = tmp_path / "episodes"
    everything = tmp_path / "all.rrd"
    view = ViewProcess(["--url", server.target, "--save-episodes", str(episodes), "--save", str(everything),
                        "--config", str(config_path(server)), "--verbose"])
    try:
        assert view.started.wait(TIMEOUT_S) and view.proc.poll() is None, "\n".join(view.lines)
        with Client(server.target) as c, c.teleop("main") as t:
            phone = [0.0, 1.2, -0.3]
            c.episodes.start("view test: move, release, move again")
            t.wait_feedback(t.clutch(True, phone))
            hold(c, "main", True)
            start = c.arm("main").robot_from_ee.position_m
            for k in range(1, 31):  # 3 cm along the phone's x over ~0.6 s: small steps, never a jump
                t.send([phone[0] + 0.001 * k, phone[1], phone[2]])
                time.sleep(0.02)
            t.wait_feedback(t.clutch(False, [phone[0] + 0.03, phone[1], phone[2]]))
            hold(c, "main", False)
            # Re-engaged: the floating zero re-indexes from here, then a 10 cm step in one sample is a jump.
            t.wait_feedback(t.clutch(True, phone))
            rejected = c.arm("main").commands_rejected
            t.wait_feedback(t.send([phone[0] + 0.10, phone[1], phone[2]]))
            assert suite.wait_until(lambda: c.arm("main").commands_rejected > rejected, TIMEOUT_S)
            hold(c, "main", True)
            end = c.arm("main").robot_from_ee.position_m
            moved_m = math.dist([start.x, start.y, start.z], [end.x, end.y, end.z])
            assert moved_m > 0.02, f"the arm moved {moved_m:.4f} m: the test's motion did not happen"
            t.wait_feedback(t.clutch(False))
            hold(c, "main", False)
            saved = c.episodes.stop()
            assert saved.episode_index == 0
            # The view names the file when it sees the recorder idle again.
            assert suite.wait_until(lambda: (episodes / "episode_000000.rrd").exists(), TIMEOUT_S), view.lines
            c.episodes.start("a take that is thrown away")
            time.sleep(0.5)  # a few frames, so the take is more than its start
            c.episodes.discard()
            assert suite.wait_until(lambda: (episodes / "episode_000001.discarded.rrd").exists(), TIMEOUT_S), \
                view.lines
            # A re-record: the take is thrown away and the same index starts again, in one recorder change.
            c.episodes.start("the second take counts")
            assert suite.wait_until(lambda: c.episodes.status().frames_recorded >= 5, TIMEOUT_S)
            time.sleep(0.5)  # the view's watch (20 Hz) sends a frame count above the new take's first one
            c.episodes.rerecord()
            assert suite.wait_until(lambda: c.episodes.status().frames_recorded >= 5, TIMEOUT_S)
            assert c.episodes.stop().episode_index == 1
            assert suite.wait_until(lambda: (episodes / "episode_000001.rrd").exists(), TIMEOUT_S), view.lines
    finally:
        code = view.stop()
    assert code == 0, "\n".join(view.lines)

    ep = read_rrd(episodes / "episode_000000.rrd")
    # Cameras: JPEG frames of the rendered scene. The episode lasts > 4 s (the holds above) at 20 Hz; the
    # view keeps only the newest observation when it falls behind, and even at a tenth of its rate on a
    # loaded machine it logs 8 frames.
    blobs = ep["/cameras/front"]["EncodedImage:blob"]
    assert len(blobs) >= 8, f"{len(blobs)} camera frames in the episode"
    assert all(b[0][:2] == [0xFF, 0xD8] for b in blobs), "camera frames are not JPEG"
    assert set(ep["/cameras/front"]["EncodedImage:media_type"][0]) == {"image/jpeg"}

    # Poses: measured and target transforms in the robot base frame, moving by the 3 cm the phone moved.
    for entity in ("/world/main/ee", "/world/main/target"):
        xs = [row[0] for row in ep[entity]["Transform3D:translation"]]
        assert len(xs) >= 8, f"{entity}: {len(xs)} poses"
        spread = max(math.dist(a, xs[0]) for a in xs)
        assert 0.02 < spread < 0.2, f"{entity} moved {spread:.4f} m over the episode"
        assert all(len(q[0]) == 4 for q in ep[entity]["Transform3D:quaternion"])
    # The workspace box of --config, as static data in the episode's own file.
    box = ep["/world/main/workspace"]
    centers, halves = box["Boxes3D:centers"][0][0], box["Boxes3D:half_sizes"][0][0]
    assert [round(c - h, 3) for c, h in zip(centers, halves)] == [0.05, -0.3, 0.0]
    assert [round(c + h, 3) for c, h in zip(centers, halves)] == [0.45, 0.3, 0.4]
    # Joints and gripper as scalar series, one value per joint per snapshot.
    joints = ep["/arms/main/joint_positions_rad"]["Scalars:scalars"]
    assert len(joints) >= 8 and len({len(j) for j in joints}) == 1 and len(joints[0]) >= 5
    assert len({tuple(j) for j in joints}) > 1, "joint positions never changed while the arm moved"
    assert all(len(g) == 2 for g in ep["/arms/main/gripper"]["Scalars:scalars"])

    # Events: the clutch cycle, the rejected jump, and the episode's own boundaries.
    arm_events = texts(ep, "/events/main")
    assert arm_events.count("clutch engaged") >= 2 and arm_events.count("clutch released") >= 2, arm_events
    assert any(re.match(r"gate rejected \d+ command", e) for e in arm_events), arm_events
    recording = texts(ep, "/events/recording")
    assert recording[0].startswith("episode 0 started: 'view test"), recording
    assert re.fullmatch(rf"episode 0 saved: {saved.length_frames} frames, .* s, task 'view test.*'", recording[-1]), \
        recording
    # The file starts at the episode's start: the arm's state when the view first saw it (logged before the
    # episode) is in --save's file, not in this one.
    assert not any(e.startswith("first seen") for e in arm_events), arm_events

    # The discarded take: its own file, ending with the discard.
    gone = read_rrd(episodes / "episode_000001.discarded.rrd")
    assert texts(gone, "/events/recording")[-1].startswith("episode 1 discarded")

    # The re-recorded take: its discarded first try under the next free name, then the saved episode 1.
    retake = texts(read_rrd(episodes / "episode_000001.discarded.1.rrd"), "/events/recording")
    assert retake[0].startswith("episode 1 started: 'the second take") and retake[-1] == "episode 1 discarded"
    one = texts(read_rrd(episodes / "episode_000001.rrd"), "/events/recording")
    assert one[0].startswith("episode 1 started") and one[-1].startswith("episode 1 saved: "), one

    # --save holds all of it: every boundary, and the frames in between.
    all_ = read_rrd(everything)
    text = texts(all_, "/events/recording")
    assert [e.split(":")[0] for e in text] == [
        "episode 0 started", "episode 0 saved", "episode 1 started", "episode 1 discarded",
        "episode 1 started", "episode 1 discarded", "episode 1 started", "episode 1 saved"], text
    assert len(all_["/cameras/front"]["EncodedImage:blob"]) >= len(blobs)
    assert texts(all_, "/events/main")[0].startswith("first seen")


def test_view_refuses_to_run_without_an_output(server: suite.Server) -> None:
    r = subprocess.run([sys.executable, "-m", "phone2act_view", "--url", server.target], check=False,
                       capture_output=True,
                       text=True, timeout=TIMEOUT_S)
    assert r.returncode == 2 and "nothing to do" in r.stderr, r.stderr


def test_view_reports_an_unreachable_server(tmp_path: Path) -> None:
    port = suite.free_port()  # nothing listens there
    r = subprocess.run([sys.executable, "-m", "phone2act_view", "--url", f"127.0.0.1:{port}", "--save",
                        str(tmp_path / "x.rrd")], check=False, capture_output=True, text=True, timeout=TIMEOUT_S)
    assert r.returncode == 1 and "cannot connect" in r.stderr, r.stderr


def test_view_streams_to_a_rerun_viewer_with_connect(server: suite.Server, tmp_path: Path) -> None:
    """`--connect` against rerun's own gRPC receiver (the `rerun` binary rerun-sdk installs, headless with
    `--save`): what the receiver got holds the camera and the poses."""
    port = suite.free_port()
    received = tmp_path / "received.rrd"
    receiver = subprocess.Popen(
        [str(Path(sys.executable).parent / "rerun"), "--bind", "127.0.0.1", "--port", str(port), "--save",
         str(received)], stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, start_new_session=True)
    try:
        def listening() -> bool:
            import socket

            with socket.socket() as s:
                return s.connect_ex(("127.0.0.1", port)) == 0

        assert suite.wait_until(listening, TIMEOUT_S), "rerun's receiver did not listen"
        r = subprocess.run([sys.executable, "-m", "phone2act_view", "--url", server.target, "--connect",
                            f"rerun+http://127.0.0.1:{port}/proxy", "--duration-s", "3"], check=False,
                           capture_output=True, text=True, timeout=TIMEOUT_S * 2)
        assert r.returncode == 0, r.stderr
    finally:
        # The `rerun` entry point is a launcher whose native viewer is a child of its own: ending only the
        # launcher left the receiver running after the suite. Its own session lets the whole group end.
        stop_process_group(receiver)
    got = read_rrd(received)
    # 3 s at 20 Hz is 60 rows; a tenth of that on a machine loaded 10x over.
    assert len(got["/cameras/front"]["EncodedImage:blob"]) >= 6, sorted(got)
    assert len(got["/world/main/ee"]["Transform3D:translation"]) >= 6
