"""Track every robot of a config through a recording (offline replay; the same code path as
live tracking) and write DIR/<robot>.tum and DIR/<robot>.jsonl.

Camera intrinsics come from the config's camera_info, else the recording's camera_info folder.
Corrupt frames are skipped and counted. Stage parameters come from the config's [detector],
[estimator], [fusion] and [track] sections; --fusion overrides the fusion method.

Example:
  cubetrack track --config rec/config.toml --extrinsics rec/extrinsics.toml --recording rec --out out
"""

from __future__ import annotations

import argparse
from pathlib import Path

HELP = "track robots through a recording -> TUM + JSONL per robot"


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--config", required=True, type=Path, help="tracker config TOML")
    p.add_argument("--recording", required=True, type=Path, metavar="REC", help="recording folder to replay")
    p.add_argument("--extrinsics", type=Path, help="camera poses from cubetrack calibrate (TOML)")
    p.add_argument("--uncalibrated", action="store_true",
                   help="no extrinsics: take each frame's own world-marker pose (the paper's uncalibrated mode)")
    p.add_argument("--fusion", metavar="METHOD", help="override [fusion] method: mean | weighted | gaussian")
    p.add_argument("--out", required=True, type=Path, metavar="DIR", help="output folder")


def run(args: argparse.Namespace) -> int:
    import dataclasses

    from cubetrack.errors import ConfigError
    from cubetrack.io.config import read_extrinsics, read_tracker_config
    from cubetrack.io.recording import Recording
    from cubetrack.params import params_from_table
    from cubetrack.pipeline import CameraPoseSource, StageParams, TrackParams, track_recording
    from cubetrack.fuse import FusionParams
    from cubetrack.progress import StderrProgress

    config = read_tracker_config(args.config)
    recording = Recording.open(args.recording)
    params = StageParams.from_config(config)
    if args.fusion:
        table = {**config.section("fusion"), "method": args.fusion}
        params = dataclasses.replace(params, fusion=params_from_table(FusionParams, table, "--fusion"))
    if args.uncalibrated:
        params = dataclasses.replace(params, track=TrackParams(camera_poses=CameraPoseSource.WORLD_MARKER))
        extrinsics = None
    elif args.extrinsics is None:
        raise ConfigError("give --extrinsics (from cubetrack calibrate) or --uncalibrated")
    else:
        extrinsics = read_extrinsics(args.extrinsics)
    result = track_recording(config, recording, extrinsics, args.out, params, StderrProgress())
    s = result.stats
    print(f"frames: {s.frames}" + "".join(f", {reason}: {n}" for reason, n in result.skipped.items()))
    for robot, (tum, jsonl) in result.outputs.items():
        print(f"{robot}: {s.poses[robot]} poses -> {tum}, {jsonl}")
    return 0
