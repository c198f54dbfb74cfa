"""asyncio client: `AsyncClient`, `AsyncEpisodes`, `AsyncScene`, `AsyncPolicySession`, `AsyncTeleopSession`.

The protocol's one implementation: the blocking layer (`phone2act.Client` and friends) runs these coroutines
on a background event loop, with the same constructor, methods, arguments and defaults
(`tests/python/test_sdk.py` checks that every coroutine has its blocking forward). The constructor does not
wait for the server: `async with AsyncClient(...)` or `await AsyncClient.connect(...)` does, up to
`connect_timeout_s`.
"""

from __future__ import annotations

import asyncio
import time
from collections.abc import AsyncIterator, Awaitable, Callable, Iterable, Sequence
from typing import Any, TypeVar

import grpc
import grpc.aio

from phone2act._common import (
    DEFAULT_TARGET,
    DELTA_EE,
    IMAGE_NONE,
    ArmLayout,
    auth_metadata,
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


class AsyncClient:
    """asyncio counterpart of `phone2act.Client`, with the same constructor.

    >>> async with AsyncClient("127.0.0.1:50051") as c:
    ...     print([a.arm for a in await c.list_arms()])
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
        self.connect_timeout_s = connect_timeout_s
        self._md = auth_metadata(token)
        address, tls = split_target(target)
        self._channel = (
            grpc.aio.secure_channel(address, channel_credentials(root_certificates), options=channel_options(address))
            if tls
            else grpc.aio.insecure_channel(address, options=channel_options(address))
        )
        self.system_stub = system_pb2_grpc.SystemStub(self._channel)
        self.policy_stub = policy_pb2_grpc.PolicyStub(self._channel)
        self.teleop_stub = teleop_pb2_grpc.TeleopStub(self._channel)
        self.episodes = AsyncEpisodes(self, episodes_pb2_grpc.EpisodesStub(self._channel))
        self.scene = AsyncScene(self, scene_pb2_grpc.SceneStub(self._channel))

    @classmethod
    async def connect(
        cls,
        target: str = DEFAULT_TARGET,
        *,
        token: str | None = None,
        connect_timeout_s: float = 5.0,
        timeout_s: float = 30.0,
        root_certificates: bytes | None = None,
    ) -> AsyncClient:
        """A client whose server answered within `connect_timeout_s` (0 skips the wait)."""
        self = cls(
            target,
            token=token,
            connect_timeout_s=connect_timeout_s,
            timeout_s=timeout_s,
            root_certificates=root_certificates,
        )
        await self._wait_ready()
        return self

    async def _wait_ready(self) -> None:
        if self.connect_timeout_s <= 0:
            return
        try:
            await asyncio.wait_for(self._channel.channel_ready(), self.connect_timeout_s)
        except asyncio.TimeoutError:
            await self._channel.close()
            raise ServerUnavailable(
                f"cannot connect to the phone2act server at {self.target} within {self.connect_timeout_s:.1f} s; "
                "is `phone2act serve` running and listening there?",
                grpc.StatusCode.UNAVAILABLE,
            ) from None

    async def _call(
        self, what: str, fn: Callable[..., Awaitable[T]], request: Any, timeout_s: float | None = None
    ) -> T:
        try:
            return await fn(request, timeout=timeout_s or self.timeout_s, metadata=self._md)
        except grpc.aio.AioRpcError as e:
            raise from_rpc_error(e, what, self.target) from None

    async def close(self) -> None:
        await self._channel.close()

    async def __aenter__(self) -> "AsyncClient":
        await self._wait_ready()
        return self

    async def __aexit__(self, *exc: object) -> None:
        await self.close()

    # --- System ---------------------------------------------------------------------------------------

    async def list_arms(self) -> list[common_pb2.ArmState]:
        r = await self._call("System.ListArms", self.system_stub.ListArms, system_pb2.ListArmsRequest())
        return list(r.arms)

    async def arm(self, name: str) -> common_pb2.ArmState:
        for a in await self.list_arms():
            if a.arm == name:
                return a
        raise NotFound(f"no arm {name!r} on {self.target}")

    async def status(self) -> system_pb2.SystemStatus:
        return await self._call("System.GetStatus", self.system_stub.GetStatus, system_pb2.GetStatusRequest())

    async def dataset_info(self) -> system_pb2.DatasetInfo:
        return await self._call(
            "System.GetDatasetInfo", self.system_stub.GetDatasetInfo, system_pb2.GetDatasetInfoRequest()
        )

    def _watch_status_call(self, interval_s: float = 0.5) -> Any:
        """The raw `System.WatchStatus` stream call (the server's status every `interval_s`), authorised;
        iterate it, or `read()` it, on this client's event loop and `cancel()` it to end it."""
        return self.system_stub.WatchStatus(system_pb2.WatchStatusRequest(interval_s=interval_s), metadata=self._md)

    async def watch_status(self, interval_s: float = 0.5) -> AsyncIterator[system_pb2.SystemStatus]:
        """The server's status every `interval_s`, until the caller stops iterating."""
        call = self._watch_status_call(interval_s)
        try:
            async for status in call:
                yield status
        except grpc.aio.AioRpcError as e:
            if e.code() != grpc.StatusCode.CANCELLED:
                raise from_rpc_error(e, "System.WatchStatus", self.target) from None
        finally:
            call.cancel()

    async def list_cameras(self) -> list[common_pb2.CameraStatus]:
        r = await self._call("System.ListCameras", self.system_stub.ListCameras, system_pb2.ListCamerasRequest())
        return list(r.cameras)

    # --- Policy ---------------------------------------------------------------------------------------

    async def observe(
        self, arms: Sequence[str] = (), image_encoding: int = IMAGE_NONE, cameras: Sequence[str] = ()
    ) -> policy_pb2.Observation:
        """One observation now, without a session."""
        req = policy_pb2.GetObservationRequest(arms=list(arms), image_encoding=image_encoding, cameras=list(cameras))
        return await self._call("Policy.GetObservation", self.policy_stub.GetObservation, req)

    async def policy_session(
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
    ) -> AsyncPolicySession:
        """Open a Policy.Session; returns once `SessionReady` arrived (and control was granted, if asked)."""
        hello = hello_request(
            arms, observation_rate_hz, request_control, image_encoding, cameras, policy_name, silence_timeout_s
        )
        session = AsyncPolicySession(self, hello)
        await session._open(ready_timeout_s)
        return session

    async def teleop(
        self, arm: str = "main", *, client_name: str = "phone2act-python", take_over: bool = False
    ) -> AsyncTeleopSession:
        """Open a Teleop.Stream for `arm` (the arm is claimed with the first sample sent)."""
        return AsyncTeleopSession(self, arm, client_name, take_over)


class AsyncScene:
    def __init__(self, client: AsyncClient, stub: scene_pb2_grpc.SceneStub) -> None:
        self._c = client
        self._stub = stub

    async def reset(self, arm: str, seed: int | None = None, home_arm: bool = False) -> scene_pb2.SceneState:
        """Re-draw the scene from `seed` (None: the arm's next seed); see `phone2act.client.Scene.reset`."""
        req = scene_pb2.ResetSceneRequest(arm=arm, seed=seed, home_arm=home_arm)
        return await self._c._call("Scene.Reset", self._stub.Reset, req)

    async def get(self, arm: str) -> scene_pb2.SceneState:
        return await self._c._call("Scene.Get", self._stub.Get, scene_pb2.GetSceneRequest(arm=arm))


def _outcome(success: bool | None) -> int:
    """`StopEpisodeRequest.outcome` for an operator's verdict."""
    if success is None:
        return common_pb2.EPISODE_OUTCOME_UNSPECIFIED
    return common_pb2.EPISODE_OUTCOME_SUCCESS if success else common_pb2.EPISODE_OUTCOME_FAILURE


class AsyncEpisodes:
    def __init__(self, client: AsyncClient, stub: episodes_pb2_grpc.EpisodesStub) -> None:
        self._c = client
        self._stub = stub

    async def start(self, task: str, operator: str = "") -> common_pb2.RecordingStatus:
        """Start recording `task`; `operator` (who records it) goes into the episode's provenance."""
        request = episodes_pb2.StartEpisodeRequest(task=task, operator=operator)
        r = await self._c._call("Episodes.Start", self._stub.Start, request)
        return r.status

    async def stop(self, success: bool | None = None) -> episodes_pb2.EpisodeInfo:
        """Stop and save; returns when the episode is on disk. `success` is the operator's outcome (True: a
        success, False: a failure, None: not given), kept in the episode's provenance and, in a dataset that
        records `next.success`, as its last frame's value."""
        return (await self.stop_with_latency(success))[0]

    async def stop_with_latency(self, success: bool | None = None) -> tuple[episodes_pb2.EpisodeInfo, float]:
        request = episodes_pb2.StopEpisodeRequest(outcome=_outcome(success))
        r = await self._c._call("Episodes.Stop", self._stub.Stop, request)
        return r.episode, r.save_latency_s

    async def discard(self) -> int:
        r = await self._c._call("Episodes.Discard", self._stub.Discard, episodes_pb2.DiscardEpisodeRequest())
        return int(r.frames_discarded)

    async def save_highlight(
        self, task: str, operator: str = "", success: bool | None = None, keep_recording: bool = False
    ) -> episodes_pb2.SaveHighlightResponse:
        """Save the last seconds the recorder kept while idle (the server's `[recorder] highlight_s`, LeRobot's
        `highlight`) as an episode of `task`; returns when it is on disk (`.episode`). `success` is the
        operator's outcome, as in `stop`. With `keep_recording` the kept seconds begin the episode in progress
        instead (`.status`), which records on until `stop`. Refused (`FAILED_PRECONDITION`) when the server keeps
        nothing, and while an episode is recorded."""
        request = episodes_pb2.SaveHighlightRequest(
            task=task, operator=operator, keep_recording=keep_recording, outcome=_outcome(success)
        )
        return await self._c._call("Episodes.SaveHighlight", self._stub.SaveHighlight, request)

    async def rerecord(self, task: str = "") -> common_pb2.RecordingStatus:
        req = episodes_pb2.RerecordEpisodeRequest(task=task)
        return (await self._c._call("Episodes.Rerecord", self._stub.Rerecord, req)).status

    async def watch(self, interval_s: float = 0.5) -> AsyncIterator[common_pb2.RecordingStatus]:
        """Recorder status on every change (and every `interval_s`), until the caller stops iterating."""
        call = self._stub.Watch(episodes_pb2.WatchEpisodesRequest(interval_s=interval_s), metadata=self._c._md)
        try:
            async for status in call:
                yield status
        except grpc.aio.AioRpcError as e:
            if e.code() != grpc.StatusCode.CANCELLED:
                raise from_rpc_error(e, "Episodes.Watch", self._c.target) from None
        finally:
            call.cancel()

    async def list(self) -> list[episodes_pb2.EpisodeInfo]:
        r = await self._c._call("Episodes.List", self._stub.List, episodes_pb2.ListEpisodesRequest())
        return list(r.episodes)

    async def status(self) -> common_pb2.RecordingStatus:
        return await self._c._call("Episodes.Status", self._stub.Status, episodes_pb2.EpisodeStatusRequest())


class AsyncPolicySession:
    """An open Policy.Session on asyncio. `async with` closes it; observations are latest-only."""

    def __init__(self, client: AsyncClient, hello: policy_pb2.PolicyRequest) -> None:
        self._client = client
        self._hello = hello
        self._call: Any = None
        self._latest: policy_pb2.Observation | None = None
        self._returned_id = 0
        self._changed = asyncio.Event()
        self.events: asyncio.Queue[policy_pb2.PolicyEvent] = asyncio.Queue(maxsize=10_000)
        self.granted: policy_pb2.ControlGranted | None = None
        self.revoked: policy_pb2.ControlRevoked | None = None
        # Arms the operator took from this session (`ControlPaused`) and has not handed back yet
        # (`ControlResumed`): chunks for them are refused meanwhile.
        self.waiting: set[str] = set()
        self._error: Phone2ActError | None = None
        self._reader: asyncio.Task[None] | None = None
        self.session_id = ""
        self.layouts: dict[str, ArmLayout] = {}

    async def _open(self, ready_timeout_s: float) -> None:
        self._call = self._client.policy_stub.Session(metadata=self._client._md)
        try:
            await self._call.write(self._hello)
            ready = await asyncio.wait_for(self._read_ready(), ready_timeout_s)
        except grpc.aio.AioRpcError as e:
            raise from_rpc_error(e, "Policy.Session", self._client.target) from None
        except asyncio.TimeoutError:
            self._call.cancel()
            raise DeadlineExceeded(f"Policy.Session: no SessionReady within {ready_timeout_s:.1f} s") from None
        self.session_id = ready.session_id
        self.layouts = layouts_from_ready(ready)
        self._reader = asyncio.get_running_loop().create_task(self._read())
        if self._hello.hello.request_control:
            await self._wait(lambda: self.granted is not None, ready_timeout_s, "ControlGranted")

    async def _read_ready(self) -> policy_pb2.SessionReady:
        ev = await self._call.read()
        if ev is grpc.aio.EOF or ev.WhichOneof("event") != "ready":
            raise SessionClosed(f"Policy.Session: expected SessionReady, got {ev}")
        return ev.ready

    async def _read(self) -> None:
        try:
            while True:
                ev = await self._call.read()
                if ev is grpc.aio.EOF:
                    self._error = SessionClosed("Policy.Session: the server ended the stream")
                    break
                kind = ev.WhichOneof("event")
                if kind == "observation":
                    self._latest = ev.observation
                else:
                    if kind == "granted":
                        self.granted = ev.granted
                    elif kind == "revoked":
                        self.revoked = ev.revoked
                        self.waiting.discard(ev.revoked.arm)
                    elif kind == "paused":
                        self.waiting.add(ev.paused.arm)
                    elif kind == "resumed":
                        self.waiting.discard(ev.resumed.arm)
                    if self.events.full():
                        self.events.get_nowait()
                    self.events.put_nowait(ev)
                self._changed.set()
        except grpc.aio.AioRpcError as e:
            self._error = (
                SessionClosed("Policy.Session: closed by the client", e.code())
                if e.code() == grpc.StatusCode.CANCELLED
                else from_rpc_error(e, "Policy.Session", self._client.target)
            )
        except asyncio.CancelledError:
            self._error = SessionClosed("Policy.Session: closed by the client")
        finally:
            self._changed.set()

    async def _wait(self, predicate: Callable[[], bool], timeout_s: float, what: str) -> None:
        loop = asyncio.get_running_loop()
        deadline = loop.time() + timeout_s
        while True:
            # Clear before checking, so a change that lands between the check and the wait is not lost.
            self._changed.clear()
            if predicate():
                return
            if self._error is not None:
                raise self._error
            left = deadline - loop.time()
            if left <= 0:
                raise DeadlineExceeded(f"Policy.Session: no {what} within {timeout_s:.1f} s")
            try:
                await asyncio.wait_for(self._changed.wait(), left)
            except asyncio.TimeoutError:
                pass

    async def next_observation(self, timeout_s: float = 5.0) -> policy_pb2.Observation:
        await self._wait(
            lambda: self._latest is not None and self._latest.observation_id > self._returned_id,
            timeout_s,
            "observation",
        )
        assert self._latest is not None
        self._returned_id = self._latest.observation_id
        return self._latest

    async def push(
        self,
        arm: str,
        steps: Iterable[Sequence[float]],
        step_period_s: float,
        *,
        observation_id: int = 0,
        mode: int = DELTA_EE,
        blend_steps: int = 0,
        keep_steps: int = 0,
        timeout_s: float | None = None,
    ) -> policy_pb2.ChunkAccepted:
        chunk = make_chunk(arm, steps, step_period_s, observation_id, mode, blend_steps, keep_steps)
        req = policy_pb2.PushChunkRequest(session_id=self.session_id, chunk=chunk)
        return await self._client._call("Policy.PushChunk", self._client.policy_stub.PushChunk, req, timeout_s)

    async def push_on_stream(
        self,
        arm: str,
        steps: Iterable[Sequence[float]],
        step_period_s: float,
        *,
        observation_id: int = 0,
        mode: int = DELTA_EE,
        blend_steps: int = 0,
        keep_steps: int = 0,
    ) -> None:
        chunk = make_chunk(arm, steps, step_period_s, observation_id, mode, blend_steps, keep_steps)
        await self._call.write(policy_pb2.PolicyRequest(chunk=chunk))

    async def request_observation(self) -> None:
        await self._call.write(policy_pb2.PolicyRequest(observe=policy_pb2.ObservationRequest()))

    async def next_event(self, timeout_s: float = 5.0) -> policy_pb2.PolicyEvent:
        try:
            return await asyncio.wait_for(self.events.get(), timeout_s)
        except asyncio.TimeoutError:
            if self._error is not None and self._reader is not None and self._reader.done():
                raise self._error from None
            raise DeadlineExceeded(f"no policy event within {timeout_s:.1f} s") from None

    @property
    def closed(self) -> bool:
        return self._reader is not None and self._reader.done()

    @property
    def error(self) -> Phone2ActError | None:
        """Why the session ended, once it has."""
        return self._error

    async def release(self) -> None:
        await self._call.write(policy_pb2.PolicyRequest(release=policy_pb2.ReleaseControl()))

    async def loading(self) -> None:
        """Say the policy is loading: its arms hold until its first chunk, at most the arm's
        `chunk.max_loading_s` (default 300 s) from the first call; later calls are keep-alives that do not
        extend it. The answer arrives as a `loading` event (`LoadingAccepted`)."""
        await self._call.write(policy_pb2.PolicyRequest(loading=policy_pb2.PolicyLoading()))

    async def close(self) -> None:
        if self._call is not None:
            self._call.cancel()
        if self._reader is not None:
            self._reader.cancel()
            try:
                await self._reader
            except asyncio.CancelledError:
                pass

    async def __aenter__(self) -> "AsyncPolicySession":
        return self

    async def __aexit__(self, *exc: object) -> None:
        await self.close()


class AsyncTeleopSession:
    """A Teleop.Stream for one arm on asyncio: send phone poses and buttons, read the latest feedback."""

    def __init__(self, client: AsyncClient, arm: str, client_name: str, take_over: bool) -> None:
        self._client = client
        self.arm = arm
        self._client_name = client_name
        self._take_over = take_over
        self._seq = 0
        self._first = True
        self.feedback: teleop_pb2.TeleopFeedback | None = None
        self._error: Phone2ActError | None = None
        self._changed = asyncio.Event()
        self._call: Any = client.teleop_stub.Stream(metadata=client._md)
        self._reader = asyncio.get_running_loop().create_task(self._read())

    async def _read(self) -> None:
        try:
            while True:
                fb = await self._call.read()
                if fb is grpc.aio.EOF:
                    self._error = SessionClosed("Teleop.Stream: the server ended the stream")
                    break
                self.feedback = fb
                self._changed.set()
        except grpc.aio.AioRpcError as e:
            self._error = (
                SessionClosed("Teleop.Stream: closed by the client", e.code())
                if e.code() == grpc.StatusCode.CANCELLED
                else from_rpc_error(e, "Teleop.Stream", self._client.target)
            )
        except asyncio.CancelledError:
            self._error = SessionClosed("Teleop.Stream: closed by the client")
        finally:
            self._changed.set()

    @property
    def closed(self) -> bool:
        return self._reader.done()

    @property
    def error(self) -> Phone2ActError | None:
        return self._error

    async def send(
        self,
        position: Sequence[float] | None = None,
        orientation_xyzw: Sequence[float] = (0.0, 0.0, 0.0, 1.0),
        *,
        buttons: Sequence[teleop_pb2.ButtonEvent] = (),
        tracking: int = teleop_pb2.TRACKING_STATE_TRACKING,
    ) -> int:
        """Send one sample (a pose in the phone's tracking frame and/or buttons); returns its seq."""
        if self.closed:
            raise self._error or SessionClosed("Teleop.Stream closed")
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
        await self._call.write(sample)
        return self._seq

    async def clutch(
        self, engage: bool, position: Sequence[float] | None = None,
        orientation_xyzw: Sequence[float] = (0.0, 0.0, 0.0, 1.0),
    ) -> int:
        kind = teleop_pb2.ClutchCommand.KIND_ENGAGE if engage else teleop_pb2.ClutchCommand.KIND_DISENGAGE
        b = teleop_pb2.ButtonEvent(clutch=teleop_pb2.ClutchCommand(kind=kind))
        return await self.send(position, orientation_xyzw, buttons=[b])

    async def gripper(self, position: float) -> int:
        b = teleop_pb2.ButtonEvent(
            gripper=teleop_pb2.GripperCommand(kind=teleop_pb2.GripperCommand.KIND_SET, position=position)
        )
        return await self.send(None, buttons=[b])

    async def hand_back(self) -> int:
        """Hand the arm back to the policy waiting for it (`ArmState.waiting_policy_id`). Nothing moves: the arm
        holds until the policy's first chunk answering an observation taken after the hand-back. Without a
        waiting policy the feedback's `error` says so."""
        b = teleop_pb2.ButtonEvent(hand_back=teleop_pb2.HandBackCommand())
        return await self.send(None, buttons=[b])

    async def wait_feedback(self, seq: int, timeout_s: float = 2.0) -> teleop_pb2.TeleopFeedback:
        """Wait until feedback echoes `seq` (or a later sample)."""
        loop = asyncio.get_running_loop()
        deadline = loop.time() + timeout_s
        while True:
            self._changed.clear()
            if self.feedback is not None and self.feedback.echoed_seq >= seq:
                return self.feedback
            if self.closed:
                raise self._error or SessionClosed("Teleop.Stream closed")
            left = deadline - loop.time()
            if left <= 0:
                raise DeadlineExceeded(f"no teleop feedback for seq {seq} within {timeout_s:.1f} s")
            try:
                await asyncio.wait_for(self._changed.wait(), left)
            except asyncio.TimeoutError:
                pass

    async def close(self) -> None:
        self._call.cancel()
        self._reader.cancel()
        try:
            await self._reader
        except asyncio.CancelledError:
            pass

    async def __aenter__(self) -> "AsyncTeleopSession":
        return self

    async def __aexit__(self, *exc: object) -> None:
        await self.close()
