"""Read some of the config's cameras live and publish each frame's sighting (corners, capture
time, the camera's clock mapping and health; never images) on Zenoh under
cubetrack/shard-sightings/<fusion>/<worker> (the robots a fusion claims, one message per fusion and pass) or
cubetrack/sightings/<worker>/<robot> (a robot no fusion claims; cubetrack/sightings/<camera> for a frame
without any), for `cubetrack fuse` (docs/scaling.md).

Without --cameras the worker claims its share of the cameras no other worker reads (automatic
assignment through Zenoh liveliness tokens: start as many workers as you like, each takes a fair
share; the cameras of a worker that stops or crashes are taken over by the others within a
fraction of a second, those of one that hangs or drops off the network within about 3 s, the
bus's lease). With --cameras it reads exactly those.

By default the worker connects to a fusion on this machine (tcp/127.0.0.1:7450) and keeps trying
until it is there; --bus-connect names another host's fusion or a Zenoh router. Frames are
stamped with their capture time through each camera's /time round trips. Runs for --duration
seconds or until Ctrl-C.

Examples:
  cubetrack worker --config lab.toml --extrinsics extrinsics.toml
  cubetrack worker --config lab.toml --extrinsics extrinsics.toml --cameras cam1,cam2
  cubetrack worker --config lab.toml --extrinsics extrinsics.toml --cameras cam3 --bus-connect tcp/10.0.0.5:7450
"""

from __future__ import annotations

import argparse
from pathlib import Path

HELP = "publish the sightings of some cameras on Zenoh for cubetrack fuse"


def add_bus_arguments(p: argparse.ArgumentParser, default: str) -> None:
    """The Zenoh session of the sighting bus (shared with cubetrack fuse)."""
    g = p.add_argument_group("sighting bus (Zenoh, docs/scaling.md)")
    g.add_argument("--bus-connect", action="append", default=[], metavar="LOCATOR",
                   help=f"connect to this Zenoh peer or router (repeatable; {default})")
    g.add_argument("--bus-listen", action="append", default=[], metavar="LOCATOR",
                   help="listen here, e.g. tcp/0.0.0.0:7450 for every interface (repeatable)")
    g.add_argument("--bus-mode", default="peer", choices=("peer", "client"), help="Zenoh mode (default peer)")
    g.add_argument("--bus-config", type=Path, metavar="FILE", help="a whole Zenoh JSON5 config instead")


def add_common_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--config", required=True, type=Path, help="tracker config TOML (cameras with url and camera_info)")
    p.add_argument("--extrinsics", type=Path, help="camera poses from cubetrack calibrate (TOML)")
    p.add_argument("--uncalibrated", action="store_true",
                   help="no extrinsics: each frame's own world-marker pose (the paper's uncalibrated mode)")
    p.add_argument("--duration", type=float, metavar="S", help="stop after this many seconds (default: Ctrl-C)")
    p.add_argument("--status-every", type=float, default=2.0, metavar="S",
                   help="seconds between status lines (default %(default)s)")


def add_arguments(p: argparse.ArgumentParser) -> None:
    add_common_arguments(p)
    p.add_argument("--cameras", default="", metavar="A,B",
                   help="the cameras this worker reads, by name (default: a share of the cameras no other "
                        "worker reads, claimed automatically)")
    add_bus_arguments(p, "default: the fusion at tcp/127.0.0.1:7450")


def load(args: argparse.Namespace):
    """The config, resolved settings and extrinsics the arguments name (checked)."""
    import dataclasses

    from cubetrack.app.config import load_config
    from cubetrack.app.tracker import CameraPoseSource
    from cubetrack.core.errors import ConfigError
    from cubetrack.core.params import params_with
    from cubetrack.io.config import read_extrinsics

    if args.duration is not None and not args.duration > 0:
        raise ConfigError(f"--duration must be a positive number of seconds, got {args.duration}")
    if not args.status_every > 0:
        raise ConfigError(f"--status-every must be a positive number of seconds, got {args.status_every}")
    config, settings = load_config(args.config)
    if args.uncalibrated:
        settings = dataclasses.replace(settings, track=params_with(
            settings.track, "--uncalibrated", camera_poses=CameraPoseSource.WORLD_MARKER))
        return config, settings, None
    if args.extrinsics is None:
        raise ConfigError("give --extrinsics (from cubetrack calibrate) or --uncalibrated")
    return config, settings, read_extrinsics(args.extrinsics)


def bus(args: argparse.Namespace, make):
    return make(tuple(args.bus_listen), tuple(args.bus_connect), args.bus_mode, args.bus_config)


def run(args: argparse.Namespace) -> int:
    import sys

    from cubetrack.app.live import live_camera_urls, live_intrinsics
    from cubetrack.app.worker import chosen_cameras, run_worker, worker_endpoints

    config, settings, extrinsics = load(args)
    cameras = [c.strip() for c in args.cameras.split(",") if c.strip()]
    every = chosen_cameras(config, cameras)
    live_camera_urls(config), live_intrinsics(config)  # a bad config fails before anything starts

    def status(text: str) -> None:
        print(f"worker: {text}", file=sys.stderr, flush=True)

    print((f"worker: {', '.join(cameras)}" if cameras else f"worker: a share of {', '.join(every)}")
          + ("" if args.duration else " (Ctrl-C to stop)"), file=sys.stderr, flush=True)
    result = run_worker(config, extrinsics, cameras, bus(args, worker_endpoints), settings.stages, settings.source,
                        duration_s=args.duration, status=status, status_every_s=args.status_every)
    s = result.stats
    print(f"{'interrupted; ' if result.interrupted else ''}worked {result.duration_s:.1f} s: frames {s.frames}, "
          f"published {result.published}, before their camera's clock was known {s.frames_before_clock_sync}")
    for name, c in result.cameras.items():
        print(f"  {name}: {c.frames} frames, {c.dropped} dropped (worker behind), {c.reconnects} reconnects")
    if not cameras:
        print("  claims: " + ", ".join(f"{'took' if taken else 'gave up'} {camera} at {at_s:.2f} s"
                                       for at_s, camera, taken in result.claims))
    return 0
