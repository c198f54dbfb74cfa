"""Fixtures: a real `phone2act serve` process per test module, on a free port, with its own dataset dir."""

from __future__ import annotations

import os
import re
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[2]
# Test data written by other software (GR00T's MsgSerializer, lerobot): see tests/fixtures/README.md.
FIXTURES = REPO / "tests" / "fixtures"
GOLDEN = FIXTURES / "gr00t_wire"

# The clients are plain directories in the repo; test them from source.
for sub in ("clients/gr00t", "clients/replay", "clients/python-bridge"):
    sys.path.insert(0, str(REPO / sub))

SIM_ARM = """
[[arms]]
name = "main"
bridge = "sim"
"""


def config_text(root: Path, arms: str = SIM_ARM, cameras: str = "", extra: str = "", token: str = "") -> str:
    server = '[server]\nlisten = "127.0.0.1:0"\n' + (f'token = "{token}"\n' if token else "")
    recorder = f'[recorder]\nroot = "{root}"\nformat = "v3.0"\nfps = 20\nrobot_type = "so101_sim"\nvideo_codec = "libx264"\n'
    return server + arms + cameras + recorder + extra


@dataclass
class Server:
    proc: subprocess.Popen
    target: str
    root: Path
    log: list[str] = field(default_factory=list)

    def stop(self) -> None:
        if self.proc.poll() is None:
            self.proc.terminate()
            try:
                self.proc.wait(timeout=10)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()


def phone2act_bin() -> Path:
    path = Path(os.environ.get("PHONE2ACT_BIN", REPO / "target" / "release" / "phone2act"))
    if not path.exists():
        pytest.fail(f"server binary {path} not found: build it or set PHONE2ACT_BIN")
    return path


def start_server(tmp: Path, config: str, startup_timeout_s: float = 60.0) -> Server:
    tmp.mkdir(parents=True, exist_ok=True)
    cfg = tmp / "config.toml"
    cfg.write_text(config)
    # The embedded phone gateway listens on fixed ports (9090, 8443); tests start several servers at once.
    env = dict(os.environ, SVT_LOG="1", RUST_LOG=os.environ.get("RUST_LOG", "warn"), PHONE2ACT_GATEWAY__ENABLED="false")
    proc = subprocess.Popen(
        [str(phone2act_bin()), "serve", "--config", str(cfg), "--listen", "127.0.0.1:0"],
        stderr=subprocess.PIPE, stdout=subprocess.DEVNULL, text=True, env=env,
    )
    log: list[str] = []
    found: dict[str, str] = {}
    ready = threading.Event()

    def drain() -> None:  # keep reading so the server never blocks on a full stderr pipe
        assert proc.stderr is not None
        for line in proc.stderr:
            log.append(line.rstrip())
            m = re.search(r"gRPC on (\S+)", line)
            if m and not ready.is_set():
                found["addr"] = m.group(1)
                ready.set()
        ready.set()

    threading.Thread(target=drain, daemon=True).start()
    if not ready.wait(startup_timeout_s) or "addr" not in found:
        proc.kill()
        raise RuntimeError("phone2act serve did not start:\n" + "\n".join(log[-30:]))
    root = Path(re.search(r'root = "([^"]+)"', config).group(1))  # type: ignore[union-attr]
    return Server(proc, found["addr"], root, log)


@pytest.fixture(scope="module")
def make_server(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Callable[..., Server]]:
    servers: list[Server] = []

    def make(arms: str = SIM_ARM, cameras: str = "", extra: str = "", token: str = "") -> Server:
        tmp = tmp_path_factory.mktemp("server")
        s = start_server(tmp, config_text(tmp / "ds", arms, cameras, extra, token))
        servers.append(s)
        return s

    yield make
    for s in servers:
        s.stop()


@pytest.fixture(scope="module")
def server(make_server: Callable[..., Server]) -> Server:
    return make_server()


def wait_until(pred: Callable[[], bool], timeout_s: float = 5.0, period_s: float = 0.02) -> bool:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if pred():
            return True
        time.sleep(period_s)
    return pred()


def free_port() -> int:
    import socket

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def golden(name: str) -> bytes:
    path = GOLDEN / name
    if not path.exists():
        pytest.fail(f"golden message {path} is missing (see tests/fixtures/README.md)")
    return path.read_bytes()


