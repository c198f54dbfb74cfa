"""`client.scene` (and its asyncio twin) against the real server binary: seeded resets of the simulated
scene, the seed sequence, and the refusals (unknown arm, an arm without a scene)."""

from __future__ import annotations

import asyncio
from typing import Callable

import pytest
from conftest import SIM_ARM, Server
from phone2act import Client, NotFound, Unimplemented
from phone2act.aio import AsyncClient
from phone2act.v1 import scene_pb2

# A remote-bridge arm: no simulator behind it, so no scene.
REMOTE_ARM = """
[[arms]]
name = "ext"
bridge = "remote"
[arms.remote]
joint_names = ["a", "b", "c"]
"""


def ball(state: scene_pb2.SceneState) -> tuple[float, float, float]:
    p = state.ball_position_m
    return (p.x, p.y, p.z)


def test_scene_reset_and_get(make_server: Callable[..., Server]) -> None:
    server = make_server(arms=SIM_ARM + REMOTE_ARM)
    with Client(server.target) as c:
        first = c.scene.reset("main", seed=3)
        again = c.scene.reset("main", seed=3, home_arm=True)
        assert ball(first) == ball(again), "same seed, same scene"
        assert (again.seed, again.resets) == (3, first.resets + 1)
        area = first.ball_area_m
        x, y, z = ball(first)
        assert area.x_min_m <= x <= area.x_max_m and area.y_min_m <= y <= area.y_max_m
        assert z == pytest.approx(first.ball_radius_m, abs=1e-12)
        assert first.ball_state == scene_pb2.BALL_STATE_RESTING and not first.success
        assert first.basket_radius_m > first.ball_radius_m
        assert not first.HasField("basket_area_m"), "the default basket stays put"

        nxt = c.scene.reset("main")
        assert nxt.seed == 4 and ball(nxt) != ball(first)
        now = c.scene.get("main")
        assert (now.seed, ball(now), now.resets) == (4, ball(nxt), nxt.resets)
        assert now.success == c.arm("main").task_success

        with pytest.raises(NotFound, match="ghost"):
            c.scene.get("ghost")
        with pytest.raises(Unimplemented, match="the remote bridge has no scene"):
            c.scene.reset("ext", seed=1)
        with pytest.raises(Unimplemented):
            c.scene.get("ext")

    async def twin() -> None:
        async with AsyncClient(server.target) as ac:
            a = await ac.scene.reset("main", seed=3)
            assert ball(a) == ball(first)
            assert (await ac.scene.get("main")).seed == 3
            with pytest.raises(NotFound):
                await ac.scene.reset("ghost")

    asyncio.run(twin())
