"""Synchronous client: `Client`, `Episodes`, `PolicySession`, `TeleopSession`.

Streams run on a background thread each, so calling code stays plain blocking Python. Observations are kept
latest-only (a slow policy sees the newest state, never a backlog), other session events are queued.
"""

from __future__ import annotations

import queue
import threading
import time
from collections.abc import Callable, Iterable, Iterator, Sequence
from typing import Any, TypeVar

import grpc

from phone2act._common import (
    DEFAULT_TARGET,
    DELTA_EE,
    IMAGE_NONE,
    ArmLayout,
    auth_interceptor,
    channel_credentials,
    channel_options,
    hello_request,
    layouts_from_ready,
    make_chunk,
    make_pose,
    split_target,
)
from phone2act.errors import (
    DeadlineExceeded,
    NotFound,
    Phone2ActError,
    ServerUnavailable,
    SessionClosed,
    from_rpc_error,
)
from phone2act.v1 import (
    common_pb2,
    episodes_pb2,
    episodes_pb2_grpc,
    policy_pb2,
    policy_pb2_grpc,
    scene_pb2,
    scene_pb2_grpc,
    system_pb2,
    system_pb2_grpc,
    teleop_pb2,
    teleop_pb2_grpc,
)

T = TypeVar("T")
_CLOSE = object()


class Client:
    """A connection to a phone2act server.

    >>> with Client("127.0.0.1:50051") as c:
    ...     print([a.arm for a in c.list_arms()])

    `target` is `host:port`, `http://host:port`, `https://host:port` (TLS; `root_certificates` is the PEM
    to trust instead of the system's roots) or `unix:/path/to.sock`. The constructor waits up to
    `connect_timeout_s` for the server and raises `ServerUnavailable` (a `ConnectionError`) if it does not
    answer; 0 skips the wait.
    """

    def __init__(
        self,
        target: str = DEFAULT_TARGET,
        *,
        token: str | None = None,
        connect_timeout_s: float = 5.0,
        timeout_s: float = 30.0,
        root_certificates: bytes | None = None,
    ) -> None:
        self.target = target
        self.timeout_s = timeout_s
        address, tls = split_target(target)
        channel = (
            grpc.secure_channel(address, channel_credentials(root_certificates), options=channel_options(address))
            if tls
            else grpc.insecure_channel(address, options=channel_options(address))
        )
        if token:
            channel = grpc.intercept_channel(channel, auth_interceptor(token))
        self._channel = channel
        if connect_timeout_s > 0:
            try:
                grpc.channel_ready_future(channel).result(timeout=connect_timeout_s)
            except grpc.FutureTimeoutError:
                channel.close()
                raise ServerUnavailable(
                    f"cannot connect to the phone2act server at {target} within {connect_timeout_s:.1f} s; "
                    "is `phone2act serve` running and listening there?",
                    grpc.StatusCode.UNAVAILABLE,
                ) from None
        self.system_stub = system_pb2_grpc.SystemStub(channel)
        self.policy_stub = policy_pb2_grpc.PolicyStub(channel)
        self.teleop_stub = teleop_pb2_grpc.TeleopStub(channel)
        self.episodes = Episodes(self, episodes_pb2_grpc.EpisodesStub(channel))
        self.scene = Scene(self, scene_pb2_grpc.SceneStub(channel))

    # --- plumbing -------------------------------------------------------------------------------------

    def _call(self, what: str, fn: Callable[..., T], request: Any, timeout_s: float | None = None) -> T:
        try:
            return fn(request, timeout=timeout_s or self.timeout_s)
        except grpc.RpcError as e:
            raise from_rpc_error(e, what, self.target) from None

    def close(self) -> None:
        self._channel.close()

    def __enter__(self) -> "Client":
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # --- System ---------------------------------------------------------------------------------------

    def list_arms(self) -> list[common_pb2.ArmState]:
        return list(self._call("System.ListArms", self.system_stub.ListArms, system_pb2.ListArmsRequest()).arms)

    def arm(self, name: str) -> common_pb2.ArmState:
        for a in self.list_arms():
            if a.arm == name:
                return a
        raise NotFound(f"no arm {name!r} on {self.target}")

    def status(self) -> system_pb2.SystemStatus:
        return self._call("System.GetStatus", self.system_stub.GetStatus, system_pb2.GetStatusRequest())

    def dataset_info(self) -> system_pb2.DatasetInfo:
        return self._call(
            "System.GetDatasetInfo", self.system_stub.GetDatasetInfo, system_pb2.GetDatasetInfoRequest()
        )

    def list_cameras(self) -> list[common_pb2.CameraStatus]:
        r = self._call("System.ListCameras", self.system_stub.ListCameras, system_pb2.ListCamerasRequest())
        return list(r.cameras)

    # --- Policy ---------------------------------------------------------------------------------------

    def observe(
        self, arms: Sequence[str] = (), image_encoding: int = IMAGE_NONE, cameras: Sequence[str] = ()
    ) -> policy_pb2.Observation:
        """One observation now, without a session."""
        req = policy_pb2.GetObservationRequest(arms=list(arms), image_encoding=image_encoding, cameras=list(cameras))
        return self._call("Policy.GetObservation", self.policy_stub.GetObservation, req)

    def policy_session(
        self,
        arms: Sequence[str] = ("main",),
        *,
        observation_rate_hz: float = 10.0,
        request_control: bool = True,
        image_encoding: int = IMAGE_NONE,
        cameras: Sequence[str] = (),
        policy_name: str = "phone2act-python",
        silence_timeout_s: float = 1.0,
        ready_timeout_s: float = 10.0,
    ) -> PolicySession:
        """Open a Policy.Session; returns once `SessionReady` arrived (and control was granted, if asked)."""
        hello = hello_request(
            arms, observation_rate_hz, request_control, image_encoding, cameras, policy_name, silence_timeout_s
        )
        return PolicySession(self, hello, ready_timeout_s)

    def teleop(self, arm: str = "main", *, client_name: str = "phone2act-python", take_over: bool = False) -> TeleopSession:
        return TeleopSession(self, arm, client_name, take_over)


class Scene:
    """The task scene of a simulated arm (ball and basket): reset it between episodes, read it (success)."""

    def __init__(self, client: Client, stub: scene_pb2_grpc.SceneStub) -> None:
        self._c = client
        self._stub = stub

    def reset(self, arm: str, seed: int | None = None, home_arm: bool = False) -> scene_pb2.SceneState:
        """Re-draw the scene from `seed` (None: the arm's next seed). `home_arm` also puts the simulated arm
        at its initial joints; refused (`FailedPrecondition`) while a phone or policy drives it. Arms
        without a scene raise `Unimplemented`."""
        req = scene_pb2.ResetSceneRequest(arm=arm, seed=seed, home_arm=home_arm)
        return self._c._call("Scene.Reset", self._stub.Reset, req)

    def get(self, arm: str) -> scene_pb2.SceneState:
        return self._c._call("Scene.Get", self._stub.Get, scene_pb2.GetSceneRequest(arm=arm))


class Episodes:
    """Recorder control: start/stop/discard/rerecord episodes, list them, watch the recorder."""

    def __init__(self, client: Client, stub: episodes_pb2_grpc.EpisodesStub) -> None:
        self._c = client
        self._stub = stub

    def start(self, task: str, operator: str = "") -> common_pb2.RecordingStatus:
        """Start recording `task`; `operator` (who records it) goes into the episode's provenance."""
        request = episodes_pb2.StartEpisodeRequest(task=task, operator=operator)
        r = self._c._call("Episodes.Start", self._stub.Start, request)
        return r.status

    def stop(self) -> episodes_pb2.EpisodeInfo:
        """Stop and save; returns when the episode is on disk."""
        return self.stop_with_latency()[0]

    def stop_with_latency(self) -> tuple[episodes_pb2.EpisodeInfo, float]:
        r = self._c._call("Episodes.Stop", self._stub.Stop, episodes_pb2.StopEpisodeRequest())
        return r.episode, r.save_latency_s

    def discard(self) -> int:
        """Throw the episode in progress away; returns the number of frames discarded."""
        r = self._c._call("Episodes.Discard", self._stub.Discard, episodes_pb2.DiscardEpisodeRequest())
        return int(r.frames_discarded)

    def rerecord(self, task: str = "") -> common_pb2.RecordingStatus:
        r = self._c._call("Episodes.Rerecord", self._stub.Rerecord, episodes_pb2.RerecordEpisodeRequest(task=task))
        return r.status

    def list(self) -> list[episodes_pb2.EpisodeInfo]:
        return list(self._c._call("Episodes.List", self._stub.List, episodes_pb2.ListEpisodesRequest()).episodes)

    def status(self) -> common_pb2.RecordingStatus:
        return self._c._call("Episodes.Status", self._stub.Status, episodes_pb2.EpisodeStatusRequest())

    def watch(self, interval_s: float = 0.5) -> Iterator[common_pb2.RecordingStatus]:
        """Recorder status on every change (and every `interval_s`), until the caller stops iterating."""
        call = self._stub.Watch(episodes_pb2.WatchEpisodesRequest(interval_s=interval_s))
        try:
            yield from call
        except grpc.RpcError as e:
            if e.code() != grpc.StatusCode.CANCELLED:
                raise from_rpc_error(e, "Episodes.Watch", self._c.target) from None
        finally:
            call.cancel()


class _Stream:
    """A bidi call fed from a queue, read on a daemon thread. Subclasses handle each response."""

    def __init__(self, what: str, target: str) -> None:
        self._what = what
        self._target = target
        self._requests: queue.Queue[Any] = queue.Queue()
        self._error: Phone2ActError | None = None
        self._done = threading.Event()
        self._call: Any = None

    def _request_iter(self) -> Iterator[Any]:
        while True:
            item = self._requests.get()
            if item is _CLOSE:
                return
            yield item

    def _start(self, call_fn: Callable[[Iterator[Any]], Any]) -> None:
        self._call = call_fn(self._request_iter())
        threading.Thread(target=self._read, name=f"phone2act-{self._what}", daemon=True).start()

    def _read(self) -> None:
        try:
            for response in self._call:
                self._on_response(response)
            self._error = SessionClosed(f"{self._what}: the server ended the stream")
        except grpc.RpcError as e:
            if e.code() == grpc.StatusCode.CANCELLED:
                self._error = SessionClosed(f"{self._what}: closed by the client", e.code())
            else:
                self._error = from_rpc_error(e, self._what, self._target)
        finally:
            self._done.set()
            self._on_end()

    def _on_response(self, response: Any) -> None:  # pragma: no cover - overridden
        raise NotImplementedError

    def _on_end(self) -> None:
        pass

    def _send(self, request: Any) -> None:
        if self._done.is_set():
            raise self._error or SessionClosed(f"{self._what}: stream is closed")
        self._requests.put(request)

    @property
    def closed(self) -> bool:
        return self._done.is_set()

    @property
    def error(self) -> Phone2ActError | None:
        return self._error

    def close(self) -> None:
        """Half-close the stream and cancel it; idempotent."""
        self._requests.put(_CLOSE)
        if self._call is not None:
            self._call.cancel()
        self._done.wait(timeout=2.0)


class PolicySession(_Stream):
    """An open Policy.Session. Use as a context manager; `close()` releases the arms (they hold).

    - `layouts[arm]`: state/action names for the arm (`action_width` is what chunks must use).
    - `next_observation()`: the next observation newer than the last one returned (latest-only).
    - `push(...)`: send a chunk with the unary `Policy.PushChunk`, so a bad chunk raises at once
      (`InvalidArgument` carries the server's reason, e.g. the expected width).
    - `push_on_stream(...)`: send on the session stream; the answer arrives as an event.
    - `events`: a queue of `PolicyEvent`s other than observations (granted, revoked, accepted, rejected).
    """

    def __init__(self, client: Client, hello: policy_pb2.PolicyRequest, ready_timeout_s: float) -> None:
        super().__init__("Policy.Session", client.target)
        self._client = client
        self._cond = threading.Condition()
        self._latest: policy_pb2.Observation | None = None
        self._returned_id = 0
        self._ready: policy_pb2.SessionReady | None = None
        self.granted: policy_pb2.ControlGranted | None = None
        self.revoked: policy_pb2.ControlRevoked | None = None
        self.events: queue.Queue[policy_pb2.PolicyEvent] = queue.Queue(maxsize=10_000)
        self._requests.put(hello)
        self._start(client.policy_stub.Session)
        want_control = hello.hello.request_control
        deadline = time.monotonic() + ready_timeout_s
        with self._cond:
            while not self._is_ready(want_control) and not self.closed:
                left = deadline - time.monotonic()
                if left <= 0:
                    break
                self._cond.wait(timeout=left)
        if self._ready is None or (want_control and self.granted is None):
            err = self._error
            self.close()
            if err is not None and not isinstance(err, SessionClosed):
                raise err
            raise DeadlineExceeded(
                f"Policy.Session on {client.target}: no SessionReady/ControlGranted within {ready_timeout_s:.1f} s"
                + (f" ({err})" if err else "")
            )
        self.session_id: str = self._ready.session_id
        self.layouts: dict[str, ArmLayout] = layouts_from_ready(self._ready)

    def _is_ready(self, want_control: bool) -> bool:
        return self._ready is not None and (self.granted is not None or not want_control)

    def _on_response(self, ev: policy_pb2.PolicyEvent) -> None:
        kind = ev.WhichOneof("event")
        with self._cond:
            if kind == "observation":
                self._latest = ev.observation
            elif kind == "ready":
                self._ready = ev.ready
            else:
                if kind == "granted":
                    self.granted = ev.granted
                elif kind == "revoked":
                    self.revoked = ev.revoked
                try:
                    self.events.put_nowait(ev)
                except queue.Full:  # nobody reads events: drop the oldest, keep memory bounded
                    self.events.get_nowait()
                    self.events.put_nowait(ev)
            self._cond.notify_all()

    def _on_end(self) -> None:
        with self._cond:
            self._cond.notify_all()

    def __enter__(self) -> "PolicySession":
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def next_observation(self, timeout_s: float = 5.0) -> policy_pb2.Observation:
        """The newest observation not yet returned; waits for one up to `timeout_s`."""
        deadline = time.monotonic() + timeout_s
        with self._cond:
            while self._latest is None or self._latest.observation_id <= self._returned_id:
                if self.closed:
                    raise self._error or SessionClosed("Policy.Session closed")
                left = deadline - time.monotonic()
                if left <= 0:
                    raise DeadlineExceeded(f"no observation within {timeout_s:.1f} s")
                self._cond.wait(timeout=left)
            self._returned_id = self._latest.observation_id
            return self._latest

    def request_observation(self) -> None:
        self._send(policy_pb2.PolicyRequest(observe=policy_pb2.ObservationRequest()))

    def push(
        self,
        arm: str,
        steps: Iterable[Sequence[float]],
        step_period_s: float,
        *,
        observation_id: int = 0,
        mode: int = DELTA_EE,
        blend_steps: int = 0,
        timeout_s: float | None = None,
    ) -> policy_pb2.ChunkAccepted:
        chunk = make_chunk(arm, steps, step_period_s, observation_id, mode, blend_steps)
        req = policy_pb2.PushChunkRequest(session_id=self.session_id, chunk=chunk)
        return self._client._call("Policy.PushChunk", self._client.policy_stub.PushChunk, req, timeout_s)

    def push_on_stream(
        self,
        arm: str,
        steps: Iterable[Sequence[float]],
        step_period_s: float,
        *,
        observation_id: int = 0,
        mode: int = DELTA_EE,
        blend_steps: int = 0,
    ) -> None:
        self._send(policy_pb2.PolicyRequest(chunk=make_chunk(arm, steps, step_period_s, observation_id, mode, blend_steps)))

    def next_event(self, timeout_s: float = 5.0) -> policy_pb2.PolicyEvent:
        try:
            return self.events.get(timeout=timeout_s)
        except queue.Empty:
            if self.closed and self._error:
                raise self._error from None
            raise DeadlineExceeded(f"no policy event within {timeout_s:.1f} s") from None

    def release(self) -> None:
        self._send(policy_pb2.PolicyRequest(release=policy_pb2.ReleaseControl()))


class TeleopSession(_Stream):
    """A Teleop.Stream for one arm: send phone poses and buttons, read the latest feedback."""

    def __init__(self, client: Client, arm: str, client_name: str, take_over: bool) -> None:
        super().__init__("Teleop.Stream", client.target)
        self.arm = arm
        self._client_name = client_name
        self._seq = 0
        self._cond = threading.Condition()
        self.feedback: teleop_pb2.TeleopFeedback | None = None
        self._first = True
        self._take_over = take_over
        self._start(client.teleop_stub.Stream)

    def _on_response(self, fb: teleop_pb2.TeleopFeedback) -> None:
        with self._cond:
            self.feedback = fb
            self._cond.notify_all()

    def __enter__(self) -> "TeleopSession":
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def send(
        self,
        position: Sequence[float] | None = None,
        orientation_xyzw: Sequence[float] = (0.0, 0.0, 0.0, 1.0),
        *,
        buttons: Sequence[teleop_pb2.ButtonEvent] = (),
        tracking: int = teleop_pb2.TRACKING_STATE_TRACKING,
    ) -> int:
        """Send one sample (a pose in the phone's tracking frame and/or buttons); returns its seq."""
        self._seq += 1
        sample = teleop_pb2.PhoneSample(
            seq=self._seq,
            capture_time_ns=time.monotonic_ns(),
            buttons=list(buttons),
            client_name=self._client_name,
        )
        if self._first:
            sample.arm, sample.take_over, self._first = self.arm, self._take_over, False
        if position is not None:
            sample.tracking_from_phone.CopyFrom(make_pose(position, orientation_xyzw))
            sample.tracking = tracking
        else:
            sample.tracking = teleop_pb2.TRACKING_STATE_UNSPECIFIED
        self._send(sample)
        return self._seq

    def clutch(self, engage: bool, position: Sequence[float] | None = None,
               orientation_xyzw: Sequence[float] = (0.0, 0.0, 0.0, 1.0)) -> int:
        kind = teleop_pb2.ClutchCommand.KIND_ENGAGE if engage else teleop_pb2.ClutchCommand.KIND_DISENGAGE
        b = teleop_pb2.ButtonEvent(clutch=teleop_pb2.ClutchCommand(kind=kind))
        return self.send(position, orientation_xyzw, buttons=[b])

    def gripper(self, position: float) -> int:
        b = teleop_pb2.ButtonEvent(
            gripper=teleop_pb2.GripperCommand(kind=teleop_pb2.GripperCommand.KIND_SET, position=position)
        )
        return self.send(None, buttons=[b])

    def wait_feedback(self, seq: int, timeout_s: float = 2.0) -> teleop_pb2.TeleopFeedback:
        """Wait until feedback echoes `seq` (or a later sample)."""
        deadline = time.monotonic() + timeout_s
        with self._cond:
            while self.feedback is None or self.feedback.echoed_seq < seq:
                if self.closed:
                    raise self._error or SessionClosed("Teleop.Stream closed")
                left = deadline - time.monotonic()
                if left <= 0:
                    raise DeadlineExceeded(f"no teleop feedback for seq {seq} within {timeout_s:.1f} s")
                self._cond.wait(timeout=left)
            return self.feedback
