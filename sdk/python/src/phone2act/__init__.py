"""phone2act: Python client for the phone2act server.

Sync:    `Client`, `Episodes` (as `client.episodes`), `Scene` (as `client.scene`), `PolicySession`,
         `TeleopSession`.
asyncio: `phone2act.aio.AsyncClient` and friends.
Raw generated stubs: `phone2act.v1.*_pb2` / `*_pb2_grpc`.
"""

from phone2act._common import (
    ABSOLUTE_EE,
    DELTA_EE,
    IMAGE_JPEG,
    IMAGE_NONE,
    IMAGE_RGB8,
    ArmLayout,
    make_chunk,
    make_pose,
    pose_tuple,
)
from phone2act.client import Client, Episodes, PolicySession, Scene, TeleopSession
from phone2act.errors import (
    DeadlineExceeded,
    FailedPrecondition,
    InvalidArgument,
    NotFound,
    Phone2ActError,
    ServerUnavailable,
    SessionClosed,
    Unauthenticated,
    Unimplemented,
)

__all__ = [
    "ABSOLUTE_EE",
    "DELTA_EE",
    "IMAGE_JPEG",
    "IMAGE_NONE",
    "IMAGE_RGB8",
    "ArmLayout",
    "Client",
    "DeadlineExceeded",
    "Episodes",
    "FailedPrecondition",
    "InvalidArgument",
    "NotFound",
    "Phone2ActError",
    "PolicySession",
    "Scene",
    "ServerUnavailable",
    "SessionClosed",
    "TeleopSession",
    "Unauthenticated",
    "Unimplemented",
    "make_chunk",
    "make_pose",
    "pose_tuple",
]
