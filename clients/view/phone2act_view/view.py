"""The live view: three server streams in, rerun log calls out.

- `Policy.Session` without control, observations at the view's rate with camera frames (JPEG by default);
- `System.WatchStatus` at the same rate: arm poses, joints, gripper, owner, clutch, gate;
- `Episodes.Watch`: every change of the recorder (episode boundaries).

Each stream is read on its own thread into an `Inbox`. Observations and status snapshots are latest-only:
a view slower than the server skips to the newest instead of building a backlog, so memory stays bounded
and what is shown is current. Recorder changes are kept in order (few, small, and boundaries must not be
lost) in a bounded queue: when it is full its reader waits, and the server's watch stream, which keeps one
pending status, coalesces.
"""

from __future__ import annotations

import collections
import logging
import threading
import time
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, field
from typing import Any

import grpc
import numpy as np
import rerun as rr
from phone2act import Client
from phone2act.errors import from_rpc_error
from phone2act.v1 import common_pb2, system_pb2

from phone2act_view.events import ERROR, INFO, WARN, EpisodeTracker, arm_events
from phone2act_view.sink import Fanout

log = logging.getLogger("phone2act_view")

TIMELINE = "server_time"
_EPISODE_QUEUE = 256
_LEVEL = {INFO: rr.TextLogLevel.INFO, WARN: rr.TextLogLevel.WARN, ERROR: rr.TextLogLevel.ERROR}


@dataclass
class Workspace:
    """A workspace box (robot base frame, metres) of one arm."""

    min_m: Sequence[float]
    max_m: Sequence[float]


@dataclass
class ViewStats:
    observations: int = 0
    frames: int = 0
    statuses: int = 0
    skipped_observations: int = 0
    skipped_statuses: int = 0
    events: list[str] = field(default_factory=list)


class Inbox:
    """Latest-only slots for observations and status, an ordered bounded queue for recorder changes."""

    def __init__(self) -> None:
        self.cond = threading.Condition()
        self.latest: dict[str, Any] = {}
        self.overwritten: collections.Counter[str] = collections.Counter()
        self.recorder: collections.deque[Any] = collections.deque()
        self.errors: list[BaseException] = []
        self.closed = False

    def put_latest(self, kind: str, msg: Any) -> None:
        with self.cond:
            if kind in self.latest:
                self.overwritten[kind] += 1
            self.latest[kind] = msg
            self.cond.notify_all()

    def put_recorder(self, msg: Any) -> None:
        with self.cond:
            while len(self.recorder) >= _EPISODE_QUEUE and not self.closed:
                self.cond.wait(0.5)
            self.recorder.append(msg)
            self.cond.notify_all()

    def fail(self, e: BaseException) -> None:
        with self.cond:
            self.errors.append(e)
            self.cond.notify_all()

    def take(self, timeout_s: float) -> tuple[list[Any], dict[str, Any]]:
        with self.cond:
            if not self.recorder and not self.latest and not self.errors and not self.closed:
                self.cond.wait(timeout_s)
            recorder = list(self.recorder)
            self.recorder.clear()
            latest, self.latest = self.latest, {}
            self.cond.notify_all()
            return recorder, latest


def _pump(
    inbox: Inbox, name: str, target: str, items: Callable[[], Iterable[Any]], put: Callable[[Any], None]
) -> None:
    def run() -> None:
        try:
            for item in items():
                if inbox.closed:
                    return
                put(item)
            if not inbox.closed:
                inbox.fail(ConnectionError(f"{name}: the server ended the stream"))
        except grpc.RpcError as e:  # a raw stub's stream: the SDK's error, which says what and where
            if not inbox.closed:
                inbox.fail(from_rpc_error(e, name, target))
        except BaseException as e:  # noqa: BLE001 - handed to the main loop, which reports it
            if not inbox.closed:
                inbox.fail(e)

    threading.Thread(target=run, name=f"phone2act-view-{name}", daemon=True).start()


def _xyz(v: common_pb2.Vec3) -> list[float]:
    return [v.x, v.y, v.z]


def _xyzw(q: common_pb2.Quaternion) -> list[float]:
    return [q.x, q.y, q.z, q.w]


def _axes(length_m: float, alpha: int) -> rr.Arrows3D:
    # The x, y, z axes of a pose in red, green, blue: the pose's orientation at a glance.
    return rr.Arrows3D(
        origins=np.zeros((3, 3)),
        vectors=np.eye(3) * length_m,
        colors=[[230, 40, 40, alpha], [40, 200, 40, alpha], [40, 80, 230, alpha]],
    )


class View:
    def __init__(
        self,
        client: Client,
        fanout: Fanout,
        *,
        rate_hz: float,
        cameras: Sequence[str] = (),
        jpeg: bool = True,
        workspaces: dict[str, Workspace] | None = None,
    ) -> None:
        self.client = client
        self.out = fanout
        self.rate_hz = rate_hz
        self.cameras = list(cameras)
        self.jpeg = jpeg
        self.workspaces = workspaces or {}
        self.inbox = Inbox()
        self.stats = ViewStats()
        self._arms: dict[str, common_pb2.ArmState] = {}
        self._frame_seq: dict[str, int] = {}
        self._episodes = EpisodeTracker()
        # Server monotonic time minus this process's, from the newest status: recorder changes carry no time.
        self._clock_offset_ns: int | None = None
        self._calls: list[Any] = []
        self._session: Any = None

    # --- setup ------------------------------------------------------------------------------------------

    def log_static(self) -> None:
        arms = self.client.list_arms()
        self.out.log_static("world", rr.ViewCoordinates.FLU)  # robot base frame: x forward, y left, z up
        for a in arms:
            base = f"world/{a.arm}"
            self.out.log_static(f"{base}/ee/axes", _axes(0.05, 255))
            self.out.log_static(f"{base}/target/axes", _axes(0.035, 140))
            ws = self.workspaces.get(a.arm)
            if ws is not None:
                lo, hi = np.asarray(ws.min_m, float), np.asarray(ws.max_m, float)
                self.out.log_static(
                    f"{base}/workspace",
                    rr.Boxes3D(centers=[(lo + hi) / 2], half_sizes=[(hi - lo) / 2], labels=[f"{a.arm} workspace"]),
                )
            names = list(a.joint_names) or [f"joint{i}" for i in range(len(a.joint_positions_rad))]
            self.out.log_static(f"arms/{a.arm}/joint_positions_rad", rr.SeriesLines(names=names))
            self.out.log_static(f"arms/{a.arm}/gripper", rr.SeriesLines(names=["measured", "target"]))
            self.out.log_static(
                f"arms/{a.arm}/position_m",
                rr.SeriesLines(names=["x", "y", "z", "target x", "target y", "target z"]),
            )
            self.out.log_static(f"arms/{a.arm}/gate", rr.SeriesLines(names=["sent", "clamped", "rejected"]))
            self.out.log_static(f"arms/{a.arm}/engaged", rr.SeriesLines(names=["engaged"]))
        self.out.log_static("recording/frames", rr.SeriesLines(names=["frames recorded"]))

    def start(self) -> None:
        """Open the three streams."""
        enc = common_pb2.IMAGE_ENCODING_JPEG if self.jpeg else common_pb2.IMAGE_ENCODING_RGB8
        self._session = self.client.policy_session(
            arms=(),
            observation_rate_hz=self.rate_hz,
            request_control=False,
            image_encoding=enc,
            cameras=self.cameras,
            policy_name="phone2act-view",
        )
        session = self._session

        def observations() -> Iterable[Any]:
            while not self.inbox.closed:
                try:
                    yield session.next_observation(timeout_s=1.0)
                except Exception:
                    if session.closed:
                        raise
                    # No observation within a second (a stalled server): keep waiting, the status stream
                    # reports a lost connection.

        status_call = self.client.watch_status(interval_s=1.0 / self.rate_hz)
        self._calls.append(status_call)
        target, inbox = self.client.target, self.inbox
        _pump(inbox, "Policy.Session", target, observations, lambda m: inbox.put_latest("observation", m))
        _pump(inbox, "System.WatchStatus", target, lambda: status_call, lambda m: inbox.put_latest("status", m))
        # The recorder signals its phase changes, not each frame: at the view's rate the watch also carries
        # the frame count, whose drop is how a re-record (discard and start, coalesced into one change) shows.
        recorder_changes = self.client.episodes.watch(interval_s=1.0 / self.rate_hz)
        _pump(inbox, "Episodes.Watch", target, lambda: recorder_changes, inbox.put_recorder)

    def close(self) -> None:
        with self.inbox.cond:
            self.inbox.closed = True
            self.inbox.cond.notify_all()
        for c in self._calls:
            c.cancel()
        if self._session is not None:
            self._session.close()
        self.out.close()

    # --- main loop ----------------------------------------------------------------------------------------

    def run(self, stop: threading.Event, duration_s: float | None = None) -> None:
        deadline = None if duration_s is None else time.monotonic() + duration_s
        while not stop.is_set() and (deadline is None or time.monotonic() < deadline):
            recorder, latest = self.inbox.take(timeout_s=0.2)
            if self.inbox.errors:
                raise self.inbox.errors[0]
            if "status" in latest:
                self.on_status(latest["status"])
            for r in recorder:
                self.on_recorder(r)
            if "observation" in latest:
                self.on_observation(latest["observation"])
        self.stats.skipped_observations = self.inbox.overwritten["observation"]
        self.stats.skipped_statuses = self.inbox.overwritten["status"]

    def _server_now_s(self) -> float:
        offset = self._clock_offset_ns or 0
        return (time.monotonic_ns() + offset) * 1e-9

    def _event(self, path: str, level: str, text: str) -> None:
        self.stats.events.append(f"{path}: {text}")
        log.info("%s: %s", path, text)
        self.out.log(path, rr.TextLog(text, level=_LEVEL[level]))

    def on_status(self, s: system_pb2.SystemStatus) -> None:
        self.stats.statuses += 1
        self._clock_offset_ns = s.server_time_ns - time.monotonic_ns()
        self.out.set_time_s(TIMELINE, s.server_time_ns * 1e-9)
        for a in s.arms:
            self.on_arm(a)
        self.out.log("recording/frames", rr.Scalars([float(s.recording.frames_recorded)]))

    def on_arm(self, a: common_pb2.ArmState) -> None:
        for e in arm_events(self._arms.get(a.arm), a):
            self._event(f"events/{a.arm}", e.level, e.text)
        self._arms[a.arm] = a
        base = f"world/{a.arm}"
        ee, target = a.robot_from_ee, a.robot_from_target
        self.out.log(f"{base}/ee", rr.Transform3D(translation=_xyz(ee.position_m),
                                                  quaternion=rr.Quaternion(xyzw=_xyzw(ee.orientation))))
        self.out.log(f"{base}/target", rr.Transform3D(translation=_xyz(target.position_m),
                                                      quaternion=rr.Quaternion(xyzw=_xyzw(target.orientation))))
        arm = f"arms/{a.arm}"
        self.out.log(f"{arm}/joint_positions_rad", rr.Scalars(list(a.joint_positions_rad)))
        self.out.log(f"{arm}/gripper", rr.Scalars([a.gripper_position, a.gripper_target]))
        self.out.log(f"{arm}/position_m", rr.Scalars(_xyz(ee.position_m) + _xyz(target.position_m)))
        self.out.log(f"{arm}/gate", rr.Scalars([float(a.commands_sent), float(a.commands_clamped),
                                                float(a.commands_rejected)]))
        self.out.log(f"{arm}/engaged", rr.Scalars([1.0 if a.engaged else 0.0]))

    def on_recorder(self, r: common_pb2.RecordingStatus) -> None:
        self.out.set_time_s(TIMELINE, self._server_now_s())
        for e in self._episodes.update(r):
            if e.kind == "started":
                self.out.start_episode(e.index, e.task)
            text = self._saved_text(e.index) if e.kind == "saved" else e.text
            self._event("events/recording", e.level, text)
            if e.kind in ("saved", "discarded"):
                self.out.end_episode(e.kind)

    def _saved_text(self, index: int) -> str:
        # The recorder's changes carry no final length (its watch stream is not sent per frame): ask for it.
        try:
            info = next((e for e in self.client.episodes.list() if e.episode_index == index), None)
        except Exception as err:  # noqa: BLE001 - the event is still worth logging without its length
            log.warning("episode %d: cannot list episodes: %s", index, err)
            info = None
        if info is None:
            return f"episode {index} saved"
        return f"episode {index} saved: {info.length_frames} frames, {info.duration_s:.2f} s, task {info.task!r}"

    def on_observation(self, o: Any) -> None:
        self.stats.observations += 1
        self.out.set_time_s(TIMELINE, o.timestamp_ns * 1e-9)
        for f in o.frames:
            if self._frame_seq.get(f.camera) == f.frame_seq:
                continue  # the camera is slower than the view: this frame is already logged
            self._frame_seq[f.camera] = f.frame_seq
            path = f"cameras/{f.camera}"
            if f.encoding == common_pb2.IMAGE_ENCODING_JPEG:
                self.out.log(path, rr.EncodedImage(contents=f.data, media_type="image/jpeg"))
            elif f.encoding == common_pb2.IMAGE_ENCODING_RGB8:
                rgb = np.frombuffer(f.data, dtype=np.uint8).reshape(f.height, f.width, 3)
                self.out.log(path, rr.Image(rgb, color_model="RGB"))
            else:
                continue
            self.stats.frames += 1
