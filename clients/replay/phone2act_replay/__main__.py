"""python -m phone2act_replay DATASET_ROOT EPISODE [--server ADDR] [--arm main] [--record TASK]

Replays a recorded episode on an arm. With --record, the replay is recorded as a new episode and compared with
the original: the executed targets (each replayed target's distance from the original's target path) and the
measured end-effector paths (each original frame's distance from the replay's path), max position and angle.
"""

from __future__ import annotations

import argparse
import math
import sys

from phone2act import Client, Phone2ActError

from phone2act_replay import align, load_episode, path_errors, pose_errors, replay, target_path_errors


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="phone2act_replay", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("root", help="dataset root (the directory holding meta/ and data/)")
    p.add_argument("episode", type=int)
    p.add_argument("--server", default="127.0.0.1:50051")
    p.add_argument("--token", default=None)
    p.add_argument("--arm", default="main", help="arm to drive")
    p.add_argument("--dataset-arm", default="", help="arm prefix in a multi-arm dataset (left, right)")
    p.add_argument("--upsample", type=int, default=4, help="interpolated steps per recorded frame")
    p.add_argument("--record", metavar="TASK", default=None, help="record the replay and compare trajectories")
    args = p.parse_args(argv)

    episode = load_episode(args.root, args.episode)
    try:
        with Client(args.server, token=args.token) as client:
            start = (lambda: client.episodes.start(args.record)) if args.record else None
            r = replay(client, episode, arm=args.arm, dataset_arm=args.dataset_arm, upsample=args.upsample,
                       on_start=start)
            print(f"replayed episode {episode.index} ({len(episode)} frames) as {r.steps} steps of "
                  f"{r.step_period_s * 1e3:.1f} ms ({r.accepted.steps_skipped} skipped)")
            if args.record:
                saved = client.episodes.stop()
                new = load_episode(args.root, int(saved.episode_index))
                ref = episode.ee_pose(args.dataset_arm)
                offset, aligned = align(ref, new.ee_pose(args.dataset_arm))
                pos, ang = pose_errors(ref, aligned)
                path_pos, path_ang = path_errors(ref, new.ee_pose(args.dataset_arm))
                target_pos, target_ang = target_path_errors(episode.targets(args.dataset_arm), new.targets(args.dataset_arm))
                print(f"recorded as episode {saved.episode_index}; max target path error "
                      f"{target_pos.max() * 1e3:.4f} mm, {math.degrees(target_ang.max()):.4f}°; "
                      f"max path error {path_pos.max() * 1e3:.3f} mm, "
                      f"{math.degrees(path_ang.max()):.3f}°; time-aligned (offset {offset:.2f} frames) max error "
                      f"{pos.max() * 1e3:.3f} mm, {math.degrees(ang.max()):.3f}°")
    except Phone2ActError as e:
        print(f"phone2act_replay: {e}", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
