"""The replay client's dataset reader on the golden lerobot-written datasets (v3.0 and v2.1) and its math."""

from __future__ import annotations

import math

import numpy as np
import pytest
from conftest import FIXTURES
from phone2act_replay import Episode, align, load_episode, path_errors, pose_errors, resample
from phone2act_replay.dataset import ACTION_NAMES, EE_NAMES, rot6d, rotation_angle, rotation_from_6d

REF = FIXTURES


@pytest.mark.parametrize("name", ["lerobot_sample_v30", "lerobot_sample_v21"])
def test_reads_lerobot_written_datasets(name: str) -> None:
    lengths, tasks = [], []
    for i in range(3):
        ep = load_episode(REF / name, i)
        assert ep.fps == 10.0 and ep.state.shape[1] == 6 and ep.action.shape == ep.state.shape
        lengths.append(len(ep))
        tasks.append(ep.task)
    assert lengths == [10, 12, 8]
    assert tasks == ["pick the red cube", "place it in the bowl", "pick the red cube"]
    with pytest.raises(KeyError, match="episode 7"):
        load_episode(REF / name, 7)
    with pytest.raises(KeyError, match="no end-effector columns"):
        load_episode(REF / name, 0).ee_pose()


def _rx(angle: float) -> np.ndarray:
    c, s_ = math.cos(angle), math.sin(angle)
    return np.array([[1.0, 0.0, 0.0], [0.0, c, -s_], [0.0, s_, c]])


def _pose_row(p: tuple[float, float, float], angle: float, gripper: float) -> np.ndarray:
    return np.concatenate([p, rot6d(_rx(angle)), [gripper]])


def _episode() -> Episode:
    # Roll goes from just below +pi to just past it (-pi + 0.04 in roll-pitch-yaw): no seam in 6D.
    ee = [_pose_row((0.2, 0.0, 0.1), math.pi - 0.04, 0.0), _pose_row((0.21, 0.0, 0.1), math.pi + 0.04, 0.5)]
    state = np.array([np.concatenate([[0.3], row]) for row in ee])
    action = np.array([_pose_row((0.21, 0.0, 0.1), math.pi + 0.04, 0.5), _pose_row((0.21, 0.01, 0.1), math.pi + 0.1, 1.0)])
    return Episode(0, 20.0, "t", ["j0", *EE_NAMES], list(ACTION_NAMES), state, action)


def test_targets_are_the_action_columns_and_6d_reads_back() -> None:
    e = _episode()
    np.testing.assert_array_equal(e.targets(), e.action)
    assert e.ee_pose().shape == (2, 10) and e.arms() == [""]
    np.testing.assert_allclose(rotation_from_6d(rot6d(_rx(2.0))), _rx(2.0), atol=1e-15)
    assert rotation_angle(rot6d(_rx(math.pi - 0.04)), rot6d(_rx(-math.pi + 0.04))) == pytest.approx(0.08, abs=1e-7)
    # A slightly non-orthonormal pair (a policy's output) reads as the nearest rotation, as the server does.
    noisy = rot6d(_rx(0.5)) + np.array([0.01, 0.0, 0.0, 0.0, 0.0, 0.01])
    assert rotation_angle(noisy, rot6d(_rx(0.5))) < 0.02
    with pytest.raises(KeyError, match="not phone2act end-effector targets"):
        Episode(0, 20.0, "t", e.state_names, ["a"] * 10, e.state, e.action).targets()


def test_resample_interpolates_across_the_roll_seam() -> None:
    t = _episode().targets()
    r = resample(t, 4)
    assert len(r) == 5
    np.testing.assert_allclose(r[0], t[0], atol=1e-12)
    np.testing.assert_allclose(r[-1], t[-1], atol=1e-12)
    # The midpoint turns half way along the short arc (through pi), never the long way round through 0.
    mid = r[2]
    assert rotation_angle(t[0, 3:9], mid[3:9]) == pytest.approx(0.03, abs=1e-4)
    assert rotation_angle(mid[3:9], t[1, 3:9]) == pytest.approx(0.03, abs=1e-4)
    assert mid[[0, 1, 2, 9]] == pytest.approx([0.21, 0.005, 0.1, 0.75])


def test_alignment_finds_a_fractional_offset_and_path_error_ignores_timing() -> None:
    t = np.linspace(0, 2 * math.pi, 120)
    traj = np.array([_pose_row((0.2 + 0.03 * math.sin(u), 0.02 * math.cos(u), 0.1), math.pi - 0.01 + 0.2 * math.sin(u), 0.0)
                     for u in t])
    ref = traj[10:100]
    new = np.vstack([traj[:1].repeat(3, 0), traj[7:]])  # ref starts at new's frame 6
    offset, aligned = align(ref, new)
    assert offset == pytest.approx(6.0, abs=0.05)
    pos, ang = pose_errors(ref, aligned)
    assert pos.max() < 1e-9 and ang.max() < 1e-6  # acos near 1 resolves ~3e-8 rad
    shifted = np.array([_pose_row((0.2 + 0.03 * math.sin(u), 0.02 * math.cos(u), 0.1), math.pi - 0.01 + 0.2 * math.sin(u), 0.0)
                        for u in np.linspace(0, 2 * math.pi, 120) + 0.4 * (2 * math.pi / 119)])
    p, a = path_errors(ref, shifted)
    assert p.max() < 5e-5 and a.max() < 1e-3  # chord error of the densified path
    off_path = shifted.copy()
    off_path[:, 2] += 0.002
    assert path_errors(ref, off_path)[0].min() > 1.9e-3
