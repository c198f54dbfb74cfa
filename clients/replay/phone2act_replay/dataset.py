"""Reading one episode of a phone2act LeRobot dataset (v3.0 or v2.1) and turning its actions into targets.

In a phone2act dataset, `action` at frame i is the executed target relative to the measured pose in
`observation.state` at frame i (delta mode: position difference and roll/pitch/yaw differences), or the target
itself (absolute mode). So the absolute target of frame i is always recoverable from the row alone.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pyarrow.compute as pc
import pyarrow.parquet as pq
from phone2act.poses import quat_from_rpy, rpy_from_quat

DELTA_NAMES = ("delta_x", "delta_y", "delta_z", "delta_roll", "delta_pitch", "delta_yaw", "gripper")
ABSOLUTE_NAMES = ("x", "y", "z", "roll", "pitch", "yaw", "gripper")
EE_NAMES = ("ee_x", "ee_y", "ee_z", "ee_roll", "ee_pitch", "ee_yaw", "gripper")


@dataclass
class Episode:
    index: int
    fps: float
    task: str
    state_names: list[str]
    action_names: list[str]
    state: np.ndarray  # (N, S) float64
    action: np.ndarray  # (N, A) float64

    def __len__(self) -> int:
        return len(self.state)

    def arms(self) -> list[str]:
        """Arm prefixes in the dataset ("" for a single-arm dataset)."""
        prefixes = [n[: -len("ee_x")] for n in self.state_names if n.endswith("ee_x")]
        return [p.rstrip("_") for p in prefixes]

    def _cols(self, names: list[str], wanted: tuple[str, ...], arm: str) -> list[int] | None:
        prefix = f"{arm}_" if arm else ""
        try:
            return [names.index(prefix + w) for w in wanted]
        except ValueError:
            return None

    def ee_pose(self, arm: str = "") -> np.ndarray:
        """(N, 7): measured x y z roll pitch yaw gripper of `arm` from `observation.state`."""
        cols = self._cols(self.state_names, EE_NAMES, arm)
        if cols is None:
            raise KeyError(f"no end-effector columns for arm {arm!r} in {self.state_names}")
        return self.state[:, cols]

    def targets(self, arm: str = "") -> np.ndarray:
        """(N, 7): the absolute target x y z roll pitch yaw gripper executed at each frame."""
        ee = self.ee_pose(arm)
        delta = self._cols(self.action_names, DELTA_NAMES, arm)
        if delta is not None:
            a = self.action[:, delta]
            out = ee.copy()
            out[:, :6] += a[:, :6]  # rpy targets = measured rpy + recorded (wrapped) rpy delta
            out[:, 6] = a[:, 6]
            return out
        absolute = self._cols(self.action_names, ABSOLUTE_NAMES, arm)
        if absolute is None:
            raise KeyError(f"action names {self.action_names} are neither delta nor absolute end-effector actions")
        return self.action[:, absolute].copy()


def _feature_names(info: dict, key: str) -> list[str]:
    names = info["features"][key]["names"]
    if isinstance(names, dict):  # some writers nest names, e.g. {"motors": [...]}
        names = next(iter(names.values()))
    return list(names)


def load_episode(root: str | Path, episode_index: int) -> Episode:
    root = Path(root)
    info = json.loads((root / "meta" / "info.json").read_text())
    files = sorted((root / "data").glob("*/*.parquet"))
    if not files:
        raise FileNotFoundError(f"no data parquet files under {root / 'data'}")
    rows = []
    for f in files:
        t = pq.read_table(f, columns=["episode_index", "frame_index", "observation.state", "action", "task_index"])
        t = t.filter(pc.equal(t["episode_index"], episode_index))
        if t.num_rows:
            rows.append(t)
    if not rows:
        raise KeyError(f"episode {episode_index} is not in {root}")
    import pyarrow as pa

    table = pa.concat_tables(rows).sort_by("frame_index")
    state = np.array(table["observation.state"].to_pylist(), dtype=np.float64)
    action = np.array(table["action"].to_pylist(), dtype=np.float64)
    task = _task_text(root, int(table["task_index"][0].as_py()))
    return Episode(
        index=episode_index,
        fps=float(info["fps"]),
        task=task,
        state_names=_feature_names(info, "observation.state"),
        action_names=_feature_names(info, "action"),
        state=state,
        action=action,
    )


def _task_text(root: Path, task_index: int) -> str:
    tasks_parquet = root / "meta" / "tasks.parquet"
    if tasks_parquet.exists():
        t = pq.read_table(tasks_parquet)
        name = "task" if "task" in t.column_names else "__index_level_0__"
        for i, s in zip(t["task_index"].to_pylist(), t[name].to_pylist()):
            if i == task_index:
                return str(s)
    tasks_jsonl = root / "meta" / "tasks.jsonl"
    if tasks_jsonl.exists():
        for line in tasks_jsonl.read_text().splitlines():
            d = json.loads(line)
            if d.get("task_index") == task_index:
                return str(d["task"])
    return ""


def resample(targets: np.ndarray, factor: int) -> np.ndarray:
    """Targets at `factor` times the rate: linear in position and gripper, slerp in orientation.

    The recorded targets are samples of a continuous target signal; holding each for a whole frame would lag
    the original motion by half a frame on average.
    """
    if factor <= 1 or len(targets) < 2:
        return targets.copy()
    out = []
    quats = [quat_from_rpy(*row[3:6]) for row in targets]
    for i in range(len(targets) - 1):
        a, b = targets[i], targets[i + 1]
        qa, qb = np.array(quats[i]), np.array(quats[i + 1])
        if np.dot(qa, qb) < 0:
            qb = -qb
        for k in range(factor):
            t = k / factor
            row = a + t * (b - a)
            q = (1 - t) * qa + t * qb  # nlerp: steps of a few degrees, indistinguishable from slerp
            q /= np.linalg.norm(q)
            row[3:6] = rpy_from_quat(tuple(q))
            out.append(row)
    out.append(targets[-1].copy())
    return np.array(out)


def pose_errors(ref: np.ndarray, new: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per-row position error (m) and orientation error (rad) between two (N, >=6) xyz-rpy arrays."""
    pos = np.linalg.norm(ref[:, :3] - new[:, :3], axis=1)
    ang = np.array([
        _angle(quat_from_rpy(*r[3:6]), quat_from_rpy(*n[3:6])) for r, n in zip(ref, new)
    ])
    return pos, ang


def _angle(a: tuple[float, ...], b: tuple[float, ...]) -> float:
    dot = abs(sum(x * y for x, y in zip(a, b)))
    return 2.0 * math.acos(min(1.0, dot))


def align(ref: np.ndarray, new: np.ndarray, resolution: float = 0.05, lead: int = 5) -> tuple[float, np.ndarray]:
    """Best time offset (in frames, fractional) of `ref` inside `new`, and `new` resampled there.

    Both are trajectories at the same fps; the replay starts at an arbitrary moment of the second recording
    (its chunk may even start a fraction of a frame before that recording's first tick), so the start is found
    by least squares on position, and `new` is extended backwards by `lead` frames of its first pose (the arm
    was holding there, settled, before the replay began). The offset may therefore be negative.
    """
    n = len(ref)
    new = np.vstack([np.repeat(new[:1], lead, axis=0), new])
    if len(new) < n:
        raise ValueError(f"replayed trajectory has {len(new) - lead} frames, fewer than the {n} recorded")
    t_new = np.arange(len(new))
    new[:, 3:6] = np.unwrap(new[:, 3:6], axis=0)  # interpolate angles across the ±pi seam correctly

    def sample(offset: float) -> np.ndarray:
        t = np.arange(n) + offset
        return np.stack([np.interp(t, t_new, new[:, c]) for c in range(new.shape[1])], axis=1)

    # Coarse on whole frames, then refine around the best one.
    coarse = min(range(len(new) - n + 1), key=lambda o: float(np.sum((new[o:o + n, :3] - ref[:, :3]) ** 2)))
    lo, hi = max(0.0, coarse - 1.0), min(float(len(new) - n), coarse + 1.0)
    candidates = np.arange(lo, hi + 1e-9, resolution)
    best = min(candidates, key=lambda o: float(np.sum((sample(o)[:, :3] - ref[:, :3]) ** 2)))
    return float(best) - lead, sample(float(best))


def path_errors(ref: np.ndarray, new: np.ndarray, density: int = 20) -> tuple[np.ndarray, np.ndarray]:
    """For each row of `ref`, the distance (m) to the nearest point of `new`'s path (densely interpolated) and
    the orientation error (rad) there. Independent of when each frame was sampled: a loaded machine can wake
    the recorder's tick late, which shifts samples along the path without the motion itself changing."""
    n = len(new)
    t = np.linspace(0, n - 1, (n - 1) * density + 1)
    unwrapped = new.copy()
    unwrapped[:, 3:6] = np.unwrap(unwrapped[:, 3:6], axis=0)
    dense = np.stack([np.interp(t, np.arange(n), unwrapped[:, c]) for c in range(6)], axis=1)
    d = np.linalg.norm(ref[:, None, :3] - dense[None, :, :3], axis=2)
    nearest = d.argmin(axis=1)
    pos = d[np.arange(len(ref)), nearest]
    ang = np.array([_angle(quat_from_rpy(*r[3:6]), quat_from_rpy(*dense[k, 3:6])) for r, k in zip(ref, nearest)])
    return pos, ang
