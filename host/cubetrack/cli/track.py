"""Track every robot of a config through a recording (--recording: offline replay) or live from
the config's camera URLs (--live), and write DIR/<robot>.tum and DIR/<robot>.jsonl. Both run the
same tracker; only the source of the frames differs.

Camera intrinsics come from the config's camera_info, else (replay only) the recording's
camera_info folder. Corrupt frames are skipped and counted. Stage parameters come from the
config's [detector], [estimator], [fusion], [filter] and [track] sections; --fusion overrides
the fusion method and --uncalibrated the [track] camera_poses (the rest of each section is kept).
Live reading is tuned by the [source] section. DIR/run.json records the version, the resolved
parameters and the inputs. A replay does the per-frame work on a worker process per idle core
beyond the first (--replay-workers N sets it); its poses are the same, bit for bit, either way.

--smooth (replay, filter fusion): also write DIR/smoothed/<robot>.tum and .jsonl, every pose
estimated from the sightings before and after it (a Rauch-Tung-Striebel smoother over the
filter's states; each JSONL line says "smoothed": true, run.json names the folder) - the best
trajectory of a recording, e.g. as ground truth for SLAM; the causal DIR/<robot>.tum (what live
tracking gives) is written as without it. Costs about 3 KB of memory per sighting (90 MB a
minute at 16 cameras x 30 fps) and about 10 % more fusion CPU, after the replay (docs/tracking.md).
Live (or in a replay), [filter] smooth_lag_s = 0.05 in the config gives every pose smoothed over
the sightings of the next 0.05 s, that much later: most of the offline gain (docs/tracking.md).

With [camera_watch] enabled (docs/calibration.md, "Watching the cameras while tracking"), live or in a
replay, a camera the watching finds moved is set aside and re-calibrated: DIR/camera_watch.jsonl and
run.json keep its events, a status line is logged for each, and its new pose is written to
DIR/extrinsics.watch-<n>.toml (over the --extrinsics file too with --update-extrinsics). A replay fits
the new pose inline, so it gives the same events and files run after run.

Live: poses are written (and flushed) as they come; a status line on stderr shows poses/s per
robot, frames/s per camera and the latency. Runs for --duration seconds or until Ctrl-C (the
outputs are kept either way); --record REC also records the session for replay.

Examples:
  cubetrack track --config rec/config.toml --extrinsics rec/extrinsics.toml --recording rec --out out
  cubetrack track --config rec/config.toml --extrinsics rec/extrinsics.toml --recording rec --out out --smooth
  cubetrack track --config lab.toml --extrinsics extrinsics.toml --live --out out --record sessions/run1
"""

from __future__ import annotations

import argparse
from pathlib import Path

from cubetrack.cli.dashboard import add_dashboard, add_dashboard_argument
from cubetrack.cli.outputs import add_output_arguments, output_sinks_from_args

HELP = "track robots through a recording or live from the cameras -> TUM + JSONL per robot"


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--config", required=True, type=Path, help="tracker config TOML")
    source = p.add_mutually_exclusive_group(required=True)
    source.add_argument("--recording", type=Path, metavar="REC", help="recording folder to replay")
    source.add_argument("--live", action="store_true", help="track live from the cameras' url in the config")
    p.add_argument("--extrinsics", type=Path, help="camera poses from cubetrack calibrate (TOML)")
    p.add_argument("--uncalibrated", action="store_true",
                   help="no extrinsics: take each frame's own world-marker pose (the paper's uncalibrated mode)")
    p.add_argument("--fusion", metavar="METHOD", help="override [fusion] method: mean | weighted | gaussian")
    p.add_argument("--out", required=True, type=Path, metavar="DIR", help="output folder")
    p.add_argument("--duration", type=float, metavar="S", help="--live: stop after this many seconds (default: Ctrl-C)")
    p.add_argument("--record", type=Path, metavar="REC", help="--live: also record the session into this folder")
    p.add_argument("--replay-workers", type=int, metavar="N",
                   help="--recording: frame worker processes beside the thread that plans and fuses (default: one "
                        "per idle core beyond the first, measured at the start; 0: one thread; the poses are the "
                        "same either way)")
    p.add_argument("--smooth", action="store_true",
                   help="--recording: also write DIR/smoothed/<robot>.tum and .jsonl, each pose from the sightings "
                        "before and after it (offline smoother; [fusion] method = filter); DIR/<robot>.tum stays the "
                        "causal track")
    p.add_argument("--status-every", type=float, default=2.0, metavar="S",
                   help="--live: seconds between status lines (default %(default)s)")
    add_output_arguments(p)
    add_update_extrinsics_argument(p)
    add_dashboard_argument(p)


def add_update_extrinsics_argument(p: argparse.ArgumentParser) -> None:
    """``--update-extrinsics``: with ``[camera_watch] enabled``, a re-calibrated camera's new pose is
    also written over the ``--extrinsics`` file (docs/calibration.md)."""
    p.add_argument("--update-extrinsics", action="store_true",
                   help="with [camera_watch] enabled: write a re-calibrated camera's new pose over the "
                        "--extrinsics file too (without it only OUT/extrinsics.watch-<n>.toml is written)")


def run(args: argparse.Namespace) -> int:
    import dataclasses
    import sys

    from cubetrack.app.calibrate import with_calibrated_bodies
    from cubetrack.app.config import load_config
    from cubetrack.app.outputs import close_sinks
    from cubetrack.app.track import track_recording
    from cubetrack.app.tracker import CameraPoseSource
    from cubetrack.core.errors import ConfigError
    from cubetrack.core.params import params_with
    from cubetrack.core.progress import StderrProgress
    from cubetrack.io.config import read_extrinsics
    from cubetrack.io.recording import Recording

    if not args.live and (args.duration is not None or args.record is not None or args.dashboard is not None):
        raise ConfigError("--duration, --record and --dashboard go with --live (a replay runs to the end "
                          "of its recording)")
    if args.smooth and args.live:
        raise ConfigError("--smooth goes with --recording (it smooths a whole recording after its replay)")
    if args.replay_workers is not None and (args.live or args.replay_workers < 0):
        raise ConfigError("--replay-workers goes with --recording and must not be negative, "
                          f"got {args.replay_workers}" + (" with --live" if args.live else ""))
    if args.duration is not None and not args.duration > 0:
        raise ConfigError(f"--duration must be a positive number of seconds, got {args.duration}")
    if not args.status_every > 0:
        raise ConfigError(f"--status-every must be a positive number of seconds, got {args.status_every}")
    if args.update_extrinsics and args.extrinsics is None:
        raise ConfigError("--update-extrinsics writes a re-calibrated camera's pose over the --extrinsics file: "
                          "give --extrinsics")
    config, settings = load_config(args.config)
    if args.fusion:
        settings = dataclasses.replace(settings, fusion=params_with(settings.fusion, "--fusion", method=args.fusion))
    if args.uncalibrated:  # only the camera poses change: the rest of [track] is kept
        settings = dataclasses.replace(settings, track=params_with(
            settings.track, "--uncalibrated", camera_poses=CameraPoseSource.WORLD_MARKER))
        extrinsics = None
    elif args.extrinsics is None:
        raise ConfigError("give --extrinsics (from cubetrack calibrate) or --uncalibrated")
    else:
        extrinsics = read_extrinsics(args.extrinsics)
        config, bodies = with_calibrated_bodies(config, args.extrinsics)
        for path in bodies:
            print(f"body calibrated with the extrinsics: {path}", file=sys.stderr)
    recording = None if args.live else Recording.open(args.recording)
    sinks = add_dashboard(args, output_sinks_from_args(args, config), config, args.out, settings.dashboard)
    try:
        if recording is None:
            return _run_live(args, config, extrinsics, settings, sinks)
        result = track_recording(config, recording, extrinsics, args.out, settings.stages, StderrProgress(), sinks,
                                 extrinsics_path=args.extrinsics, workers=args.replay_workers, smooth=args.smooth,
                                 update_extrinsics=args.update_extrinsics)
    finally:
        close_sinks(sinks)
    s = result.stats
    print(f"frames: {s.frames}" + "".join(f", {reason}: {n}" for reason, n in result.skipped.items()))
    print(dropped_line(s))
    for robot, (tum, jsonl) in result.outputs.items():
        print(f"{robot}: {s.poses[robot]} poses -> {tum}, {jsonl}")
    for robot, (tum, jsonl) in result.smoothed.items():
        print(f"{robot}: smoothed poses -> {tum}, {jsonl}")
    if result.camera_watch is not None:
        print(watch_line(result.camera_watch))
    if result.ended_by is not None:
        print(f"track: {result.ended_by}: the replay stopped early; the poses of the frames taken so far are saved "
              f"(run.json says how it ended)", file=sys.stderr)
        return 130
    return 0


def watch_line(watch_log) -> str:
    """The run summary's line on the camera watching: its events and the extrinsics files it wrote."""
    from cubetrack.app.watch_log import EVENTS_FILE

    events = len(watch_log.records)
    line = f"camera watch: {events} event{'' if events == 1 else 's'}"
    if events:
        line += f" -> {watch_log.out_dir / EVENTS_FILE}"
    if watch_log.written:
        line += "; new extrinsics -> " + ", ".join(str(p) for p in watch_log.written)
    return line


def dropped_line(stats) -> str:
    """The run summary's line on markers found and then dropped, per reason; loud when no pose came of them."""
    dropped = stats.dropped_detections
    if not dropped:
        return "markers dropped after detection: none"
    line = "markers dropped after detection: " + ", ".join(f"{r}: {n}" for r, n in sorted(dropped.items()))
    if not sum(stats.poses.values()):
        line += " -- WARNING: markers were found but none was kept, so there are no poses (docs/detection.md)"
    return line


def _run_live(args: argparse.Namespace, config, extrinsics, settings, sinks) -> int:
    import sys

    from cubetrack.app.live import live_camera_urls, live_intrinsics, track_live

    live_camera_urls(config), live_intrinsics(config)  # a bad config fails before the session starts
    params = settings.stages

    def status(s) -> None:
        print(f"track: {s.line()}", file=sys.stderr, flush=True)

    print(f"tracking live into {args.out}" + ("" if args.duration else " (Ctrl-C to stop)"),
          file=sys.stderr, flush=True)
    result = track_live(config, extrinsics, args.out, params, settings.source, duration_s=args.duration,
                        record_to=args.record, status=status, status_every_s=args.status_every, sinks=sinks,
                        live_params=settings.live, extrinsics_path=args.extrinsics,
                        update_extrinsics=args.update_extrinsics)
    s = result.stats
    if s is None:  # track_live always returns its counters (only record_live has none)
        raise AssertionError("a live tracking session without counters")
    latency = "-" if result.latency_s is None else f"{result.latency_s * 1000:.0f} ms"
    print(f"{'interrupted; ' if result.interrupted else ''}tracked live for {result.duration_s:.1f} s: "
          f"frames: {s.frames}, before their camera's clock was known: {s.frames_before_clock_sync}, "
          f"corrupt frame: {s.corrupt_frames}, median latency {latency}")
    print(dropped_line(s))
    for name, c in result.cameras.items():
        bad = "".join(f", {n} {why}" for why, n in sorted(c.bad_parts.items()))
        print(f"  {name}: {c.frames} frames, {c.dropped} dropped (tracker behind), {c.clock_samples} clock samples, "
              f"{c.reconnects} reconnects{bad}")
    for robot, (tum, jsonl) in result.outputs.items():
        print(f"{robot}: {s.poses[robot]} poses -> {tum}, {jsonl}")
    if result.recording is not None:
        print(f"recorded into {result.recording}")
    return 0
