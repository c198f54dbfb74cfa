"""Synchronous client: `Client`, `Episodes`, `Scene`, `PolicySession`, `TeleopSession`.

A blocking face on the asyncio client (`phone2act.aio`): every call runs the `AsyncClient`'s coroutine on
one event loop that a daemon thread keeps for the whole process, and waits for its result. There is one
implementation of the protocol; this module only carries calls across the thread. Observations are kept
latest-only (a slow policy sees the newest state, never a backlog), other session events are queued.
"""

from __future__ import annotations

import asyncio
import threading
from collections.abc import AsyncIterator, Coroutine, Iterable, Iterator, Sequence
from typing import Any, TypeVar

import grpc
import grpc.aio

from phone2act import aio
from phone2act._common import DEFAULT_TARGET, DELTA_EE, IMAGE_NONE, ArmLayout
from phone2act.errors import Phone2ActError, from_rpc_error
from phone2act.v1 import common_pb2, episodes_pb2, policy_pb2, scene_pb2, system_pb2, teleop_pb2

T = TypeVar("T")

_loop: asyncio.AbstractEventLoop | None = None
_loop_lock = threading.Lock()


def _run(coro: Coroutine[Any, Any, T]) -> T:
    """Runs `coro` on the process's client loop and waits for its result (or its exception)."""
    global _loop
    with _loop_lock:
        if _loop is None:
            # One loop for every blocking client: grpc.aio binds a channel to the loop that made it, and a
            # daemon thread never keeps the interpreter from exiting.
            _loop = asyncio.new_event_loop()
            threading.Thread(target=_loop.run_forever, name="phone2act-client", daemon=True).start()
        loop = _loop
    return asyncio.run_coroutine_threadsafe(coro, loop).result()


async def _call(fn: Any, *args: Any, **kwargs: Any) -> Any:
    return await fn(*args, **kwargs)


def _iterate(agen: AsyncIterator[T]) -> Iterator[T]:
    """A blocking iterator over an async one running on the client loop; closing it closes the async one."""

    async def next_item() -> tuple[bool, T | None]:
        try:
            return True, await agen.__anext__()
        except StopAsyncIteration:
            return False, None

    try:
        while True:
            more, item = _run(next_item())
            if not more:
                return
            yield item  # type: ignore[misc]
    finally:
        aclose = getattr(agen, "aclose", None)
        if aclose is not None:
            _run(_call(aclose))


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
        self._a: aio.AsyncClient = _run(
            _call(
                aio.AsyncClient.connect,
                target,
                token=token,
                connect_timeout_s=connect_timeout_s,
                timeout_s=timeout_s,
                root_certificates=root_certificates,
            )
        )
        self.target = target
        self.timeout_s = timeout_s
        self.episodes = Episodes(self._a.episodes)
        self.scene = Scene(self._a.scene)

    def close(self) -> None:
        _run(self._a.close())

    def __enter__(self) -> "Client":
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # --- System ---------------------------------------------------------------------------------------

    def list_arms(self) -> list[common_pb2.ArmState]:
        return _run(self._a.list_arms())

    def arm(self, name: str) -> common_pb2.ArmState:
        return _run(self._a.arm(name))

    def status(self) -> system_pb2.SystemStatus:
        return _run(self._a.status())

    def dataset_info(self) -> system_pb2.DatasetInfo:
        return _run(self._a.dataset_info())

    def list_cameras(self) -> list[common_pb2.CameraStatus]:
        return _run(self._a.list_cameras())

    def watch_status(self, interval_s: float = 0.5) -> StatusWatch:
        """The server's status every `interval_s` as a blocking iterator; `cancel()` ends it from any thread."""
        return StatusWatch(self._a, interval_s)

    # --- Policy ---------------------------------------------------------------------------------------

    def observe(
        self, arms: Sequence[str] = (), image_encoding: int = IMAGE_NONE, cameras: Sequence[str] = ()
    ) -> policy_pb2.Observation:
        """One observation now, without a session."""
        return _run(self._a.observe(arms, image_encoding, cameras))

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
        session = _run(
            self._a.policy_session(
                arms,
                observation_rate_hz=observation_rate_hz,
                request_control=request_control,
                image_encoding=image_encoding,
                cameras=cameras,
                policy_name=policy_name,
                silence_timeout_s=silence_timeout_s,
                ready_timeout_s=ready_timeout_s,
            )
        )
        return PolicySession(session)

    def teleop(
        self, arm: str = "main", *, client_name: str = "phone2act-python", take_over: bool = False
    ) -> TeleopSession:
        """Open a Teleop.Stream for `arm` (the arm is claimed with the first sample sent)."""
        return TeleopSession(_run(self._a.teleop(arm, client_name=client_name, take_over=take_over)))


class Scene:
    """The Scene service of a simulated arm: its ball and basket."""

    def __init__(self, scene: aio.AsyncScene) -> None:
        self._a = scene

    def reset(self, arm: str, seed: int | None = None, home_arm: bool = False) -> scene_pb2.SceneState:
        """Re-draw `arm`'s scene from `seed` (None: the arm's next seed); `home_arm` also puts the simulated
        arm at its initial joints, which the server refuses while a source drives it."""
        return _run(self._a.reset(arm, seed, home_arm))

    def get(self, arm: str) -> scene_pb2.SceneState:
        return _run(self._a.get(arm))


class Episodes:
    """The Episodes service: start, stop, discard, re-record, list, watch."""

    def __init__(self, episodes: aio.AsyncEpisodes) -> None:
        self._a = episodes

    def start(self, task: str, operator: str = "") -> common_pb2.RecordingStatus:
        """Start recording `task`; `operator` (who records it) goes into the episode's provenance."""
        return _run(self._a.start(task, operator))

    def stop(self, success: bool | None = None) -> episodes_pb2.EpisodeInfo:
        """Stop and save; returns when the episode is on disk. `success`: the operator's outcome (None: not
        given; see `AsyncEpisodes.stop`)."""
        return _run(self._a.stop(success))

    def stop_with_latency(self, success: bool | None = None) -> tuple[episodes_pb2.EpisodeInfo, float]:
        return _run(self._a.stop_with_latency(success))

    def discard(self) -> int:
        return _run(self._a.discard())

    def rerecord(self, task: str = "") -> common_pb2.RecordingStatus:
        return _run(self._a.rerecord(task))

    def save_highlight(
        self, task: str, operator: str = "", success: bool | None = None, keep_recording: bool = False
    ) -> episodes_pb2.SaveHighlightResponse:
        """Save the last seconds the server kept while idle as an episode (see `AsyncEpisodes.save_highlight`)."""
        return _run(self._a.save_highlight(task, operator, success, keep_recording))

    def list(self) -> list[episodes_pb2.EpisodeInfo]:
        return _run(self._a.list())

    def status(self) -> common_pb2.RecordingStatus:
        return _run(self._a.status())

    def watch(self, interval_s: float = 0.5) -> Iterator[common_pb2.RecordingStatus]:
        """Recorder status on every change (and every `interval_s`), until the caller stops iterating."""
        return _iterate(self._a.watch(interval_s))


class StatusWatch(Iterator[system_pb2.SystemStatus]):
    """`System.WatchStatus` as a blocking iterator. It ends when the server ends the stream or when
    `cancel()` is called (from any thread, also while another thread waits in `next`); any other failure
    raises the SDK's error for it (a `Phone2ActError`)."""

    def __init__(self, client: aio.AsyncClient, interval_s: float) -> None:
        self._target = client.target

        async def open_call() -> Any:
            return client._watch_status_call(interval_s)

        self._call = _run(open_call())

    def __iter__(self) -> StatusWatch:
        return self

    def __next__(self) -> system_pb2.SystemStatus:
        call = self._call

        async def read() -> system_pb2.SystemStatus | None:
            try:
                message = await call.read()
            except asyncio.CancelledError:
                return None
            except grpc.aio.AioRpcError as e:
                if e.code() == grpc.StatusCode.CANCELLED:
                    return None
                raise from_rpc_error(e, "System.WatchStatus", self._target) from None
            return None if message is grpc.aio.EOF else message

        status = _run(read())
        if status is None:
            raise StopIteration
        return status

    def cancel(self) -> None:
        loop = _loop
        if loop is not None:
            loop.call_soon_threadsafe(self._call.cancel)


_S = TypeVar("_S", bound="_Session")


class _Session:
    """What both blocking sessions share: the asyncio session they run, its end, the context manager."""

    _a: aio.AsyncPolicySession | aio.AsyncTeleopSession

    @property
    def closed(self) -> bool:
        return self._a.closed

    @property
    def error(self) -> Phone2ActError | None:
        """Why the session ended, once it has."""
        return self._a.error

    def close(self) -> None:
        """Cancel the stream; idempotent."""
        _run(self._a.close())

    def __enter__(self: _S) -> _S:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


class PolicySession(_Session):
    """An open Policy.Session. Use as a context manager; `close()` releases the arms (they hold).

    - `layouts[arm]`: state/action names for the arm (`action_width` is what chunks must use).
    - `next_observation()`: the next observation newer than the last one returned (latest-only).
    - `push(...)`: send a chunk with the unary `Policy.PushChunk`, so a bad chunk raises at once
      (`InvalidArgument` carries the server's reason, e.g. the expected width).
    - `push_on_stream(...)`: send on the session stream; the answer arrives as an event.
    - `next_event()`: the next `PolicyEvent` other than an observation (granted, revoked, paused, resumed,
      accepted, rejected, loading).
    - `waiting`: arms the operator took with the clutch (`ControlPaused`) and has not handed back.
    """

    def __init__(self, session: aio.AsyncPolicySession) -> None:
        self._a = session
        self.session_id: str = session.session_id
        self.layouts: dict[str, ArmLayout] = session.layouts

    @property
    def granted(self) -> policy_pb2.ControlGranted | None:
        return self._a.granted

    @property
    def revoked(self) -> policy_pb2.ControlRevoked | None:
        return self._a.revoked

    @property
    def waiting(self) -> set[str]:
        """Arms the operator took from this session and has not handed back yet."""
        return set(self._a.waiting)

    def next_observation(self, timeout_s: float = 5.0) -> policy_pb2.Observation:
        """The newest observation not yet returned; waits for one up to `timeout_s`."""
        return _run(self._a.next_observation(timeout_s))

    def request_observation(self) -> None:
        _run(self._a.request_observation())

    def push(
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
        return _run(
            self._a.push(
                arm,
                steps,
                step_period_s,
                observation_id=observation_id,
                mode=mode,
                blend_steps=blend_steps,
                keep_steps=keep_steps,
                timeout_s=timeout_s,
            )
        )

    def push_on_stream(
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
        _run(
            self._a.push_on_stream(
                arm,
                steps,
                step_period_s,
                observation_id=observation_id,
                mode=mode,
                blend_steps=blend_steps,
                keep_steps=keep_steps,
            )
        )

    def next_event(self, timeout_s: float = 5.0) -> policy_pb2.PolicyEvent:
        return _run(self._a.next_event(timeout_s))

    def release(self) -> None:
        _run(self._a.release())

    def loading(self) -> None:
        """Say the policy is loading (see `AsyncPolicySession.loading`); answered by a `loading` event."""
        _run(self._a.loading())



class TeleopSession(_Session):
    """A Teleop.Stream for one arm: send phone poses and buttons, read the latest feedback."""

    def __init__(self, session: aio.AsyncTeleopSession) -> None:
        self._a = session
        self.arm = session.arm

    @property
    def feedback(self) -> teleop_pb2.TeleopFeedback | None:
        """The newest feedback received."""
        return self._a.feedback

    def send(
        self,
        position: Sequence[float] | None = None,
        orientation_xyzw: Sequence[float] = (0.0, 0.0, 0.0, 1.0),
        *,
        buttons: Sequence[teleop_pb2.ButtonEvent] = (),
        tracking: int = teleop_pb2.TRACKING_STATE_TRACKING,
    ) -> int:
        """Send one sample (a pose in the phone's tracking frame and/or buttons); returns its seq."""
        return _run(self._a.send(position, orientation_xyzw, buttons=buttons, tracking=tracking))

    def clutch(
        self, engage: bool, position: Sequence[float] | None = None,
        orientation_xyzw: Sequence[float] = (0.0, 0.0, 0.0, 1.0),
    ) -> int:
        return _run(self._a.clutch(engage, position, orientation_xyzw))

    def gripper(self, position: float) -> int:
        return _run(self._a.gripper(position))

    def hand_back(self) -> int:
        """Hand the arm back to the policy waiting for it (see `AsyncTeleopSession.hand_back`)."""
        return _run(self._a.hand_back())

    def wait_feedback(self, seq: int, timeout_s: float = 2.0) -> teleop_pb2.TeleopFeedback:
        """Wait until feedback echoes `seq` (or a later sample)."""
        return _run(self._a.wait_feedback(seq, timeout_s))

