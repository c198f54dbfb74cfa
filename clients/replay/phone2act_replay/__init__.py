"""Replay a recorded phone2act episode's actions through the Policy API."""

from phone2act_replay.dataset import (
    Episode,
    align,
    load_episode,
    path_errors,
    pose_errors,
    resample,
    target_path_errors,
)
from phone2act_replay.replay import ReplayResult, move_to, replay

__all__ = ["Episode", "ReplayResult", "align", "load_episode", "move_to", "path_errors", "pose_errors", "replay", "resample",
           "target_path_errors"]
