"""What happened between two snapshots: clutch, owner, gate and success changes of an arm, and the episode
boundaries in the recorder's status stream. Pure functions of the messages, no I/O, so they are tested
without a server.

Snapshots are samples (the status stream at the view's rate), so a change that comes and goes between two
of them is not seen; counters (rejections) are cumulative and never missed, only merged.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from phone2act.v1 import common_pb2

# TextLog levels rerun understands; chosen so the viewer colours refusals apart from normal events.
INFO = "INFO"
WARN = "WARN"
ERROR = "ERROR"

_OWNER = {
    common_pb2.CONTROL_SOURCE_UNSPECIFIED: "nobody",
    common_pb2.CONTROL_SOURCE_NONE: "nobody",
    common_pb2.CONTROL_SOURCE_TELEOP: "teleop",
    common_pb2.CONTROL_SOURCE_POLICY: "policy",
}
_VERDICT = {
    common_pb2.GATE_VERDICT_UNSPECIFIED: "none",
    common_pb2.GATE_VERDICT_ACCEPTED: "accepted",
    common_pb2.GATE_VERDICT_CLAMPED: "clamped",
    common_pb2.GATE_VERDICT_REJECTED_JUMP: "rejected (jump)",
    common_pb2.GATE_VERDICT_REJECTED_INVALID: "rejected (invalid)",
    common_pb2.GATE_VERDICT_HELD_STALE: "held (stale)",
}
_REJECTED = (common_pb2.GATE_VERDICT_REJECTED_JUMP, common_pb2.GATE_VERDICT_REJECTED_INVALID)
_HEALTH = {
    common_pb2.BRIDGE_HEALTH_UNSPECIFIED: "unknown",
    common_pb2.BRIDGE_HEALTH_CONNECTING: "connecting",
    common_pb2.BRIDGE_HEALTH_READY: "ready",
    common_pb2.BRIDGE_HEALTH_ERROR: "error",
    common_pb2.BRIDGE_HEALTH_DISCONNECTED: "disconnected",
}
# Recording (or paused) with an episode in progress; SAVING already has none (the server reports the next
# index and zero frames while it commits the stopped one).
_ACTIVE = (common_pb2.RECORDING_PHASE_RECORDING, common_pb2.RECORDING_PHASE_PAUSED)


@dataclass(frozen=True)
class Event:
    level: str
    text: str


def owner_name(owner: int, owner_id: str) -> str:
    name = _OWNER.get(owner, f"source {owner}")
    return f"{name} ({owner_id})" if owner_id and name != "nobody" else name


def arm_events(prev: Any | None, cur: Any) -> list[Event]:
    """Events of one arm between the snapshot `prev` (None: the first one seen) and `cur` (both `ArmState`)."""
    out: list[Event] = []
    if prev is None:
        out.append(Event(INFO, f"first seen: owner {owner_name(cur.owner, cur.owner_id)}, "
                               f"clutch {'engaged' if cur.engaged else 'released'}, "
                               f"bridge {_HEALTH.get(cur.health, cur.health)}"))
        return out
    if cur.engaged != prev.engaged:
        out.append(Event(INFO, "clutch engaged" if cur.engaged else "clutch released"))
    if (cur.owner, cur.owner_id) != (prev.owner, prev.owner_id):
        out.append(Event(INFO, f"owner: {owner_name(prev.owner, prev.owner_id)} -> {owner_name(cur.owner, cur.owner_id)}"))
    rejected = cur.commands_rejected - prev.commands_rejected
    if rejected > 0:
        d = cur.last_decision
        if d.verdict in _REJECTED:
            why = f": {d.reason or _VERDICT[d.verdict]}"
        else:  # later commands passed before this snapshot: the rejection's reason is gone
            why = f" (latest decision: {_VERDICT.get(d.verdict, d.verdict)})"
        out.append(Event(WARN, f"gate rejected {rejected} command{'s' if rejected > 1 else ''}{why}"))
    elif cur.last_decision.verdict != prev.last_decision.verdict:
        # Rejections are reported by their counter above; this reports the other changes of mind (clamping
        # starting or ending, the arm holding because its source went stale).
        verdict = _VERDICT.get(cur.last_decision.verdict, str(cur.last_decision.verdict))
        reason = f": {cur.last_decision.reason}" if cur.last_decision.reason else ""
        level = INFO if cur.last_decision.verdict == common_pb2.GATE_VERDICT_ACCEPTED else WARN
        out.append(Event(level, f"gate {verdict}{reason}"))
    if cur.task_success != prev.task_success:
        out.append(Event(INFO, "task success" if cur.task_success else "task success cleared"))
    if cur.health != prev.health:
        msg = f": {cur.health_message}" if cur.health_message else ""
        level = INFO if cur.health == common_pb2.BRIDGE_HEALTH_READY else ERROR
        out.append(Event(level, f"bridge {_HEALTH.get(cur.health, cur.health)}{msg}"))
    return out


@dataclass(frozen=True)
class EpisodeEvent:
    """`kind`: "started", "saved", "discarded" (a boundary), or "paused"/"resumed" (the recorder held back by
    a stale source). `index` is the episode's index in the dataset (a discarded one's is reused)."""

    kind: str
    index: int
    task: str
    frames: int
    text: str

    @property
    def level(self) -> str:
        return WARN if self.kind in ("discarded", "paused") else INFO


class EpisodeTracker:
    """Turns the `Episodes.Watch` stream (one `RecordingStatus` per change) into episode boundaries.

    An episode starts when the recorder enters RECORDING; it ends when the recorder leaves RECORDING/PAUSED.
    It was saved if `episodes_saved` grew by the time the recorder is idle again (through SAVING, which a
    discard passes too), else it was discarded. A re-record restarts the same index from frame 0.
    """

    def __init__(self) -> None:
        self._prev: Any | None = None
        # The episode in progress or being saved: (index, task, frames seen, episodes_saved before it).
        self._open: tuple[int, str, int, int] | None = None

    @property
    def recording(self) -> bool:
        return self._open is not None

    def update(self, cur: Any) -> list[EpisodeEvent]:
        prev, self._prev = self._prev, cur
        active = cur.phase in _ACTIVE
        out: list[EpisodeEvent] = []
        if self._open is not None:
            index, task, frames, saved_before = self._open
            restarted = active and (
                cur.episodes_saved > saved_before or cur.episode_index != index or cur.frames_recorded < frames
            )
            if active and not restarted:
                self._open = (index, task, cur.frames_recorded, saved_before)
                if prev is not None and prev.phase != cur.phase:
                    if cur.phase == common_pb2.RECORDING_PHASE_PAUSED:
                        out.append(EpisodeEvent("paused", index, task, cur.frames_recorded,
                                                f"recording paused: {cur.warning or 'a source is stale'}"))
                    else:
                        out.append(EpisodeEvent("resumed", index, task, cur.frames_recorded, "recording resumed"))
                return out
            if cur.phase == common_pb2.RECORDING_PHASE_SAVING:
                return out  # the outcome shows when the recorder is idle again
            if cur.episodes_saved > saved_before:
                out.append(EpisodeEvent("saved", index, task, frames, f"episode {index} saved"))
            else:
                why = f": {cur.warning}" if cur.warning else ""
                out.append(EpisodeEvent("discarded", index, task, frames, f"episode {index} discarded{why}"))
            self._open = None
        if active:
            note = " (already recording when the view started)" if prev is None else ""
            self._open = (cur.episode_index, cur.task, cur.frames_recorded, cur.episodes_saved)
            out.append(EpisodeEvent("started", cur.episode_index, cur.task, cur.frames_recorded,
                                    f"episode {cur.episode_index} started: {cur.task!r}{note}"))
        return out
