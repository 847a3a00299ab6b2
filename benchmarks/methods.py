"""The paper's comparison (its Figs. 6-8) on simulated recordings.

{0.8, 1.0, 1.2 m cameras with 20 / 30 / 40° tilt} x {3, 5 cameras} x {calibrated, raw
world-marker poses} x {mean, weighted, gaussian fusion}: position RMSE and detection ratio,
printed as tables shaped like the paper's figures, with the paper's own numbers beside ours.

    .venv/bin/python benchmarks/methods.py [--duration 30] [--seeds 1 2] [--out bench-methods] [--plot]

Rendering dominates the run time (about 6 scenes x seeds).
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from cubetrack.app.calibrate import calibrate_recording
from cubetrack.app.track import track_recording
from cubetrack.app.tracker import CameraPoseSource, StageParams, TrackParams
from cubetrack.evaluate.metrics import evaluate
from cubetrack.fuse.fusion import FusionMethod
from cubetrack.io.config import read_tracker_config
from cubetrack.io.recording import Recording
from cubetrack.io.trajectory import read_tum
from cubetrack.simulate import SimulationParams, simulate

HEIGHTS = ((0.8, 20.0), (1.0, 30.0), (1.2, 40.0))
# The paper's results (cm, detection ratio %), Figs. 6-8, multi-marker rows.
PAPER_FIG6 = {"mean": (3.96, 3.67, 3.65), "gaussian": (4.01, 3.71, 3.68), "weighted": (3.97, 3.68, 3.65)}
PAPER_FIG7 = {"3 cams, calibrated": (4.0, 3.7, 3.6), "5 cams, calibrated": (5.8, 5.3, 6.1),
              "3 cams, raw": (6.5, 6.2, 5.9)}
PAPER_FIG8 = {"3 cams, calibrated": (95.3, 86.5, 78.5), "5 cams, calibrated": (99.1, 100.0, 98.8),
              "3 cams, raw": (61.6, 55.4, 53.6)}


def run_scene(work: Path, cameras: int, height: float, tilt: float, seed: int, duration: float) -> dict:
    """Simulate one scene; return {(calibrated?, method): (rmse_m, detection_ratio)}."""
    rec = work / f"c{cameras}_h{height}_s{seed}"
    simulate(SimulationParams(cameras=cameras, height_m=height, tilt_deg=tilt, seed=seed, duration_s=duration), rec)
    config = read_tracker_config(rec / "config.toml")
    extrinsics = calibrate_recording(config, Recording.open(rec / "calibration")).extrinsics
    truth = read_tum(rec / "ground_truth.tum")
    base = StageParams.from_config(config)
    out = {}
    for calibrated in (True, False):
        for method in FusionMethod:
            params = dataclasses.replace(
                base,
                fusion=dataclasses.replace(base.fusion, method=method),
                track=TrackParams(camera_poses=CameraPoseSource.EXTRINSICS if calibrated
                                  else CameraPoseSource.WORLD_MARKER),
            )
            result = track_recording(config, Recording.open(rec), extrinsics if calibrated else None,
                                     rec / "track" / f"{'cal' if calibrated else 'raw'}_{method.value}", params)
            traj = read_tum(result.outputs[config.robots[0].name][0])
            score = evaluate(traj, truth)
            out[(calibrated, method.value)] = (score.position_rmse_m, score.detection_ratio)
    return out


def table(title: str, rows: dict[str, tuple], paper: dict[str, tuple], unit: str) -> str:
    head = f"{title:<26}" + "".join(f"{f'{h:.1f} m':>16}" for h, _ in HEIGHTS)
    lines = [head, "-" * len(head)]
    for name, values in rows.items():
        ref = paper.get(name, (None,) * 3)
        cells = "".join(
            f"{v:>8.2f}{unit} ({r:>5.1f})" if r is not None else f"{v:>8.2f}{unit}        "
            for v, r in zip(values, ref, strict=True)
        )
        lines.append(f"{name:<26}{cells}")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--duration", type=float, default=30.0, help="seconds per simulated session (default 30)")
    ap.add_argument("--seeds", type=int, nargs="+", default=[1], help="random seeds (results are averaged)")
    ap.add_argument("--out", type=Path, help="keep recordings here (default: a temporary folder)")
    ap.add_argument("--plot", action="store_true", help="write rmse_by_method.png and rmse_by_setup.png into --out")
    args = ap.parse_args(argv)
    work = args.out or Path(tempfile.mkdtemp(prefix="cubetrack-bench-"))
    work.mkdir(parents=True, exist_ok=True)
    t0 = time.monotonic()
    scores: dict[tuple, list] = {}
    for cameras in (3, 5):
        for height, tilt in HEIGHTS:
            for seed in args.seeds:
                print(f"scene: {cameras} cameras at {height} m / {tilt:.0f}°, seed {seed} ...", file=sys.stderr,
                      flush=True)
                for key, value in run_scene(work, cameras, height, tilt, seed, args.duration).items():
                    scores.setdefault((cameras, height) + key, []).append(value)

    def mean(cameras, height, calibrated, method, k):
        return float(np.mean([v[k] for v in scores[(cameras, height, calibrated, method)]]))

    fig6 = {m.value: tuple(mean(3, h, True, m.value, 0) * 100 for h, _ in HEIGHTS) for m in FusionMethod}
    setups = {"3 cams, calibrated": (3, True), "5 cams, calibrated": (5, True), "3 cams, raw": (3, False),
              "5 cams, raw": (5, False)}
    fig7 = {n: tuple(mean(c, h, cal, "mean", 0) * 100 for h, _ in HEIGHTS) for n, (c, cal) in setups.items()}
    fig8 = {n: tuple(mean(c, h, cal, "mean", 1) * 100 for h, _ in HEIGHTS) for n, (c, cal) in setups.items()}
    print(f"\nseeds {args.seeds}, {args.duration:.0f} s per session; ours (paper's) in brackets\n")
    print(table("Fig. 6: RMSE by fusion [cm]", fig6, PAPER_FIG6, "") + "\n")
    print(table("Fig. 7: RMSE, mean [cm]", fig7, PAPER_FIG7, "") + "\n")
    print(table("Fig. 8: detection ratio [%]", fig8, PAPER_FIG8, "") + "\n")
    print(f"total {time.monotonic() - t0:.0f} s; recordings in {work}")
    if args.plot:
        from cubetrack.evaluate.plot import plot_rmse_bars

        plot_rmse_bars({(f"{h} m", m): fig6[m][i] / 100 for m in fig6 for i, (h, _) in enumerate(HEIGHTS)},
                       work / "rmse_by_method.png", "RMSE by fusion method (3 cameras, calibrated)")
        plot_rmse_bars({(f"{h} m", n): fig7[n][i] / 100 for n in fig7 for i, (h, _) in enumerate(HEIGHTS)},
                       work / "rmse_by_setup.png", "RMSE by setup (mean fusion)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
