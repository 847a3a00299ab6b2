"""Score estimated trajectories against a ground truth: position and rotation RMSE against the
ground truth interpolated to each pose's own time (slerp for rotation), with the paper's eq. 7
(the nearest ground-truth sample) beside them, detection ratio with a message timeout (paper
eq. 8) and output rate. No alignment is applied: the world frame comes from calibration.

Example:
  cubetrack evaluate --estimate out/robot.tum --ground-truth rec/ground_truth.tum --plot figs/
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

HELP = "score trajectories against a ground truth (RMSE, detection ratio)"


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--estimate", action="append", required=True, type=Path, metavar="TUM",
                   help="estimated trajectory (TUM); repeat to compare several")
    p.add_argument("--label", action="append", default=None,
                   help="label for each --estimate, in order (default: the file name)")
    p.add_argument("--ground-truth", required=True, type=Path, metavar="TUM", help="reference trajectory (TUM)")
    p.add_argument("--timeout", type=float, metavar="S",
                   help="detection-ratio message timeout in seconds (default: the paper's)")
    p.add_argument("--max-time-diff", type=float, metavar="S",
                   help="estimates farther than this many seconds from any ground-truth sample are not scored")
    p.add_argument("--plot", type=Path, metavar="DIR", help="write paper-style figures into DIR")
    p.add_argument("--json", action="store_true", help="print the scores as JSON")


def run(args: argparse.Namespace) -> int:
    from cubetrack.core.errors import EvaluationError
    from cubetrack.core.params import params_with
    from cubetrack.evaluate.metrics import EvaluationParams, evaluate
    from cubetrack.io.trajectory import read_tum

    labels = args.label or [p.stem if len(args.estimate) == 1 else str(p) for p in args.estimate]
    if len(labels) != len(args.estimate):
        raise EvaluationError(f"{len(labels)} --label for {len(args.estimate)} --estimate: give one per estimate")
    params = EvaluationParams()
    if args.timeout is not None:
        params = params_with(params, "--timeout", detection_timeout_s=args.timeout)
    if args.max_time_diff is not None:
        params = params_with(params, "--max-time-diff", max_time_diff_s=args.max_time_diff)
    truth = read_tum(args.ground_truth)
    estimates = {label: read_tum(path) for label, path in zip(labels, args.estimate, strict=True)}
    results = {label: evaluate(traj, truth, params) for label, traj in estimates.items()}
    if args.json:
        print(json.dumps({label: r.as_dict() for label, r in results.items()}, indent=2))
    else:
        print(format_table(results))
    if args.plot:
        from cubetrack.evaluate.plot import plot_rmse_bars, plot_xy

        args.plot.mkdir(parents=True, exist_ok=True)
        xy = plot_xy(estimates, truth, args.plot / "trajectory_xy.png")
        bars = plot_rmse_bars({("", label): r.position_rmse_m for label, r in results.items()},
                              args.plot / "rmse.png")
        print(f"figures: {xy} {bars}")
    return 0


def format_table(results: dict) -> str:
    """A plain-text table of evaluation results, one row per estimate."""
    head = (f"{'estimate':<28} {'pos RMSE':>10} {'rot RMSE':>9} {'eq.7 pos':>10} {'eq.7 rot':>9} {'det ratio':>9} "
            f"{'rate':>8} {'scored':>8}")
    rows = [head, "-" * len(head)]  # eq.7: against the nearest ground-truth sample (the paper's)
    for label, r in results.items():
        rows.append(
            f"{label[:28]:<28} {r.position_rmse_m * 100:>8.2f}cm {r.rotation_rmse_deg:>7.2f}° "
            f"{r.position_rmse_nearest_m * 100:>8.2f}cm {r.rotation_rmse_nearest_deg:>7.2f}° "
            f"{r.detection_ratio:>9.3f} {r.output_rate_hz:>6.1f}Hz {r.poses_scored:>4}/{r.poses_total:<4}"
        )
    return "\n".join(rows)
