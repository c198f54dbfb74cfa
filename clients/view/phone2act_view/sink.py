"""Where the view's data goes: one long recording (a live viewer and/or `--save`), plus one recording per
episode under `--save-episodes`, each a rerun `RecordingStream` with its own file sink.

Every log call goes to all the recordings open at that moment. Static data (coordinate frame, workspace
boxes, series names) is remembered and replayed into each new episode recording, so each `.rrd` stands alone.
"""

from __future__ import annotations

import logging
import uuid
from pathlib import Path
from typing import Any

import rerun as rr

log = logging.getLogger("phone2act_view")

APPLICATION_ID = "phone2act"


class Fanout:
    def __init__(self, main: rr.RecordingStream | None, episodes_dir: Path | None) -> None:
        self._main = main
        self._episodes_dir = episodes_dir
        self._static: list[tuple[str, Any]] = []
        # The episode recording in progress: (stream, path it is written to, episode index).
        self._episode: tuple[rr.RecordingStream, Path, int] | None = None
        self._time: tuple[str, float] | None = None
        self.saved_episodes: list[Path] = []

    def _streams(self) -> list[rr.RecordingStream]:
        out = [self._main] if self._main is not None else []
        if self._episode is not None:
            out.append(self._episode[0])
        return out

    def set_time_s(self, timeline: str, seconds: float) -> None:
        self._time = (timeline, seconds)
        for s in self._streams():
            s.set_time(timeline, duration=seconds)

    def log(self, path: str, value: Any) -> None:
        for s in self._streams():
            s.log(path, value)

    def log_static(self, path: str, value: Any) -> None:
        self._static.append((path, value))
        for s in self._streams():
            s.log(path, value, static=True)

    def start_episode(self, index: int, task: str) -> None:
        """Open `episode_<index>.rrd` (written as `.recording.rrd` until the episode ends)."""
        if self._episodes_dir is None:
            return
        if self._episode is not None:
            self.end_episode("unfinished")
        path = self._episodes_dir / f"episode_{index:06d}.recording.rrd"
        stream = rr.RecordingStream(APPLICATION_ID, recording_id=uuid.uuid4())
        stream.save(str(path))
        stream.send_recording_name(f"episode {index}: {task}")
        for p, v in self._static:
            stream.log(p, v, static=True)
        if self._time is not None:
            stream.set_time(self._time[0], duration=self._time[1])
        self._episode = (stream, path, index)

    def end_episode(self, outcome: str) -> Path | None:
        """Close the episode recording; `outcome` "saved" names it `episode_<index>.rrd`, anything else
        `episode_<index>.<outcome>.rrd` (a discarded take's index is reused by the next one)."""
        if self._episode is None:
            return None
        stream, path, index = self._episode
        self._episode = None
        _close(stream)
        stem = f"episode_{index:06d}" if outcome == "saved" else f"episode_{index:06d}.{outcome}"
        final = path.with_name(stem + ".rrd")
        n = 1
        while final.exists():
            final = path.with_name(f"{stem}.{n}.rrd")
            n += 1
        path.rename(final)
        self.saved_episodes.append(final)
        log.info("wrote %s", final)
        return final

    def close(self) -> None:
        self.end_episode("unfinished")
        if self._main is not None:
            _close(self._main)
            self._main = None


def _close(stream: rr.RecordingStream) -> None:
    # Flushing then disconnecting closes the file sink, so the .rrd is complete when this returns.
    stream.flush()
    stream.disconnect()
