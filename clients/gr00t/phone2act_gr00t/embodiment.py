"""How phone2act observations and actions map onto a GR00T model's modality keys, in either wire dialect.

A GR00T model fine-tuned on a phone2act dataset (v2.1 + `meta/modality.json`) uses the groups the recorder
writes: per arm, state `arm` (joints + end-effector pose) and `gripper`, action `arm` (the arm's action axes in
its configured representation) and `gripper`, video `<camera>`. With several arms the groups carry the arm's
name (`left_arm`, `left_gripper`, `right_arm`, ...), exactly as the recorder names them.
`Embodiment.phone2act()` builds that mapping from the session's layouts. Other data configs (e.g. GR00T's
`so100`) list, per GR00T group, which arm and which phone2act names its columns are.

Group keys are stored bare (`arm`, `single_arm`, `webcam`); N1.5 prefixes them with their modality
(`state.arm`), N1.6 nests them under it (`{"state": {"arm": ...}}`).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from phone2act import ArmLayout
from phone2act.v1 import common_pb2, policy_pb2

from phone2act_gr00t.modes import ABSOLUTE, DELTA, RECORDED_ABSOLUTE_AXES, is_gripper, kind_of_mode
from phone2act_gr00t.wire import N15, N16, N16_SIM, ModalityConfig, shapes_of

LANGUAGE_KEY = "annotation.human.task_description"


class ChunkShapeError(ValueError):
    """The policy's answer does not fit the arm's action layout."""


class NonFiniteActionError(ChunkShapeError):
    """The policy answered NaN or infinity: a bad answer, not a model that cannot fit the arm."""


class ObservationError(ValueError):
    """The phone2act observation lacks something the GR00T data config needs."""


class EmbodimentMismatch(ValueError):
    """The GR00T server's modality config wants other keys than this embodiment provides."""


@dataclass(frozen=True)
class Group:
    """One GR00T state or action group: its columns are these phone2act names of one arm."""

    key: str
    arm: str
    columns: tuple[str, ...]
    # Multiplies the model's output (e.g. a model trained in millimetres on a metre API).
    scale: float = 1.0


# The name older code used for action groups.
ActionGroup = Group


@dataclass(frozen=True)
class Embodiment:
    state: tuple[Group, ...]
    # GR00T video key (bare) -> phone2act camera name.
    video: Mapping[str, str]
    actions: tuple[Group, ...]
    language_key: str = LANGUAGE_KEY

    @property
    def arms(self) -> tuple[str, ...]:
        seen: dict[str, None] = {}
        for g in (*self.state, *self.actions):
            seen.setdefault(g.arm, None)
        return tuple(seen)

    @staticmethod
    def phone2act(layouts: Mapping[str, ArmLayout] | Sequence[ArmLayout] | ArmLayout,
                  cameras: Sequence[str] = ()) -> Embodiment:
        """The groups of a dataset recorded by phone2act (as its modality.json names them).

        One arm: `arm`, `gripper`. Several arms: `<arm>_arm`, `<arm>_gripper` per arm, in the order given.
        """
        if isinstance(layouts, ArmLayout):
            layouts = [layouts]
        elif isinstance(layouts, Mapping):
            layouts = list(layouts.values())
        several = len(layouts) > 1
        state: list[Group] = []
        actions: list[Group] = []
        for layout in layouts:
            prefix = f"{layout.arm}_" if several else ""
            state += [Group(f"{prefix}arm", layout.arm, layout.state_names[:-1]),
                      Group(f"{prefix}gripper", layout.arm, layout.state_names[-1:])]
            actions += [Group(f"{prefix}arm", layout.arm, layout.action_names[:-1]),
                        Group(f"{prefix}gripper", layout.arm, layout.action_names[-1:])]
        return Embodiment(tuple(state), {c: c for c in cameras}, tuple(actions))

    @staticmethod
    def so100(layout: ArmLayout, camera: str, action_scale: float = 1.0) -> Embodiment:
        """GR00T's `so100` data config keys (`single_arm` 5 joints, `gripper`, video `webcam`).

        That config's `single_arm` action is 5 joint targets. On an arm that takes joint targets its columns are
        the arm's five joints; on an end-effector delta arm they drive the first five delta axes scaled by
        `action_scale` (to run the protocol against so100-shaped servers and the golden messages).
        """
        joints = tuple(n for n in layout.state_names if not n.startswith("ee_") and not is_gripper(n))
        if len(joints) != 5:
            raise ObservationError(f"so100 wants 5 joints; arm {layout.arm!r} has {list(joints)}")
        return Embodiment(
            state=(Group("single_arm", layout.arm, joints), Group("gripper", layout.arm, layout.state_names[-1:])),
            video={"webcam": camera},
            actions=(Group("single_arm", layout.arm, layout.action_names[:5], action_scale),
                     Group("gripper", layout.arm, layout.action_names[-1:])),
        )

    # --- checks against the server's modality config --------------------------------------------------------

    def check_against(self, config: Mapping[str, ModalityConfig] | None, wire: str) -> Embodiment:
        """This embodiment, with the server's language key, or EmbodimentMismatch naming both key sets."""
        if not config:
            return self
        prefix = {"video": "video.", "state": "state.", "action": "action."} if wire == N15 else {}
        problems = []
        for modality, ours in (("video", tuple(self.video)), ("state", tuple(g.key for g in self.state)),
                               ("action", tuple(g.key for g in self.actions))):
            if modality not in config:
                continue
            p = prefix.get(modality, "")
            theirs = {k[len(p):] if k.startswith(p) else k for k in config[modality].modality_keys}
            if set(ours) != theirs:
                problems.append(f"{modality} keys {sorted(theirs)} (the adapter sends {sorted(ours)})")
        if problems:
            raise EmbodimentMismatch(
                "the GR00T server's model wants " + "; ".join(problems)
                + ". Pick the matching --config, arms (--arm, in the dataset's order) and cameras (--camera)"
            )
        language = config.get("language")
        if language is not None and language.modality_keys:
            return Embodiment(self.state, self.video, self.actions, language.modality_keys[0])
        return self

    # --- observation -> GR00T request ---------------------------------------------------------------------

    def arrays(self, obs: policy_pb2.Observation) -> tuple[dict[str, np.ndarray], dict[str, np.ndarray]]:
        """(video key -> (H, W, 3) uint8, state key -> (D,) float64) for one observation."""
        arms = {a.arm: a for a in obs.arms}
        frames = {f.camera: f for f in obs.frames}
        video: dict[str, np.ndarray] = {}
        for key, camera in self.video.items():
            frame = frames.get(camera)
            if frame is None:
                raise ObservationError(f"video {key!r} needs camera {camera!r}; observation has {sorted(frames)}")
            video[key] = frame_rgb(frame)
        state: dict[str, np.ndarray] = {}
        for g in self.state:
            a = arms.get(g.arm)
            if a is None:
                raise ObservationError(f"observation {obs.observation_id} has no arm {g.arm!r} ({sorted(arms)})")
            index = {n: i for i, n in enumerate(a.state_names)}
            missing = [n for n in g.columns if n not in index]
            if missing:
                raise ObservationError(f"state {g.key!r} needs {missing}; arm {g.arm!r} has {list(a.state_names)}")
            state[g.key] = np.array([a.state[index[n]] for n in g.columns], dtype=np.float64)
        return video, state

    def request_data(self, obs: policy_pb2.Observation, task: str, wire: str = N15) -> dict[str, Any]:
        """The `get_action` data for one observation in the server's dialect (unbatched N1.5, batched N1.6/N1.7)."""
        video, state = self.arrays(obs)
        wire = shapes_of(wire)
        if wire == N15:
            # Key order as the upstream client sends it (video, state, language): the golden request is built so.
            data: dict[str, Any] = {f"video.{k}": v[None] for k, v in video.items()}  # (T=1, H, W, 3)
            data.update({f"state.{k}": v[None] for k, v in state.items()})  # (T=1, D)
            data[self.language_key] = [task]
            return data
        if wire == N16:
            # N1.6's Gr00tPolicy checks (B, T, H, W, 3) uint8 video, (B, T, D) float32 state, [[text]] language.
            return {
                "observation": {
                    "video": {k: v[None, None] for k, v in video.items()},
                    "state": {k: v.astype(np.float32)[None, None] for k, v in state.items()},
                    "language": {self.language_key: [[task]]},
                },
                "options": None,
            }
        if wire == N16_SIM:
            # Gr00tSimPolicyWrapper: flat keys, still batched (B, T, ...), language (B,) strings.
            flat: dict[str, Any] = {f"video.{k}": v[None, None] for k, v in video.items()}
            flat.update({f"state.{k}": v.astype(np.float32)[None, None] for k, v in state.items()})
            flat[self.language_key] = [task]
            return {"observation": flat, "options": None}
        raise ValueError(f"unknown GR00T wire version {wire!r}")

    # --- GR00T answer -> phone2act chunks -------------------------------------------------------------------

    def answer_groups(self, answer: Any, wire: str = N15) -> dict[str, np.ndarray]:
        """The answer's action arrays by bare group key, each (horizon, D)."""
        if shapes_of(wire) in (N16, N16_SIM):
            if not isinstance(answer, (list, tuple)) or len(answer) != 2 or not isinstance(answer[0], Mapping):
                raise ChunkShapeError(f"a GR00T N1.6 answer is [action, info]; got {type(answer).__name__}")
            answer = answer[0]
        if not isinstance(answer, Mapping):
            raise ChunkShapeError(f"a GR00T N1.5 answer is a map of action.<group>; got {type(answer).__name__}")
        groups: dict[str, np.ndarray] = {}
        for key, value in answer.items():
            if isinstance(key, str):
                groups[key.removeprefix("action.")] = value
        return groups

    def chunk_steps(self, answer: Any, layouts: Mapping[str, ArmLayout] | ArmLayout, max_steps: int | None = None,
                    *, wire: str = N15, modes: Mapping[str, int] | None = None) -> Any:
        """Per arm, (horizon, action_width) rows in the arm's layout, or ChunkShapeError saying what is off.

        With a single ArmLayout, returns that arm's rows directly. Columns no group provides stay 0, which only
        means "stay" for delta actions: for absolute or joint arms every column must come from the model.
        """
        single = isinstance(layouts, ArmLayout)
        by_arm = {layouts.arm: layouts} if isinstance(layouts, ArmLayout) else dict(layouts)
        groups = self.answer_groups(answer, wire)
        horizon: int | None = None
        parts: list[tuple[Group, np.ndarray]] = []
        for group in self.actions:
            if group.key not in groups:
                raise ChunkShapeError(f"GR00T answer has no {group.key!r} action (it has {sorted(groups)})")
            a = np.asarray(groups[group.key])
            n = len(group.columns)
            if a.ndim == 3 and a.shape[0] == 1:  # a batched answer (N1.6 always, N1.5 to a batched request)
                a = a[0]
            if a.ndim == 1 and n == 1:  # N1.5 from 2025-09-11 to 2025-09-18 squeezed single-column groups
                a = a[:, None]
            if a.ndim != 2 or a.shape[1] != n or a.shape[0] == 0:
                raise ChunkShapeError(
                    f"action {group.key} has shape {a.shape}; expected (horizon, {n}) for {list(group.columns)}"
                    + _absolute_model_hint(a, group, (modes or {}).get(group.arm))
                )
            if not np.issubdtype(a.dtype, np.number):
                raise ChunkShapeError(f"action {group.key} holds non-numeric values (dtype {a.dtype})")
            if not np.all(np.isfinite(a)):
                raise NonFiniteActionError(f"action {group.key} holds non-finite values (NaN or infinity)")
            if horizon is not None and a.shape[0] != horizon:
                raise ChunkShapeError(f"action {group.key} has horizon {a.shape[0]}, other groups {horizon}")
            horizon = a.shape[0]
            layout = by_arm.get(group.arm)
            if layout is None:
                raise ChunkShapeError(f"action {group.key} is for arm {group.arm!r}, not in this session")
            for c in group.columns:
                if c not in layout.action_names:
                    raise ChunkShapeError(f"action {group.key} maps to {c!r}, not an action of arm {group.arm!r}")
            parts.append((group, a.astype(np.float64) * group.scale))
        assert horizon is not None, "an embodiment without action groups"
        steps = {arm: np.zeros((horizon, by_arm[arm].action_width)) for arm in {g.arm for g, _ in parts}}
        filled = {arm: np.zeros(by_arm[arm].action_width, dtype=bool) for arm in steps}
        for group, a in parts:
            column_of = {n: i for i, n in enumerate(by_arm[group.arm].action_names)}
            for j, c in enumerate(group.columns):
                steps[group.arm][:, column_of[c]] = a[:, j]
                filled[group.arm][column_of[c]] = True
        for arm, mode in (modes or {}).items():
            if arm in filled and not filled[arm].all() and kind_of_mode(mode) != DELTA:
                missing = [n for n, f in zip(by_arm[arm].action_names, filled[arm], strict=True) if not f]
                raise ChunkShapeError(
                    f"arm {arm!r} takes {kind_of_mode(mode)} actions and the model gives no {missing}; a guessed "
                    f"target would move the arm"
                )
        if max_steps:
            steps = {arm: s[:max_steps] for arm, s in steps.items()}
        return steps[next(iter(by_arm))] if single else steps


def _absolute_model_hint(a: np.ndarray, group: Group, mode: int | None) -> str:
    """What to change when the answer is as wide as the absolute targets a phone2act dataset records but the arm
    takes another representation: the arm's configuration, not the model."""
    if a.ndim < 1 or a.shape[-1] != len(RECORDED_ABSOLUTE_AXES) or any(is_gripper(c) for c in group.columns):
        return ""
    if mode is not None and kind_of_mode(mode) == ABSOLUTE:
        return ""
    taken = kind_of_mode(mode) if mode is not None else "non-absolute"
    return (
        f". {len(RECORDED_ABSOLUTE_AXES)} columns are the absolute end-effector targets a phone2act dataset records "
        f"({' '.join(RECORDED_ABSOLUTE_AXES)}): this model was trained on absolute targets, and arm {group.arm!r} "
        f"takes {taken} actions. Set action_mode = \"absolute\" on arm {group.arm!r} in the phone2act server's "
        f"config (then restart it)"
    )


def frame_rgb(frame: common_pb2.CameraFrame) -> np.ndarray:
    """(H, W, 3) uint8 pixels of an RGB8 frame."""
    if frame.encoding != common_pb2.IMAGE_ENCODING_RGB8:
        name = common_pb2.ImageEncoding.Name(frame.encoding)
        raise ObservationError(f"camera {frame.camera!r} frame is {name}; the adapter asks for RGB8")
    expected = frame.width * frame.height * 3
    if len(frame.data) != expected:
        raise ObservationError(f"camera {frame.camera!r}: {len(frame.data)} bytes, expected {expected}")
    return np.frombuffer(frame.data, dtype=np.uint8).reshape(frame.height, frame.width, 3)
