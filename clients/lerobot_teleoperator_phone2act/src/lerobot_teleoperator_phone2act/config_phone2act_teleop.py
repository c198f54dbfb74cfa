"""Configuration of the `phone2act` teleoperator type (`--teleop.type=phone2act`)."""

from __future__ import annotations

from dataclasses import dataclass

from lerobot.teleoperators.config import TeleoperatorConfig


@TeleoperatorConfig.register_subclass("phone2act")
@dataclass(kw_only=True)
class Phone2ActTeleopConfig(TeleoperatorConfig):
    # The phone2act server the phone streams to (`host:port`, `https://host:port`, `unix:/path`).
    server: str = "127.0.0.1:50051"
    token: str | None = None
    # The phone2act arm the phone is bound to; its commanded target is this teleoperator's action.
    arm: str = "main"
    connect_timeout_s: float = 5.0
    # How often the server sends the arm's state (the action can be no fresher than this).
    status_interval_s: float = 0.02
