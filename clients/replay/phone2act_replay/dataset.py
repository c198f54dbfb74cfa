"""Reading one episode of a phone2act LeRobot dataset (v3.0 or v2.1) and its end-effector poses and targets.

The action definition (phone2act-core `layout.rs`, the proto's `ActionMode`): `action` at frame i is the absolute
end-effector target commanded at that frame, `x y z` (m, robot base frame), `r00 r10 r20 r01 r11 r21` (the first
two columns of the target's rotation matrix, "6D rotation") and the gripper target; `observation.state` ends with
the measured pose in the same layout (`ee_x` ... `ee_r21`, `gripper`). Rows here are those 10 values. The 6D form has
no seam, so rows can be interpolated column by column and projected back onto a rotation (Gram-Schmidt).
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pyarrow.compute as pc
import pyarrow.parquet as pq

ACTION_NAMES = ("x", "y", "z", "r00", "r10", "r20", "r01", "r11", "r21", "gripper")
EE_NAMES = ("ee_x", "ee_y", "ee_z", "ee_r00", "ee_r10", "ee_r20", "ee_r01", "ee_r11", "ee_r21", "gripper")


def rotation_from_6d(v: np.ndarray) -> np.ndarray:
    """The rotation matrix nearest a 6D value (its first column's direction kept), as the server reads it."""
    a, b = np.asarray(v[:3], dtype=np.float64), np.asarray(v[3:6], dtype=np.float64)
    x = a / np.linalg.norm(a)
    b = b - x * (x @ b)
    y = b / np.linalg.norm(b)
    return np.stack([x, y, np.cross(x, y)], axis=1)


def rot6d(m: np.ndarray) -> np.ndarray:
    """The 6D form of a rotation matrix: its first two columns."""
    return np.concatenate([m[:, 0], m[:, 1]])


def rotation_angle(a: np.ndarray, b: np.ndarray) -> float:
    """Angle (rad) between two rotations given in 6D form."""
    r = rotation_from_6d(a).T @ rotation_from_6d(b)
    return float(math.acos(max(-1.0, min(1.0, (np.trace(r) - 1.0) / 2.0))))


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
        """(N, 10): measured x y z, 6D rotation and gripper of `arm` from `observation.state`."""
        cols = self._cols(self.state_names, EE_NAMES, arm)
        if cols is None:
            raise KeyError(f"no end-effector columns for arm {arm!r} in {self.state_names}")
        return self.state[:, cols]

    def targets(self, arm: str = "") -> np.ndarray:
        """(N, 10): the absolute target (x y z, 6D rotation, gripper) commanded at each frame: the action."""
        cols = self._cols(self.action_names, ACTION_NAMES, arm)
        if cols is None:
            raise KeyError(f"action names {self.action_names} are not phone2act end-effector targets")
        return self.action[:, cols].copy()


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


def _project(rows: np.ndarray) -> np.ndarray:
    """Rows whose 6D part is made a rotation again (after linear interpolation)."""
    out = rows.copy()
    for row in out:
        row[3:9] = rot6d(rotation_from_6d(row[3:9]))
    return out


def _interp(rows: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Rows at fractional frame times `t`: linear per column, then projected onto rotations. Between frames a
    few degrees apart this is the geodesic to within a hair (the 6D form is continuous, with no seam)."""
    idx = np.arange(len(rows))
    return _project(np.stack([np.interp(t, idx, rows[:, c]) for c in range(rows.shape[1])], axis=1))


def resample(targets: np.ndarray, factor: int) -> np.ndarray:
    """Targets at `factor` times the rate. The recorded targets are samples of a continuous target signal;
    holding each for a whole frame would lag the original motion by half a frame on average."""
    if factor <= 1 or len(targets) < 2:
        return targets.copy()
    return _interp(targets, np.arange((len(targets) - 1) * factor + 1) / factor)


def pose_errors(ref: np.ndarray, new: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per-row position error (m) and orientation error (rad) between two (N, >=9) pose arrays."""
    pos = np.linalg.norm(ref[:, :3] - new[:, :3], axis=1)
    ang = np.array([rotation_angle(r[3:9], n[3:9]) for r, n in zip(ref, new)])
    return pos, ang


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

    def positions(offset: float) -> np.ndarray:
        t = np.arange(n) + offset
        return np.stack([np.interp(t, np.arange(len(new)), new[:, c]) for c in range(3)], axis=1)

    # Coarse on whole frames, then refine around the best one.
    coarse = min(range(len(new) - n + 1), key=lambda o: float(np.sum((new[o:o + n, :3] - ref[:, :3]) ** 2)))
    lo, hi = max(0.0, coarse - 1.0), min(float(len(new) - n), coarse + 1.0)
    candidates = np.arange(lo, hi + 1e-9, resolution)
    best = float(min(candidates, key=lambda o: float(np.sum((positions(o) - ref[:, :3]) ** 2))))
    return best - lead, _interp(new, np.arange(n) + best)


def path_errors(ref: np.ndarray, new: np.ndarray, density: int = 20) -> tuple[np.ndarray, np.ndarray]:
    """For each row of `ref`, the distance (m) to the nearest point of `new`'s path (densely interpolated) and
    the orientation error (rad) there. Independent of when each frame was sampled: a loaded machine can wake
    the recorder's tick late, which shifts samples along the path without the motion itself changing."""
    n = len(new)
    dense = _interp(new, np.linspace(0, n - 1, (n - 1) * density + 1))
    d = np.linalg.norm(ref[:, None, :3] - dense[None, :, :3], axis=2)
    nearest = d.argmin(axis=1)
    pos = d[np.arange(len(ref)), nearest]
    ang = np.array([rotation_angle(r[3:9], dense[k, 3:9]) for r, k in zip(ref, nearest)])
    return pos, ang


def target_path_errors(ref: np.ndarray, new: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """How far the targets a replay executed (`new`, its recorded action column) lie from the original's target
    path (`ref`, densified as the replay resampled it). The replay's leading rows, which repeat its first
    (the pose it was brought to before its chunk started), are left out."""
    moved = np.flatnonzero(np.any(np.abs(new - new[0]) > 1e-6, axis=1))
    start = int(moved[0]) if len(moved) else 0
    return path_errors(new[start:], ref)
