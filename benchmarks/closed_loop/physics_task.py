"""The physics task of the closed-loop benchmark (`closed_loop.py --sim physics`): the MuJoCo SO-101 of
`mujoco_bridge.py` attached as a remote arm, its scripted demonstrations, the held-out seeds and the two
baselines that run beside the trained policy (a blind policy, and the nearest demonstration replayed).
"""

from __future__ import annotations

import json
import math
import shutil
import subprocess
import sys
import threading
import time
from pathlib import Path

from mujoco_bridge import AREA_M, GRASP_TOLERANCE_M, draw_layout

HERE = Path(__file__).resolve().parent
ARM_JOINTS = ["shoulder_pan", "shoulder_lift", "elbow_flex", "wrist_flex", "wrist_roll"]
TASK = "put the red block in the basket"


# The server's arm and camera for `closed_loop.server_config`: a remote arm with the SO-101's joints (so the
# server solves joint actions with the kinematics the MuJoCo model has) and a pushed camera.
SERVER = {
    "bridge": f'"remote"\n[arms.remote]\njoint_names = {json.dumps(ARM_JOINTS)}',
    "camera_kind": "remote",
    "robot_type": "so101_mujoco",
}


class BridgeProcess:
    """`mujoco_bridge.py` in its own process (as a user's bridge would run), attached to the server."""

    def __init__(self, target: str, token: str, arm: str, camera: str, image_px: int, fps: int, log_path: Path,
                 extra: list[str] | None = None) -> None:
        cmd = [sys.executable, str(HERE / "mujoco_bridge.py"), "--server", target, "--token", token, "--arm", arm,
               "--camera", camera, "--image-px", str(image_px), "--camera-fps", str(fps), *(extra or [])]
        self.log_path = log_path
        self.log = log_path.open("a")
        self.log.write(f"--- {' '.join(cmd)}\n")
        self.log.flush()
        self.proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=self.log, text=True, cwd=HERE)
        self.lines: list[str] = []
        attached = threading.Event()

        def pump() -> None:
            assert self.proc.stdout is not None
            for line in self.proc.stdout:
                self.lines.append(line)
                self.log.write(line)
                self.log.flush()
                if '"attached"' in line:
                    attached.set()
            attached.set()

        threading.Thread(target=pump, daemon=True).start()
        # Starting Python with MuJoCo and building the model: a few seconds, far more on a loaded machine.
        attached.wait(timeout=120)
        if self.proc.poll() is not None or not any('"attached"' in x for x in self.lines):
            self.stop()
            raise RuntimeError(f"the MuJoCo bridge did not attach; see {log_path}")

    def wait(self) -> int:
        return self.proc.wait()

    def stop(self) -> None:
        if self.proc.poll() is None:
            self.proc.terminate()
            try:
                self.proc.wait(timeout=10)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()
        self.log.close()


def record_demos(args, server, token: str, arm: str, camera: str, out: Path) -> dict:
    """`--demos` scripted demonstrations from seeds `--seed`...; failed attempts are discarded and counted."""
    bridge = BridgeProcess(server.target, token, arm, camera, args.image_px, args.fps, out / "bridge-demos.log",
                           ["--demos", str(args.demos), "--seed", str(args.seed), "--task", TASK,
                            "--fps", str(args.fps), "--episode-time-s", str(args.episode_time_s)])
    rc = bridge.wait()
    bridge.stop()
    summary = {}
    for line in reversed(bridge.lines):
        try:
            summary = json.loads(line)
            if "saved" in summary:
                break
        except json.JSONDecodeError:
            continue
    if rc != 0 or "saved" not in summary:
        raise RuntimeError(f"scripted demonstrations failed (exit {rc}); see {out / 'bridge-demos.log'}")
    return summary


def nearest_start_m(seed: int, train_seeds: list[int]) -> tuple[float, int]:
    """Distance from `seed`'s block start to the nearest training start, and that training seed."""
    xy = draw_layout(seed).block_xy
    return min((math.dist(xy, draw_layout(s).block_xy), s) for s in train_seeds)


def held_out_seeds(first: int, count: int, train_seeds: list[int]) -> tuple[list[int], int]:
    """`count` evaluation seeds from `first` on whose block starts farther than the grasp tolerance from every
    training start (a policy that replays a memorised start misses them); also how many candidates were
    passed over for lying nearer."""
    seeds, skipped, seed = [], 0, first
    while len(seeds) < count:
        if nearest_start_m(seed, train_seeds)[0] > GRASP_TOLERANCE_M:
            seeds.append(seed)
        else:
            skipped += 1
        seed += 1
    return seeds, skipped


def distance_summary(seeds: list[int], train_seeds: list[int]) -> dict:
    d = sorted(nearest_start_m(s, train_seeds)[0] for s in seeds)

    def q(f: float) -> float:
        return round(d[min(len(d) - 1, int(f * len(d)))] * 100, 2)

    return {"nearest_training_start_cm": {"min": round(d[0] * 100, 2), "p10": q(0.1), "median": q(0.5),
                                          "p90": q(0.9), "max": round(d[-1] * 100, 2)},
            "grasp_tolerance_cm": GRASP_TOLERANCE_M * 100,
            "share_beyond_tolerance": round(sum(x > GRASP_TOLERANCE_M for x in d) / len(d), 3),
            "workspace_m": AREA_M}


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


def demo_actions(dataset_root: Path) -> dict[int, list[list[float]]]:
    """Each episode's recorded actions (the dataset's layout: joints in degrees, gripper 0..100)."""
    import pyarrow.parquet as pq

    episodes: dict[int, list[list[float]]] = {}
    for f in sorted((dataset_root / "data").rglob("*.parquet")):
        t = pq.read_table(f, columns=["episode_index", "frame_index", "action"]).to_pylist()
        for row in sorted(t, key=lambda r: (r["episode_index"], r["frame_index"])):
            episodes.setdefault(int(row["episode_index"]), []).append([float(v) for v in row["action"]])
    return episodes


def evaluate_replay(args, server, token: str, arm: str, dataset_root: Path, train_seeds: list[int],
                    seeds: list[int], result):
    """Nearest-demonstration replay: for each trial, the recorded actions of the demonstration whose block
    started nearest, played open loop through the Policy API (joint chunks)."""
    from phone2act import Client
    from phone2act.v1 import policy_pb2
    from scripted_demo import drive_plan, reset_scene
    from tqdm import tqdm

    actions = demo_actions(dataset_root)
    start = time.monotonic()
    with Client(server.target, token=token) as c:
        for seed in tqdm(seeds, desc="eval: nearest-demo replay", unit="trial"):
            distance, nearest = nearest_start_m(seed, train_seeds)
            steps = actions[train_seeds.index(nearest)]
            reset_scene(c, arm, seed)
            t0 = time.monotonic()
            ok = drive_plan(c, arm, steps, args.fps, args.episode_time_s, mode=policy_pb2.ACTION_MODE_JOINT)
            result.trials += 1
            result.successes += int(ok)
            result.per_trial.append({"seed": seed, "success": ok, "seconds": time.monotonic() - t0,
                                     "replayed_seed": nearest, "start_distance_cm": round(distance * 100, 2)})
    result.seconds = time.monotonic() - start
    return result


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
