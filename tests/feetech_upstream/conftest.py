"""The Feetech bus emulator (`feetech-emulator`, server/bridges) as a process on a pseudo-terminal, for lerobot's
own Feetech client. Binaries come from $FEETECH_EMULATOR and $SO101_CHECK (run.sh builds and sets them)."""

from __future__ import annotations

import os
import subprocess
from collections.abc import Iterator
from pathlib import Path

import pytest


class Emulator:
    """One emulated bus. `cmd` sends a line of the emulator's stdin protocol and returns what follows `ok`."""

    def __init__(self, *args: str) -> None:
        self.proc = subprocess.Popen(
            [os.environ["FEETECH_EMULATOR"], *args],
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            text=True,
            bufsize=1,
        )
        assert self.proc.stdout is not None
        self.port = self.proc.stdout.readline().strip()
        assert self.port.startswith("/dev/"), f"emulator printed {self.port!r}"

    def cmd(self, line: str) -> str:
        assert self.proc.stdin is not None and self.proc.stdout is not None
        self.proc.stdin.write(line + "\n")
        self.proc.stdin.flush()
        answer = self.proc.stdout.readline().strip()
        assert answer.startswith("ok"), f"{line!r}: {answer!r}"
        return answer[2:].strip()

    def close(self) -> None:
        self.proc.kill()
        self.proc.wait()


# How long lerobot waits for a servo's answer beyond the transfer time: 50 ms in lerobot (its
# `patch_setPacketTimeout`), 500 ms here. A real servo answers within microseconds; the emulator is a process
# that a loaded 2-core machine may deschedule for longer than 50 ms. Only the wait changes, not what is sent.
PATIENCE_MS = 500


@pytest.fixture(autouse=True)
def patient_sdk(monkeypatch: pytest.MonkeyPatch) -> None:
    import lerobot.motors.feetech.feetech as feetech

    def set_packet_timeout(self, packet_length):  # noqa: N802 (the SDK's name)
        self.packet_start_time = self.getCurrentTime()
        self.packet_timeout = self.tx_time_per_byte * (packet_length + 3.0) + PATIENCE_MS

    monkeypatch.setattr(feetech, "patch_setPacketTimeout", set_packet_timeout)


@pytest.fixture
def start_emulator() -> Iterator:
    started: list[Emulator] = []

    def start(*args: str) -> Emulator:
        e = Emulator(*args)
        started.append(e)
        return e

    yield start
    for e in started:
        e.close()


def so101_check(*args: str | Path) -> subprocess.CompletedProcess[str]:
    """phone2act's bring-up check (and, with --positions, the SO-101 bridge's joint angles)."""
    return subprocess.run(
        [os.environ["SO101_CHECK"], "--timeout-ms", str(PATIENCE_MS), *map(str, args)],
        capture_output=True,
        text=True,
        timeout=60,
        check=False,
    )
