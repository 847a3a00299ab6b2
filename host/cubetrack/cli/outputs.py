"""The output flags shared by ``cubetrack track`` and ``cubetrack demo``.

Each flag adds one output, as a ``[[outputs]]`` table of the config would (and replaces a
config output of the same type). Servers listen on loopback unless an address is given.
"""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path


def add_output_arguments(p: argparse.ArgumentParser) -> None:
    """The output flags (see the module doc)."""
    g = p.add_argument_group("outputs (docs/outputs.md)")
    g.add_argument("--zenoh", action="store_true", help="publish JSON on Zenoh under cubetrack/** (docs/zenoh.md)")
    g.add_argument("--ros2", action="store_true",
                   help="publish ROS 2 topics (PoseStamped, Odometry, /tf, /tf_static) over Zenoh (docs/ros2.md)")
    g.add_argument("--ros-distro", default="jazzy", metavar="DISTRO",
                   help="--ros2: humble | iron | jazzy | kilted | rolling (type hashes; default jazzy)")
    g.add_argument("--ros-domain-id", type=int, metavar="N",
                   help="--ros2: ROS_DOMAIN_ID (default: the environment's, else 0)")
    g.add_argument("--ros-bridge", action="store_true",
                   help="--ros2: for zenoh-bridge-ros2dds (ROS 2 on DDS) instead of rmw_zenoh")
    g.add_argument("--zenoh-connect", action="append", default=[], metavar="LOCATOR",
                   help="--zenoh/--ros2: connect to this Zenoh router or peer, e.g. tcp/192.168.1.10:7447 (repeatable)")
    g.add_argument("--zenoh-listen", action="append", default=[], metavar="LOCATOR",
                   help="--zenoh/--ros2: listen here instead (tcp/0.0.0.0:7447 = every interface)")
    g.add_argument("--zenoh-config", type=Path, metavar="FILE", help="--zenoh/--ros2: a whole Zenoh JSON5 config")
    g.add_argument("--vrpn", nargs="?", const="", metavar="ADDR:PORT",
                   help="serve VRPN trackers <robot>@ADDR:PORT (default 127.0.0.1:3883) (docs/vrpn.md)")
    g.add_argument("--foxglove", nargs="?", const="", metavar="ADDR:PORT",
                   help="serve Foxglove over WebSocket (default 127.0.0.1:8765) (docs/foxglove.md)")
    g.add_argument("--mcap", type=Path, metavar="FILE", help="record the Foxglove channels to FILE (.mcap)")


def flag_output_specs(args: argparse.Namespace):
    """The outputs the flags ask for, as :class:`cubetrack.app.outputs.OutputSpec`."""
    from cubetrack.app.outputs import OutputSpec

    zenoh = {k: v for k, v in (("listen", args.zenoh_listen), ("connect", args.zenoh_connect),
                               ("zenoh_config", str(args.zenoh_config) if args.zenoh_config else None)) if v}
    tables = []
    if args.zenoh:
        tables.append(("--zenoh", {"type": "zenoh", **zenoh}))
    if args.ros2:
        ros = {"distro": args.ros_distro, "profile": "bridge" if args.ros_bridge else "rmw_zenoh"}
        if args.ros_domain_id is not None:
            ros["domain_id"] = args.ros_domain_id
        tables.append(("--ros2", {"type": "ros2", **ros, **zenoh}))
    if args.vrpn is not None:
        tables.append(("--vrpn", {"type": "vrpn", "address": args.vrpn}))
    if args.foxglove is not None:
        tables.append(("--foxglove", {"type": "foxglove", "address": args.foxglove}))
    if args.mcap is not None:
        tables.append(("--mcap", {"type": "mcap", "path": str(args.mcap)}))
    return [OutputSpec(table, Path.cwd(), flag) for flag, table in tables]


def output_sinks_from_args(args: argparse.Namespace, config=None, robots: tuple[str, ...] = ()) -> list:
    """Start the outputs of the config (``[[outputs]]``) and of the flags; ROS_DOMAIN_ID from the
    environment is the default domain; ``robots`` (default: the config's) are announced from the start."""
    from cubetrack.app.outputs import config_output_specs, merge_outputs, start_outputs
    from cubetrack.core.errors import ConfigError

    domain = os.environ.get("ROS_DOMAIN_ID", "0")
    if not domain.isdigit():
        raise ConfigError(f"ROS_DOMAIN_ID must be a number, got {domain!r}")
    specs = merge_outputs(config_output_specs(config) if config is not None else [], flag_output_specs(args))
    robots = robots or (tuple(r.name for r in config.robots) if config is not None else ())
    sinks = start_outputs(specs, int(domain), robots)
    for sink in sinks:
        print(f"output: {sink.where}", file=sys.stderr, flush=True)
    return sinks
