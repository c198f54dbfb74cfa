"""The view's inbox: observations and status snapshots are latest-only (a slow view skips to the newest, memory
stays bounded), recorder changes are all kept, in order, in a bounded queue whose writer waits."""

from __future__ import annotations

import threading
import time

from phone2act_view.view import _EPISODE_QUEUE, Inbox


def test_a_slow_reader_gets_only_the_newest_observation_and_status() -> None:
    inbox = Inbox()
    for i in range(1000):
        inbox.put_latest("observation", i)
        inbox.put_latest("status", -i)
    recorder, latest = inbox.take(timeout_s=0.0)
    assert recorder == [] and latest == {"observation": 999, "status": -999}
    assert inbox.overwritten == {"observation": 999, "status": 999}
    assert inbox.take(timeout_s=0.0) == ([], {})


def test_recorder_changes_are_kept_in_order_and_bounded() -> None:
    inbox = Inbox()
    n = _EPISODE_QUEUE + 50
    writer = threading.Thread(target=lambda: [inbox.put_recorder(i) for i in range(n)], daemon=True)
    writer.start()
    # The writer fills the queue (microseconds; 30 s is a ceiling for a loaded machine), then waits for the
    # reader instead of growing it: 0.2 s later it is still blocked with the queue at its bound.
    deadline = time.monotonic() + 30.0
    while len(inbox.recorder) < _EPISODE_QUEUE and time.monotonic() < deadline:
        time.sleep(0.01)
    time.sleep(0.2)
    assert writer.is_alive() and len(inbox.recorder) == _EPISODE_QUEUE
    got: list[int] = []
    while len(got) < n:
        recorder, _ = inbox.take(timeout_s=1.0)
        got += recorder
    assert got == list(range(n))
    writer.join(timeout=5.0)
    assert not writer.is_alive()
