"""python -m phone2act_gr00t --server 127.0.0.1:50051 --gr00t tcp://gpu-box:5555 --camera front --task "..." """

from __future__ import annotations

import argparse
import logging
import sys

from phone2act import IMAGE_NONE, IMAGE_RGB8, Client, Phone2ActError

from phone2act_gr00t import (
    MSGPACK_NUMPY,
    N15,
    N16,
    N16_SIM,
    N17,
    N17_SIM,
    NPY,
    ActionModeError,
    ChunkShapeError,
    Embodiment,
    EmbodimentMismatch,
    Gr00tAdapter,
    Gr00tClient,
    Gr00tError,
    Gr00tProtocolError,
    Gr00tTimeout,
    MissingTaskError,
    check_forced_wire,
)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="phone2act_gr00t", description=__doc__)
    p.add_argument("--server", default="127.0.0.1:50051", help="phone2act gRPC address")
    p.add_argument("--token", default=None, help="phone2act bearer token")
    p.add_argument("--gr00t", default="tcp://127.0.0.1:5555", help="GR00T inference server (ZeroMQ)")
    p.add_argument("--gr00t-token", default=None, help="api_token of the GR00T server")
    p.add_argument("--gr00t-version", choices=["auto", N15, N16, N16_SIM, N17, N17_SIM], default="auto",
                   help="GR00T wire dialect; auto asks the server's get_modality_config (n1.6-sim / n1.7-sim: a "
                        "server started with --use-sim-policy-wrapper; n1.7 speaks N1.6's shapes)")
    p.add_argument("--gr00t-codec", choices=["auto", NPY, MSGPACK_NUMPY], default="auto",
                   help="how arrays travel; auto follows the server's get_modality_config (msgpack-numpy: GR00T main "
                        "since 2026-05-26, the N1.7 General Release; npy: N1.5, N1.6 and the n1.7-release tag)")
    p.add_argument("--arm", action="append", default=[],
                   help="arm to drive (repeat for bimanual, in the dataset's order: --arm left --arm right)")
    p.add_argument("--camera", action="append", default=[], help="camera to send as video <camera> (repeat)")
    p.add_argument("--task", default=None,
                   help="language instruction; default: the task of the episode in progress (or the server's default)")
    p.add_argument("--config", choices=["phone2act", "so100"], default="phone2act",
                   help="GR00T data config: a model fine-tuned on a phone2act dataset, or so100 keys")
    p.add_argument("--so100-action-scale", type=float, default=0.001)
    p.add_argument("--step-period", type=float, default=0.05, help="seconds between action steps")
    p.add_argument("--max-steps", type=int, default=16, help="steps of each chunk to execute")
    p.add_argument("--timeout", type=float, default=1.0, help="GR00T answer deadline, seconds")
    p.add_argument("--silence-timeout", type=float, default=1.0, help="arm holds after this long without a chunk")
    p.add_argument("--chunks", type=int, default=None, help="stop after this many chunks")
    args = p.parse_args(argv)
    arms = args.arm or ["main"]
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(levelname)s %(message)s")

    gr00t = Gr00tClient(args.gr00t, timeout_s=args.timeout, api_token=args.gr00t_token, codec=args.gr00t_codec)
    try:
        if args.gr00t_version == "auto":
            wire, modality = gr00t.detect_wire()
        else:
            gr00t.ping()
            wire, modality = args.gr00t_version, gr00t.modality_config()
            check_forced_wire(wire, modality, args.gr00t)
    except (Gr00tTimeout, Gr00tError) as e:
        print(f"phone2act_gr00t: {e}", file=sys.stderr)
        return 2
    logging.info("GR00T server at %s speaks %s (%s arrays)", args.gr00t, wire, gr00t.codec)
    try:
        with Client(args.server, token=args.token) as client, client.policy_session(
            arms, observation_rate_hz=1.0 / args.step_period,
            image_encoding=IMAGE_RGB8 if args.camera else IMAGE_NONE, cameras=args.camera,
            policy_name=f"gr00t-{wire}", silence_timeout_s=args.silence_timeout,
        ) as session:
            if args.config == "so100":
                if len(arms) != 1:
                    raise EmbodimentMismatch("--config so100 drives one arm")
                emb = Embodiment.so100(session.layouts[arms[0]], args.camera[0] if args.camera else "front",
                                       args.so100_action_scale)
            else:
                emb = Embodiment.phone2act([session.layouts[a] for a in arms], args.camera)
            emb = emb.check_against(modality, wire)
            adapter = Gr00tAdapter(session, gr00t, emb, wire=wire, task=args.task, step_period_s=args.step_period,
                                   max_steps=args.max_steps, arm_states={a.arm: a for a in client.list_arms()})
            stats = adapter.run(max_chunks=args.chunks)
            print(f"chunks {stats.chunks}, timeouts {stats.timeouts}, errors {stats.errors}")
            if stats.chunks == 0 and stats.last_error:
                print(f"phone2act_gr00t: {stats.last_error}", file=sys.stderr)
                return 1
    except (Gr00tProtocolError, EmbodimentMismatch, ActionModeError, MissingTaskError, ChunkShapeError) as e:
        print(f"phone2act_gr00t: {e}", file=sys.stderr)
        return 2
    except Phone2ActError as e:
        print(f"phone2act_gr00t: {e}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        pass
    return 0


if __name__ == "__main__":
    sys.exit(main())
