"""The physics task of the closed-loop benchmark (`closed_loop.py --sim physics`): the MuJoCo SO-101 of
`mujoco_bridge.py` attached as a remote arm, its scripted demonstrations and where its block starts. The
held-out seeds and the baselines are `baselines.py`'s, shared with the kinematic task.
"""

from __future__ import annotations

import json
import subprocess
import sys
import threading
import time
from pathlib import Path

from mujoco_bridge import AREA_M, GRASP_TOLERANCE_M, draw_layout  # noqa: F401 (the task's workspace and tolerance)

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


def block_start(seed: int) -> tuple[float, float]:
    """The block's start `seed` draws (for `baselines.held_out_seeds` and the replay baseline)."""
    return draw_layout(seed).block_xy
