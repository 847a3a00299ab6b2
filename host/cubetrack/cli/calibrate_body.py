"""Calibrate where each marker sits on a robot's body from a recording of it driving about.

A hand-built cube is not its layout file: markers are glued a millimetre or two off, turned by
a degree, printed slightly small. From the body's sightings in a tracking recording REC (the
robot driving where several cameras see it, a minute is plenty) a bundle adjustment estimates
each marker's pose on the body and its size, with the nominal layout (the config's [[robots]]
layout) as a prior; the cameras are refined alongside, held near --extrinsics. The calibrated
layout is written to --out in the layout format (contracts §4), in the body frame that fits the
nominal layout best; point the robot's [[robots]] layout at it. A run record goes beside it
(body.toml -> body.run.json). Settings: the config's [bundle_adjustment] section (body_* sigmas,
refine_intrinsics; `cubetrack defaults --section bundle_adjustment`). See docs/calibration.md.

Prints one line per marker: corners seen, RMS reprojection error, and how far the result is
from the nominal layout (shift, turn, size); with --truth (e.g. a simulation's true_cube.toml)
also the error of each marker's placement. A marker never seen by two cameras at once, or seen
in fewer than 10 frames, is named in a warning: drive where the cameras see it more.

Example:
  cubetrack calibrate-body --config rec/config.toml --extrinsics extrinsics.toml --recording rec \\
      --out body.toml --truth rec/true_cube.toml
"""

from __future__ import annotations

import argparse
from pathlib import Path

HELP = "calibrate each marker's pose on a robot's body from a tracking recording"


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--config", required=True, type=Path, metavar="CFG", help="tracker config (TOML)")
    p.add_argument("--extrinsics", required=True, type=Path, metavar="EXTRINSICS",
                   help="camera extrinsics (cubetrack calibrate; not yet --refine-with, which takes the nominal "
                   "layout as exact: refine afterwards with the calibrated one)")
    p.add_argument("--recording", required=True, type=Path, metavar="REC",
                   help="tracking recording: the robot driving where several cameras see it")
    p.add_argument("--out", required=True, type=Path, metavar="LAYOUT", help="calibrated layout TOML to write")
    p.add_argument("--robot", metavar="NAME", help="which robot's body (needed when the config has several)")
    p.add_argument("--refine-intrinsics", action="store_true",
                   help="refine the cameras' intrinsics too (overrides [bundle_adjustment] refine_intrinsics)")
    p.add_argument("--truth", type=Path, metavar="LAYOUT",
                   help="the true layout (e.g. REC/true_cube.toml of a simulation): also print the errors")


def run(args: argparse.Namespace) -> int:
    import dataclasses

    from cubetrack.app.calibrate import run_body_calibration
    from cubetrack.app.config import load_config
    from cubetrack.calib.body import placement_errors
    from cubetrack.core.layout import read_layout
    from cubetrack.core.params import params_with
    from cubetrack.core.progress import StderrProgress
    from cubetrack.io.config import read_extrinsics
    from cubetrack.io.recording import Recording

    config, settings = load_config(args.config)
    if args.refine_intrinsics:
        settings = dataclasses.replace(settings, bundle_adjustment=params_with(
            settings.bundle_adjustment, "--refine-intrinsics", refine_intrinsics=True))
    extrinsics = read_extrinsics(args.extrinsics)
    truth = read_layout(args.truth) if args.truth else None
    result = run_body_calibration(config, Recording.open(args.recording), extrinsics, args.out, settings,
                                  robot=args.robot, extrinsics_path=args.extrinsics, progress=StderrProgress())
    report = result.report
    errors = placement_errors(report.layout, truth) if truth is not None else {}
    followed = f", {report.frames} frames on its continuous-time trajectory" if report.frames else ""
    print(f"robot {report.robot}: {report.instants} multi-camera instants{followed}; wrote {args.out} "
          f"({result.run_record_path.name})")
    header = (f"{'face':<8} {'id':>4} {'corners':>7} {'rms px':>6} {'shift mm':>8} {'turn deg':>8} "
              f"{'size mm':>8} {'nominal':>8}")
    if errors:
        header += f" {'err mm':>7} {'err deg':>7} {'size err mm':>11}"
    print(header)
    for m in report.markers:
        line = (f"{m.face:<8} {m.marker_id:>4} {m.corners:>7} {m.rms_px:>6.3f} {1000 * m.shift_m:>8.2f} "
                f"{m.turn_deg:>8.2f} {1000 * m.size_m:>8.2f} {1000 * m.nominal_size_m:>8.2f}")
        if m.face in errors:
            e = errors[m.face]
            line += f" {1000 * e[0]:>7.2f} {e[1]:>7.3f} {1000 * e[2]:>11.3f}"
        print(line)
    for warning in report.warnings:
        print(f"warning: {warning}")
    return 0
