"""How phone2act observations and actions map onto a GR00T data config's modality keys.

A GR00T model fine-tuned on a phone2act dataset (v2.1 + `meta/modality.json`) uses the groups the recorder
writes: state `arm` (joints + end-effector pose) and `gripper`, action `arm` (6-DoF end-effector delta) and
`gripper`, video `<camera>`. `Embodiment.phone2act()` builds exactly that mapping from the server's layout.
Other data configs (e.g. GR00T's `so100`) are described by listing, per GR00T key, which phone2act names its
columns are.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from phone2act import ArmLayout
from phone2act.v1 import common_pb2, policy_pb2

LANGUAGE_KEY = "annotation.human.task_description"


class ChunkShapeError(ValueError):
    """The policy's answer does not fit the arm's action layout."""


class ObservationError(ValueError):
    """The phone2act observation lacks something the GR00T data config needs."""


@dataclass(frozen=True)
class ActionGroup:
    """One `action.<name>` array of the GR00T answer: its columns are these phone2act action names."""

    key: str
    columns: tuple[str, ...]
    # Multiplies the model's output (e.g. a model trained in millimetres on a metre API).
    scale: float = 1.0


@dataclass(frozen=True)
class Embodiment:
    # GR00T key -> phone2act state names, in the order of the array's last axis.
    state: Mapping[str, tuple[str, ...]]
    # GR00T key -> phone2act camera name.
    video: Mapping[str, str]
    actions: tuple[ActionGroup, ...]
    language_key: str = LANGUAGE_KEY
    # Value for action names no group provides (0 = no delta on that axis).
    defaults: Mapping[str, float] = field(default_factory=dict)

    @staticmethod
    def phone2act(layout: ArmLayout, cameras: Sequence[str] = ()) -> Embodiment:
        """The mapping of a dataset recorded by phone2act (groups `arm` and `gripper`, as in modality.json)."""
        return Embodiment(
            state={"state.arm": layout.state_names[:-1], "state.gripper": layout.state_names[-1:]},
            video={f"video.{c}": c for c in cameras},
            actions=(
                ActionGroup("action.arm", layout.action_names[:-1]),
                ActionGroup("action.gripper", layout.action_names[-1:]),
            ),
        )

    @staticmethod
    def so100(layout: ArmLayout, camera: str, action_scale: float = 1.0) -> Embodiment:
        """GR00T's `so100` data config keys (`state.single_arm` 5 joints, `state.gripper`, `video.webcam`).

        That config's `action.single_arm` is 5 joint targets, which the phone2act API does not take; here its
        5 columns drive the first five end-effector delta axes, scaled by `action_scale`. It exists to run the
        protocol against so100-shaped servers (and the golden messages); real use is `phone2act()`.
        """
        joints = tuple(n for n in layout.state_names if not n.startswith("ee_") and n != "gripper")
        if len(joints) != 5:
            raise ObservationError(f"so100 wants 5 joints; arm {layout.arm!r} has {list(joints)}")
        return Embodiment(
            state={"state.single_arm": joints, "state.gripper": ("gripper",)},
            video={"video.webcam": camera},
            actions=(
                ActionGroup("action.single_arm", layout.action_names[:5], action_scale),
                ActionGroup("action.gripper", layout.action_names[-1:]),
            ),
        )

    # --- observation -> GR00T request ------------------------------------------------------------------

    def request_data(self, obs: policy_pb2.Observation, arm: str) -> dict[str, Any]:
        """The `get_action` data map for one (unbatched) observation: video, state, then language."""
        arm_obs = next((a for a in obs.arms if a.arm == arm), None)
        if arm_obs is None:
            raise ObservationError(f"observation {obs.observation_id} has no arm {arm!r}")
        data: dict[str, Any] = {}
        frames = {f.camera: f for f in obs.frames}
        for key, camera in self.video.items():
            frame = frames.get(camera)
            if frame is None:
                raise ObservationError(f"{key} needs camera {camera!r}; observation has {sorted(frames)}")
            data[key] = frame_rgb(frame)[None]  # (T=1, H, W, 3)
        index = {n: i for i, n in enumerate(arm_obs.state_names)}
        for key, names in self.state.items():
            missing = [n for n in names if n not in index]
            if missing:
                raise ObservationError(f"{key} needs state {missing}; arm {arm!r} has {list(arm_obs.state_names)}")
            data[key] = np.array([[arm_obs.state[index[n]] for n in names]], dtype=np.float64)  # (T=1, D)
        data[self.language_key] = [obs.task]
        return data

    # --- GR00T answer -> phone2act chunk ---------------------------------------------------------------

    def chunk_steps(self, answer: Mapping[str, Any], layout: ArmLayout, max_steps: int | None = None) -> np.ndarray:
        """(horizon, action_width) action rows in the arm's layout, or ChunkShapeError saying what is off."""
        width = layout.action_width
        column_of = {n: i for i, n in enumerate(layout.action_names)}
        horizon: int | None = None
        parts: list[tuple[ActionGroup, np.ndarray]] = []
        for group in self.actions:
            if group.key not in answer:
                have = sorted(k for k in answer if isinstance(k, str))
                raise ChunkShapeError(f"GR00T answer has no {group.key!r} (it has {have})")
            a = np.asarray(answer[group.key])
            n = len(group.columns)
            if a.ndim == 3 and a.shape[0] == 1:  # a batched answer to an unbatched request
                a = a[0]
            if a.ndim == 1 and n == 1:  # older N1.5 squeezed single-column groups to (horizon,)
                a = a[:, None]
            if a.ndim != 2 or a.shape[1] != n or a.shape[0] == 0:
                raise ChunkShapeError(
                    f"{group.key} has shape {a.shape}; expected (horizon, {n}) for {list(group.columns)}"
                )
            if not np.issubdtype(a.dtype, np.number) or not np.all(np.isfinite(a)):
                raise ChunkShapeError(f"{group.key} holds non-finite or non-numeric values (dtype {a.dtype})")
            if horizon is not None and a.shape[0] != horizon:
                raise ChunkShapeError(f"{group.key} has horizon {a.shape[0]}, other groups {horizon}")
            horizon = a.shape[0]
            for c in group.columns:
                if c not in column_of:
                    raise ChunkShapeError(f"{group.key} maps to {c!r}, not an action of arm {layout.arm!r}")
            parts.append((group, a.astype(np.float64) * group.scale))
        assert horizon is not None
        steps = np.zeros((horizon, width))
        for name, value in self.defaults.items():
            steps[:, column_of[name]] = value
        for group, a in parts:
            for j, c in enumerate(group.columns):
                steps[:, column_of[c]] = a[:, j]
        return steps[:max_steps] if max_steps else steps


def frame_rgb(frame: common_pb2.CameraFrame) -> np.ndarray:
    """(H, W, 3) uint8 pixels of an RGB8 frame."""
    if frame.encoding != common_pb2.IMAGE_ENCODING_RGB8:
        name = common_pb2.ImageEncoding.Name(frame.encoding)
        raise ObservationError(f"camera {frame.camera!r} frame is {name}; the adapter asks for RGB8")
    expected = frame.width * frame.height * 3
    if len(frame.data) != expected:
        raise ObservationError(f"camera {frame.camera!r}: {len(frame.data)} bytes, expected {expected}")
    return np.frombuffer(frame.data, dtype=np.uint8).reshape(frame.height, frame.width, 3)
