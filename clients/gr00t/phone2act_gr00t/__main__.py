"""python -m phone2act_gr00t --server 127.0.0.1:50051 --gr00t tcp://gpu-box:5555 --camera front"""

from __future__ import annotations

import argparse
import logging
import sys

from phone2act import IMAGE_NONE, IMAGE_RGB8, Client, Phone2ActError

from phone2act_gr00t import Embodiment, Gr00tAdapter, Gr00tClient, Gr00tError, Gr00tTimeout


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="phone2act_gr00t", description=__doc__)
    p.add_argument("--server", default="127.0.0.1:50051", help="phone2act gRPC address")
    p.add_argument("--token", default=None, help="phone2act bearer token")
    p.add_argument("--gr00t", default="tcp://127.0.0.1:5555", help="GR00T inference server (ZeroMQ)")
    p.add_argument("--gr00t-token", default=None, help="api_token of the GR00T server")
    p.add_argument("--arm", default="main")
    p.add_argument("--camera", action="append", default=[], help="camera to send as video.<camera> (repeat)")
    p.add_argument("--config", choices=["phone2act", "so100"], default="phone2act",
                   help="GR00T data config: a model fine-tuned on a phone2act dataset, or so100 keys")
    p.add_argument("--so100-action-scale", type=float, default=0.001)
    p.add_argument("--step-period", type=float, default=0.05, help="seconds between action steps")
    p.add_argument("--max-steps", type=int, default=16, help="steps of each 16-step chunk to execute")
    p.add_argument("--timeout", type=float, default=1.0, help="GR00T answer deadline, seconds")
    p.add_argument("--silence-timeout", type=float, default=1.0, help="arm holds after this long without a chunk")
    p.add_argument("--chunks", type=int, default=None, help="stop after this many chunks")
    args = p.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(levelname)s %(message)s")

    gr00t = Gr00tClient(args.gr00t, timeout_s=args.timeout, api_token=args.gr00t_token)
    try:
        gr00t.ping()
    except (Gr00tTimeout, Gr00tError) as e:
        print(f"phone2act_gr00t: {e}", file=sys.stderr)
        return 2
    try:
        with Client(args.server, token=args.token) as client, client.policy_session(
            [args.arm], observation_rate_hz=1.0 / args.step_period,
            image_encoding=IMAGE_RGB8 if args.camera else IMAGE_NONE, cameras=args.camera,
            policy_name="gr00t-n1.5", silence_timeout_s=args.silence_timeout,
        ) as session:
            layout = session.layouts[args.arm]
            if args.config == "so100":
                emb = Embodiment.so100(layout, args.camera[0] if args.camera else "front", args.so100_action_scale)
            else:
                emb = Embodiment.phone2act(layout, args.camera)
            adapter = Gr00tAdapter(session, gr00t, emb, arm=args.arm, step_period_s=args.step_period,
                                   max_steps=args.max_steps)
            stats = adapter.run(max_chunks=args.chunks)
            print(f"chunks {stats.chunks}, timeouts {stats.timeouts}, errors {stats.errors}")
    except Phone2ActError as e:
        print(f"phone2act_gr00t: {e}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        pass
    return 0


if __name__ == "__main__":
    sys.exit(main())
