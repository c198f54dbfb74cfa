"""`phone2act-view`: stream a phone2act server's cameras, arms and events into Rerun.

    phone2act-view --spawn                                  # a live viewer (needs the `rerun` viewer)
    phone2act-view --save session.rrd --save-episodes rrd/  # files only: one per recorded episode too
"""

from __future__ import annotations

import argparse
import logging
import os
import signal
import sys
import threading
import time
from pathlib import Path

import rerun as rr
import tomllib
from phone2act import Client, Phone2ActError

from phone2act_view.sink import APPLICATION_ID, Fanout
from phone2act_view.view import View, Workspace

log = logging.getLogger("phone2act_view")


def workspaces_from_config(path: Path) -> dict[str, Workspace]:
    """Each arm's workspace box from the server's TOML config: the API does not expose the gate's limits.
    Arms without `[arms.teleop.gate]` limits get the server's documented defaults."""
    with path.open("rb") as f:
        cfg = tomllib.load(f)
    out = {}
    for arm in cfg.get("arms", []):
        gate = arm.get("teleop", {}).get("gate", {})
        out[arm.get("name", "main")] = Workspace(
            gate.get("workspace_min_m", [0.10, -0.25, 0.02]), gate.get("workspace_max_m", [0.40, 0.25, 0.35])
        )
    return out


def _session_file_sink(path: Path) -> rr.FileSink:
    """A file sink for a session of any length. rerun >= 0.32 keeps every chunk's manifest entry in memory
    to write a footer at the end (measured: +5 MB a minute at 20 Hz with a camera); without it, memory stays
    flat, the file stays valid, and `rerun rrd optimize` adds the footer. Episode files keep theirs: they
    are bounded by the episode, and the footer gives readers random access."""
    try:
        return rr.FileSink(str(path), write_footer=False)
    except TypeError:  # rerun < 0.32 writes no footer, so holds no manifest
        return rr.FileSink(str(path))


def _cpu_s() -> float:
    t = os.times()
    return t.user + t.system


def parse_args(argv: list[str] | None) -> argparse.Namespace:
    p = argparse.ArgumentParser(prog="phone2act-view", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--url", default=os.environ.get("PHONE2ACT_URL", "127.0.0.1:50051"),
                   help="server: host:port, http(s)://host:port or unix:/path (default $PHONE2ACT_URL or %(default)s)")
    p.add_argument("--token", default=os.environ.get("PHONE2ACT_TOKEN"), help="bearer token (default $PHONE2ACT_TOKEN)")
    p.add_argument("--rate-hz", type=float, default=0.0,
                   help="observation and status rate (default: the dataset's fps, the recorder's rate)")
    p.add_argument("--camera", action="append", default=[], help="a camera to show (repeatable; default: all)")
    p.add_argument("--rgb", action="store_true",
                   help="ask for raw RGB frames instead of JPEG (no server-side encoding, a much larger .rrd)")
    p.add_argument("--config", type=Path,
                   help="the server's TOML config, to draw each arm's workspace box (the API does not expose it)")
    p.add_argument("--save", type=Path, metavar="PATH.rrd", help="save everything to this .rrd")
    p.add_argument("--save-episodes", type=Path, metavar="DIR",
                   help="write one episode_<index>.rrd per recorded episode, from its start to its stop")
    p.add_argument("--spawn", action="store_true", help="start a Rerun viewer and stream to it")
    p.add_argument("--connect", metavar="URL", help="stream to a running Rerun viewer (rerun+http://host:9876/proxy)")
    p.add_argument("--duration-s", type=float, help="stop after this long (default: until interrupted)")
    p.add_argument("-v", "--verbose", action="store_true", help="print every event")
    args = p.parse_args(argv)
    if not (args.save or args.save_episodes or args.spawn or args.connect):
        p.error("nothing to do: give --spawn, --connect URL, --save PATH.rrd and/or --save-episodes DIR")
    if args.rate_hz < 0 or args.rate_hz > 120:
        p.error(f"--rate-hz must be in (0, 120], got {args.rate_hz}")
    return args


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    logging.basicConfig(level=logging.INFO if args.verbose else logging.WARNING,
                        format="phone2act-view: %(message)s")
    workspaces = {}
    if args.config is not None:
        try:
            workspaces = workspaces_from_config(args.config)
        except (OSError, tomllib.TOMLDecodeError) as e:
            print(f"phone2act-view: cannot read the server config {args.config}: {e}", file=sys.stderr)
            return 2
    if args.save_episodes is not None:
        args.save_episodes.mkdir(parents=True, exist_ok=True)
    try:
        client = Client(args.url, token=args.token)
        rate_hz = args.rate_hz or client.dataset_info().fps or 20.0
    except Phone2ActError as e:
        print(f"phone2act-view: {e}", file=sys.stderr)
        return 1

    main_stream = None
    if args.save or args.spawn or args.connect:
        main_stream = rr.RecordingStream(APPLICATION_ID)
        main_stream.send_recording_name(f"phone2act {args.url}")
        if args.spawn:
            main_stream.spawn(connect=False)
        sinks = []
        if args.save:
            sinks.append(_session_file_sink(args.save))
        if args.spawn or args.connect:
            sinks.append(rr.GrpcSink(args.connect) if args.connect else rr.GrpcSink())
        main_stream.set_sinks(*sinks)
    view = View(client, Fanout(main_stream, args.save_episodes), rate_hz=rate_hz, cameras=args.camera,
                jpeg=not args.rgb, workspaces=workspaces)
    stop = threading.Event()
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: stop.set())
    code = 0
    started, cpu_started = time.monotonic(), _cpu_s()
    try:
        view.log_static()
        view.start()
        print(f"phone2act-view: {args.url} at {rate_hz:g} Hz", file=sys.stderr, flush=True)
        started, cpu_started = time.monotonic(), _cpu_s()  # the steady state, without imports and setup
        view.run(stop, args.duration_s)
    except Phone2ActError as e:
        print(f"phone2act-view: {e}", file=sys.stderr)
        code = 1
    except ConnectionError as e:
        print(f"phone2act-view: lost the server: {e}", file=sys.stderr)
        code = 1
    finally:
        view.close()
        client.close()
    s = view.stats
    wall_s = time.monotonic() - started
    print(f"phone2act-view: {s.observations} observations ({s.skipped_observations} skipped for newer ones), "
          f"{s.frames} camera frames, {s.statuses} status snapshots ({s.skipped_statuses} skipped), "
          f"{len(s.events)} events, {len(view.out.saved_episodes)} episode files; "
          f"cpu {_cpu_s() - cpu_started:.2f} s over {wall_s:.1f} s", file=sys.stderr)
    return code


if __name__ == "__main__":
    sys.exit(main())
