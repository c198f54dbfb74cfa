"""Checks phone2act datasets with the real lerobot reader.

Usage: python check.py DATASET_DIR...   (all of one codebase version: lerobot 0.4.x reads v3.0, 0.3.3 v2.1)

For every dataset: load it with LeRobotDataset (local root, no network), iterate every frame with decoded
video, and assert timestamps (at or just after frame_index / fps, docs/timestamps.md), that every step decodes
to frame k of its video in LeRobot's and each of GR00T's readers (`Pairing`), indices, episode lengths, tasks and feature shapes against
meta/info.json. For v2.1 also run a GR00T-style check of meta/modality.json and meta/stats.json (mean, std,
min, max, q01, q99 for every parquet column, consistent with the data). Statistics of the numeric columns
(both formats) are checked against numpy over every frame read with pyarrow: quantiles are numpy's default
(linear) quantiles of the whole dataset, exactly while a column has at most SKETCH_EXACT_ROWS rows and
within the recorder's stated rank error (0.5 % of the rows) beyond. A dataset directory may hold
`phone2act_expect.json` ({"episodes": N, "tasks": [...]}) written by the Rust test that produced it.
Prints one PASS/FAIL line per dataset and a closing "N passed, M failed" line; exits 1 on any failure.
"""

import json
import os
import sys
import traceback
from pathlib import Path

os.environ.setdefault("HF_HUB_OFFLINE", "1")
os.environ.setdefault("HF_DATASETS_OFFLINE", "1")

import numpy as np  # noqa: E402
import pyarrow.parquet as pq  # noqa: E402


def fail(msg):
    raise AssertionError(msg)


# The recorder's quantile sketch keeps every value up to this many per column (SKETCH_LEVEL_CAPACITY in
# server/dataset/src/stats.rs) and guarantees a rank error of at most RANK_ERROR of the rows beyond.
SKETCH_EXACT_ROWS = 4096
RANK_ERROR = 0.005
QUANTILE_KEYS = {"q01": 0.01, "q10": 0.10, "q50": 0.50, "q90": 0.90, "q99": 0.99}


def v21_commit_window(root: Path, info: dict, n_frames: int, version: str) -> bool:
    """A v2.1 save renames the data file and its episodes.jsonl line first and rewrites info.json last (three
    files cannot change atomically). A kill in between leaves exactly one committed-but-uncounted episode:
    lerobot loads it whole, and the recorder's next open brings info.json up to date. Accept exactly that
    state and nothing looser."""
    if not version.startswith("v2"):
        return False
    lines = [json.loads(l) for l in (root / "meta/episodes.jsonl").read_text().splitlines() if l.strip()]
    if len(lines) != info["total_episodes"] + 1:
        return False
    return sum(int(e["length"]) for e in lines) == n_frames == info["total_frames"] + int(lines[-1]["length"])


def check_common(root: Path, info: dict, ds, version: str, pairing=None):
    fps = info["fps"]
    total_frames = info["total_frames"]
    total_episodes = info["total_episodes"]
    features = info["features"]
    video_keys = [k for k, v in features.items() if v["dtype"] == "video"]
    in_window = len(ds) != total_frames and v21_commit_window(root, info, len(ds), version)
    if in_window:
        # Killed inside a v2.1 save's commit window: count the episode that is already whole on disk.
        total_frames, total_episodes = len(ds), total_episodes + 1
        print(f"note: {root.name}: killed between the v2.1 data commit and the info.json update")
    if len(ds) != total_frames:
        fail(f"len(ds)={len(ds)} but info.json total_frames={total_frames}")
    # lerobot 0.3.3 reports num_episodes straight from info.json, which inside the window is one short.
    reported_episodes = total_episodes - 1 if in_window else total_episodes
    if ds.num_episodes != reported_episodes:
        fail(f"num_episodes={ds.num_episodes} but info.json says {reported_episodes}")
    expect_path = root / "phone2act_expect.json"
    expect = json.loads(expect_path.read_text()) if expect_path.exists() else {}
    if "episodes" in expect and total_episodes != expect["episodes"]:
        fail(f"dataset has {total_episodes} episodes, the producing test expected {expect['episodes']}")
    if "min_episodes" in expect and total_episodes < expect["min_episodes"]:
        fail(f"dataset has {total_episodes} episodes, expected at least {expect['min_episodes']}")
    check_dagger(root, info, ds, version, expect)
    check_success(info, ds, expect)
    ep_len = {}
    last_ep, last_fi = -1, -1
    for i in range(len(ds)):
        item = ds[i]
        ep = int(item["episode_index"])
        fi = int(item["frame_index"])
        ts = float(item["timestamp"])
        if int(item["index"]) != i:
            fail(f"row {i}: index={int(item['index'])}")
        if ep == last_ep:
            if fi != last_fi + 1:
                fail(f"row {i}: frame_index {fi} after {last_fi} (gap) in episode {ep}")
        else:
            if ep != last_ep + 1 or fi != 0:
                fail(f"row {i}: episode {ep} frame {fi} follows episode {last_ep}")
        last_ep, last_fi = ep, fi
        ep_len[ep] = fi + 1
        # phone2act's rule (docs/timestamps.md): at or after fi/fps, within LeRobot's 1e-4 s. Compared exactly:
        # a float32 times a whole fps is exact in float64.
        if ts * fps < fi or ts - fi / fps >= 1e-4:
            fail(f"row {i}: timestamp {ts!r} is not in [frame_index/fps, +1e-4 s) = [{fi / fps!r}, ...)")
        task = item.get("task")
        if not isinstance(task, str) or not task:
            fail(f"row {i}: task is {task!r}, not the task text")
        if "tasks" in expect and task not in expect["tasks"]:
            fail(f"row {i}: task {task!r} not among {expect['tasks']}")
        for key, spec in features.items():
            if spec["dtype"] == "video":
                h, w, c = spec["shape"]
                t = item[key]
                if pairing is not None:
                    pairing.lerobot_frame(ep, fi, ts, key, t)
                if tuple(t.shape) != (c, h, w):
                    fail(f"row {i}: {key} decoded to shape {tuple(t.shape)}, expected {(c, h, w)}")
                if float(t.min()) < 0.0 or float(t.max()) > 1.0:
                    fail(f"row {i}: {key} outside 0..1")
            elif key in ("observation.state", "action"):
                if tuple(item[key].shape) != tuple(spec["shape"]):
                    fail(f"row {i}: {key} shape {tuple(item[key].shape)} != {spec['shape']}")
                if not np.isfinite(item[key].numpy()).all():
                    fail(f"row {i}: {key} not finite")
            elif spec["dtype"] == "bool":
                # `next.success` and friends: a boolean scalar per frame, as lerobot's sim datasets have.
                if str(item[key].dtype) != "torch.bool" or item[key].numel() != 1:
                    fail(f"row {i}: {key} is {item[key].dtype} of {item[key].numel()} values, not one bool")
    if sorted(ep_len) != list(range(total_episodes)):
        fail(f"episodes in data {sorted(ep_len)} != 0..{total_episodes - 1}")
    for e, n in expect.get("lengths", {}).items():
        if ep_len.get(int(e)) != n:
            fail(f"episode {e} has {ep_len.get(int(e))} frames, {n} were saved before the kill")
    return ep_len, video_keys, in_window


# The column lerobot's human-in-the-loop recording adds (lerobot 0.6.1 `rollout/context.py`, DAgger strategy):
# True while a person corrects, False while the policy drives.
DAGGER_FEATURE = ("intervention", {"dtype": "bool", "shape": (1,), "names": None})


def bool_column(ds, key: str, declared: dict, declared_by: str) -> np.ndarray:
    """A bool feature's values, as lerobot's table hands them out (no video decoding), once lerobot sees it
    declared as `declared_by` declares it."""
    seen = ds.meta.features[key]
    seen = {"dtype": seen["dtype"], "shape": tuple(seen["shape"]), "names": seen["names"]}
    if seen != declared:
        fail(f"lerobot sees {key} as {seen}, {declared_by} declares {declared}")
    return np.asarray([bool(np.asarray(v).reshape(-1)[0]) for v in ds.hf_dataset[key]])


def check_dagger(root: Path, info: dict, ds, version: str, expect: dict):
    """A dataset with `intervention` declares it exactly as lerobot's DAgger recording does, lerobot loads it
    as that feature, its stats are those lerobot writes for a bool column (min/max as floats in v3.0 from
    lerobot 0.6, as bools in v2.1 from lerobot 0.3), and the producing test's count of intervention frames
    (`phone2act_expect.json` "intervention_frames") is what the data holds."""
    key, declared = DAGGER_FEATURE
    if key not in info["features"]:
        if "intervention_frames" in expect:
            fail(f"the producing test recorded interventions but info.json has no {key} feature")
        return
    values = bool_column(ds, key, declared, "lerobot's DAgger recording")
    if "intervention_frames" in expect and int(values.sum()) != expect["intervention_frames"]:
        fail(f"{int(values.sum())} intervention frames, the producing test saw {expect['intervention_frames']}")
    if version == "v3.0":
        entry = json.loads((root / "meta/stats.json").read_text())[key]
        for k in ("min", "max"):
            if not all(isinstance(v, float) for v in entry[k]):
                fail(f"stats.json {key}.{k} = {entry[k]}: lerobot 0.6 writes a bool column's {k} as a float")
        if values.size and abs(entry["mean"][0] - values.mean()) > 1e-6:
            fail(f"stats.json {key}.mean = {entry['mean']} but the frames give {values.mean()}")


# `next.success` as lerobot's evaluation recording declares it (lerobot 0.6.1 `scripts/lerobot_eval.py`).
SUCCESS_FEATURE = ("next.success", {"dtype": "bool", "shape": (1,), "names": None})


def check_success(info: dict, ds, expect: dict):
    """A dataset with `next.success` declares it as lerobot's evaluation recording does, and the values lerobot
    reads are those the producing test set (`phone2act_expect.json`: "success_last", each episode's last frame
    in order; "success_frames", the count of true frames)."""
    key, declared = SUCCESS_FEATURE
    if key not in info["features"]:
        if "success_last" in expect or "success_frames" in expect:
            fail(f"the producing test marked outcomes but info.json has no {key} feature")
        return
    values = bool_column(ds, key, declared, "lerobot's evaluation recording")
    if "success_frames" in expect and int(values.sum()) != expect["success_frames"]:
        fail(f"{int(values.sum())} frames with {key}, the producing test marked {expect['success_frames']}")
    if "success_last" in expect:
        episodes = np.asarray([int(np.asarray(v).reshape(-1)[0]) for v in ds.hf_dataset["episode_index"]])
        last = [bool(values[np.nonzero(episodes == e)[0][-1]]) for e in range(int(episodes.max()) + 1)]
        if last != expect["success_last"]:
            fail(f"last frames' {key} = {last}, the producing test gave {expect['success_last']}")


class Skip(Exception):
    """A reader that cannot run here (not installable, or its FFmpeg lacks the codec): reported, loudly."""


def _rgb_u8_from_chw_float(t) -> np.ndarray:
    """LeRobot's decoded frame (float CHW in 0..1, uint8 / 255) back to the uint8 HWC pixels it came from."""
    return np.clip(np.rint(t.numpy().transpose(1, 2, 0) * 255.0), 0, 255).astype(np.uint8)


def gr00t_n15_torchcodec(path: str, ts: np.ndarray) -> np.ndarray:
    """GR00T N1.5's default reader: the frame played at each timestamp."""
    from torchcodec.decoders import VideoDecoder

    decoder = VideoDecoder(path, device="cpu", dimension_order="NHWC", num_ffmpeg_threads=0)
    return decoder.get_frames_played_at(seconds=[float(t) for t in ts]).data.numpy()


def gr00t_n16_torchcodec(path: str, ts: np.ndarray) -> np.ndarray:
    """GR00T N1.6's torchcodec reader: timestamps snapped to the nearest multiple of 1 / average_fps (refused
    beyond 1 % of a frame), then the frame played at that time."""
    from torchcodec.decoders import VideoDecoder

    decoder = VideoDecoder(path, device="cpu", dimension_order="NHWC", num_ffmpeg_threads=0)
    interval = 1.0 / decoder.metadata.average_fps
    t = np.asarray(ts, dtype=np.float64)
    snapped = np.round(t / interval) * interval
    off = np.abs(snapped - t) / interval
    if (off >= 0.01).any():
        fail(f"GR00T N1.6 refuses timestamps {t[off >= 0.01][:3]} (more than 1 % of a frame off the grid)")
    return decoder.get_frames_played_at(seconds=[float(x) for x in snapped]).data.numpy()


def gr00t_decord(path: str, ts: np.ndarray) -> np.ndarray:
    """GR00T's decord reader (N1.5's documented default): the frame whose start is nearest each timestamp."""
    try:
        import decord
    except ImportError as e:
        raise Skip(f"decord is not installed here ({e}); tests/conformance/setup-venv.sh installs it where a wheel exists")
    try:
        vr = decord.VideoReader(path)
    except decord.DECORDError as e:
        raise Skip(f"decord's bundled FFmpeg cannot open this file ({_codec(path)}): {str(e).splitlines()[0][:120]}")
    starts = vr.get_frame_timestamp(range(len(vr)))[:, :1]
    indices = np.abs(starts - np.asarray(ts, dtype=np.float64)).argmin(axis=0)
    try:
        return vr.get_batch(indices).asnumpy()
    except decord.DECORDError as e:
        # decord pads a frame's rows to its own alignment and then refuses to copy them out (a 48 px wide
        # video): a decord limit whatever the timestamps.
        first = str(e).splitlines()[0]
        raise Skip(f"decord cannot copy out this file's {vr[0].shape[1]} px wide frames: {first[first.find('Check'):][:80]}")


def _codec(path: str) -> str:
    import av

    with av.open(path) as c:
        return c.streams.video[0].codec_context.name


def gr00t_opencv(path: str, ts: np.ndarray) -> np.ndarray:
    """GR00T N1.6's OpenCV reader: the nearest of arange(frames) / CAP_PROP_FPS, read after a frame seek."""
    import cv2

    cap = cv2.VideoCapture(path)
    try:
        n = int(cap.get(cv2.CAP_PROP_FRAME_COUNT))
        ok, _ = cap.read()
        if not ok:
            raise Skip(f"opencv-python-headless's bundled FFmpeg cannot decode {_codec(path)}")
        starts = (np.arange(n) / cap.get(cv2.CAP_PROP_FPS))[:, None]
        indices = np.abs(starts - np.asarray(ts, dtype=np.float64)).argmin(axis=0)
        out = []
        for idx in indices:
            cap.set(cv2.CAP_PROP_POS_FRAMES, int(idx))
            ok, frame = cap.read()
            if not ok:
                fail(f"OpenCV cannot read frame {idx}")
            out.append(frame[..., ::-1])
        return np.stack(out)
    finally:
        cap.release()


def lerobot_pyav(path: str, ts: np.ndarray) -> np.ndarray:
    """LeRobot's PyAV reader, the successor of torchvision's av reader (and GR00T's `torchvision_av`): seek to
    the keyframe before the first timestamp, decode up to the last, take the nearest frame within 1e-4 s."""
    import lerobot.datasets.video_utils as vu

    try:
        frames = vu.decode_video_frames(path, [float(t) for t in ts], 1e-4, backend="pyav")
    except AttributeError as e:
        # lerobot 0.3.3's pyav path goes through torchvision.io.VideoReader, which this torchvision lacks.
        raise Skip(f"this lerobot's pyav reader needs torchvision's video reader: {e}")
    return np.stack([_rgb_u8_from_chw_float(f) for f in frames])


def torchvision_av(path: str, ts: np.ndarray) -> np.ndarray:
    import torchvision

    if not hasattr(torchvision.io, "VideoReader"):
        raise Skip(
            f"torchvision {torchvision.__version__} has no video reader (torchvision.io.VideoReader is gone from the "
            "torchvision that lerobot 0.6's torch pins); its algorithm is checked as lerobot's pyav reader"
        )
    fail("torchvision's VideoReader exists here: add its check")


# Every reader of GR00T and LeRobot that decodes by timestamp; decord last, since its bundled FFmpeg may
# disturb torchcodec's once loaded.
PAIRING_READERS = [
    ("GR00T N1.5 torchcodec (get_frames_played_at)", gr00t_n15_torchcodec),
    ("GR00T N1.6 torchcodec (snapped to the frame grid)", gr00t_n16_torchcodec),
    ("GR00T N1.6 opencv (nearest frame start)", gr00t_opencv),
    ("lerobot pyav / torchvision av (nearest loaded frame)", lerobot_pyav),
    ("torchvision av (torchvision.io.VideoReader)", torchvision_av),
    ("GR00T decord (nearest frame start)", gr00t_decord),
]


class Pairing:
    """Step k of every episode must decode to frame k of its video in every reader: the frame LeRobot's
    dataset returns for the row, and the frame each GR00T reader returns for `from_timestamp + timestamp`
    (docs/timestamps.md), must be pixel-equal to frame k decoded by index (PyAV, every frame in presentation
    order; torchcodec, decord and OpenCV decode the same pixels through FFmpeg)."""

    def __init__(self, root: Path, info: dict, locate):
        self.root, self.info, self.locate = root, info, locate
        self.steps: dict = {}
        self.lerobot: dict = {}
        self.refs: dict = {}
        expect_path = root / "phone2act_expect.json"
        self.distinct = json.loads(expect_path.read_text()).get("distinct_frames", False) if expect_path.exists() else False

    def lerobot_frame(self, ep: int, fi: int, ts: float, key: str, t):
        self.steps.setdefault((ep, key), {})[fi] = ts
        self.lerobot.setdefault((ep, key), {})[fi] = _rgb_u8_from_chw_float(t)

    def reference(self, path: str) -> np.ndarray:
        if path not in self.refs:
            import av

            with av.open(path) as c:
                frames = sorted(((f.pts, f.to_ndarray(format="rgb24")) for f in c.decode(video=0)), key=lambda x: x[0])
            self.refs[path] = np.stack([f for _, f in frames])
        return self.refs[path]

    def run(self):
        fps = self.info["fps"]
        results = {"lerobot (LeRobotDataset, its default reader)": [0, None]}
        results.update({name: [0, None] for name, _ in PAIRING_READERS})
        discriminating = total = 0
        for (ep, key), steps in sorted(self.steps.items()):
            n = len(steps)
            if sorted(steps) != list(range(n)):
                fail(f"episode {ep} {key}: steps {sorted(steps)[:5]}... are not 0..{n - 1}")
            path, from_s = self.locate(ep, key)
            ref = self.reference(str(path))
            first = round(from_s * fps)
            if first + n > len(ref):
                fail(f"episode {ep} {key}: {path} has {len(ref)} frames, the episode needs {first + n}")
            for k in range(n):
                j = first + k
                total += 1
                if all(not np.array_equal(ref[j], ref[i]) for i in (j - 1, j + 1) if 0 <= i < len(ref)):
                    discriminating += 1
            times = np.asarray([from_s + steps[k] for k in range(n)], dtype=np.float64)

            def compare(name, frames):
                if len(frames) != n:
                    fail(f"{name}: episode {ep} {key}: {len(frames)} frames for {n} steps")
                for k in range(n):
                    j = first + k
                    if not np.array_equal(frames[k], ref[j]):
                        near = [i - first for i in (j - 1, j + 1) if 0 <= i < len(ref) and np.array_equal(frames[k], ref[i])]
                        got = f"frame {near[0]}" if near else "no neighbouring frame"
                        fail(f"{name}: episode {ep} {key} step {k} (time {times[k]!r}) decoded {got}, not frame {k}")
                results[name][0] += n

            compare("lerobot (LeRobotDataset, its default reader)", [self.lerobot[(ep, key)][k] for k in range(n)])
            for name, reader in PAIRING_READERS:
                if results[name][1] is not None:
                    continue
                try:
                    compare(name, reader(str(path), times))
                except Skip as why:
                    results[name][1] = str(why)
        if self.distinct and discriminating != total:
            fail(f"only {discriminating} of {total} steps differ from both neighbours: the pairing check cannot see an off-by-one there")
        for name, (steps, skipped) in results.items():
            if skipped is not None:
                print(f"SKIP pairing {self.root.name}: {name}: {skipped}", flush=True)
            else:
                print(f"pairing {self.root.name}: {name}: frame k at step k for {steps} steps ({discriminating} of {total} distinguishable from their neighbours)", flush=True)


def v30_locate(root: Path, info: dict, ds):
    def locate(ep: int, key: str):
        row = ds.meta.episodes[ep]
        path = root / info["video_path"].format(
            video_key=key, chunk_index=row[f"videos/{key}/chunk_index"], file_index=row[f"videos/{key}/file_index"]
        )
        return path, float(row[f"videos/{key}/from_timestamp"])

    return locate


def v21_locate(root: Path, info: dict):
    def locate(ep: int, key: str):
        path = root / info["video_path"].format(
            episode_chunk=ep // info["chunks_size"], video_key=key, episode_index=ep
        )
        return path, 0.0

    return locate


def check_v30(root: Path, info: dict):
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    ds = LeRobotDataset("local/" + root.name, root=root)
    pairing = Pairing(root, info, v30_locate(root, info, ds))
    ep_len, video_keys, _ = check_common(root, info, ds, "v3.0", pairing)
    pairing.run()
    eps = ds.meta.episodes
    for e in range(info["total_episodes"]):
        row = eps[e]
        if row["length"] != ep_len[e]:
            fail(f"episode {e}: metadata length {row['length']} != {ep_len[e]} rows")
        for vk in video_keys:
            d = row[f"videos/{vk}/to_timestamp"] - row[f"videos/{vk}/from_timestamp"]
            if abs(d - ep_len[e] / info["fps"]) > 1e-6:
                fail(f"episode {e}: {vk} spans {d} s, expected {ep_len[e] / info['fps']}")
    tasks = pq.read_table(root / "meta/tasks.parquet")
    if "pandas" not in (tasks.schema.metadata or {}).keys() and b"pandas" not in (tasks.schema.metadata or {}):
        fail("meta/tasks.parquet lacks pandas metadata")
    stats = json.loads((root / "meta/stats.json").read_text())
    for key in ("observation.state", "action", *video_keys):
        for s in ("min", "max", "mean", "std", "count", "q01", "q10", "q50", "q90", "q99"):
            if s not in stats.get(key, {}):
                fail(f"meta/stats.json: {key} lacks {s}")
    check_v30_stats(root, info, stats)
    check_video_files_v30(root, info, ds)
    if (root / "meta/modality.json").exists():
        check_v30_modality(root, info)


def check_v30_modality(root: Path, info: dict):
    """phone2act's v3.0 carries GR00T's modality.json. GR00T's own loader (N1.7) reads only the v2.1 layout
    (episodes.jsonl, tasks.jsonl, one data file per episode), so what is checked here is the layout file itself
    and that its groups, applied to the v3.0 data as GR00T's `_extract_joint_groups` applies them, give every
    frame's state and action back whole."""
    modality = check_modality(root, info, decord_codecs=False)
    tasks = pq.read_table(root / "meta/tasks.parquet").to_pandas()
    task_of = dict(zip(tasks["task_index"], tasks.index)) if "task_index" in tasks else {}
    for f in sorted((root / "data").rglob("*.parquet")):
        t = pq.read_table(f)
        for part, key in (("state", "observation.state"), ("action", "action")):
            full = np.stack(t.column(key).to_numpy(zero_copy_only=False))
            parts = [full[:, g["start"]:g["end"]] for g in sorted(modality[part].values(), key=lambda g: g["start"])]
            if not np.array_equal(np.concatenate(parts, axis=1), full):
                fail(f"{f}: modality.json {part} groups do not give {key} back")
        for name, a in modality.get("annotation", {}).items():
            col = a.get("original_key", f"annotation.{name}")
            if col == "task_index" and task_of:
                missing = set(t.column(col).to_pylist()) - set(task_of)
                if missing:
                    fail(f"{f}: annotation.{name}: task indices {sorted(missing)} not in meta/tasks.parquet")


def check_video_files_v30(root: Path, info: dict, ds):
    import av

    for e in range(info["total_episodes"]):
        row = ds.meta.episodes[e]
        for vk in [k for k, v in info["features"].items() if v["dtype"] == "video"]:
            p = root / info["video_path"].format(
                video_key=vk, chunk_index=row[f"videos/{vk}/chunk_index"], file_index=row[f"videos/{vk}/file_index"]
            )
            check_cfr(p, info["fps"], None)


def check_cfr(path: Path, fps: int, expected_frames):
    import av

    with av.open(str(path)) as c:
        s = c.streams.video[0]
        pts = [p.pts for p in c.demux(s) if p.pts is not None]
        tb = s.time_base
    pts.sort()
    times = [float(p * tb) for p in pts]
    for i, t in enumerate(times):
        if abs(t - i / fps) > 1e-4:
            fail(f"{path}: frame {i} presented at {t}, expected {i / fps}")
    if expected_frames is not None and len(times) != expected_frames:
        fail(f"{path}: {len(times)} frames, expected {expected_frames}")


def check_v21(root: Path, info: dict):
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    ds = LeRobotDataset("local/" + root.name, root=root)
    pairing = Pairing(root, info, v21_locate(root, info))
    ep_len, _, in_window = check_common(root, info, ds, "v2.1", pairing)
    pairing.run()
    check_gr00t(root, info, ep_len, in_window)


def column_array(tables, col: str) -> np.ndarray:
    return np.concatenate(
        [np.asarray(t.column(col).to_pylist(), dtype=np.float64).reshape(t.num_rows, -1) for t in tables]
    )


def quantile_mismatch(got, data: np.ndarray, q: float) -> str | None:
    """Why `got` is not the q-quantile of every column of `data` (numpy's linear method), or None."""
    got = np.asarray(got, dtype=np.float64).reshape(-1)
    n = data.shape[0]
    exact = np.quantile(data, q, axis=0)
    if got.shape != exact.shape:
        return f"shape {got.shape}, data has {exact.shape}"
    if n <= SKETCH_EXACT_ROWS:
        if not np.allclose(got, exact, rtol=1e-5, atol=1e-6):
            return f"{got[:4]}... but numpy over all {n} frames gives {exact[:4]}..."
        return None
    # Beyond the exact range: between the order statistics RANK_ERROR * n ranks either side.
    srt = np.sort(data, axis=0)
    b = int(np.floor(RANK_ERROR * n))
    pos = q * (n - 1)
    lo, hi = srt[max(int(np.floor(pos)) - b, 0)], srt[min(int(np.ceil(pos)) + b, n - 1)]
    tol = 1e-6 * np.maximum(np.abs(lo), np.abs(hi)) + 1e-9
    bad = (got < lo - tol) | (got > hi + tol)
    if bad.any():
        i = int(np.argmax(bad))
        return f"[{i}] = {got[i]} outside [{lo[i]}, {hi[i]}] ({RANK_ERROR:.1%} rank error of {n} frames)"
    return None


def stats_mismatch(entry: dict, col: str, tables) -> str | None:
    """Why `entry` (one stats.json column) is not the mean/std/min/max/quantiles of `col` over `tables`, or
    None."""
    data = column_array(tables, col)
    for k, ref in (("mean", data.mean(0)), ("std", data.std(0)), ("min", data.min(0)), ("max", data.max(0))):
        got = np.asarray(entry[k], dtype=np.float64).reshape(-1)
        if got.shape != ref.shape or not np.allclose(got, ref, rtol=1e-4, atol=1e-4):
            return f"stats.json {col}.{k} = {got[:4]}... but the data gives {ref[:4]}..."
    if "count" in entry and int(np.asarray(entry["count"]).reshape(-1)[0]) != data.shape[0]:
        return f"stats.json {col}.count = {entry['count']} but the data has {data.shape[0]} frames"
    for k, q in QUANTILE_KEYS.items():
        if k in entry:
            why = quantile_mismatch(entry[k], data, q)
            if why:
                return f"stats.json {col}.{k}: {why}"
    return None


def check_v30_stats(root: Path, info: dict, stats: dict):
    """meta/stats.json of every parquet column against numpy over the data files. A kill between the data
    commit and the info.json update may leave one episode's data (and stats.json) ahead of info.json:
    then the stats are those with or without that episode, exactly."""
    files = sorted((root / "data").glob("*/*.parquet"))
    tables = [pq.read_table(f) for f in files]
    if not tables:
        fail("no data files")
    all_rows = pa_concat(tables)
    n_eps = info["total_episodes"]
    ep = np.asarray(all_rows.column("episode_index").to_pylist())
    committed = all_rows.filter(pa_mask(ep < n_eps))
    candidates = [[committed]]
    if ep.max() >= n_eps:
        candidates.append([all_rows])
    for col in committed.column_names:
        entry = stats.get(col)
        if entry is None:
            fail(f"meta/stats.json lacks column {col}")
        mismatches = [m for m in (stats_mismatch(entry, col, ts) for ts in candidates) if m]
        if len(mismatches) == len(candidates):
            fail(mismatches[0])
    check_v30_episode_stats(root, stats, all_rows, n_eps, ep.max() >= n_eps)


def check_v30_episode_stats(root: Path, stats: dict, rows, n_eps: int, one_ahead: bool):
    """The per-episode stats in meta/episodes are numpy's over that episode's rows, and meta/stats.json's
    min, max, mean, std and count are what lerobot's own aggregate_stats makes of them (its quantiles are
    a count-weighted mean of the episodes'; phone2act writes the dataset's, checked above; images keep
    lerobot's aggregate)."""
    from lerobot.datasets.compute_stats import aggregate_stats

    meta = pa_concat([pq.read_table(f) for f in sorted((root / "meta/episodes").glob("*/*.parquet"))])
    ep_col = np.asarray(rows.column("episode_index").to_pylist())
    per_episode = {}
    for i, e in enumerate(meta.column("episode_index").to_pylist()):
        st = {}
        for name in meta.column_names:
            if name.startswith("stats/"):
                feature, key = name[len("stats/"):].rsplit("/", 1)
                st.setdefault(feature, {})[key] = np.asarray(meta.column(name)[i].as_py(), dtype=np.float64)
        per_episode[e] = st
        mask = ep_col == e
        if not mask.any():
            if e < n_eps:
                fail(f"meta/episodes lists episode {e} but the data has no rows of it")
            continue  # killed between the episode-metadata and data renames: not committed yet
        for col in rows.column_names:
            data = np.asarray(rows.column(col).filter(pa_mask(mask)).to_pylist(), dtype=np.float64).reshape(int(mask.sum()), -1)
            got = st.get(col)
            if got is None:
                fail(f"meta/episodes: episode {e} has no stats for {col}")
            for k, ref in (("min", data.min(0)), ("max", data.max(0)), ("mean", data.mean(0)), ("std", data.std(0))):
                if not np.allclose(got[k].reshape(-1), ref, rtol=1e-4, atol=1e-4):
                    fail(f"meta/episodes: episode {e} {col}.{k} = {got[k][:4]} but its rows give {ref[:4]}")
            for k, q in QUANTILE_KEYS.items():
                if not np.allclose(got[k].reshape(-1), np.quantile(data, q, axis=0), rtol=1e-5, atol=1e-6):
                    fail(f"meta/episodes: episode {e} {col}.{k} is not numpy's over its rows")
    candidates = [[per_episode[e] for e in sorted(per_episode) if e < n_eps]]
    if one_ahead:
        candidates.append([per_episode[e] for e in sorted(per_episode)])
    problems = []
    for eps in candidates:
        agg = aggregate_stats(eps)
        why = None
        for feature, ref in agg.items():
            keys = ["min", "max", "mean", "std", "count"]
            if "image" in feature:
                keys += list(QUANTILE_KEYS)
            for k in keys:
                got = np.asarray(stats[feature][k], dtype=np.float64)
                if k == "std" and got.shape == np.asarray(ref[k]).shape:
                    # lerobot aggregates the variance as E[x^2] - mean^2 in float64: for a dimension that
                    # barely moves (std ~1e-8 around a mean ~1) that difference carries a cancellation error of
                    # a few 1e-16 * (mean^2 + std^2), a few percent of such a std. Compare variances within it.
                    mean = np.asarray(ref["mean"], dtype=np.float64)
                    var_atol = 1e-13 * (1.0 + mean**2)
                    if np.all(np.abs(got**2 - np.asarray(ref[k]) ** 2) <= var_atol + 1e-6 * np.asarray(ref[k]) ** 2):
                        continue
                if got.shape != np.asarray(ref[k]).shape or not np.allclose(got, ref[k], rtol=1e-6, atol=1e-9):
                    why = f"meta/stats.json {feature}.{k} = {got.reshape(-1)[:4]} but lerobot aggregates {np.asarray(ref[k]).reshape(-1)[:4]}"
                    break
            if why:
                break
        if why is None:
            return
        problems.append(why)
    fail(problems[0])


def pa_concat(tables):
    import pyarrow as pa

    return pa.concat_tables(tables)


def pa_mask(mask: np.ndarray):
    import pyarrow as pa

    return pa.array(mask)


def check_modality(root: Path, info: dict, decord_codecs: bool) -> dict:
    """meta/modality.json as Isaac-GR00T's loader reads it (N1.5 LeRobotSingleDataset, N1.7 LeRobotEpisodeLoader):
    state/action groups slice `original_key` (default observation.state / action) by [start, end) and tile it,
    videos name video features, annotations name columns. `decord_codecs`: N1.5 decodes with decord (h264/hevc)."""
    meta = root / "meta"
    modality = json.loads((meta / "modality.json").read_text())
    features = info["features"]
    for part, key in (("state", "observation.state"), ("action", "action")):
        groups = modality.get(part)
        if not groups:
            fail(f"modality.json has no {part} groups")
        dim = features[key]["shape"][0]
        covered = []
        for name, g in groups.items():
            okey = g.get("original_key", key)
            if okey not in features:
                fail(f"modality.json {part}.{name}: original_key {okey} is not a feature")
            if not (0 <= g["start"] < g["end"] <= dim):
                fail(f"modality.json {part}.{name}: [{g['start']}, {g['end']}) outside 0..{dim}")
            covered.extend(range(g["start"], g["end"]))
            if part == "action":
                # GR00T pads past an episode's end with the last value of an absolute group and zero for a
                # relative one: a group of deltas (names delta_*) must say "absolute": false, and any other
                # group must not (absent means true).
                names = features[okey].get("names") or []
                deltas = [n.startswith("delta_") for n in names[g["start"]:g["end"]]]
                absolute = g.get("absolute", True)
                if not isinstance(absolute, bool):
                    fail(f"modality.json action.{name}.absolute is {absolute!r}, not a bool")
                if deltas and all(deltas) and absolute:
                    fail(f"modality.json action.{name} holds deltas but is not marked \"absolute\": false")
                if deltas and not any(deltas) and not absolute:
                    fail(f"modality.json action.{name} holds absolute targets but is marked \"absolute\": false")
        if sorted(covered) != list(range(dim)):
            fail(f"modality.json {part} groups do not tile 0..{dim}: {sorted(covered)}")
    for name, v in modality.get("video", {}).items():
        okey = v.get("original_key", name)
        spec = features.get(okey)
        if spec is None or spec["dtype"] != "video":
            fail(f"modality.json video.{name}: {okey} is not a video feature")
        names = spec["names"]
        if not ("height" in names and "width" in names and "channels" in names and "video.fps" in spec["info"]):
            fail(f"{okey}: GR00T needs names height/width/channels and info.video.fps")
        if decord_codecs and spec["info"]["video.codec"] not in ("h264", "hevc"):
            fail(f"{okey}: codec {spec['info']['video.codec']} is not decodable by GR00T N1.5's decord")
    for name, a in modality.get("annotation", {}).items():
        col = a.get("original_key", f"annotation.{name}")
        if col not in features:
            fail(f"modality.json annotation.{name}: column {col} is not a feature")
    return modality


def check_gr00t(root: Path, info: dict, ep_len: dict, in_window: bool):
    """What Isaac-GR00T N1.5's LeRobotSingleDataset needs from a v2 layout."""
    meta = root / "meta"
    features = info["features"]
    check_modality(root, info, decord_codecs=True)
    # stats.json: every parquet column, each with exactly the keys GR00T validates, consistent with data.
    stats = json.loads((meta / "stats.json").read_text())
    tables = []
    episodes = [json.loads(l) for l in (meta / "episodes.jsonl").read_text().splitlines() if l.strip()]
    for ep in episodes:
        e = ep["episode_index"]
        p = root / info["data_path"].format(episode_chunk=e // info["chunks_size"], episode_index=e)
        t = pq.read_table(p)
        if t.num_rows != ep["length"]:
            fail(f"{p}: {t.num_rows} rows, episodes.jsonl says {ep['length']}")
        tables.append(t)
        for vk in [k for k, v in features.items() if v["dtype"] == "video"]:
            vp = root / info["video_path"].format(episode_chunk=e // info["chunks_size"], video_key=vk, episode_index=e)
            check_cfr(vp, info["fps"], ep["length"])
    # Inside the v2.1 commit window (see v21_commit_window) the save was killed after the data went in:
    # stats.json is then either the old aggregate or the new one, exactly.
    candidates = [tables, tables[:-1]] if in_window else [tables]
    columns = tables[0].column_names
    for col in columns:
        entry = stats.get(col)
        if entry is None:
            fail(f"stats.json lacks column {col} (GR00T would recompute and overwrite it)")
        for k in ("mean", "std", "min", "max", "q01", "q99"):
            if k not in entry:
                fail(f"stats.json {col} lacks {k}")
        mismatches = [m for m in (stats_mismatch(entry, col, ts) for ts in candidates) if m]
        if len(mismatches) == len(candidates):
            fail(mismatches[0])
        lo, q01, q99, hi = (np.asarray(entry[k]).reshape(-1) for k in ("min", "q01", "q99", "max"))
        if not (np.all(lo <= q01 + 1e-6) and np.all(q01 <= q99 + 1e-6) and np.all(q99 <= hi + 1e-6)):
            fail(f"stats.json {col}: quantiles not within min..max")


def main(dirs):
    passed = failed = 0
    for d in dirs:
        root = Path(d)
        try:
            info = json.loads((root / "meta/info.json").read_text())
            version = info["codebase_version"]
            if version == "v3.0":
                check_v30(root, info)
            elif version == "v2.1":
                check_v21(root, info)
            else:
                fail(f"unknown codebase_version {version}")
            print(f"PASS {root} ({version}, {info['total_episodes']} episodes, {info['total_frames']} frames)", flush=True)
            passed += 1
        except Exception as e:  # noqa: BLE001 - report every dataset, then fail overall
            print(f"FAIL {root}: {type(e).__name__}: {e}", flush=True)
            if os.environ.get("PHONE2ACT_CONFORMANCE_VERBOSE"):
                traceback.print_exc()
            failed += 1
    print(f"{passed} passed, {failed} failed")
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
