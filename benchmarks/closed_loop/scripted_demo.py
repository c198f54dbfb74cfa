"""The scripted demonstrator of the physics scene: a privileged expert that reads the block's true pose from
the MuJoCo world and drives the arm through phone2act's Policy API (absolute end-effector chunks) while the
server records the episode, exactly as a policy would drive it. Only successful episodes are kept.

The same planner, replayed open loop from a training scene's plan on another scene, is the benchmark's
"nearest demonstration" baseline (`plan_for_layout`).
"""

from __future__ import annotations

import math
import time

import numpy as np

from baselines import drive_plan
from mujoco_bridge import BASKET_WALL_M, BLOCK_HALF_M, HOME_RAD, Layout, World, rotvec

APPROACH_Z_M = 0.07
GRASP_Z_M = 0.024
CARRY_Z_M = 0.075
SPEED_M_S = 0.12
# Well inside the safety gate's jump threshold per step (0.5 rad) at 20 steps a second.
TURN_RAD_S = 1.0


def rotation_of(v: np.ndarray) -> np.ndarray:
    """Rotation matrix of a rotation vector (Rodrigues)."""
    angle = float(np.linalg.norm(v))
    if angle < 1e-12:
        return np.eye(3)
    k = v / angle
    kx = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + math.sin(angle) * kx + (1 - math.cos(angle)) * kx @ kx


def top_down(yaw: float) -> np.ndarray:
    """Tool pointing down, jaws closing along `yaw` (the site's x axis is the closing direction)."""
    x = np.array([math.cos(yaw), math.sin(yaw), 0.0])
    z = np.array([0.0, 0.0, -1.0])
    return np.stack([x, np.cross(z, x), z], axis=1)


def reachable(world: World, position: np.ndarray, rotation: np.ndarray) -> np.ndarray:
    """The orientation nearest `rotation` the arm can hold at `position` (a five-joint arm cannot point straight
    down everywhere): every waypoint of a plan is then a pose the arm reaches exactly."""
    q = np.array(HOME_RAD)
    for _ in range(3):
        q = world.solve(position, rotation, q)
    p, r = world.fk(q)
    if np.linalg.norm(p - position) > 0.002:
        for _ in range(3):
            q = world.solve(position, rotation, q, w_rot=0.01)
        p, r = world.fk(q)
    return r


def grasp_yaw(world: World, block_xy, block_yaw: float, start_r: np.ndarray) -> float:
    """The block is symmetric under half a turn: of its two grasp yaws take the one the wrist reaches best."""
    best, best_err = block_yaw, float("inf")
    for yaw in (block_yaw, block_yaw + math.pi, block_yaw - math.pi):
        r = top_down(yaw)
        q = world.solve(np.array([*block_xy, APPROACH_Z_M]), r, np.array(HOME_RAD))
        _, got = world.fk(q)
        # Reachable first, then the least turn from where the tool starts.
        err = float(np.linalg.norm(got[:, 0] - r[:, 0])) + 0.05 * float(np.linalg.norm(rotvec(r @ start_r.T)))
        if err < best_err:
            best, best_err = yaw, err
    return best


def plan_for_layout(world: World, layout: Layout, start_pos: np.ndarray, start_r: np.ndarray,
                    fps: int) -> list[list[float]]:
    """Absolute end-effector steps (the Policy API's ABSOLUTE_EE layout) at `fps` for one scene."""
    bx, by = layout.block_xy
    yaw = grasp_yaw(world, layout.block_xy, layout.block_yaw, start_r)
    grasp_r = top_down(yaw)
    # Aim the jaws' midpoint (not the tool frame, which sits on the fixed jaw) at the block.
    off = grasp_r @ world.grasp_offset_tool_m
    bx, by = bx - off[0], by - off[1]
    kx, ky = layout.basket_xy[0] - off[0], layout.basket_xy[1] - off[1]
    drop_r = top_down(yaw)
    # (position, rotation, gripper, dwell seconds at the waypoint)
    raw = [
        (np.array([bx, by, APPROACH_Z_M]), grasp_r, 0.0, 0.3),
        (np.array([bx, by, GRASP_Z_M]), grasp_r, 0.0, 0.3),
        (np.array([bx, by, GRASP_Z_M]), grasp_r, 1.0, 0.6),
        (np.array([bx, by, CARRY_Z_M]), grasp_r, 1.0, 0.1),
        (np.array([kx, ky, CARRY_Z_M]), drop_r, 1.0, 0.2),
        (np.array([kx, ky, BASKET_WALL_M + 0.03]), drop_r, 1.0, 0.2),
        (np.array([kx, ky, BASKET_WALL_M + 0.03]), drop_r, 0.0, 0.5),
        (np.array([kx, ky, CARRY_Z_M]), drop_r, 0.0, 1.0),
    ]
    waypoints = [(p, reachable(world, p, r), g, dwell) for p, r, g, dwell in raw]
    steps: list[list[float]] = []
    pos, rot, grip = start_pos.copy(), start_r.copy(), 0.0
    dt = 1.0 / fps
    for target, r, g, dwell in waypoints:
        turn = rotvec(rot.T @ r)
        n = max(1, math.ceil(np.linalg.norm(target - pos) / SPEED_M_S / dt),
                math.ceil(np.linalg.norm(turn) / TURN_RAD_S / dt))
        for i in range(1, n + 1):
            p = pos + (target - pos) * i / n
            steps.append(ee_step(p, rot @ rotation_of(turn * i / n), grip))
        pos, rot = target, r
        grip = g
        for _ in range(max(1, round(dwell / dt))):
            steps.append(ee_step(pos, rot, grip))
    return steps


def ee_step(p: np.ndarray, r: np.ndarray, gripper: float) -> list[float]:
    return [*p.tolist(), *r[:, 0].tolist(), *r[:, 1].tolist(), float(gripper)]


def reset_scene(client, arm: str, seed: int) -> None:
    """`Scene.Reset(seed, home_arm)`, retried while the previous session still owns the arm."""
    from closed_loop import reset_scene as reset

    reset(client, seed, arm)


def record_demos(bridge, args) -> dict:
    """`args.demos` successful episodes from seeds `args.seed`, ... (failures discarded and counted)."""
    from phone2act import Client, FailedPrecondition

    saved, failed, seeds = 0, 0, []
    seed = args.seed
    not_ready = 0
    with Client(bridge.target, token=bridge.token) as c:
        while saved < args.demos:
            reset_scene(c, bridge.arm, seed)
            with bridge.lock:
                layout = bridge.world.layout
                start_p, start_r = bridge.world.ee_pose()
                steps = plan_for_layout(bridge.world, layout, start_p, start_r, args.fps)
            c.episodes.start(args.task, operator="scripted-demo")
            try:
                ok = drive_plan(c, bridge.arm, steps, args.fps, args.episode_time_s)
            except FailedPrecondition as e:
                # The server refused the arm (its feedback went stale: this process was starved on a loaded
                # machine). Not the plan's failure: the same seed again, a few times at most.
                c.episodes.discard()
                not_ready += 1
                print(f"demo seed {seed}: arm not ready ({e}); retrying", flush=True)
                if not_ready > 5:
                    raise
                time.sleep(1.0)
                continue
            if ok:
                c.episodes.stop()
                saved += 1
                seeds.append(seed)
            else:
                c.episodes.discard()
                failed += 1
            print(f"demo seed {seed}: {'saved' if ok else 'failed, discarded'}", flush=True)
            seed += 1
            if failed > 3 * args.demos + 5:
                raise SystemExit(f"scripted demonstrator: {failed} failures for {saved} successes; stopping")
    return {"saved": saved, "failed": failed, "seeds": seeds,
            "block_half_m": BLOCK_HALF_M}
