"""Bad input from the client side: a server that is down, a chunk of the wrong shape, unknown names."""

from __future__ import annotations

import asyncio
import math
import time

import pytest
from conftest import Server, free_port, wait_until
from phone2act import Client, InvalidArgument, NotFound, ServerUnavailable, pose_tuple
from phone2act.aio import AsyncClient


def test_server_down_is_a_clear_connection_error() -> None:
    target = f"127.0.0.1:{free_port()}"
    t0 = time.monotonic()
    with pytest.raises(ConnectionError) as info:
        Client(target, connect_timeout_s=1.0)
    assert time.monotonic() - t0 < 5.0
    assert isinstance(info.value, ServerUnavailable)
    assert target in str(info.value) and "phone2act serve" in str(info.value)

    async def aio() -> None:
        await AsyncClient.connect(target, connect_timeout_s=1.0)

    with pytest.raises(ServerUnavailable, match=target):
        asyncio.run(aio())


def test_server_going_away_mid_session(make_server) -> None:  # type: ignore[no-untyped-def]
    srv: Server = make_server()
    c = Client(srv.target)
    s = c.policy_session(["main"])
    s.next_observation()
    srv.stop()
    with pytest.raises(ConnectionError, match="unavailable"):
        for _ in range(50):  # the channel notices within a few calls
            c.list_arms()
            time.sleep(0.05)
    assert wait_until(lambda: s.closed, 5.0)
    s.close()
    c.close()


def test_wrong_width_chunk_is_invalid_argument_with_the_widths_and_the_arm_holds(server: Server) -> None:
    with Client(server.target) as c, c.policy_session(["main"], observation_rate_hz=20) as s:
        obs = s.next_observation()
        before = c.arm("main")
        sent_before = before.commands_sent
        with pytest.raises(InvalidArgument) as info:
            s.push("main", [[0.01, 0, 0, 0, 0, 0]] * 4, 0.05, observation_id=obs.observation_id)
        msg = str(info.value)
        assert "INVALID_ARGUMENT" in msg and "6 values" in msg and "takes 7" in msg, msg
        assert "delta_x" in info.value.details
        with pytest.raises(InvalidArgument, match="not finite"):
            s.push("main", [[math.nan, 0, 0, 0, 0, 0, 0]], 0.05)
        with pytest.raises(InvalidArgument, match="step_period_s"):
            s.push("main", [[0.0] * 7], 0.0)
        with pytest.raises(NotFound, match="unknown arm"):
            s.push("nope", [[0.0] * 7], 0.05)
        time.sleep(0.3)
        after = c.arm("main")
        assert after.commands_sent == sent_before, "a refused chunk must not move the arm"
        p0, p1 = pose_tuple(before.robot_from_ee)[0], pose_tuple(after.robot_from_ee)[0]
        assert math.dist(p0, p1) < 2e-4


def test_unknown_arm_in_the_hello(server: Server) -> None:
    with Client(server.target) as c, pytest.raises(NotFound, match="nope"):
        c.policy_session(["nope"])
