""""Save the last N seconds" (`[recorder] highlight_s`, LeRobot's `highlight`) through the Python SDK (blocking and
asyncio), read back with pyarrow, PyAV and lerobot 0.6.1: a real `phone2act serve` with a sim arm and a
test-pattern camera keeps the last 2 s while idle; the saved episodes have N·fps rows (one more at most: they
start at a video key frame), frame indices and timestamps contiguous from 0, one decoded video frame per row at
k/fps, and lerobot loads them as its own."""

from __future__ import annotations

import asyncio
from pathlib import Path

import pyarrow.parquet as pq
import pytest
from conftest import CAMERA, py_conftest
from phone2act import Client, FailedPrecondition
from phone2act.aio import AsyncClient
from phone2act.v1 import common_pb2

FPS = 20
KEEP_S = 2.0
KEEP = int(KEEP_S * FPS)
# Each wait is for a few seconds of recorder ticks, which a loaded machine writes late but never skips: only a
# stalled server takes this long.
WAIT_S = 60.0


def kept_at_least(c: Client, seconds: float) -> bool:
    return py_conftest.wait_until(lambda: c.episodes.status().highlight_buffered_s >= seconds, timeout_s=WAIT_S)


def rows(root: Path, episode: int) -> list[dict]:
    table = pq.read_table(sorted((root / "data").rglob("*.parquet")))
    out = [r for r in table.to_pylist() if r["episode_index"] == episode]
    return sorted(out, key=lambda r: r["frame_index"])


def video_frames(root: Path, episode: int) -> list[float]:
    """Presentation times, s, of the frames of episode `episode`'s video (one episode per file here)."""
    import av

    files = sorted((root / "videos" / "observation.images.front").rglob("*.mp4"))
    with av.open(str(files[episode])) as c:
        stream = c.streams.video[0]
        return [float(f.pts * stream.time_base) for f in c.decode(video=0)]


@pytest.fixture(scope="module")
def kept(tmp_path_factory: pytest.TempPathFactory):  # type: ignore[no-untyped-def]
    tmp = tmp_path_factory.mktemp("highlight")
    srv = py_conftest.start_server(
        tmp, py_conftest.config_text(tmp / "ds", cameras=CAMERA, extra=f"highlight_s = {KEEP_S}\n")
    )
    yield srv
    srv.stop()


def test_the_last_seconds_load_in_pyarrow_pyav_and_lerobot(kept) -> None:  # type: ignore[no-untyped-def]
    from lerobot.datasets import LeRobotDataset

    with Client(kept.target) as c:
        assert c.episodes.status().highlight_s == KEEP_S
        assert kept_at_least(c, KEEP_S)
        r = c.episodes.save_highlight("the last two seconds", operator="py", success=False)
        first = r.episode
        assert KEEP <= first.length_frames <= KEEP + 1, first.length_frames
        assert first.outcome == common_pb2.EPISODE_OUTCOME_FAILURE and first.operator == "py"

        async def live_start() -> int:
            async with AsyncClient(kept.target) as a:
                while (await a.episodes.status()).highlight_buffered_s < KEEP_S:
                    await asyncio.sleep(0.05)
                r = await a.episodes.save_highlight("kept and recorded on", keep_recording=True)
                assert r.status.phase == common_pb2.RECORDING_PHASE_RECORDING and not r.HasField("episode")
                with pytest.raises(FailedPrecondition, match="being recorded"):
                    await a.episodes.save_highlight("again")
                while (await a.episodes.status()).frames_recorded < KEEP + 10:
                    await asyncio.sleep(0.05)
                return (await a.episodes.stop()).length_frames

        second = asyncio.run(asyncio.wait_for(live_start(), WAIT_S))
        assert second >= KEEP + 10

    root = kept.root
    for episode, n in ((0, first.length_frames), (1, second)):
        got = rows(root, episode)
        assert [r["frame_index"] for r in got] == list(range(n))
        assert all(abs(r["timestamp"] - k / FPS) < 1e-4 for k, r in enumerate(got))
        assert [r["index"] - got[0]["index"] for r in got] == list(range(n))
        times = video_frames(root, episode)
        assert len(times) == n, f"episode {episode}: {len(times)} video frames, {n} rows"
        assert all(abs(t - k / FPS) < 1e-6 for k, t in enumerate(times))

    ds = LeRobotDataset("local/highlight", root=root)
    assert ds.meta.total_episodes == 2
    assert ds.num_frames == first.length_frames + second
    for i in (0, first.length_frames - 1, first.length_frames, ds.num_frames - 1):
        frame = ds[i]
        assert tuple(frame["observation.images.front"].shape) == (3, 48, 64)
    last = ds[first.length_frames - 1]
    assert int(last["episode_index"]) == 0
    assert abs(float(last["timestamp"]) - (first.length_frames - 1) / FPS) < 1e-4
