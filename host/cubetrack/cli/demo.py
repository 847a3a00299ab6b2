"""Run the whole workflow on simulated cameras and print the scores:
simulate a session (the paper's arena: 3 cameras at 1.0 m, 30° tilt, the five-face cube),
calibrate the cameras on the empty-arena recording, serve the session with the camera
emulator on 127.0.0.1 (the firmware's HTTP API) and track it live over HTTP for its whole
duration, then evaluate against the simulator's ground truth (moved onto the live clock).
The offline replay of the same recording with each fusion method (the paper's mean, weighted
and gaussian, and the filter) is scored too, for comparison. --offline skips the live part.

Example:
  cubetrack demo --out cubetrack-demo --duration 20
"""

from __future__ import annotations

import argparse
from pathlib import Path

from cubetrack.cli.dashboard import add_dashboard, add_dashboard_argument
from cubetrack.cli.outputs import add_output_arguments, output_sinks_from_args
from cubetrack.simulate.params import SimulationParams

HELP = "simulate, calibrate, track live over HTTP (emulated cameras) and evaluate"


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--out", type=Path, default=Path("cubetrack-demo"), metavar="DIR",
                   help="working folder (default ./%(default)s); must not hold an earlier demo unless --force")
    p.add_argument("--force", action="store_true", help="replace an earlier demo in --out")
    p.add_argument("--duration", type=float, default=20.0, metavar="S",
                   help="seconds of simulated tracking, also the length of the live session (default %(default)s)")
    p.add_argument("--offline", action="store_true", help="skip the live part: replay the recording offline only")
    scene = SimulationParams()  # the simulator's arena is the demo's (the paper's 1.0 m setup)
    p.add_argument("--cameras", type=int, default=scene.cameras, help="number of cameras (default %(default)s)")
    p.add_argument("--height", type=float, default=scene.height_m, metavar="M",
                   help="camera height in metres (default %(default)s)")
    p.add_argument("--tilt", type=float, default=scene.tilt_deg, metavar="DEG",
                   help="camera tilt in degrees (default %(default)s)")
    p.add_argument("--seed", type=int, default=1, help="random seed (default %(default)s)")
    add_output_arguments(p)
    add_dashboard_argument(p)


def run(args: argparse.Namespace) -> int:
    import shutil
    import sys

    from cubetrack.app.demo import run_demo
    from cubetrack.core.errors import SimulationError
    from cubetrack.core.progress import StderrProgress

    if args.offline and args.dashboard is not None:
        raise SimulationError("--dashboard shows the live session: not with --offline")
    if args.out.exists() and any(args.out.iterdir()):
        if not args.force:
            raise SimulationError(f"{args.out}: not empty; choose another --out or pass --force")
        if not (args.out / "rec" / "recording.json").exists():
            raise SimulationError(f"{args.out}: not an earlier demo folder; refusing to delete it")
        shutil.rmtree(args.out)
    sim = SimulationParams(cameras=args.cameras, height_m=args.height, tilt_deg=args.tilt,
                           duration_s=args.duration, seed=args.seed)
    def status(st) -> None:
        print(f"live: {st.line()}", file=sys.stderr, flush=True)

    from cubetrack.app.outputs import close_sinks
    sinks = add_dashboard(args, output_sinks_from_args(args, robots=sim.robot_names),
                          out_dir=args.out / "live" / "track")
    try:
        result = run_demo(args.out, sim, progress=StderrProgress(), live=not args.offline, status=status, sinks=sinks)
    finally:
        close_sinks(sinks)
    print(f"\ncalibration ({args.out / 'extrinsics.toml'}), error against the true camera poses:")
    for cam, (pos_m, rot_deg) in result.calibration_errors.items():
        print(f"  {cam}: position {pos_m * 100:.2f} cm, rotation {rot_deg:.3f}°")
    from cubetrack.cli.evaluate import format_table

    if result.live is not None:
        live = result.live
        lr = live.result
        latency = "-" if lr.latency_s is None else f"{lr.latency_s * 1000:.0f} ms"
        cams = ", ".join(f"{n} {c.frames} frames" + (f" ({c.bad} bad)" if c.bad else "") for n, c in lr.cameras.items())
        print(f"\nlive tracking over HTTP ({args.out / 'live'}): emulated cameras on 127.0.0.1, {lr.duration_s:.1f} s, "
              f"median latency {latency}; {cams}")
        if live.score is None:
            print(f"{lr.ended_by}: the live session stopped early; its poses are saved in "
                  f"{args.out / 'live' / 'track'} "
                  f"(run.json there says how it ended); not scored, and the offline replay was not run",
                  file=sys.stderr)
            return 130
        print(f"scored against {live.ground_truth_path} (the ground truth moved onto the live clock by "
              f"{live.clock_shift_s:+.3f} s):")
        print(format_table({f"live {live.method}": live.score}))
    print(f"\noffline replay of the same recording ({args.out / 'track'}), each fusion method, "
          f"scored against {args.out / 'rec' / 'ground_truth.tum'}:")
    print(format_table({f"offline {name}": score for name, score in result.scores.items()}))
    return 0
