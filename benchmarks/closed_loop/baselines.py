"""What the two tasks of the closed-loop benchmark share beside the trained policy: the held-out seeds (drawn so
that most lie farther than the grasp tolerance from every training start) and their distance summary, the
dataset copies the blind baseline and the timing ablation train on, and the nearest-demonstration replay.

A task describes its starts with a `start_of(seed) -> (x, y)` function: the physics task computes it from the
seed (`mujoco_bridge.draw_layout`), the kinematic one asks the server (`Scene.Reset`, see `SceneStarts`).
"""

from __future__ import annotations

import math
import shutil
import subprocess
import time
from collections.abc import Callable
from pathlib import Path

StartOf = Callable[[int], tuple[float, float]]


def nearest_start_m(seed: int, train_seeds: list[int], start_of: StartOf) -> tuple[float, int]:
    """Distance from `seed`'s object start to the nearest training start, and that training seed."""
    xy = start_of(seed)
    return min((math.dist(xy, start_of(s)), s) for s in train_seeds)


def held_out_seeds(first: int, count: int, train_seeds: list[int], start_of: StartOf,
                   tolerance_m: float) -> tuple[list[int], int]:
    """`count` evaluation seeds from `first` on whose object starts farther than `tolerance_m` (the grasp
    tolerance) from every training start (a policy that replays a memorised start misses them); also how many
    candidates were passed over for lying nearer."""
    seeds, skipped, seed = [], 0, first
    while len(seeds) < count:
        if skipped > 1000 * count:
            raise SystemExit(f"held-out seeds: {skipped} candidates from {first} lie within {tolerance_m * 100} cm "
                             f"of a training start and only {len(seeds)} beyond; too few gaps between the "
                             f"{len(train_seeds)} training starts")
        if nearest_start_m(seed, train_seeds, start_of)[0] > tolerance_m:
            seeds.append(seed)
        else:
            skipped += 1
        seed += 1
    return seeds, skipped


def distance_summary(seeds: list[int], train_seeds: list[int], start_of: StartOf, tolerance_m: float,
                     workspace_m: dict) -> dict:
    d = sorted(nearest_start_m(s, train_seeds, start_of)[0] for s in seeds)

    def q(f: float) -> float:
        return round(d[min(len(d) - 1, int(f * len(d)))] * 100, 2)

    return {"nearest_training_start_cm": {"min": round(d[0] * 100, 2), "p10": q(0.1), "median": q(0.5),
                                          "p90": q(0.9), "max": round(d[-1] * 100, 2)},
            "grasp_tolerance_cm": tolerance_m * 100,
            "share_beyond_tolerance": round(sum(x > tolerance_m for x in d) / len(d), 3),
            "workspace_m": workspace_m}


class SceneStarts:
    """The object's start of each seed as the server's scene draws it: `Scene.Reset(seed, home_arm)` once per
    seed (cached), read from the state it returns. Only while nobody drives the arm (the reset homes it)."""

    def __init__(self, client, arm: str) -> None:
        self.client, self.arm = client, arm
        self.cache: dict[int, tuple[float, float]] = {}

    def __call__(self, seed: int) -> tuple[float, float]:
        if seed not in self.cache:
            p = self.client.scene.reset(self.arm, seed=seed, home_arm=True).ball_position_m
            self.cache[seed] = (p.x, p.y)
        return self.cache[seed]


def blank_dataset(src: Path, dst: Path) -> Path:
    """A copy of the dataset whose camera frames are all black (same frames, timestamps and actions): what the
    blind baseline trains on."""
    if dst.exists():
        shutil.rmtree(dst)
    shutil.copytree(src, dst)
    for video in sorted((dst / "videos").rglob("*.mp4")):
        tmp = video.with_suffix(".black.mp4")
        subprocess.run(["ffmpeg", "-v", "error", "-y", "-i", str(video), "-vf", "drawbox=color=black:t=fill",
                        "-c:v", "libx264", "-pix_fmt", "yuv420p", "-g", "2", str(tmp)], check=True)
        tmp.replace(video)
    return dst


def shifted_dataset(src: Path, dst: Path, frames: int) -> Path:
    """A copy of the dataset whose actions lag the observations by `frames` (a recorder timing bug: the action
    recorded at frame t is the one commanded at t - frames; an episode's first frames repeat its first action).
    What the data-quality ablation trains on."""
    import pyarrow as pa
    import pyarrow.parquet as pq

    if dst.exists():
        shutil.rmtree(dst)
    shutil.copytree(src, dst)
    for f in sorted((dst / "data").rglob("*.parquet")):
        table = pq.read_table(f)
        episodes = table.column("episode_index").to_pylist()
        actions = table.column("action").to_pylist()
        # Rows are in frame order within each episode (the recorder appends them so).
        shifted, first_row = [], {}
        for i, ep in enumerate(episodes):
            first_row.setdefault(ep, i)
            shifted.append(actions[max(first_row[ep], i - frames)])
        column = pa.array(shifted, type=table.schema.field("action").type)
        table = table.set_column(table.schema.get_field_index("action"), "action", column)
        pq.write_table(table, f)
    return dst


def demo_actions(dataset_root: Path) -> dict[int, list[list[float]]]:
    """Each episode's recorded actions (the dataset's layout: joints in degrees, gripper 0..100)."""
    import pyarrow.parquet as pq

    episodes: dict[int, list[list[float]]] = {}
    for f in sorted((dataset_root / "data").rglob("*.parquet")):
        t = pq.read_table(f, columns=["episode_index", "frame_index", "action"]).to_pylist()
        for row in sorted(t, key=lambda r: (r["episode_index"], r["frame_index"])):
            episodes.setdefault(int(row["episode_index"]), []).append([float(v) for v in row["action"]])
    return episodes


def drive_plan(client, arm: str, steps: list[list[float]], fps: int, episode_time_s: float,
               chunk: int = 20, mode: int | None = None) -> bool:
    """Plays `steps` (in `mode`'s layout, default absolute end-effector) open loop through a policy session,
    a chunk at a time; True once the scene reports success."""
    from phone2act import ABSOLUTE_EE, InvalidArgument

    mode = ABSOLUTE_EE if mode is None else mode
    period = 1.0 / fps
    with client.policy_session([arm], observation_rate_hz=fps, policy_name="scripted-demo",
                               silence_timeout_s=10.0) as s:
        t0 = time.monotonic()
        while time.monotonic() - t0 < episode_time_s:
            s.next_observation(timeout_s=10.0)  # paces the loop on the server's observations
            k = min(len(steps) - 1, int((time.monotonic() - t0) / period))
            # Past the plan's end the last step is held (padded, so the chunk never lies wholly in the past).
            window = (steps[k:k + chunk] + [steps[-1]] * chunk)[:chunk]
            try:
                # Anchored at its arrival (observation 0): the plan runs on this process's clock, and an
                # observation that waited in the session's queue would shift it.
                s.push(arm, window, period, observation_id=0, mode=mode)
            except InvalidArgument:  # answered an observation too late (a loaded machine): take a newer one
                continue
            if client.scene.get(arm).success:
                return True
            if k >= len(steps) - 1 and time.monotonic() - t0 > len(steps) * period + 2.0:
                break
            time.sleep(chunk * period / 4)
    return bool(client.scene.get(arm).success)


def evaluate_replay(args, server, token: str, arm: str, dataset_root: Path, train_seeds: list[int],
                    seeds: list[int], result, start_of: StartOf):
    """Nearest-demonstration replay: for each trial, the recorded actions of the demonstration whose object
    started nearest, played open loop through the Policy API (joint chunks). `train_seeds` in episode order."""
    from closed_loop import reset_scene
    from phone2act import Client
    from phone2act.v1 import policy_pb2
    from tqdm import tqdm

    actions = demo_actions(dataset_root)
    start = time.monotonic()
    with Client(server.target, token=token) as c:
        for seed in tqdm(seeds, desc="eval: nearest-demo replay", unit="trial"):
            distance, nearest = nearest_start_m(seed, train_seeds, start_of)
            steps = actions[train_seeds.index(nearest)]
            reset_scene(c, seed, arm)
            t0 = time.monotonic()
            ok = drive_plan(c, arm, steps, args.fps, args.episode_time_s, mode=policy_pb2.ACTION_MODE_JOINT)
            result.trials += 1
            result.successes += int(ok)
            result.per_trial.append({"seed": seed, "success": ok, "seconds": time.monotonic() - t0,
                                     "replayed_seed": nearest, "start_distance_cm": round(distance * 100, 2)})
    result.seconds = time.monotonic() - start
    return result
