"""Serve a web page showing the config's cameras and robots live, with the guided calibration.

Reads every camera of the config (its url and camera_info, as track --live does) and serves one
page, by default on http://127.0.0.1:8770/:

  cameras     each camera's newest frame (scaled down) with the markers it sees, their ids and
              cube faces, the predicted cube and the world axes; under it frames/s, frames
              dropped, transfer latency, clock offset and drift, reconnects, last error and JPEG
              size. A camera that cannot be reached stays on the page; one that stops sending
              turns red within about a second and says why;
  top view    the floor with the world marker, each camera's position and field of view, each
              robot's pose, its trail and which cameras see it;
  calibration check that every camera sees the world marker, collect samples, each camera's
              result (spread, reprojection error) with advice when it is poor, save the
              extrinsics; then drive the robot around and refine (how far each camera moved).
              It runs what `cubetrack calibrate` runs, on recordings it makes;
  session     start/stop recording; the trajectory files to download.

Everything the page shows is also served as JSON (the endpoints: docs/dashboard.md).

Files go to --out: sessions/<time>/ (<robot>.tum and .jsonl, the frames in recording/) and
calibration/<time>/ (world/ and drive/ recordings, extrinsics.toml, refined.toml, run records).
"Save" writes --extrinsics (default OUT/extrinsics.toml; an earlier file is kept beside it with
its time); a file already there is loaded at the start. Until every camera is calibrated the
robots are tracked in the paper's uncalibrated mode (each frame's world-marker pose).

The page is served on 127.0.0.1 only unless --bind says otherwise; then anyone who can reach it
can start recordings and save extrinsics, and a warning says so. Runs until Ctrl-C (or --duration).
track --live and demo take --dashboard [ADDR:PORT] to show their session on the same page.

Examples:
  cubetrack dashboard --config lab.toml
  cubetrack dashboard --config lab.toml --extrinsics extrinsics.toml --port 8080
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

HELP = "serve the web dashboard: camera health and views, top view, guided calibration, recording"
DEFAULT_ADDRESS = ("127.0.0.1", 8770)


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--config", required=True, type=Path, help="tracker config TOML (cameras with url and camera_info)")
    p.add_argument("--extrinsics", type=Path, metavar="FILE",
                   help="camera poses: loaded when the file exists, written by the page's Save (default "
                        "OUT/extrinsics.toml)")
    p.add_argument("--out", type=Path, default=Path("cubetrack-dashboard"), metavar="DIR",
                   help="folder for recorded sessions and calibrations (default ./%(default)s)")
    p.add_argument("--bind", default=DEFAULT_ADDRESS[0], metavar="ADDR",
                   help="address to serve on (default %(default)s; 0.0.0.0 serves the network)")
    p.add_argument("--port", type=int, default=DEFAULT_ADDRESS[1], metavar="N",
                   help="port (default %(default)s; 0 = any free port)")
    p.add_argument("--duration", type=float, metavar="S", help="stop after this many seconds (default: Ctrl-C)")


def add_dashboard_argument(p: argparse.ArgumentParser) -> None:
    """``--dashboard [ADDR:PORT]`` for commands that run a live session (track --live, demo)."""
    p.add_argument("--dashboard", nargs="?", const="", metavar="ADDR:PORT",
                   help="also show the session in the web dashboard (default 127.0.0.1:8770) (docs/dashboard.md)")


def add_dashboard(args: argparse.Namespace, sinks: list, config=None, out_dir: Path | None = None,
                  params=None) -> list:
    """``sinks`` and, with ``--dashboard``, a dashboard of the session (its page lists the
    trajectory files of ``out_dir`` for download), run with ``params`` (the config's
    ``[dashboard]`` as the command resolved it; None: the defaults). When the dashboard cannot
    start, ``sinks`` are closed again before the error goes on."""
    if getattr(args, "dashboard", None) is None:
        return sinks
    from cubetrack.app.outputs import close_sinks
    from cubetrack.sink.dashboard.server import TRAJECTORY_FILES, DashboardServer, DashboardSink, folder_downloads
    from cubetrack.sink.dashboard.state import DashboardParams
    from cubetrack.sink.output_params import parse_address

    try:
        host, port = parse_address(args.dashboard, DEFAULT_ADDRESS, "--dashboard")
        urls = {c.name: c.url for c in config.cameras} if config is not None else None
        server = DashboardServer(host, port, params or DashboardParams(), camera_urls=urls)
    except BaseException:
        close_sinks(sinks)
        raise
    if out_dir is not None:
        server.set_downloads(lambda: folder_downloads(Path(out_dir), "this session", TRAJECTORY_FILES))
    server.state.set_panel("recording", {"mode": args.command, "recording": getattr(args, "record", None) is not None,
                                         "since_s": None, "out_dir": str(out_dir) if out_dir else None,
                                         "recording_dir": str(args.record) if getattr(args, "record", None) else None,
                                         "message": f"the session of cubetrack {args.command}", "controls": False,
                                         "actions": []})
    sink = DashboardSink(server, owns_server=True)
    print(f"output: {sink.where}", file=sys.stderr, flush=True)
    return [*sinks, sink]


def run(args: argparse.Namespace) -> int:
    from cubetrack.app.config import load_config
    from cubetrack.app.dashboard import DashboardApp
    from cubetrack.app.live import live_camera_urls, live_intrinsics
    from cubetrack.core.errors import ConfigError
    from cubetrack.io.config import read_extrinsics
    from cubetrack.sink.dashboard.server import DashboardServer

    if args.duration is not None and not args.duration > 0:
        raise ConfigError(f"--duration must be a positive number of seconds, got {args.duration}")
    if not 0 <= args.port <= 65535:
        raise ConfigError(f"--port must be 0..65535, got {args.port}")
    config, settings = load_config(args.config)
    urls = live_camera_urls(config)
    live_intrinsics(config)  # a camera without intrinsics fails here, before anything starts
    extrinsics_path = args.extrinsics or args.out / "extrinsics.toml"
    extrinsics = read_extrinsics(extrinsics_path) if extrinsics_path.exists() else None
    if extrinsics is not None:
        unknown = sorted(set(extrinsics) - set(urls))
        if unknown:
            raise ConfigError(f"{extrinsics_path}: camera(s) {', '.join(unknown)} are not in {args.config}")
    server = DashboardServer(args.bind, args.port, settings.dashboard, camera_urls=urls)
    try:
        app = DashboardApp(config, settings, server, args.out, extrinsics_path, extrinsics)
        calibrated = f"{len(extrinsics)} of {len(urls)} cameras calibrated ({extrinsics_path})" if extrinsics else \
            f"not calibrated yet (Save writes {extrinsics_path})"
        print(f"dashboard: {server.url} ({len(urls)} cameras, {calibrated}; "
              f"{'Ctrl-C to stop' if args.duration is None else f'for {args.duration:g} s'})",
              file=sys.stderr, flush=True)
        app.run(args.duration)
    finally:
        server.close()
    return 0
