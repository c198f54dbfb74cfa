"""lerobot's async inference (`lerobot.async_inference`: a policy server and a robot client) run unchanged
against a phone2act arm, through the `phone2act` robot plugin: both processes started as a user starts them,

    python -m lerobot.async_inference.policy_server --host=127.0.0.1 --port=PORT --fps=FPS
    python -m lerobot.async_inference.robot_client --robot.type=phone2act --robot.server=HOST:PORT ... \
        --server_address=127.0.0.1:PORT --policy_type=act --pretrained_name_or_path=MODEL ...

Used by the closed-loop benchmark (its `async` path) and by tests/lerobot_plugins. Both processes write their
console to a log file, and lerobot's own loggers write `logs/<name>_<time>.log` under the working directory,
so each runs in a directory of the caller's choosing.
"""

from __future__ import annotations

import json
import random
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path


def _listen_port_range() -> tuple[int, int]:
    """Ports to listen on: below the kernel's ephemeral range, which the OS hands out to every outgoing
    connection and every `:0` listener (the phone2act servers of other tests), so nothing takes ours by chance
    in the seconds between choosing it and the policy server binding it."""
    try:
        low = int(Path("/proc/sys/net/ipv4/ip_local_port_range").read_text().split()[0])
    except (OSError, ValueError, IndexError):
        low = 32768
    return (max(1024, low - 12000), low - 1)


def free_port() -> int:
    lo, hi = _listen_port_range()
    for _ in range(100):
        port = random.randint(lo, hi)
        with socket.socket() as s:
            try:
                s.bind(("127.0.0.1", port))
            except OSError:
                continue
            return port
    raise RuntimeError(f"no free port in {lo}..{hi}")


def stop_process(proc: subprocess.Popen, timeout_s: float = 15.0) -> None:
    """SIGTERM, and SIGKILL when that has not ended it within `timeout_s`."""
    if proc.poll() is None:
        proc.terminate()
        try:
            proc.wait(timeout=timeout_s)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()


def policy_chunk_size(model: Path) -> int:
    """The trained policy's chunk length (`chunk_size` of its config.json): the robot client's
    `actions_per_chunk`, so the server sends every action the policy predicts."""
    return int(json.loads((Path(model) / "config.json").read_text())["chunk_size"])


class PolicyServer:
    """`python -m lerobot.async_inference.policy_server` on a free loopback port. It loads the policy only when
    a robot client sends its instructions, so one server serves any number of clients, one after another."""

    def __init__(self, python: Path, workdir: Path, fps: int, startup_timeout_s: float = 120.0) -> None:
        workdir.mkdir(parents=True, exist_ok=True)
        self.log_path = workdir / "policy_server.log"
        self._log = self.log_path.open("a")
        # A port can still be taken by another listener between `free_port` and the server's bind (grpc then
        # refuses to start and the process exits): try another.
        for _attempt in range(3):
            self.port = free_port()
            self.address = f"127.0.0.1:{self.port}"
            cmd = [str(python), "-m", "lerobot.async_inference.policy_server", "--host=127.0.0.1",
                   f"--port={self.port}", f"--fps={fps}"]
            self._log.write(f"--- {' '.join(cmd)}\n")
            self._log.flush()
            self.proc = subprocess.Popen(cmd, cwd=workdir, stdout=self._log, stderr=subprocess.STDOUT)
            if self._wait_listening(startup_timeout_s):
                return
        self.stop()
        raise RuntimeError(f"lerobot's policy server did not start; see {self.log_path}")

    def _wait_listening(self, timeout_s: float) -> bool:
        deadline = time.monotonic() + timeout_s
        while self.proc.poll() is None:
            try:
                socket.create_connection(("127.0.0.1", self.port), timeout=1.0).close()
                return True
            except OSError:
                if time.monotonic() > deadline:
                    return False
                time.sleep(0.2)
        return False

    def stop(self) -> None:
        stop_process(self.proc)
        self._log.close()

    def __enter__(self) -> PolicyServer:
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()


def robot_client_command(
    python: Path,
    *,
    robot_server: str,
    token: str | None,
    arm: str,
    cameras: list[str],
    fps: int,
    policy_server: str,
    model: Path,
    task: str,
    actions_per_chunk: int,
    chunk_size_threshold: float = 0.5,
) -> list[str]:
    """The robot client's command line. The model path is made absolute: the policy server loads it from its own
    working directory, and a path that does not exist there is taken for a Hugging Face Hub id."""
    cmd = [str(python), "-m", "lerobot.async_inference.robot_client", "--robot.type=phone2act",
           f"--robot.server={robot_server}", f"--robot.arm={arm}", f"--robot.camera_names=[{','.join(cameras)}]",
           f"--robot.fps={fps}", f"--server_address={policy_server}", "--policy_type=act",
           f"--pretrained_name_or_path={Path(model).resolve()}", "--policy_device=cpu", f"--actions_per_chunk={actions_per_chunk}",
           f"--chunk_size_threshold={chunk_size_threshold}", f"--fps={fps}", f"--task={task}"]
    if token:
        cmd.append(f"--robot.token={token}")
    return cmd


def _with_default_sigint(cmd: list[str]) -> list[str]:
    """`cmd`, exec'd with SIGINT at its default disposition. A shell without job control starts background
    commands with SIGINT ignored, exec keeps it ignored, and Python then installs no KeyboardInterrupt handler:
    the client would not stop on Ctrl-C at all (seen when the benchmark ran as `run.sh … &`). The same process
    (pid) then runs `cmd` itself."""
    reset = "import os, signal, sys; signal.signal(signal.SIGINT, signal.SIG_DFL); os.execv(sys.argv[1], sys.argv[1:])"
    return [sys.executable, "-c", reset, *cmd]


class RobotClient:
    """`python -m lerobot.async_inference.robot_client`: it runs until interrupted, as a user stops it."""

    def __init__(self, cmd: list[str], workdir: Path, log_path: Path) -> None:
        workdir.mkdir(parents=True, exist_ok=True)
        self.log_path = log_path
        self._log = log_path.open("a")
        self._log.write(f"--- {' '.join(cmd)}\n")
        self._log.flush()
        self.proc = subprocess.Popen(_with_default_sigint(cmd), cwd=workdir, stdout=self._log,
                                     stderr=subprocess.STDOUT)
        # How many Ctrl-C it took to end it (see `stop`).
        self.ctrl_c_sent = 0

    def running(self) -> bool:
        return self.proc.poll() is None

    def ctrl_c(self) -> None:
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGINT)
            self.ctrl_c_sent += 1

    def stop(self, grace_s: float = 15.0, timeout_s: float = 30.0) -> int:
        """Ctrl-C (unless `ctrl_c` was already called), and the exit status.

        An uncaught KeyboardInterrupt ends a Python program by SIGINT itself, so a client that stopped as lerobot
        means it to (its `finally` disconnects the robot, closes its channel, joins its receiver thread) exits with
        `STOPPED_BY_SIGINT`. lerobot 0.6.1's client sometimes never gets there: a KeyboardInterrupt that lands
        while its main thread is inside a gRPC call on the channel it shares with the receiver thread can leave
        that channel's lock held, and the receiver thread then waits for it forever, as does the join. The robot
        is already disconnected by then; a second Ctrl-C, as a user would press, ends the join. So: a second
        Ctrl-C after `grace_s` (a clean exit took 0.9 to 1.9 s in 93 timed runs on this 2-core machine under a
        training run's load), and a process still alive `timeout_s` later is killed and reported as a RuntimeError."""
        if self.ctrl_c_sent == 0:
            self.ctrl_c()
        try:
            self.proc.wait(timeout=grace_s)
        except subprocess.TimeoutExpired:
            self.ctrl_c()
            try:
                self.proc.wait(timeout=timeout_s)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()
                self._log.close()
                raise RuntimeError(f"the robot client outlived {self.ctrl_c_sent} Ctrl-C; see {self.log_path}") from None
        self._log.close()
        return self.proc.returncode


STOPPED_BY_SIGINT = -signal.SIGINT
