"""Configuration of the `phone2act` robot type (`--robot.type=phone2act` on lerobot's command lines)."""

from __future__ import annotations

from dataclasses import dataclass, field

from lerobot.robots.config import RobotConfig


@RobotConfig.register_subclass("phone2act")
@dataclass(kw_only=True)
class Phone2ActRobotConfig(RobotConfig):
    # The phone2act server: `host:port`, `https://host:port` or `unix:/path` (as the SDK's `Client`).
    server: str = "127.0.0.1:50051"
    # Bearer token, when the server is configured with one.
    token: str | None = None
    # The phone2act arm this robot drives.
    arm: str = "main"
    # Server cameras to observe; empty means every camera the server reports. Not named `cameras`: lerobot's
    # RobotConfig expects that field to hold its own camera configs.
    camera_names: list[str] = field(default_factory=list)
    # Period the executor gives each single step of `send_action` (lerobot loops at the dataset fps).
    fps: float = 30.0
    # A policy that sends no action for this long loses control and the arm holds (the server's rule); the
    # next `send_action` claims control again unless the operator took over.
    silence_timeout_s: float = 1.0
    # How long `connect` waits for the server.
    connect_timeout_s: float = 5.0
