"""Out-of-process robot bridges: one `Bridge.Attach` stream and its plumbing.

A bridge sends a hello, then feedback, status and (for a robot that owns its scene) scene reports upstream,
and receives the welcome, commands, controls and scene resets downstream. `BridgeLink` holds what every
bridge needs around that stream: a bounded up-queue that drops feedback rather than block the robot's
loop when the server stops draining (newer feedback follows), the blocking read loop, the channel (shared
with `Cameras.Push` for a bridge that also pushes frames) and a `stop()` that ends it from any thread. The
robot is a `BridgeHandler`: it answers the downstream messages and decides what to report.

    class MyRobot(BridgeHandler):
        def on_welcome(self, link, welcome):
            link.ready()
            start_my_feedback_thread(link)
        def on_command(self, link, command):
            robot_sdk.move_to(command.robot_from_target)

    hello = pb.BridgeHello(arm="ext", bridge_name="my-robot", joint_names=[...])
    BridgeLink("127.0.0.1:50051", hello, MyRobot()).run()
"""

from __future__ import annotations

import queue
import threading
from collections.abc import Iterator
from typing import Any

import grpc

from ._common import auth_metadata, channel_options
from .v1 import bridge_pb2 as pb
from .v1 import bridge_pb2_grpc as rpc
from .v1 import common_pb2


class BridgeHandler:
    """The robot side of a `BridgeLink`. Every method is optional; each runs on the link's read thread, so
    one that blocks delays the next downstream message."""

    def on_welcome(self, link: BridgeLink, welcome: pb.BridgeWelcome) -> None:
        """The server accepted the hello. Report readiness (`link.ready()`) and start the feedback."""
        link.ready()

    def on_command(self, link: BridgeLink, command: pb.BridgeCommand) -> None:
        """A target to follow (pose, gripper, and `joint_targets_rad` when the hello declared a joint model)."""

    def on_control(self, link: BridgeLink, control: pb.BridgeControl) -> None:
        """Enable, disable, clear an error, reconnect: meaningless to a robot without them."""

    def on_scene_reset(self, link: BridgeLink, reset: pb.BridgeSceneReset) -> None:
        """Re-draw the scene and answer with `link.scene(..., reset_request_id=reset.request_id)`."""

    def on_end(self, link: BridgeLink) -> None:
        """The stream ended (stopped, refused, or the server went away); `link.error` says which."""


class BridgeLink:
    """One attachment of a robot to an arm. `run()` blocks until `stop()` or the stream ends; `start()` runs
    it on a daemon thread. After the end, `error` holds the server's refusal or the transport error (None
    when stopped)."""

    def __init__(self, target: str, hello: pb.BridgeHello, handler: BridgeHandler, token: str | None = None,
                 queue_size: int = 64) -> None:
        self.target, self.hello, self.handler, self.token = target, hello, handler, token
        self._up: queue.Queue[pb.BridgeUpstream | None] = queue.Queue(maxsize=queue_size)
        self._stopped = threading.Event()
        self._call: Any = None
        self.channel: grpc.Channel | None = None
        self.welcome: pb.BridgeWelcome | None = None
        self.error: grpc.RpcError | None = None
        #: Set once welcomed, and also when the stream ends without a welcome (check `welcome`).
        self.attached = threading.Event()
        self.commands = 0

    @property
    def stopped(self) -> threading.Event:
        """Set when the link stops, for the robot's own loops to wait on."""
        return self._stopped

    def send(self, message: pb.BridgeUpstream, drop_if_full: bool = True) -> bool:
        """Queues `message` upstream. With `drop_if_full` (feedback: a newer one follows) a full queue drops
        it and returns False; otherwise the call waits for room (a status or a scene answer must arrive)."""
        if self._stopped.is_set():
            return False
        if not drop_if_full:
            self._up.put(message)
            return True
        try:
            self._up.put_nowait(message)
            return True
        except queue.Full:
            return False

    def feedback(self, feedback: pb.RobotFeedback) -> bool:
        """Reports the robot's measured state; dropped when the stream is not draining."""
        return self.send(pb.BridgeUpstream(feedback=feedback))

    def ready(self, message: str = "") -> None:
        """Reports the robot ready to be commanded."""
        self.status(common_pb2.BRIDGE_HEALTH_READY, message)

    def status(self, health: int, message: str = "") -> None:
        """Reports the robot's health (a `common_pb2.BRIDGE_HEALTH_*` value) and why."""
        self.send(pb.BridgeUpstream(status=pb.BridgeStatusReport(health=health, message=message)),
                  drop_if_full=False)

    def scene(self, state: Any, reset_request_id: int = 0, error: str = "") -> None:
        """Reports the scene (`Scene.Get` answers from it); with `reset_request_id`, answers that reset."""
        self.send(pb.BridgeUpstream(scene=pb.BridgeScene(state=state, reset_request_id=reset_request_id,
                                                         error=error)), drop_if_full=False)

    def _upstream(self) -> Iterator[pb.BridgeUpstream]:
        yield pb.BridgeUpstream(hello=self.hello)
        while True:
            message = self._up.get()
            if message is None:
                return
            yield message

    def run(self) -> None:
        with grpc.insecure_channel(self.target, options=channel_options(self.target)) as channel:
            self.channel = channel
            call = rpc.BridgeStub(channel).Attach(self._upstream(), metadata=auth_metadata(self.token))
            self._call = call
            if self._stopped.is_set():  # stopped before the call existed to be cancelled
                call.cancel()
            try:
                for down in call:
                    kind = down.WhichOneof("message")
                    if kind == "welcome":
                        self.welcome = down.welcome
                        self.handler.on_welcome(self, down.welcome)
                        self.attached.set()
                    elif kind == "command":
                        self.commands += 1
                        self.handler.on_command(self, down.command)
                    elif kind == "control":
                        self.handler.on_control(self, down.control)
                    elif kind == "scene_reset":
                        self.handler.on_scene_reset(self, down.scene_reset)
            except grpc.RpcError as e:
                if e.code() != grpc.StatusCode.CANCELLED or not self._stopped.is_set():
                    self.error = e
            finally:
                self._stopped.set()
                self.attached.set()
                self.handler.on_end(self)

    def start(self, name: str = "phone2act-bridge") -> threading.Thread:
        thread = threading.Thread(target=self.run, name=name, daemon=True)
        thread.start()
        return thread

    def stop(self) -> None:
        """Ends the stream (from any thread, also before `run()`); the read loop then returns."""
        self._stopped.set()
        try:
            self._up.put_nowait(None)
        except queue.Full:
            pass  # the cancel below ends the stream; its generator is not read again
        if self._call is not None:
            self._call.cancel()
