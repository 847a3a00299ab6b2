"""Serve every camera of a recording as a camera node (the firmware's HTTP API, contracts §1).

Each camera gets its own port (--port is the first, the next cameras +1, ...) or, with
--addresses, its own loopback address on --port. One line per camera is printed on stdout:
its name and stream URL. Frames are replayed with their recorded timing, device timestamps
and frame numbers (recorded drops stay gaps); /time answers on the same replayed device clock
as X-Timestamp, drifting as the recording's clock did. Corrupt or missing frame files are
skipped and counted. Ctrl-C stops.

  cubecam emulate --recording rec/ --loop
  cubecam emulate --images shots/ --fps 10 --port 8080
  cubecam emulate --recording rec/ --addresses auto --port 80
  cubecam emulate --recording rec/ --bandwidth 100k --latency 0.05 --jitter 0.02

It listens on 127.0.0.1 unless --bind or --addresses say otherwise, and warns when a camera is
reachable from the network.

Fault options mimic a Wi-Fi node, to test clients: --latency/--jitter (s, on every answer
and part), --drop-rate (frames lost at capture), --bandwidth (bytes/s per camera, suffix k
or M; a GS2200M manages roughly 100k), --disconnect-every (s), --stall-after/--stall-for
(s; a connection that goes silent), --corrupt-every N with --corrupt-kind jpeg|truncate.
--bump CAM:AT_S:DEG[:X,Y,Z] knocks a camera of a recording on its tripod AT_S seconds after the
start: from then on its frames are those of the camera turned by DEG degrees (docs/emulator.md).
"""

from __future__ import annotations

import argparse
import ipaddress
import json
import os
import sys
import time
from pathlib import Path

from cubecam.errors import EmulatorError

HELP = "serve a recording or a folder of JPEGs as camera nodes (with fault injection)"


def _bytes_per_s(text: str) -> float:
    scale = {"k": 1e3, "K": 1e3, "M": 1e6}.get(text[-1:], 1.0)
    number = text[:-1] if scale != 1.0 else text
    try:
        value = float(number) * scale
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a byte rate like 100000, 100k or 1.5M") from None
    return value


def add_arguments(p: argparse.ArgumentParser) -> None:
    src = p.add_mutually_exclusive_group(required=True)
    src.add_argument("--recording", metavar="REC", help="recording folder (contracts §3) to replay")
    src.add_argument("--images", metavar="DIR", help="folder of .jpg files, served as one camera in name order")
    p.add_argument("--fps", type=float, default=10.0, help="frame rate for --images (default 10)")
    p.add_argument("--name", help="camera name for --images (default: the folder's name)")
    p.add_argument("--bind", default="127.0.0.1", metavar="ADDR",
                   help="address to listen on (default 127.0.0.1; 0.0.0.0 serves the network)")
    p.add_argument("--port", type=int, default=8080,
                   help="first camera's port; the next cameras use port+1, ... (default 8080; 0 = any free port)")
    p.add_argument("--addresses", metavar="LIST",
                   help="one address per camera, all on --port: a comma list (127.0.0.11,127.0.0.12) "
                        "or 'auto' (--bind, then the next addresses)")
    p.add_argument("--loop", action="store_true", help="start over after the last frame (clocks and frame "
                                                       "numbers keep counting)")
    p.add_argument("--parent-pid", type=int, metavar="PID",
                   help="end when process PID (the one starting this emulator) ends, even by SIGKILL")
    p.add_argument("--exit-at-end", action="store_true", help="stop after the last frame (without --loop)")
    p.add_argument("--duration", type=float, metavar="S", help="stop after S seconds")
    p.add_argument("--ready-file", metavar="FILE",
                   help="once serving, write FILE (JSON): each camera's URL, the replay's period (s) and "
                        "clock_shift_s, what moves a recorded host time onto this machine's Unix time "
                        "(for programs that start the emulator and score against a recorded ground truth)")
    p.add_argument("--max-clients", type=int, default=4, metavar="N",
                   help="clients served at once per camera; more get 503 (default 4, as the node)")
    p.add_argument("--jpeg-quality", type=int, default=80, metavar="Q",
                   help="JPEG quality reported in /status (default 80)")
    f = p.add_argument_group("faults")
    f.add_argument("--latency", type=float, default=0.0, metavar="S",
                   help="added delay of every answer and stream part, seconds")
    f.add_argument("--jitter", type=float, default=0.0, metavar="S", help="random extra delay in [0, S] seconds")
    f.add_argument("--drop-rate", type=float, default=0.0, metavar="P",
                   help="probability a frame is lost at capture (gap in X-Frame)")
    f.add_argument("--bandwidth", type=_bytes_per_s, metavar="B",
                   help="bytes per second per camera, shared by its clients (e.g. 100k)")
    f.add_argument("--disconnect-every", type=float, metavar="S", help="cut each stream connection after S seconds")
    f.add_argument("--stall-after", type=float, metavar="S", help="a stream connection goes silent after S seconds")
    f.add_argument("--stall-for", type=float, metavar="S", help="... for S seconds (default: until the client leaves)")
    f.add_argument("--corrupt-every", type=int, metavar="N", help="corrupt every N-th part of a stream connection")
    f.add_argument("--corrupt-kind", choices=("jpeg", "truncate"), default="jpeg",
                   help="jpeg: garbage JPEG data, framing intact; truncate: part shorter than its Content-Length")
    f.add_argument("--seed", type=int, metavar="N", help="random seed for drops, jitter and garbage")
    f.add_argument("--bump", action="append", default=[], metavar="CAM:AT_S:DEG[:X,Y,Z]",
                   help="turn camera CAM by DEG degrees about its vertical image axis (or the axis X,Y,Z of its "
                        "frame: x right, y down, z forward) AT_S seconds after the start, as a knock on its tripod "
                        "would; repeatable (--recording only)")


def _addresses(text: str | None) -> list[str] | str | None:
    if not text or text == "auto":
        return text
    out = [a.strip() for a in text.split(",") if a.strip()]
    for a in out:
        try:
            ipaddress.ip_address(a)
        except ValueError:
            raise EmulatorError(f"--addresses: {a!r} is not an IP address (e.g. 127.0.0.11,127.0.0.12)") from None
    return out


def write_ready_file(path: str, emu) -> None:
    """The serving emulator's URLs and clock, written atomically (readers never see half a file)."""
    doc = {"urls": emu.urls, "period_s": emu.timeline.period_s,
           "clock_shift_s": emu.unix_time(emu.timeline.start_host_s) - emu.timeline.start_host_s}
    target = Path(path)
    tmp = target.with_name(target.name + ".tmp")
    try:
        tmp.write_text(json.dumps(doc, indent=1), encoding="utf-8")
        os.replace(tmp, target)
    except OSError as exc:
        raise EmulatorError(f"--ready-file {path}: cannot write: {exc.strerror}") from None


def run(args: argparse.Namespace) -> int:
    from cubecam.bump import parse_bump
    from cubecam.emulator import Emulator, Faults, skipped_summary

    if args.parent_pid is not None:
        from cubetrack.core.lifetime import end_with_parent

        end_with_parent(args.parent_pid)
    faults = Faults(latency_s=args.latency, jitter_s=args.jitter, drop_rate=args.drop_rate,
                    bandwidth_bytes_per_s=args.bandwidth, disconnect_every_s=args.disconnect_every,
                    stall_after_s=args.stall_after, stall_for_s=args.stall_for,
                    corrupt_every=args.corrupt_every, corrupt_kind=args.corrupt_kind, seed=args.seed)
    emu = Emulator(args.recording, images=args.images, fps=args.fps, name=args.name, host=args.bind,
                   port=args.port, addresses=_addresses(args.addresses),
                   loop=args.loop, faults=faults, max_clients=args.max_clients, jpeg_quality=args.jpeg_quality,
                   bumps=tuple(parse_bump(text) for text in args.bump))
    source = args.recording or args.images
    print(f"cubecam emulate: {source}: {len(emu.cameras)} camera(s), {skipped_summary(emu.skipped)} "
          "corrupt or missing frame(s)", file=sys.stderr)
    with emu:
        for name, url in emu.urls.items():
            print(f"{name} {url}", flush=True)
        if args.ready_file:
            write_ready_file(args.ready_file, emu)
        print("cubecam emulate: serving; Ctrl-C stops", file=sys.stderr, flush=True)
        deadline = time.monotonic() + args.duration if args.duration else None
        while True:
            if args.exit_at_end and not args.loop and emu.finished.is_set():
                time.sleep(0.2)  # let the last frame reach connected clients
                break
            if deadline is not None and time.monotonic() >= deadline:
                break
            time.sleep(0.05)
    return 0
