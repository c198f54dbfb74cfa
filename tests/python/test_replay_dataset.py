"""The replay client's dataset reader on the golden lerobot-written datasets (v3.0 and v2.1) and its math."""

from __future__ import annotations

import math

import numpy as np
import pytest
from conftest import FIXTURES
from phone2act.poses import quat_angle, quat_from_rpy, rpy_from_quat
from phone2act_replay import Episode, align, load_episode, path_errors, pose_errors, resample

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


def _episode(delta: bool) -> Episode:
    names = ["j0", "ee_x", "ee_y", "ee_z", "ee_roll", "ee_pitch", "ee_yaw", "gripper"]
    state = np.array([[0.0, 0.2, 0.0, 0.1, 3.1, 0.1, 0.0, 0.0], [0.0, 0.21, 0.0, 0.1, -3.1, 0.1, 0.0, 0.5]])
    if delta:
        action = np.array([[0.01, 0, 0, 0.08, 0, 0, 0.5], [0.0, 0.01, 0, 0, 0, 0.2, 1.0]])
        action_names = ["delta_x", "delta_y", "delta_z", "delta_roll", "delta_pitch", "delta_yaw", "gripper"]
    else:
        action = np.array([[0.21, 0, 0.1, 3.18, 0.1, 0, 0.5], [0.21, 0.01, 0.1, -3.1, 0.1, 0.2, 1.0]])
        action_names = ["x", "y", "z", "roll", "pitch", "yaw", "gripper"]
    return Episode(0, 20.0, "t", names, action_names, state, action)


def test_delta_and_absolute_actions_give_the_same_targets() -> None:
    d, a = _episode(True).targets(), _episode(False).targets()
    np.testing.assert_allclose(d[:, :3], a[:, :3], atol=1e-12)
    np.testing.assert_allclose(d[:, 6], a[:, 6])
    for rd, ra in zip(d, a):  # rpy may differ by 2*pi (roll across the seam); the rotation may not
        assert quat_angle(quat_from_rpy(*rd[3:6]), quat_from_rpy(*ra[3:6])) < 1e-9


def test_resample_interpolates_across_the_roll_seam() -> None:
    t = _episode(True).targets()
    r = resample(t, 4)
    assert len(r) == 5
    for got, want in ((r[0], t[0]), (r[-1], t[-1])):  # rpy may come back as another triple of the same rotation
        assert np.allclose(got[[0, 1, 2, 6]], want[[0, 1, 2, 6]])
        assert quat_angle(quat_from_rpy(*got[3:6]), quat_from_rpy(*want[3:6])) < 1e-6
    # Roll goes 3.18 -> 3.18 (as -3.10 + 2 pi would be): the midpoint must not swing through 0.
    q0, q1 = quat_from_rpy(*t[0, 3:6]), quat_from_rpy(*t[1, 3:6])
    mid = quat_from_rpy(*r[2, 3:6])
    assert quat_angle(q0, mid) + quat_angle(mid, q1) == pytest.approx(quat_angle(q0, q1), abs=1e-6)
    assert rpy_from_quat(quat_from_rpy(0.3, -0.2, 1.0)) == pytest.approx((0.3, -0.2, 1.0))


def test_alignment_finds_a_fractional_offset_and_path_error_ignores_timing() -> None:
    t = np.linspace(0, 2 * math.pi, 120)
    traj = np.stack([0.2 + 0.03 * np.sin(t), 0.02 * np.cos(t), 0.1 + 0 * t, np.pi - 0.01 + 0 * t, 0 * t, 0.2 * np.sin(t)], 1)
    ref = traj[10:100]
    new = np.vstack([traj[:1].repeat(3, 0), traj[7:]])  # ref starts at new's frame 6
    offset, aligned = align(ref, new)
    assert offset == pytest.approx(6.0, abs=0.05)
    pos, ang = pose_errors(ref, aligned)
    assert pos.max() < 1e-9 and ang.max() < 1e-6  # acos near 1 resolves ~3e-8 rad
    shifted = np.stack([np.interp(np.arange(len(traj)) + 0.4, np.arange(len(traj)), traj[:, c]) for c in range(6)], 1)
    p, a = path_errors(ref, shifted)
    assert p.max() < 5e-5 and a.max() < 1e-3  # chord error of the densified path
    off_path = shifted.copy()
    off_path[:, 2] += 0.002
    assert path_errors(ref, off_path)[0].min() > 1.9e-3
