"""Pieces shared by the sync and asyncio clients: channel options, auth metadata, message builders."""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from dataclasses import dataclass

import grpc

from phone2act.v1 import common_pb2, policy_pb2

DEFAULT_TARGET = "127.0.0.1:50051"

# Action modes and image encodings, re-exported under short names.
DELTA_EE = policy_pb2.ACTION_MODE_DELTA_EE
ABSOLUTE_EE = policy_pb2.ACTION_MODE_ABSOLUTE_EE
IMAGE_NONE = common_pb2.IMAGE_ENCODING_NONE
IMAGE_RGB8 = common_pb2.IMAGE_ENCODING_RGB8
IMAGE_JPEG = common_pb2.IMAGE_ENCODING_JPEG


def split_target(target: str) -> tuple[str, bool]:
    """(grpc address, TLS?) for a target typed as `host:port`, `http://host:port`, `https://host:port` or
    `unix:/path`: the same forms the `phone2act` CLI and the Rust SDK accept. No scheme means plaintext."""
    t = target.strip()
    lower = t.lower()
    if lower.startswith("https://"):
        return t[len("https://"):].rstrip("/"), True
    if lower.startswith("http://"):
        return t[len("http://"):].rstrip("/"), False
    return t, False


def channel_credentials(root_certificates: bytes | None) -> grpc.ChannelCredentials:
    """TLS credentials: the system's roots, or `root_certificates` (PEM) for a self-signed deployment."""
    return grpc.ssl_channel_credentials(root_certificates=root_certificates)


def channel_options(target: str) -> list[tuple[str, object]]:
    options: list[tuple[str, object]] = [
        # Observations with RGB frames are large (640x480x3 = 921 kB per camera).
        ("grpc.max_receive_message_length", 64 * 1024 * 1024),
        ("grpc.max_send_message_length", 64 * 1024 * 1024),
    ]
    if target.startswith("unix:"):
        # grpcio sends the socket path as :authority over a Unix socket, which the server's h2 rejects.
        options.append(("grpc.default_authority", "localhost"))
    return options


def auth_metadata(token: str | None) -> tuple[tuple[str, str], ...]:
    return (("authorization", f"Bearer {token}"),) if token else ()


@dataclass(frozen=True)
class ArmLayout:
    """The vector layout of one arm, from `SessionReady`: what observations carry and what chunks must use."""

    arm: str
    state_names: tuple[str, ...]
    action_names: tuple[str, ...]

    @property
    def action_width(self) -> int:
        return len(self.action_names)


def hello_request(
    arms: Sequence[str],
    observation_rate_hz: float,
    request_control: bool,
    image_encoding: int,
    cameras: Sequence[str],
    policy_name: str,
    silence_timeout_s: float,
) -> policy_pb2.PolicyRequest:
    hello = policy_pb2.PolicyHello(
        arms=list(arms),
        observation_rate_hz=observation_rate_hz,
        image_encoding=image_encoding,
        cameras=list(cameras),
        request_control=request_control,
        policy_name=policy_name,
        silence_timeout_s=silence_timeout_s,
    )
    return policy_pb2.PolicyRequest(hello=hello)


def make_chunk(
    arm: str,
    steps: Iterable[Sequence[float]],
    step_period_s: float,
    observation_id: int = 0,
    mode: int = DELTA_EE,
    blend_steps: int = 0,
    keep_steps: int = 0,
) -> policy_pb2.ActionChunk:
    """An ActionChunk from rows of floats (lists, tuples or numpy rows). `keep_steps`: leading steps not
    played, the replaced plan keeps their windows (real-time chunking; see `Observation.inference_delay_steps`
    and `ArmObservation.pending_steps`)."""
    return policy_pb2.ActionChunk(
        arm=arm,
        steps=[policy_pb2.ActionStep(values=[float(v) for v in row]) for row in steps],
        step_period_s=float(step_period_s),
        observation_id=int(observation_id),
        mode=mode,
        blend_steps=blend_steps,
        keep_steps=keep_steps,
    )


def layouts_from_ready(ready: policy_pb2.SessionReady) -> dict[str, ArmLayout]:
    return {
        a.arm: ArmLayout(a.arm, tuple(a.state_names), tuple(a.action_names)) for a in ready.arms
    }


def pose_tuple(pose: common_pb2.Pose) -> tuple[tuple[float, float, float], tuple[float, float, float, float]]:
    """(position m, quaternion xyzw) of a Pose message."""
    p, q = pose.position_m, pose.orientation
    return (p.x, p.y, p.z), (q.x, q.y, q.z, q.w)


def make_pose(position: Sequence[float], orientation_xyzw: Sequence[float]) -> common_pb2.Pose:
    return common_pb2.Pose(
        position_m=common_pb2.Vec3(x=position[0], y=position[1], z=position[2]),
        orientation=common_pb2.Quaternion(
            x=orientation_xyzw[0], y=orientation_xyzw[1], z=orientation_xyzw[2], w=orientation_xyzw[3]
        ),
    )
