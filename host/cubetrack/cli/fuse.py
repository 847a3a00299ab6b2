"""Fuse the sightings `cubetrack worker` processes publish on Zenoh (cubetrack/sightings/*) into
DIR/<robot>.tum and DIR/<robot>.jsonl and the outputs the flags or the config's [[outputs]] ask
for (the same as `cubetrack track --live`; docs/scaling.md). A status line on stderr says which
cameras it hears from and which are silent.

By default the fusion listens on tcp/127.0.0.1:7450 (this machine only); --bus-listen
tcp/0.0.0.0:7450 takes workers on other hosts, --bus-connect joins a Zenoh router. Workers and
the fusion may start in any order. Runs for --duration seconds or until Ctrl-C.

Example:
  cubetrack fuse --config lab.toml --extrinsics extrinsics.toml --out out --foxglove
"""

from __future__ import annotations

import argparse
from pathlib import Path

from cubetrack.cli.outputs import add_output_arguments, output_sinks_from_args
from cubetrack.cli.track import add_update_extrinsics_argument
from cubetrack.cli.worker import add_bus_arguments, add_common_arguments, bus, load

HELP = "fuse the sightings of cubetrack worker processes -> TUM + JSONL per robot and outputs"


def add_arguments(p: argparse.ArgumentParser) -> None:
    add_common_arguments(p)
    p.add_argument("--out", required=True, type=Path, metavar="DIR", help="output folder")
    add_bus_arguments(p, "default: listen on tcp/127.0.0.1:7450")
    add_output_arguments(p)
    add_update_extrinsics_argument(p)


def run(args: argparse.Namespace) -> int:
    import sys

    from cubetrack.app.fusion_service import run_fusion
    from cubetrack.app.outputs import close_sinks
    from cubetrack.app.worker import fuse_endpoints

    config, settings, extrinsics = load(args)
    sinks = output_sinks_from_args(args, config)

    def status(text: str) -> None:
        print(f"fuse: {text}", file=sys.stderr, flush=True)

    print(f"fusing into {args.out}" + ("" if args.duration else " (Ctrl-C to stop)"), file=sys.stderr, flush=True)
    try:
        result = run_fusion(config, extrinsics, args.out, bus(args, fuse_endpoints), settings.stages,
                            duration_s=args.duration, status=status, status_every_s=args.status_every, sinks=sinks,
                            extrinsics_path=args.extrinsics, update_extrinsics=args.update_extrinsics)
    finally:
        close_sinks(sinks)
    print(f"{'interrupted; ' if result.interrupted else ''}fused for {result.duration_s:.1f} s: "
          f"refused messages {result.bad_messages}, duplicate frames dropped {result.duplicates}; heard from "
          + ", ".join(f"{c} ({n} sightings)" for c, n in result.heard.items() if n)
          + "".join(f"; never heard from {c}" for c, n in result.heard.items() if not n))
    for robot, (tum, jsonl) in result.outputs.items():
        print(f"{robot}: {result.stats.poses[robot]} poses -> {tum}, {jsonl}")
    return 0
