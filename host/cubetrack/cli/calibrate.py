"""Calibrate where each camera stands (T_world_cam) from a recording of the world marker.

Per camera of the recording, the world marker ([world] in the config: dictionary, marker_id,
marker_size) is detected in up to --samples frames and the camera pose is computed:

  robust  (default) corners re-measured from the marker's edges, outlier frames rejected,
          one PnP on the averaged corners — free of the detector's corner bias
  cma     the paper's recursive cumulative moving average of per-frame poses (eq. 1)

Intrinsics come from the config's camera_info or the recording's camera_info/<camera>.yaml.
Writes the extrinsics TOML (contracts §4) with sample counts and spread, and beside it the run
record (extrinsics.toml -> extrinsics.run.json: version, resolved parameters, inputs); corrupt
frames are skipped and counted. A camera that never sees the world marker is an error unless
--allow-missing. Parameters come from the config's [calibration] and [detector] sections
(`cubetrack defaults` prints them); --method and --samples override two of them. See
docs/calibration.md.

With --refine-with REC the calibrated poses are then refined by a bundle adjustment over the
cube corners of a tracking recording REC (instants where several cameras saw the cube) and
the world marker's averaged corners ([bundle_adjustment] section); --out gets the refined poses.
The same drive first calibrates each robot's body (where its markers really sit, as
`cubetrack calibrate-body` does; [body_calibration] section), the refinement takes the calibrated
bodies, and each is written beside --out as <out stem>.<robot>.body.toml, where `cubetrack track
--extrinsics` finds it (--no-body: neither).
Per-camera residuals are printed, and a camera that moved after the calibration recording is named with how far.

Example:
  cubetrack calibrate --config rec/config.toml --recording rec/calibration --out extrinsics.toml
  cubetrack calibrate --config rec/config.toml --recording rec/calibration --out extrinsics.toml \
      --refine-with rec
"""

from __future__ import annotations

import argparse
from pathlib import Path

HELP = "calibrate camera poses from the world marker (paper's CMA or robust)"


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--config", required=True, type=Path, metavar="CFG", help="tracker config (TOML)")
    p.add_argument("--recording", required=True, type=Path, metavar="REC",
                   help="recording folder with the cameras looking at the world marker")
    p.add_argument("--out", required=True, type=Path, metavar="EXTRINSICS", help="extrinsics TOML to write")
    p.add_argument("--method", choices=("robust", "cma"), default=None,
                   help="robust or cma (the paper's); overrides [calibration] method")
    p.add_argument("--samples", type=int, default=None, metavar="N",
                   help="world-marker sightings to use per camera; overrides [calibration] samples")
    p.add_argument("--allow-missing", action="store_true",
                   help="leave out cameras that do not see the world marker, or recorded no frame, instead of failing")
    p.add_argument("--refine-with", type=Path, metavar="REC",
                   help="tracking recording (the robot driving where several cameras see it): refine the "
                        "calibrated poses with its cube sightings (bundle adjustment); --out gets the refined poses")
    p.add_argument("--no-body", action="store_true",
                   help="with --refine-with: do not calibrate the robots' bodies (the refinement takes the config's "
                        "layouts as exact; no <out stem>.<robot>.body.toml is written)")
    p.add_argument("--truth", type=Path, metavar="EXTRINSICS",
                   help="true extrinsics (e.g. REC/true_extrinsics.toml of a simulation): also print the errors")


def run(args: argparse.Namespace) -> int:
    import dataclasses

    from cubetrack.app.calibrate import run_calibration
    from cubetrack.app.config import load_config
    from cubetrack.calib.extrinsics import extrinsics_errors
    from cubetrack.core.params import params_with
    from cubetrack.core.progress import StderrProgress
    from cubetrack.io.config import read_extrinsics
    from cubetrack.io.recording import Recording

    config, settings = load_config(args.config)
    calibration = settings.calibration
    if args.method is not None:
        calibration = params_with(calibration, "--method", method=args.method)
    if args.samples is not None:
        calibration = params_with(calibration, "--samples", samples=args.samples,
                                  min_samples=min(calibration.min_samples, max(args.samples, 1)))
    settings = dataclasses.replace(settings, calibration=calibration)
    params = calibration
    truth = read_extrinsics(args.truth) if args.truth else None
    recording, empty = Recording.open(args.recording), dict[str, str]()
    if args.allow_missing:  # a camera that was down while recording (its index empty) is one more missing
        recording, empty = recording.with_frames()
    adjust_with, left_out = None, dict[str, str]()
    if args.refine_with is not None:  # the refinement keeps the calibration of a camera with no frames in it
        adjust_with, left_out = Recording.open(args.refine_with).with_frames()
    result = run_calibration(config, recording, args.out, settings, adjust_with=adjust_with,
                             allow_missing=args.allow_missing, progress=StderrProgress(),
                             with_bodies=not args.no_body)
    report, refined = result.report, result.adjusted
    errors = extrinsics_errors(report.extrinsics, truth) if truth else {}
    if refined is None:
        print(f"method {params.method.value}; wrote {args.out} ({result.run_record_path.name})")
    else:
        what = "refinement refused, the world-marker calibration kept" if refined.refused else "refined"
        print(f"method {params.method.value}, refined with {args.refine_with}; wrote {args.out} ({what}; "
              f"{result.run_record_path.name})")
    header = f"{'camera':<10} {'samples':>7} {'frames':>6}  {'position [m]':<26} {'spread cm':>9} {'spread deg':>10}"
    if truth:
        header += f" {'err cm':>7} {'err deg':>7}"
    print(header)
    for name, cal in report.cameras.items():
        e = cal.extrinsics
        x, y, z = e.T_world_cam[:3, 3]
        line = (f"{name:<10} {e.samples:>7} {cal.frames_read:>6}  ({x:+.3f}, {y:+.3f}, {z:+.3f})"
                f"{'':<4} {100 * e.spread_position_m:>9.2f} {e.spread_rotation_deg:>10.3f}")
        if name in errors:
            line += f" {100 * errors[name][0]:>7.2f} {errors[name][1]:>7.3f}"
        print(line)
        if cal.skipped:
            print(f"{'':<10} skipped: " + ", ".join(f"{n} {why}" for why, n in sorted(cal.skipped.items())))
    for name, why in {**report.missing, **empty}.items():
        print(f"{name:<10} NOT CALIBRATED: {why}")
    for name, why in left_out.items():
        print(f"refinement: {name} left out ({why})")
    for why, n in sorted(recording.skipped.items()):
        print(f"recording: skipped {n} ({why})")
    if refined is not None:
        _print_refined(refined, extrinsics_errors(refined.extrinsics, truth) if truth else {})
    for robot, path in result.body_paths.items():
        body = result.bodies[robot]
        worst = max(body.markers, key=lambda m: m.shift_m)
        print(f"body {robot}: calibrated from {body.instants} instants, wrote {path} (track --extrinsics "
              f"{args.out} uses it); largest marker shift {1000 * worst.shift_m:.2f} mm ({worst.face})")
        for warning in body.warnings:
            print(f"warning: body {robot}: {warning}")
    for robot, why in result.body_failures.items():
        print(f"warning: body {robot} not calibrated (it keeps its layout): {why}")
    return 0


def _print_refined(refined, errors: dict) -> None:
    print(f"{'the refused refinement' if refined.refused else 'refined'} with {refined.instants} multi-camera "
          "instants:")
    header = (f"{'camera':<10} {'instants':>8} {'corners':>7} {'rms px':>6} {'world px':>8} "
              f"{'shift cm':>8} {'shift deg':>9}")
    if errors:
        header += f" {'err cm':>7} {'err deg':>7}"
    print(header)
    for name, r in refined.cameras.items():
        line = (f"{name:<10} {r.instants:>8} {r.corners:>7} {r.rms_px:>6.3f} {r.world_rms_px:>8.3f} "
                f"{100 * r.shift_m:>8.2f} {r.shift_deg:>9.3f}")
        if name in errors:
            line += f" {100 * errors[name][0]:>7.2f} {errors[name][1]:>7.3f}"
        print(line + ("  MOVED" if r.moved else ""))
    for warning in refined.warnings:
        print(f"warning: {warning}")
