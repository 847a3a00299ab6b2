"""Cameras stamped off their capture time (issue 25): the scenes of ``benchmarks/accuracy.py --out DIR``
tracked again with some cameras' stamps moved by tens of ms, with the default filter and with the
per-camera time offsets estimated (``[filter] correction_time_sigma_s = 0.05``, docs/tracking.md
"Per-camera corrections").

A camera without a clock is stamped when its frames arrive, late by its own transfer time; a
camera whose clock sync is off is early or late by that error. Here the same rendered frames
are used with each listed camera's stamps (``X-Timestamp``, the recording's ``device_time``) moved
by its offset, so a frame's stamp is off its true capture by exactly that (``clock.csv`` is left as
it is: the tracker maps the moved stamps to the host clock as before). Scored as accuracy.py scores
(position and rotation RMSE against the ground truth at each pose's time, detection ratio, poses
more than 5 cm off); the unmoved recording with both settings alongside, so a setting that costs
accuracy where every stamp is right shows too.

``--set filter.KEY=VALUE`` compares other [filter] settings instead (e.g. the hand-held scenes'
motion: ``--set filter.angular_accel_noise=3.0 --offsets-ms``, no offsets: the unmoved recording only).

Usage: python benchmarks/stamp_offsets.py --scenes DIR [--offsets-ms 40 -25] [--only PATTERN] [--set ...]
"""

from __future__ import annotations

import argparse
import csv
import dataclasses
import os
import shutil
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

import accuracy  # noqa: E402  (the scoring of the scenes it rendered)

SWITCH = {"correction_time_sigma_s": 0.05}  # the [filter] settings compared with the defaults, unless --set


def moved_stamps(rec: Path, out: Path, offsets_s: dict[str, float]) -> Path:
    """A copy of recording ``rec`` in ``out`` (frames hard-linked) with each camera of ``offsets_s``
    stamped that many seconds after its frames' capture."""
    if out.exists():
        shutil.rmtree(out)
    shutil.copytree(rec, out, copy_function=os.link, ignore=shutil.ignore_patterns("track", "calibration"))
    for camera, offset_s in offsets_s.items():
        index = out / camera / "index.csv"
        with index.open(newline="") as f:
            rows = list(csv.DictReader(f))
        index.unlink()  # a hard link: write a new file, not into the original's
        with index.open("w", newline="") as f:
            writer = csv.DictWriter(f, fieldnames=list(rows[0]))
            writer.writeheader()
            for row in rows:
                writer.writerow({**row, "device_time": f"{float(row['device_time']) + offset_s:.6f}"})
    return out


def track_scores(rec: Path, extrinsics: dict, truth, work: Path, switch: dict) -> dict[str, dict]:
    """Scores of ``rec`` tracked with the defaults and with the [filter] settings ``switch``."""
    from cubetrack.app.track import track_recording
    from cubetrack.app.tracker import StageParams
    from cubetrack.io.config import read_tracker_config
    from cubetrack.io.recording import Recording

    config = read_tracker_config(rec / "config.toml")
    base = StageParams.from_config(config)
    switched = dataclasses.replace(base, filter=dataclasses.replace(base.filter, **switch))
    out = {}
    for name, params in (("default", base), ("switched", switched)):
        result = track_recording(config, Recording.open(rec), extrinsics, work / name.replace(" ", "_"), params,
                                 workers=0)
        out[name] = accuracy.score(result.outputs[config.robots[0].name][0], truth)
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scenes", type=Path, required=True, help="an accuracy.py --out folder (its rendered scenes "
                    "and their robust extrinsics, track/extrinsics_robust.toml)")
    ap.add_argument("--offsets-ms", type=float, nargs="*", default=[40.0, -25.0],
                    help="stamp offsets of the scene's first cameras, in order (default: 40 -25: the first camera "
                    "stamped 40 ms late, the second 25 ms early, the others right)")
    ap.add_argument("--only", default="", help="only scenes whose folder name contains this")
    ap.add_argument("--set", action="append", default=[], metavar="filter.KEY=VALUE",
                    help="a [filter] setting to compare with the defaults (repeat; default: "
                    "filter.correction_time_sigma_s=0.05)")
    args = ap.parse_args(argv)
    switch = dict(SWITCH)
    if args.set:
        switch = {}
        for item in args.set:
            key, _, value = item.partition("=")
            if not key.startswith("filter.") or not value:
                ap.error(f"--set takes filter.KEY=VALUE, got {item!r}")
            switch[key.removeprefix("filter.")] = float(value)
    from cubetrack.io.config import read_extrinsics, read_tracker_config
    from cubetrack.io.trajectory import read_tum

    scenes = sorted(p for p in args.scenes.iterdir() if (p / accuracy.COMPLETE_FILE).exists() and args.only in p.name
                    and (p / "track" / accuracy.ROBUST_EXTRINSICS_FILE).exists())
    if not scenes:
        ap.error(f"no rendered scene with robust extrinsics in {args.scenes}")
    print(f"offsets {args.offsets_ms} ms; switched: {switch}; cores {os.cpu_count()}; load {os.getloadavg()[0]:.1f}",
          flush=True)
    for rec in scenes:
        cameras = [c.name for c in read_tracker_config(rec / "config.toml").cameras]
        offsets = {c: ms / 1000.0 for c, ms in zip(cameras, args.offsets_ms, strict=False)}
        extrinsics = read_extrinsics(rec / "track" / accuracy.ROBUST_EXTRINSICS_FILE)
        truth = read_tum(rec / "ground_truth.tum")
        work = args.scenes / "stamp_offsets" / rec.name
        runs = [("stamps right", rec)]
        if offsets:
            runs.append(("stamps moved", moved_stamps(rec, work / "recording", offsets)))
        for label, recording in runs:
            scores = track_scores(recording, extrinsics, truth, work / label.replace(" ", "_"), switch)
            for name, s in scores.items():
                print(f"{rec.name:<24} {label:<13} {name:<13} position RMSE {s['pos_cm']:.3f} cm, rotation RMSE "
                      f"{s['rot_deg']:.3f} deg, max {s['max_cm']:.2f} cm, detection ratio {s['dr']:.3f}, "
                      f"poses > 5 cm {s['far_count']}", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
