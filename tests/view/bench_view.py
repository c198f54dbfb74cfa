"""Control-path latency with the live view off and on, in one run: runs `control-bench` alternately without
and with a `phone2act-view` attached to each server it starts, and reports each phase's p99 side by side,
with the view's CPU use (user + system time over its wall time, which the view prints when it exits).

    cargo build --release -p phone2act-tests --bin control-bench
    tests/view/run.sh   # once: creates the venv with the view installed (~/.cache/phone2act/view-venv)
    ~/.cache/phone2act/view-venv/bin/python tests/view/bench_view.py --seconds 8 --rounds 3

control-bench starts its servers in-process on ports it does not print: the script finds them in the
kernel's socket table (`ss -ltnp`, the bench's own pid) as they open, and starts a view on each one
(`--save` to a scratch .rrd, so the view does all its work: JPEG frames of the full-load phase's three
cameras, status at the recorder's rate, file writes). A view needs about a second to import rerun before
it connects, so it misses the first second of each server's first phase.
"""

from __future__ import annotations

import argparse
import os
import re
import signal
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from collections import defaultdict
from pathlib import Path

LINE = re.compile(r"^(?P<name>\S.*?)\s+n=\s*(?P<n>\d+)\s+p50=\s*(?P<p50>[\d.]+) µs\s+p99=\s*(?P<p99>[\d.]+) µs")


def listening_ports(pid: int) -> set[int]:
    out = subprocess.run(["ss", "-ltnpH"], capture_output=True, text=True, check=False).stdout
    return {int(m.group(1)) for line in out.splitlines() if f"pid={pid}," in line
            for m in [re.search(r":(\d+)\s", line)] if m}


def run_bench(bench: str, seconds: float, view: bool, scratch: Path, extra: list[str]) -> tuple[dict, list]:
    env = dict(os.environ, SVT_LOG="1")  # the full-load phase's AV1 encoders: errors only
    proc = subprocess.Popen([bench, "--seconds", str(seconds)], stdout=subprocess.PIPE, text=True, env=env)
    views: list[tuple[subprocess.Popen, float]] = []
    done = threading.Event()

    def attach() -> None:
        seen: set[int] = set()
        while not done.is_set():
            for port in sorted(listening_ports(proc.pid) - seen):
                seen.add(port)
                rrd = scratch / f"view-{proc.pid}-{port}.rrd"
                cmd = [sys.executable, "-m", "phone2act_view", "--url", f"127.0.0.1:{port}", "--save", str(rrd),
                       *extra]
                views.append((subprocess.Popen(cmd, stderr=subprocess.PIPE, text=True), time.monotonic()))
            time.sleep(0.05)

    watcher = threading.Thread(target=attach, daemon=True)
    if view:
        watcher.start()
    assert proc.stdout is not None
    results = {}
    for line in proc.stdout:
        sys.stdout.write(("  [view on ] " if view else "  [view off] ") + line)
        m = LINE.match(line)
        if m:
            results[m.group("name")] = (float(m.group("p50")), float(m.group("p99")))
    proc.wait()
    done.set()
    usage = []
    for v, _ in views:
        v.send_signal(signal.SIGTERM)
        _, err = v.communicate(timeout=60)
        # The view's own account at exit: "...; cpu 1.23 s over 10.0 s".
        m = re.search(r"cpu ([\d.]+) s over ([\d.]+) s", err)
        summary = next((ln for ln in err.splitlines() if "observations" in ln), err.strip()[-300:])
        usage.append((float(m.group(1)) / float(m.group(2)) if m else float("nan"), summary))
    return results, usage


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--bench", default="target/release/control-bench")
    p.add_argument("--seconds", type=float, default=8.0)
    p.add_argument("--rounds", type=int, default=2, help="off/on pairs, alternated so drift hits both alike")
    p.add_argument("--rgb", action="store_true", help="the view asks for RGB frames instead of JPEG")
    args = p.parse_args()
    extra = ["--rgb"] if args.rgb else []
    p99: dict[tuple[str, bool], list[float]] = defaultdict(list)
    usages = []
    with tempfile.TemporaryDirectory() as scratch:
        for r in range(args.rounds):
            for view in (False, True):
                print(f"round {r + 1}, view {'on' if view else 'off'}", flush=True)
                results, usage = run_bench(args.bench, args.seconds, view, Path(scratch), extra)
                for name, (_, q99) in results.items():
                    p99[(name, view)].append(q99)
                usages += usage
    print("\ncontrol-bench p99 (µs), median over rounds [each round]:")
    names = dict.fromkeys(n for n, _ in p99)
    for name in names:
        off, on = p99[(name, False)], p99[(name, True)]
        print(f"  {name:<60} off {statistics.median(off):8.1f} {off}   on {statistics.median(on):8.1f} {on}")
    for cpu, summary in usages:
        print(f"  view: {cpu * 100:5.1f} % of a core; {summary}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
