"""Run the whole offline workflow on simulated cameras and print the scores:
simulate a session (the paper's arena: 3 cameras at 1.0 m, 30° tilt, the five-face cube),
calibrate the cameras on the empty-arena recording, track with each fusion method, and
evaluate against the simulator's ground truth.

Example:
  cubetrack demo --out cubetrack-demo --duration 20
"""

from __future__ import annotations

import argparse
from pathlib import Path

HELP = "simulate, calibrate, track and evaluate on simulated cameras"


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--out", type=Path, default=Path("cubetrack-demo"), metavar="DIR",
                   help="working folder (default ./cubetrack-demo); must not hold an earlier demo unless --force")
    p.add_argument("--force", action="store_true", help="replace an earlier demo in --out")
    p.add_argument("--duration", type=float, default=30.0, metavar="S", help="seconds of simulated tracking (default 30)")
    p.add_argument("--cameras", type=int, default=3, help="number of cameras (default 3)")
    p.add_argument("--height", type=float, default=1.0, metavar="M", help="camera height in metres (default 1.0)")
    p.add_argument("--tilt", type=float, default=30.0, metavar="DEG", help="camera tilt in degrees (default 30)")
    p.add_argument("--seed", type=int, default=1, help="random seed (default 1)")


def run(args: argparse.Namespace) -> int:
    import shutil

    from cubetrack.demo import run_demo
    from cubetrack.errors import SimulationError
    from cubetrack.progress import StderrProgress
    from cubetrack.simulate import SimulationParams

    if args.out.exists() and any(args.out.iterdir()):
        if not args.force:
            raise SimulationError(f"{args.out}: not empty; choose another --out or pass --force")
        if not (args.out / "rec" / "recording.json").exists():
            raise SimulationError(f"{args.out}: not an earlier demo folder; refusing to delete it")
        shutil.rmtree(args.out)
    sim = SimulationParams(cameras=args.cameras, height_m=args.height, tilt_deg=args.tilt,
                           duration_s=args.duration, seed=args.seed)
    result = run_demo(args.out, sim, progress=StderrProgress())
    print(f"\ncalibration ({args.out / 'extrinsics.toml'}), error against the true camera poses:")
    for cam, (pos_m, rot_deg) in result.calibration_errors.items():
        print(f"  {cam}: position {pos_m * 100:.2f} cm, rotation {rot_deg:.3f}°")
    from cubetrack.cli.evaluate import format_table

    print(f"\ntracking ({args.out / 'track'}), scored against {args.out / 'rec' / 'ground_truth.tum'}:")
    print(format_table(result.scores))
    return 0
