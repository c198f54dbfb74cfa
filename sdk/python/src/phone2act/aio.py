"""asyncio client: `AsyncClient`, `AsyncEpisodes`, `AsyncPolicySession` (same shapes as the sync layer)."""

from __future__ import annotations

import asyncio
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
    channel_options,
    hello_request,
    layouts_from_ready,
    make_chunk,
)
from phone2act.errors import (
    DeadlineExceeded,
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
    system_pb2,
    system_pb2_grpc,
)

T = TypeVar("T")


class AsyncClient:
    """asyncio counterpart of `phone2act.Client`. Create with `await AsyncClient.connect(...)`."""

    def __init__(self, target: str, token: str | None, timeout_s: float) -> None:
        self.target = target
        self.timeout_s = timeout_s
        self._md = auth_metadata(token)
        self._channel = grpc.aio.insecure_channel(target, options=channel_options(target))
        self.system_stub = system_pb2_grpc.SystemStub(self._channel)
        self.policy_stub = policy_pb2_grpc.PolicyStub(self._channel)
        self.episodes = AsyncEpisodes(self, episodes_pb2_grpc.EpisodesStub(self._channel))

    @classmethod
    async def connect(
        cls,
        target: str = DEFAULT_TARGET,
        *,
        token: str | None = None,
        connect_timeout_s: float = 5.0,
        timeout_s: float = 30.0,
    ) -> AsyncClient:
        self = cls(target, token, timeout_s)
        if connect_timeout_s > 0:
            try:
                await asyncio.wait_for(self._channel.channel_ready(), connect_timeout_s)
            except asyncio.TimeoutError:
                await self._channel.close()
                raise ServerUnavailable(
                    f"cannot connect to the phone2act server at {target} within {connect_timeout_s:.1f} s; "
                    "is `phone2act serve` running and listening there?",
                    grpc.StatusCode.UNAVAILABLE,
                ) from None
        return self

    async def _call(self, what: str, fn: Callable[..., Awaitable[T]], request: Any) -> T:
        try:
            return await fn(request, timeout=self.timeout_s, metadata=self._md)
        except grpc.aio.AioRpcError as e:
            raise from_rpc_error(e, what, self.target) from None

    async def close(self) -> None:
        await self._channel.close()

    async def __aenter__(self) -> "AsyncClient":
        return self

    async def __aexit__(self, *exc: object) -> None:
        await self.close()

    async def list_arms(self) -> list[common_pb2.ArmState]:
        r = await self._call("System.ListArms", self.system_stub.ListArms, system_pb2.ListArmsRequest())
        return list(r.arms)

    async def status(self) -> system_pb2.SystemStatus:
        return await self._call("System.GetStatus", self.system_stub.GetStatus, system_pb2.GetStatusRequest())

    async def observe(self, arms: Sequence[str] = (), image_encoding: int = IMAGE_NONE) -> policy_pb2.Observation:
        req = policy_pb2.GetObservationRequest(arms=list(arms), image_encoding=image_encoding)
        return await self._call("Policy.GetObservation", self.policy_stub.GetObservation, req)

    async def policy_session(
        self,
        arms: Sequence[str] = ("main",),
        *,
        observation_rate_hz: float = 10.0,
        request_control: bool = True,
        image_encoding: int = IMAGE_NONE,
        cameras: Sequence[str] = (),
        policy_name: str = "phone2act-python-aio",
        silence_timeout_s: float = 1.0,
        ready_timeout_s: float = 10.0,
    ) -> AsyncPolicySession:
        hello = hello_request(
            arms, observation_rate_hz, request_control, image_encoding, cameras, policy_name, silence_timeout_s
        )
        session = AsyncPolicySession(self, hello)
        await session._open(ready_timeout_s)
        return session


class AsyncEpisodes:
    def __init__(self, client: AsyncClient, stub: episodes_pb2_grpc.EpisodesStub) -> None:
        self._c = client
        self._stub = stub

    async def start(self, task: str) -> common_pb2.RecordingStatus:
        r = await self._c._call("Episodes.Start", self._stub.Start, episodes_pb2.StartEpisodeRequest(task=task))
        return r.status

    async def stop(self) -> episodes_pb2.EpisodeInfo:
        r = await self._c._call("Episodes.Stop", self._stub.Stop, episodes_pb2.StopEpisodeRequest())
        return r.episode

    async def discard(self) -> int:
        r = await self._c._call("Episodes.Discard", self._stub.Discard, episodes_pb2.DiscardEpisodeRequest())
        return int(r.frames_discarded)

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
        self.error: Phone2ActError | None = None
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
                    self.error = SessionClosed("Policy.Session: the server ended the stream")
                    break
                kind = ev.WhichOneof("event")
                if kind == "observation":
                    self._latest = ev.observation
                else:
                    if kind == "granted":
                        self.granted = ev.granted
                    elif kind == "revoked":
                        self.revoked = ev.revoked
                    if self.events.full():
                        self.events.get_nowait()
                    self.events.put_nowait(ev)
                self._changed.set()
        except grpc.aio.AioRpcError as e:
            self.error = (
                SessionClosed("Policy.Session: closed by the client", e.code())
                if e.code() == grpc.StatusCode.CANCELLED
                else from_rpc_error(e, "Policy.Session", self._client.target)
            )
        except asyncio.CancelledError:
            self.error = SessionClosed("Policy.Session: closed by the client")
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
            if self.error is not None:
                raise self.error
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
    ) -> policy_pb2.ChunkAccepted:
        chunk = make_chunk(arm, steps, step_period_s, observation_id, mode, blend_steps)
        req = policy_pb2.PushChunkRequest(session_id=self.session_id, chunk=chunk)
        return await self._client._call("Policy.PushChunk", self._client.policy_stub.PushChunk, req)

    async def push_on_stream(
        self, arm: str, steps: Iterable[Sequence[float]], step_period_s: float, *,
        observation_id: int = 0, mode: int = DELTA_EE,
    ) -> None:
        chunk = make_chunk(arm, steps, step_period_s, observation_id, mode)
        await self._call.write(policy_pb2.PolicyRequest(chunk=chunk))

    async def release(self) -> None:
        await self._call.write(policy_pb2.PolicyRequest(release=policy_pb2.ReleaseControl()))

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
