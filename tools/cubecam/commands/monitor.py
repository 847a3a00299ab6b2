"""Show a node's log lines from its USB serial port (without resetting it).

Improv frames on the same port are shown as one bracketed line each. Ctrl-C stops.

  cubecam monitor /dev/ttyUSB0
"""

from __future__ import annotations

import argparse
import sys
import time

HELP = "show a node's log over USB serial"


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("device", metavar="DEV", help="the board's serial device, e.g. /dev/ttyUSB0")
    p.add_argument("--duration", type=float, metavar="S", help="stop after S seconds")


def describe_frame(frame) -> str:
    from cubecam import improv
    from cubecam.errors import ImprovError

    try:
        if frame.type == improv.FrameType.CURRENT_STATE:
            state = improv.decode_state(frame)
            return f"[improv] state {getattr(state, 'name', state)}"
        if frame.type == improv.FrameType.ERROR_STATE:
            err = improv.decode_error(frame)
            return f"[improv] error {getattr(err, 'name', err)}"
        if frame.type == improv.FrameType.RPC_RESULT:
            command, strings = improv.decode_rpc_result(frame)
            return f"[improv] result of command {command}: {', '.join(strings)}"
        if frame.type == improv.FrameType.RPC:
            command, _ = improv.decode_rpc(frame)
            return f"[improv] command {command}"  # strings left out: they may hold a password
    except ImprovError as exc:
        return f"[improv] malformed frame: {exc}"
    return f"[improv] frame type {frame.type}"


def run(args: argparse.Namespace) -> int:
    from cubecam.link import NodeLink

    def show(text: str) -> None:
        print(text, flush=True)

    print(f"cubecam monitor: {args.device}: 115200 baud; Ctrl-C stops", file=sys.stderr, flush=True)
    deadline = time.monotonic() + args.duration if args.duration else None
    with NodeLink.open(args.device, on_log=show) as node:
        while deadline is None or time.monotonic() < deadline:
            node.pump()
            while node.frames:
                show(describe_frame(node.frames.popleft()))
    return 0
