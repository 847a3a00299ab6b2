"""The end-to-end demo as a library flow: simulate -> calibrate -> serve the recording with the
camera emulator (its own process) -> track it live over HTTP -> evaluate; plus the offline replay of the same
recording with each fusion method (the paper's three and the filter), for comparison.

:func:`run_demo` is what ``cubetrack demo`` runs (``live=False``: the offline part only).

Clocks. The simulated recording and its ground truth live on the *recorded* host clock (Unix
time of the simulated session). The emulator replays that timeline shifted to now: a recorded
host time h is reached at live Unix time ``emulator.unix_time(h) = h + shift``, one constant for
the whole replay, and every emulated device clock (X-Timestamp and ``/time``) keeps its recorded
relation to that timeline. The live tracker maps device times to the live host clock through its
own ``/time`` round trips, so its poses are stamped on the live clock; the ground truth is moved
there by adding ``shift`` (written as ``live/ground_truth_live.tum``). See docs/live.md.
"""

from __future__ import annotations

import dataclasses
import threading
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path

from cubetrack.app.calibrate import run_calibration
from cubetrack.app.config import ConfigParams, config_params, parameter_tables
from cubetrack.app.emulated import EmulatedCameras
from cubetrack.app.live import LiveResult, track_live
from cubetrack.app.track import track_recording
from cubetrack.calib.extrinsics import extrinsics_errors
from cubetrack.core.errors import ConfigError
from cubetrack.core.progress import Progress
from cubetrack.evaluate.metrics import EvaluationResult, evaluate
from cubetrack.fuse.fusion import FusionMethod
from cubetrack.io.config import (
    CameraConfig,
    read_extrinsics,
    read_tracker_config,
    tracker_config_to_table,
    write_toml,
)
from cubetrack.io.recording import Recording
from cubetrack.io.run import RUN_FILE, write_run_record
from cubetrack.io.trajectory import Trajectory, read_tum, write_tum
from cubetrack.simulate import SimulationParams, simulate
from cubetrack.sink.base import Sink
from cubetrack.source.health import LiveStatus

END_GRACE_S = 1.5  # after the replay's last frame: its transfer, the clock poll, the filter's reorder delay


@dataclass(frozen=True, slots=True)
class LiveDemo:
    """The live part: its score against the ground truth moved to the live clock (None: Ctrl-C or
    SIGTERM ended the session before the replay did), the session's result, the clock shift (live
    Unix time minus recorded host time) and the files."""

    method: str
    score: EvaluationResult | None
    result: LiveResult
    clock_shift_s: float
    config_path: Path
    ground_truth_path: Path


@dataclass(frozen=True, slots=True)
class DemoResult:
    """Calibration errors per camera (position m, rotation deg), offline scores per fusion
    method (none when the live part was stopped by Ctrl-C or SIGTERM: the demo ends there), and
    the live part (None with ``live=False``)."""

    out_dir: Path
    calibration_errors: dict[str, tuple[float, float]]
    scores: dict[str, EvaluationResult]
    live: LiveDemo | None = None


def shift_trajectory(trajectory: Trajectory, shift_s: float) -> Trajectory:
    """The same poses with every timestamp moved by ``shift_s``."""
    return Trajectory(trajectory.times_s + shift_s, trajectory.positions_m, trajectory.quats_xyzw)


def write_live_config(config_path: Path, urls: dict[str, str], out: Path) -> Path:
    """A copy of the tracker config at ``config_path`` whose cameras read ``urls`` (paths inside
    made absolute, so the copy works from any folder); returns where it was written."""
    config = read_tracker_config(config_path)
    cameras = [CameraConfig(c.name, urls[c.name], c.camera_info.resolve() if c.camera_info else None)
               for c in config.cameras]
    if any(r.layout_path is None for r in config.robots):
        raise ConfigError(f"{config_path}: every robot of a live demo config needs its layout file")
    robots = [(r.name, str(r.layout_path.resolve())) for r in config.robots if r.layout_path is not None]
    out.parent.mkdir(parents=True, exist_ok=True)
    write_toml(tracker_config_to_table(config.world, cameras, robots, config.sections), out)
    return out


def run_live_demo(rec_dir: Path, config_path: Path, extrinsics, out_dir: Path, settings: ConfigParams,
                  status: Callable[[LiveStatus], None] | None = None, sinks: Sequence[Sink] = ()) -> LiveDemo:
    """Serve ``rec_dir`` with the emulator on 127.0.0.1 (ephemeral ports), track it live over HTTP
    until the replay has ended, and score the result against the ground truth on the live clock."""
    rec = Recording.open(rec_dir)
    truth = read_tum(rec.ground_truth_path or rec_dir / "ground_truth.tum")
    live_dir = out_dir / "live"
    with EmulatedCameras(rec_dir) as emu:
        live_config = read_tracker_config(write_live_config(config_path, emu.urls, live_dir / "config.toml"))
        stop = threading.Event()
        span_s = emu.period_s

        def end_with_the_replay() -> None:
            if emu.wait_finished(span_s + 30.0):
                stop.wait(END_GRACE_S)
            stop.set()

        watcher = threading.Thread(target=end_with_the_replay, name="cubetrack-demo-end", daemon=True)
        watcher.start()
        try:
            result = track_live(live_config, extrinsics, live_dir / "track", settings.stages, settings.source,
                                live_params=settings.live, stop=stop, status=status,
                                duration_s=span_s + 30.0, sinks=sinks)
        finally:
            stop.set()
        shift_s = emu.clock_shift_s
    live_truth = shift_trajectory(truth, shift_s)
    truth_path = live_dir / "ground_truth_live.tum"
    write_tum(live_truth, truth_path)
    robot = live_config.robots[0].name
    score = None if result.interrupted else evaluate(read_tum(result.outputs[robot][0]), live_truth)
    return LiveDemo(settings.stages.fusion.method.value, score, result, shift_s, live_dir / "config.toml", truth_path)


def run_demo(out_dir: Path, sim: SimulationParams, methods: tuple[FusionMethod, ...] = tuple(FusionMethod),
             progress: Progress | None = None, live: bool = True,
             status: Callable[[LiveStatus], None] | None = None, sinks: Sequence[Sink] = ()) -> DemoResult:
    """Simulate a session into ``out_dir/rec``, calibrate, track it live over HTTP from the
    emulator (``live``), then replay it offline with each fusion method; evaluate everything.
    ``out_dir/run.json`` records the version, the scenario and the resolved parameters; each
    output inside has its own run record. ``sinks`` (other outputs) are fed the live session, or
    with ``live=False`` the last offline replay. Ctrl-C or SIGTERM during the live part end the
    demo after it, like the end of the replay would, but without the offline replays."""
    rec_dir = out_dir / "rec"
    simulate(sim, rec_dir, progress=progress)
    config = read_tracker_config(rec_dir / "config.toml")
    settings = config_params(config)
    write_run_record(out_dir / RUN_FILE, "demo", {"simulation": sim, **parameter_tables(settings)}, {},
                     {"live": live, "methods": [m.value for m in methods]})
    calibration = Recording.open(rec_dir / "calibration")
    report = run_calibration(config, calibration, out_dir / "extrinsics.toml", settings, progress=progress).report
    errors = extrinsics_errors(report.extrinsics, read_extrinsics(rec_dir / "true_extrinsics.toml"))
    truth = read_tum(rec_dir / "ground_truth.tum")
    base = settings.stages
    live_part = (run_live_demo(rec_dir, rec_dir / "config.toml", report.extrinsics, out_dir, settings, status, sinks)
                 if live else None)
    scores: dict[str, EvaluationResult] = {}
    if live_part is not None and live_part.result.interrupted:
        return DemoResult(out_dir, errors, scores, live_part)
    for method in methods:
        params = dataclasses.replace(base, fusion=dataclasses.replace(base.fusion, method=method))
        result = track_recording(config, Recording.open(rec_dir), report.extrinsics, out_dir / "track" / method.value,
                                 params, progress, () if live or method is not methods[-1] else sinks,
                                 extrinsics_path=out_dir / "extrinsics.toml")
        robot = config.robots[0].name
        scores[method.value] = evaluate(read_tum(result.outputs[robot][0]), truth)
    return DemoResult(out_dir, errors, scores, live_part)
