"""Record the cameras of a tracker config into a recording folder (contracts §3): every camera's
MJPEG stream (its url) as JPEGs with index.csv, its /time round trips as clock.csv,
recording.json with the source URLs, camera_info/ copied from the config's camera_info where it
names one, and run.json (version, the [source] parameters, the config). `cubetrack track
--recording` and `cubecam emulate` replay the result.

Runs for --duration seconds, or until Ctrl-C; either way everything received so far is kept
(rows are flushed as they are written). Lost streams are reconnected; a status line on stderr
shows frames/s, bad parts, reconnects and clock samples. Reading is tuned by the config's
[source] section (timeouts, back-off, clock poll period).

Example:
  cubetrack record --config lab.toml --out sessions/run1 --duration 60
"""

from __future__ import annotations

import argparse
from pathlib import Path

HELP = "record the config's live cameras into a recording folder"


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--config", required=True, type=Path, help="tracker config TOML (cameras with url)")
    p.add_argument("--out", required=True, type=Path, metavar="REC",
                   help="recording folder to write (must not hold one)")
    p.add_argument("--duration", type=float, metavar="S", help="stop after this many seconds (default: until Ctrl-C)")


def run(args: argparse.Namespace) -> int:
    import sys

    from cubetrack.app.config import load_config
    from cubetrack.app.live import live_camera_urls, record_live
    from cubetrack.core.errors import ConfigError

    if args.duration is not None and not args.duration > 0:
        raise ConfigError(f"--duration must be a positive number of seconds, got {args.duration}")
    config, settings = load_config(args.config)
    live_camera_urls(config)  # a config without urls fails before anything is written

    def status(s) -> None:
        print(f"record: {s.line()}", file=sys.stderr, flush=True)

    print(f"recording into {args.out}" + ("" if args.duration else " (Ctrl-C to stop)"), file=sys.stderr, flush=True)
    result = record_live(config, args.out, settings.source, duration_s=args.duration, status=status)
    print(f"{'interrupted; ' if result.interrupted else ''}recorded {result.duration_s:.1f} s into {result.recording}")
    for name, s in result.cameras.items():
        bad = "".join(f", {n} {why}" for why, n in sorted(s.bad_parts.items()))
        print(f"  {name}: {s.frames} frames, {s.clock_samples} clock samples, {s.reconnects} reconnects{bad}")
    return 0
