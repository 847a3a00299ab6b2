"""Fuse the sightings `cubetrack worker` processes publish on Zenoh (cubetrack/sightings/**, and under
cubetrack/shard-sightings/<this fusion>/* those of the robots it claims) into
DIR/<robot>.tum and DIR/<robot>.jsonl and the outputs the flags or the config's [[outputs]] ask
for (the same as `cubetrack track --live`; docs/scaling.md). A status line on stderr says which
cameras it hears from and which are silent.

By default the fusion listens on tcp/127.0.0.1:7450 (this machine only); --bus-listen
tcp/0.0.0.0:7450 takes workers on other hosts, --bus-connect joins a Zenoh router. Workers and
the fusion may start in any order. Runs for --duration seconds or until Ctrl-C.

A fleet's fusion can be split by robot over several processes (shards, on one host or many): each
fuses, receives and decodes only its robots' sightings. --robots a,b names them; --shard claims a
share of the robots no other fusion fuses and takes over those of a shard that stops or dies
(within about 3 s, the bus's lease). Each shard has its own --out and outputs, with only its robots'
poses in them.

Examples:
  cubetrack fuse --config lab.toml --extrinsics extrinsics.toml --out out --foxglove
  cubetrack fuse --config lab.toml --extrinsics extrinsics.toml --out out1 --shard
  cubetrack fuse --config lab.toml --extrinsics extrinsics.toml --out out2 --shard \\
      --bus-listen tcp/127.0.0.1:7451 --bus-connect tcp/127.0.0.1:7450
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
    p.add_argument("--robots", default="", metavar="A,B",
                   help="fuse only these robots (a shard of a fleet; default: every robot of the config)")
    p.add_argument("--shard", action="store_true",
                   help="claim a share of the robots (of --robots, else of every robot) that no other fusion "
                        "fuses, and take over those of a shard that leaves (docs/scaling.md)")
    add_bus_arguments(p, "default: listen on tcp/127.0.0.1:7450")
    add_output_arguments(p)
    add_update_extrinsics_argument(p)


def run(args: argparse.Namespace) -> int:
    import sys

    from cubetrack.app.fusion_service import chosen_robots, run_fusion
    from cubetrack.app.outputs import close_sinks
    from cubetrack.app.worker import fuse_endpoints

    config, settings, extrinsics = load(args)
    robots = chosen_robots(config, [r.strip() for r in args.robots.split(",") if r.strip()])
    sinks = output_sinks_from_args(args, config)

    def status(text: str) -> None:
        print(f"fuse: {text}", file=sys.stderr, flush=True)

    print(f"fusing into {args.out}" + ("" if args.duration else " (Ctrl-C to stop)"), file=sys.stderr, flush=True)
    try:
        result = run_fusion(config, extrinsics, args.out, bus(args, fuse_endpoints), settings.stages,
                            duration_s=args.duration, status=status, status_every_s=args.status_every, sinks=sinks,
                            extrinsics_path=args.extrinsics, robots=robots if args.robots else (),
                            shard=args.shard, update_extrinsics=args.update_extrinsics)
    finally:
        close_sinks(sinks)
    print(f"{'interrupted; ' if result.interrupted else ''}fused for {result.duration_s:.1f} s: "
          f"refused messages {result.bad_messages}, duplicate frames dropped {result.duplicates}; heard from "
          + ", ".join(f"{c} ({n} sightings)" for c, n in result.heard.items() if n)
          + "".join(f"; never heard from {c}" for c, n in result.heard.items() if not n))
    for robot, (tum, jsonl) in result.outputs.items():
        print(f"{robot}: {result.stats.poses[robot]} poses -> {tum}, {jsonl}")
    if args.shard:
        print("  claims: " + (", ".join(f"{'took' if taken else 'gave up'} {robot} at {at_s:.2f} s"
                                         for at_s, robot, taken in result.claims) or "none"))
    return 0
