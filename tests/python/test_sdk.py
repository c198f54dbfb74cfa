"""The typed Python layer against a real server: system, episodes, policy sessions, teleop, asyncio, auth."""

from __future__ import annotations

import asyncio
import inspect
import math
import statistics
import subprocess
import sys
import time

import phone2act
import pytest
from conftest import REPO, Server, wait_until
from phone2act import (
    ABSOLUTE_EE,
    Client,
    FailedPrecondition,
    InvalidArgument,
    NotFound,
    Unauthenticated,
    aio,
    client,
    pose_tuple,
)
from phone2act.aio import AsyncClient
from phone2act.v1 import common_pb2

EXAMPLE = REPO / "sdk" / "python" / "examples" / "record_episode.py"


def ee_position(client: Client, arm: str = "main") -> tuple[float, float, float]:
    return pose_tuple(client.arm(arm).robot_from_ee)[0]


def test_list_arms_names_the_sim_arm(server: Server) -> None:
    with Client(server.target) as c:
        arms = c.list_arms()
        assert [a.arm for a in arms] == ["main"]
        a = arms[0]
        assert a.bridge_kind == "sim"
        assert wait_until(lambda: c.arm("main").health == common_pb2.BRIDGE_HEALTH_READY)
        assert len(a.joint_names) == 5
        x, y, z = ee_position(c)
        assert 0.05 < x < 0.45 and 0.0 < z < 0.4, (x, y, z)
        assert c.status().version
        with pytest.raises(NotFound, match="no arm 'nope'"):
            c.arm("nope")


def test_example_script_records_stops_and_lists(server: Server) -> None:
    lines = [ln for ln in EXAMPLE.read_text().splitlines() if ln.strip()]
    assert len(lines) < 15, f"the example must stay under 15 lines, has {len(lines)}"
    out = subprocess.run([sys.executable, str(EXAMPLE), server.target], capture_output=True, text=True, timeout=60, check=False)
    assert out.returncode == 0, out.stderr
    assert "saved episode" in out.stdout
    with Client(server.target) as c:
        eps = c.episodes.list()
        assert eps, out.stdout
        last = eps[-1]
        assert last.task == "pick up the ball and put it in the basket"
        assert 5 <= last.length_frames <= 40, last  # 1 s at 20 fps (an overloaded recorder loses ticks)
        assert f"{last.episode_index} 'pick up the ball and put it in the basket' {last.length_frames}" in out.stdout
    assert any((server.root / "data").rglob("*.parquet"))


def test_episode_lifecycle_and_errors(server: Server) -> None:
    with Client(server.target) as c:
        before = len(c.episodes.list())
        status = c.episodes.start("stack the cubes")
        assert status.phase == common_pb2.RECORDING_PHASE_RECORDING and status.task == "stack the cubes"
        with pytest.raises(FailedPrecondition, match="Episodes.Start failed: FAILED_PRECONDITION"):
            c.episodes.start("again")
        time.sleep(0.3)
        assert c.episodes.discard() > 0
        assert c.episodes.status().phase == common_pb2.RECORDING_PHASE_IDLE
        with pytest.raises(InvalidArgument):
            c.episodes.start("")
        c.episodes.start("stack the cubes")
        time.sleep(0.3)
        ep, latency_s = c.episodes.stop_with_latency()
        assert ep.task == "stack the cubes" and ep.length_frames > 0
        assert latency_s < 5.0
        assert len(c.episodes.list()) == before + 1
        statuses = c.episodes.watch(0.1)
        assert next(statuses).phase == common_pb2.RECORDING_PHASE_IDLE
        statuses.close()


def test_stop_with_the_operators_outcome(server: Server) -> None:
    with Client(server.target) as c:
        outcomes = []
        for success in (True, False, None):
            c.episodes.start("stack the cubes")
            time.sleep(0.3)
            outcomes.append(c.episodes.stop(success=success).outcome)
        expected = [common_pb2.EPISODE_OUTCOME_SUCCESS, common_pb2.EPISODE_OUTCOME_FAILURE,
                    common_pb2.EPISODE_OUTCOME_UNSPECIFIED]
        assert outcomes == expected
        assert [e.outcome for e in c.episodes.list()[-3:]] == expected


def test_policy_delta_chunk_moves_the_arm_and_reports_events(server: Server) -> None:
    # The silence clock runs from the last chunk's arrival; this test pauses longer than the default 1 s.
    with Client(server.target) as c, c.policy_session(["main"], observation_rate_hz=20, silence_timeout_s=10) as s:
        layout = s.layouts["main"]
        assert layout.action_names == ("delta_x", "delta_y", "delta_z", "delta_rx", "delta_ry", "delta_rz", "gripper")
        assert layout.state_names[-10:] == ("ee_x", "ee_y", "ee_z", "ee_r00", "ee_r10", "ee_r20", "ee_r01", "ee_r11",
                                            "ee_r21", "gripper")
        obs = s.next_observation()
        arm = obs.arms[0]
        assert arm.owner == common_pb2.CONTROL_SOURCE_POLICY
        start = pose_tuple(arm.robot_from_ee)[0]
        # State carries the same pose as robot_from_ee: x y z, then the rotation matrix's first two columns.
        assert arm.state[5:8] == pytest.approx(start, abs=1e-9)
        qx, qy, qz, qw = pose_tuple(arm.robot_from_ee)[1]
        first_two_columns = [1 - 2 * (qy * qy + qz * qz), 2 * (qx * qy + qz * qw), 2 * (qx * qz - qy * qw),
                             2 * (qx * qy - qz * qw), 1 - 2 * (qx * qx + qz * qz), 2 * (qy * qz + qx * qw)]
        assert list(arm.state[8:14]) == pytest.approx(first_two_columns, abs=1e-6)
        # 2 cm along +x over 20 steps, relative to this observation's pose (however old it is by now: on a
        # loaded machine early steps may already be past and are skipped; the last one is the goal).
        steps = [[0.001 * (k + 1), 0, 0, 0, 0, 0, 0] for k in range(20)]
        acc = s.push("main", steps, 0.1, observation_id=obs.observation_id)
        assert acc.steps_scheduled + acc.steps_skipped == 20 and acc.steps_scheduled >= 1
        assert wait_until(lambda: abs(ee_position(c)[0] - (start[0] + 0.02)) < 1e-3, 5.0), ee_position(c)
        assert abs(ee_position(c)[1] - start[1]) < 1e-3 and abs(ee_position(c)[2] - start[2]) < 1e-3

        # The same on the stream: answers arrive as events; a bad chunk is a ChunkRejected with the reason.
        obs = s.next_observation()
        s.push_on_stream("main", [[0, 0, 0, 0, 0, 0, 0]] * 20, 0.1, observation_id=obs.observation_id)
        s.push_on_stream("main", [[0, 0, 0]], 0.05, observation_id=obs.observation_id)
        kinds = []
        while len(kinds) < 2:
            ev = s.next_event(5.0)
            if ev.WhichOneof("event") in ("accepted", "rejected"):
                kinds.append(ev)
        assert kinds[0].WhichOneof("event") == "accepted", kinds[0]
        assert kinds[1].WhichOneof("event") == "rejected"
        assert "3 values" in kinds[1].rejected.reason and "takes 7" in kinds[1].rejected.reason


def test_a_loading_policy_holds_its_arm_past_the_silence_timeout(server: Server) -> None:
    with Client(server.target) as c, c.policy_session(["main"], observation_rate_hz=5, silence_timeout_s=0.2) as s:
        s.loading()
        ev = s.next_event(5.0)
        while ev.WhichOneof("event") != "loading":
            ev = s.next_event(5.0)
        assert list(ev.loading.arms) == ["main"] and not ev.loading.error
        # The default limit is 300 s: a loading policy keeps the arm for minutes, not for its silence timeout.
        assert 250.0 < ev.loading.remaining_s <= 300.0
        time.sleep(1.0)
        arm = c.list_arms()[0]
        assert arm.owner == common_pb2.CONTROL_SOURCE_POLICY and arm.policy_loading
        s.push("main", [[0, 0, 0, 0, 0, 0, 0]], 0.1)
        assert not c.list_arms()[0].policy_loading


def test_a_taken_over_policy_waits_and_the_phone_hands_the_arm_back(server: Server) -> None:
    with Client(server.target) as c, c.policy_session(["main"], observation_rate_hz=5, silence_timeout_s=5,
                                                       policy_name="py-policy") as s:
        s.push("main", [[0.0] * 7] * 10, 0.1)
        assert c.list_arms()[0].plan_preview.positions_m, "a driving policy's plan is previewed"
        with c.teleop("main", take_over=True) as phone:
            fb = phone.wait_feedback(phone.clutch(True, (0.0, 0.0, 0.0)))
            assert fb.arm_state.waiting_policy_id.startswith("py-policy:")
            # The session hears it (ControlPaused), sent as the clutch is handled; 10 s covers a stalled machine.
            ev = s.next_event(timeout_s=10.0)
            while ev.WhichOneof("event") != "paused":
                ev = s.next_event(timeout_s=10.0)
            assert ev.paused.arm == "main" and s.waiting == {"main"}
            with pytest.raises(FailedPrecondition, match="waits for the operator to hand the arm back"):
                s.push("main", [[0.0] * 7], 0.1)
            fb = phone.wait_feedback(phone.hand_back())
            assert not fb.error and fb.arm_state.owner == common_pb2.CONTROL_SOURCE_POLICY
            assert not fb.arm_state.waiting_policy_id
            ev = s.next_event(timeout_s=10.0)
            while ev.WhichOneof("event") != "resumed":
                ev = s.next_event(timeout_s=10.0)
            assert ev.resumed.arm == "main" and s.waiting == set()
            # A chunk anchored on the arm's pose at its arrival (observation 0) answers a fresh observation.
            assert s.push("main", [[0.0] * 7] * 3, 0.1).steps_scheduled >= 1
            # Nothing waits any more: a second hand-back is refused in the feedback and changes nothing.
            fb = phone.wait_feedback(phone.hand_back())
            assert "no policy waits" in fb.error


def test_observations_carry_the_pending_plan_and_the_inference_delay(server: Server) -> None:
    with Client(server.target) as c, c.policy_session(["main"], observation_rate_hz=0, silence_timeout_s=5) as s:
        s.request_observation()
        obs = s.next_observation()
        assert obs.inference_delay_s == 0 and not obs.arms[0].pending_steps, "nothing played, nothing measured"
        time.sleep(0.2)
        # 40 steps of 0.1 s holding the observation's pose (relative zeros), the first 2 kept from the old plan.
        acc = s.push("main", [[0.0] * 7] * 40, 0.1, observation_id=obs.observation_id, keep_steps=2)
        assert acc.steps_scheduled >= 1
        s.request_observation()
        later = s.next_observation()
        assert later.inference_delay_s >= 0.2
        assert later.inference_delay_steps == math.ceil(later.inference_delay_s / 0.1 - 1e-9)
        arm = later.arms[0]
        assert arm.pending_step_period_s == pytest.approx(0.1)
        assert 10 <= len(arm.pending_steps) <= 40
        # In the arm's mode against this observation: holding the same pose, so (near) zero deltas.
        assert all(abs(v) < 2e-3 for v in arm.pending_steps[0].values[:6]), arm.pending_steps[0]
        with pytest.raises(phone2act.Phone2ActError, match="keep_steps"):
            s.push("main", [[0.0] * 7] * 3, 0.1, observation_id=later.observation_id, keep_steps=3)


def test_absolute_chunk_and_latency(server: Server) -> None:
    """ABSOLUTE_EE goes where it says; also measures unary and stream round trips from Python."""
    # A long silence timeout: the measuring loops below push nothing for more than the default 1 s.
    with Client(server.target) as c, c.policy_session(["main"], observation_rate_hz=20, silence_timeout_s=30) as s:
        obs = s.next_observation()
        a = obs.arms[0]
        goal = list(a.state[5:14]) + [0.5]  # x y z and the 6D rotation as observed, gripper half closed
        goal[1] += 0.015
        s.push("main", [goal] * 10, 0.05, mode=ABSOLUTE_EE)
        assert wait_until(lambda: abs(ee_position(c)[1] - goal[1]) < 1e-3, 3.0)
        assert wait_until(lambda: abs(c.arm("main").gripper_position - 0.5) < 0.02, 3.0)

        unary = []
        for _ in range(200):
            t0 = time.perf_counter()
            c.list_arms()
            unary.append(time.perf_counter() - t0)
        stream, rejected = [], []
        for _ in range(100):
            t0 = time.perf_counter()
            s.push_on_stream("main", [goal], 0.05, mode=ABSOLUTE_EE)  # anchored at its arrival
            while (ev := s.next_event(2.0)).WhichOneof("event") not in ("accepted", "rejected"):
                pass
            stream.append(time.perf_counter() - t0)
            if ev.WhichOneof("event") == "rejected":
                rejected.append(ev.rejected.reason)
        assert not rejected, rejected
        push = []
        for _ in range(100):
            t0 = time.perf_counter()
            s.push("main", [goal], 0.05, mode=ABSOLUTE_EE)
            push.append(time.perf_counter() - t0)
        p50 = {k: statistics.median(v) * 1e3 for k, v in [("unary", unary), ("stream", stream), ("push", push)]}
        print(f"\nPython latency p50: ListArms {p50['unary']:.2f} ms, PushChunk {p50['push']:.2f} ms, "
              f"stream chunk->accepted {p50['stream']:.2f} ms")
        assert p50["push"] < 20 and p50["stream"] < 20, p50
        # ListArms answers are a few hundred bytes in two writes: without TCP_NODELAY on the server's accepted
        # sockets, Nagle + the client's delayed ACK add ~40 ms (seen with tonic's serve_with_incoming).
        assert p50["unary"] < 20, f"ListArms p50 {p50['unary']:.1f} ms: server sockets lack TCP_NODELAY?"


def test_teleop_drives_the_sim_arm(server: Server) -> None:
    with Client(server.target) as c, c.teleop("main") as t:
        phone = [0.0, 1.2, -0.3]
        seq = t.clutch(True, phone)
        fb = t.wait_feedback(seq)
        assert fb.error == ""
        start = ee_position(c)
        for k in range(1, 31):  # 3 cm to the phone's right over 0.6 s
            t.send([phone[0] + 0.001 * k, phone[1], phone[2]])
            time.sleep(0.02)
        fb = t.wait_feedback(t.send([phone[0] + 0.03, phone[1], phone[2]]))
        assert fb.arm_state.engaged and fb.arm_state.owner == common_pb2.CONTROL_SOURCE_TELEOP
        assert wait_until(lambda: abs(math.dist(ee_position(c), start) - 0.03) < 2e-3, 3.0), (
            start, ee_position(c))
        seq = t.clutch(False)
        assert not t.wait_feedback(seq).arm_state.engaged
        bad = t.send([float("nan"), 0, 0])
        assert "nan" in t.wait_feedback(bad).error.lower()


def test_asyncio_client(server: Server) -> None:
    async def main() -> None:
        async with await AsyncClient.connect(server.target) as c:
            arms = await c.list_arms()
            assert arms[0].arm == "main"
            assert (await c.episodes.status()).phase == common_pb2.RECORDING_PHASE_IDLE
            watch = c.episodes.watch(0.1)
            first = await watch.__anext__()
            assert first.phase == common_pb2.RECORDING_PHASE_IDLE and first.dataset_format == "v3.0"
            await watch.aclose()
            session = await c.policy_session(["main"], observation_rate_hz=20)
            async with session:
                obs = await session.next_observation()
                start = pose_tuple(obs.arms[0].robot_from_ee)[0]
                acc = await session.push("main", [[0, 0, 0.01 * (k + 1) / 5, 0, 0, 0, 0] for k in range(5)],
                                         0.05, observation_id=obs.observation_id)
                assert acc.steps_scheduled >= 4
                with pytest.raises(InvalidArgument, match="takes 7"):
                    await session.push("main", [[0.0] * 8], 0.05)
                await asyncio.sleep(0.6)
                obs = await session.next_observation()
                z = pose_tuple(obs.arms[0].robot_from_ee)[0][2]
                assert abs(z - (start[2] + 0.01)) < 1.5e-3, (start, z)

    asyncio.run(main())


PAIRS = [
    (client.Client, aio.AsyncClient),
    (client.Episodes, aio.AsyncEpisodes),
    (client.Scene, aio.AsyncScene),
    (client.PolicySession, aio.AsyncPolicySession),
    (client.TeleopSession, aio.AsyncTeleopSession),
]


def _public(cls: type) -> dict[str, object]:
    return {n: v for n, v in inspect.getmembers(cls) if not n.startswith("_") or n == "__init__"}


@pytest.mark.parametrize(("sync_cls", "async_cls"), PAIRS, ids=[a.__name__ for _, a in PAIRS])
def test_the_blocking_layer_forwards_every_async_call(sync_cls: type, async_cls: type) -> None:
    """The blocking classes run the asyncio ones (`phone2act.client` holds no protocol of its own): every
    public coroutine (or async iterator) of the asyncio class has a blocking forward with the same parameters
    and defaults, so nothing added to the asyncio client is missing from the blocking one."""
    sync, asyn = _public(sync_cls), _public(async_cls)
    extra_allowed = {"connect"}  # `await AsyncClient.connect(...)`: a constructor cannot await readiness
    assert set(asyn) - extra_allowed <= set(sync), f"{sync_cls.__name__} lacks {sorted(set(asyn) - set(sync))}"
    for name, twin in asyn.items():
        if name in extra_allowed:
            continue
        member = sync[name]
        if isinstance(twin, property):
            assert isinstance(member, property), name
            continue
        if name == "__init__" and sync_cls is not client.Client:
            continue  # sessions are made by the client, their constructors are private
        want = [(p.name, p.kind, p.default) for p in inspect.signature(twin).parameters.values()]
        got = [(p.name, p.kind, p.default) for p in inspect.signature(member).parameters.values()]
        assert got == want, f"{sync_cls.__name__}.{name}{inspect.signature(member)} != {inspect.signature(twin)}"
        if name != "__init__":
            assert inspect.iscoroutinefunction(twin) or inspect.isasyncgenfunction(twin), name
            assert not inspect.iscoroutinefunction(member), name


def test_the_blocking_client_runs_the_async_one(server: Server) -> None:
    with Client(server.target) as c:
        assert isinstance(c._a, aio.AsyncClient)
        with c.teleop("main") as t:
            assert isinstance(t._a, aio.AsyncTeleopSession)
            seq = t.clutch(True, [0.0, 1.2, -0.3])
            # A control tick (~10 ms) answers; 10 s only absorbs a loaded 2-core machine's stalls.
            assert t.wait_feedback(seq, timeout_s=10.0).arm_state.engaged
            assert t.feedback is t._a.feedback
        assert t.closed


def test_async_client_as_the_sync_one_is_used(server: Server) -> None:
    async def main() -> None:
        # Constructed exactly like the sync client (no token, no timeout arguments), URL with a scheme.
        async with AsyncClient(f"http://{server.target}") as c:
            cams = await c.list_cameras()
            info = await c.dataset_info()
            assert (await c.arm("main")).arm == "main"
            with pytest.raises(NotFound):
                await c.arm("nope")
            async with await c.teleop("main") as t:
                # Feedback echoes a sample within a control tick (~10 ms); 10 s only absorbs scheduling
                # stalls of a loaded 2-core machine, it is not a latency claim.
                seq = await t.clutch(True, [0.0, 1.2, -0.3])
                fb = await t.wait_feedback(seq, timeout_s=10.0)
                assert fb.error == "" and fb.arm_state.engaged, fb
                seq = await t.clutch(False)
                assert not (await t.wait_feedback(seq, timeout_s=10.0)).arm_state.engaged
        return cams, info

    cams, info = asyncio.run(main())
    with Client(server.target) as c:
        assert [x.camera for x in cams] == [x.camera for x in c.list_cameras()]
        assert info.root == c.dataset_info().root


@pytest.mark.parametrize("form", ["{}", "http://{}", "HTTP://{}/"])
def test_every_url_form_reaches_the_server(server: Server, form: str) -> None:
    target = form.format(server.target)
    # The server is already up: connecting is a loopback handshake; 10 s absorbs a loaded machine's stalls.
    with Client(target, connect_timeout_s=10.0) as c:
        assert c.list_arms()[0].arm == "main"

    async def main() -> str:
        async with AsyncClient(target, connect_timeout_s=10.0) as c:
            return (await c.list_arms())[0].arm

    assert asyncio.run(main()) == "main"


def test_token_is_required_and_sent(make_server) -> None:  # type: ignore[no-untyped-def]
    srv = make_server(token="s3cret")
    with Client(srv.target) as c, pytest.raises(Unauthenticated):
        c.list_arms()
    with Client(srv.target, token="wrong") as c, pytest.raises(Unauthenticated):
        c.list_arms()
    with Client(srv.target, token="s3cret") as c:
        assert c.list_arms()[0].arm == "main"
        with c.policy_session(["main"]) as s:  # the streaming call carries the token too
            assert s.next_observation().arms[0].arm == "main"


def test_package_exports_are_typed() -> None:
    assert (REPO / "sdk" / "python" / "src" / "phone2act" / "py.typed").exists()
    assert phone2act.Client is Client
