"""The view's event derivation on hand-made status sequences, including the coalesced ones a watch stream
delivers when changes come faster than it sends (stop and start together, SAVING skipped, a re-record)."""

from __future__ import annotations

from phone2act.v1 import common_pb2 as pb
from phone2act_view.events import EpisodeTracker, arm_events

IDLE, REC, PAUSED, SAVING = (pb.RECORDING_PHASE_IDLE, pb.RECORDING_PHASE_RECORDING, pb.RECORDING_PHASE_PAUSED,
                             pb.RECORDING_PHASE_SAVING)


def status(phase: int, index: int, saved: int, frames: int = 0, task: str = "t", warning: str = "") -> pb.RecordingStatus:
    return pb.RecordingStatus(phase=phase, episode_index=index, episodes_saved=saved, frames_recorded=frames,
                              task=task if phase in (REC, PAUSED) else "", warning=warning)


def run(*statuses: pb.RecordingStatus) -> list[tuple[str, int]]:
    tracker = EpisodeTracker()
    return [(e.kind, e.index) for s in statuses for e in tracker.update(s)]


def test_start_save_through_saving() -> None:
    assert run(status(IDLE, 0, 0), status(REC, 0, 0, 5), status(REC, 0, 0, 40), status(SAVING, 0, 0),
               status(IDLE, 1, 1)) == [("started", 0), ("saved", 0)]


def test_save_with_saving_coalesced_away() -> None:
    assert run(status(IDLE, 3, 3), status(REC, 3, 3, 9), status(IDLE, 4, 4)) == [("started", 3), ("saved", 3)]


def test_discard_goes_back_to_idle_without_a_new_episode() -> None:
    assert run(status(IDLE, 3, 3), status(REC, 3, 3, 9), status(SAVING, 3, 3), status(IDLE, 3, 3)) == [
        ("started", 3), ("discarded", 3)]


def test_stop_and_start_between_two_updates() -> None:
    assert run(status(REC, 0, 0, 30), status(REC, 1, 1, 2)) == [("started", 0), ("saved", 0), ("started", 1)]


def test_rerecord_restarts_the_same_index() -> None:
    assert run(status(REC, 2, 2, 30), status(REC, 2, 2, 1)) == [("started", 2), ("discarded", 2), ("started", 2)]


def test_pause_and_resume_are_not_boundaries() -> None:
    assert run(status(IDLE, 0, 0), status(REC, 0, 0, 5), status(PAUSED, 0, 0, 6, warning="camera stale"),
               status(REC, 0, 0, 7), status(IDLE, 1, 1)) == [
        ("started", 0), ("paused", 0), ("resumed", 0), ("saved", 0)]


def test_idle_updates_say_nothing() -> None:
    assert run(status(IDLE, 0, 0), status(IDLE, 0, 0), status(IDLE, 0, 0)) == []


def arm(**kw: object) -> pb.ArmState:
    return pb.ArmState(arm="main", health=pb.BRIDGE_HEALTH_READY, **kw)  # type: ignore[arg-type]


def texts(prev: pb.ArmState, cur: pb.ArmState) -> list[str]:
    return [e.text for e in arm_events(prev, cur)]


def test_clutch_owner_and_success_changes() -> None:
    a = arm(owner=pb.CONTROL_SOURCE_NONE)
    b = arm(owner=pb.CONTROL_SOURCE_TELEOP, owner_id="phone-1", engaged=True, task_success=True)
    assert texts(a, b) == ["clutch engaged", "owner: nobody -> teleop (phone-1)", "task success"]
    assert texts(b, a) == ["clutch released", "owner: teleop (phone-1) -> nobody", "task success cleared"]
    assert texts(a, a) == []


def test_rejections_are_counted_even_between_snapshots() -> None:
    jump = pb.GateDecision(verdict=pb.GATE_VERDICT_REJECTED_JUMP, reason="position step 0.100 m exceeds 0.060 m")
    a = arm(commands_rejected=1, last_decision=jump)
    # Three more rejections between two snapshots, and the latest decision accepted again: still reported.
    b = arm(commands_rejected=4, last_decision=pb.GateDecision(verdict=pb.GATE_VERDICT_ACCEPTED))
    assert texts(a, b) == ["gate rejected 3 commands (latest decision: accepted)"]
    c = arm(commands_rejected=5, last_decision=jump)
    assert texts(b, c) == ["gate rejected 1 command: position step 0.100 m exceeds 0.060 m"]


def test_clamping_is_reported_when_it_starts_and_ends() -> None:
    ok = arm(last_decision=pb.GateDecision(verdict=pb.GATE_VERDICT_ACCEPTED))
    clamped = arm(last_decision=pb.GateDecision(verdict=pb.GATE_VERDICT_CLAMPED, reason="z clamped to 0.35 m"))
    assert texts(ok, clamped) == ["gate clamped: z clamped to 0.35 m"]
    assert texts(clamped, clamped) == []
    assert texts(clamped, ok) == ["gate accepted"]


def test_bridge_health_changes() -> None:
    down = pb.ArmState(arm="main", health=pb.BRIDGE_HEALTH_DISCONNECTED, health_message="connection reset")
    assert [(e.level, e.text) for e in arm_events(arm(), down)] == [("ERROR", "bridge disconnected: connection reset")]
