"""Issues 5 and 15's goal benchmark: our tracker against the paper's mean fusion on the paper's
arena, in the simulator's clean and realistic presets side by side.

Simulated recordings (``cubetrack simulate``) shaped like the paper's experiments: 3 cameras at
0.8 / 1.0 / 1.2 m (tilt 20 / 30 / 40°) and 5 cameras at 1.0 m (30°), 2.2 m from the arena
centre; the paper's cube (11 cm, 8 cm markers, one id on all five faces) on a robot driving a
figure eight; VGA greyscale JPEG q80; 7.5 fps per camera with latency jitter, spikes and 5 %
dropped frames; /time round trips recorded. Each scene in two presets (``--presets``):

- **clean**: the simulator's defaults (a pinhole camera with exactly known intrinsics, a global
  shutter, a perfect cube on a robot that never tilts, a figure eight at 0.25 m/s);
- **realistic**: ``SimulationParams.realistic()`` (``cubetrack simulate --realistic``: a
  wide-angle lens, intrinsics off as a calibration leaves them, a 30 ms rolling shutter, motion
  blur, sharp turns at 0.5 m/s on an uneven floor, a hand-built cube, light steps, people).

Every scene is tracked these ways (the same frames for each):

- **ours**: the default configuration (StageParams from the config: capture-time stamps from
  the camera clocks, ``[fusion] method = filter``) with the default robust calibration;
- **paper mean**: the paper's pipeline, as faithfully as the package allows: arrival-time stamps
  (``[track] timestamps = arrival``), the paper's mean over per-face poses (``[fusion] method =
  mean``, eq. 2) and the paper's CMA world-marker calibration (``[calibration] method = cma``,
  eq. 1). Detection and per-face estimation are the package's (edge-refined corners, upright
  face identification), which, if anything, makes this baseline better than the paper's;
- **our mean**: the paper's mean fusion on our calibration and capture-time stamps (reference);
- **ours + refine** (``--refine``, when :mod:`cubetrack.calib.bundle` exists): ours with the camera
  extrinsics refined from the cube observations of the tracking recording;
- **ours + body** (``--body``): ours with the body calibrated (``cubetrack calibrate-body``) from
  a separate drive of the same robot and cube, as a user would calibrate it (out of sample: the
  scene is rendered again for the session's duration plus ``--body-drive`` seconds, 60 by
  default, and only the frames after the session's end calibrate the body; the scored session
  plays no part), the remedy for the realistic preset's hand-built cube that ``cube.toml`` calls
  nominal;
- **README workflow** (``--workflow``): what the README's real-camera workflow gives with the
  default settings: ``cubetrack calibrate --recording calibration --refine-with DRIVE`` (a separate
  drive, made as for ``--body``: ``--body-drive`` seconds after the session's end), then ``cubetrack
  track --extrinsics`` on the session, both run as commands from the code under test; with
  ``--workflow-baseline COMMIT`` also **README workflow, baseline**: the same commands from that
  commit's ``host/`` (``git archive``, ``PYTHONPATH``) on the same recordings;
- **ours smoothed** (and **ours + body smoothed** with ``--body``): the same replay's poses
  smoothed over the whole recording (``cubetrack track --smooth``: a Rauch-Tung-Striebel smoother
  over the filter's states, :mod:`cubetrack.fuse.smoother`), what a user who records a session
  gets offline; the rows above are causal (each pose from the sightings up to its time, as live);
- **ours, fixed lag** (``--lag S``): ours with ``[filter] smooth_lag_s = S``, each pose smoothed
  over the sightings of the next S seconds, what a live user gets who waits that long;
- **ours + template** (``--template``): ours with ``[detector] corner_refinement = "template"``
  and nothing else changed (the nominal ``cube.toml``, the config's filter): what flipping the
  switch alone gives; with ``--body`` also **ours + body + template**: the calibrated body,
  template corners and a filter that trusts them (``[filter] corner_noise_px = 0.05``,
  ``angular_accel_noise = 5``: docs/tracking.md), smoothed too, and with ``--lag`` that lag.

and scored with :func:`cubetrack.evaluate.evaluate`: position and rotation RMSE against the ground
truth interpolated to each pose's own time (the paper's eq. 7 takes the nearest ground-truth
sample, up to 5 ms away at 100 Hz; that score is printed beside, "eq. 7"), detection ratio with a
0.5 s timeout (eq. 8) and the fraction of output poses more than 5 cm from the truth ("without inventing
poses": it must be 0). Targets, each in every configuration and for the worst seed: realistic
(issues 5 and 15) position RMSE <= 1.0 cm, rotation RMSE <= 1°; clean (issue 15) <= 0.3 cm and
<= 0.5°; both: detection ratio >= 0.99, no pose > 5 cm off, paper-mean RMSE / ours >= 5. Default
seeds differ from every seed the tests use (0-11).

Speed: on the first seed's recordings, one core (``cv2.setNumThreads(1)``, the process pinned to
one CPU), frames/s of the naive loop (``cv2.imdecode`` colour + default ``ArucoDetector``
(DICT_4X4_50) + ``solvePnP(SOLVEPNP_IPPE_SQUARE)`` per marker) and of our per-frame pipeline
(``cubetrack.app.tracker.Tracker.process`` over the merged frames with the clock round trips, then
``finish``: decode + detect + estimate + filter). The frames are read into memory first; the two
loops alternate (ABBA) for ``--speed-rounds`` rounds and the medians are reported (target: ours
at least the naive rate).

    .venv/bin/python benchmarks/accuracy.py [--duration 30] [--seeds 101 202 303] [--jobs 2]
                                            [--presets clean realistic] [--out DIR] [--quick] [--refine] [--body]
                                            [--body-drive 60] [--lag 0.05] [--template]

The exit code is 0 for a completed run (this is a report); the last line lists failing targets.
``--out`` keeps the recordings and writes ``accuracy_report.json``; an existing complete
recording made with the same parameters is reused, and so is a body calibrated by the same
code from the same drive and extrinsics (the scene's ``track/calibrated_body.toml``).
"""

from __future__ import annotations

import argparse
import dataclasses
import importlib.util
import json
import math
import os
import shutil
import statistics
import sys
import tempfile
import time
from concurrent.futures import ProcessPoolExecutor, as_completed
from pathlib import Path

import numpy as np

# (name, cameras, height m, tilt deg, the paper's published mean-fusion RMSE cm (Fig. 7, calibrated))
CONFIGS = (
    ("3 cams 0.8 m/20°", 3, 0.8, 20.0, 4.0),
    ("3 cams 1.0 m/30°", 3, 1.0, 30.0, 3.7),
    ("3 cams 1.2 m/40°", 3, 1.2, 40.0, 3.6),
    ("5 cams 1.0 m/30°", 5, 1.0, 30.0, 5.3),
)
DEFAULT_SEEDS = (101, 202, 303)  # the tests use seeds 0..11: these scenes were not tuned on
FPS = 7.5
DROP_RATE = 0.05
FAR_M = 0.05  # an output pose this far from the truth counts as invented

CLEAN, REALISTIC, RIG, HAND = "clean", "realistic", "rig", "hand"
PRESETS = (CLEAN, REALISTIC, RIG, HAND)
HAND_SPEED_M_S = 0.2  # the hand preset: the rig preset's body carried by hand (free 6-DoF) at this RMS speed
DEFAULT_PRESETS = (CLEAN, REALISTIC)
QUICK_REALISTIC = (1, 3)  # --quick renders the realistic and rig presets of these configurations only (they cost more)
# preset -> (position RMSE cm, rotation RMSE °)
TARGETS = {CLEAN: (0.3, 0.5), REALISTIC: (1.0, 1.0), RIG: (1.0, 1.0), HAND: (1.0, 1.0)}
TARGET_DR = 0.99
TARGET_RATIO = 5.0
TARGET_SPEED = 1.0

OURS, PAPER, OUR_MEAN, REFINED, BODY = "ours", "paper_mean", "our_mean", "ours_refined", "ours_body"
SMOOTHED, BODY_SMOOTHED, LAGGED = "ours_smoothed", "ours_body_smoothed", "ours_lag"
WORKFLOW, WORKFLOW_BASE = "readme_workflow", "readme_workflow_baseline"
TEMPLATE, BODY_TEMPLATE = "ours_template", "ours_body_template"
BODY_TEMPLATE_SMOOTHED, BODY_TEMPLATE_LAG = "ours_body_template_smoothed", "ours_body_template_lag"
SMOOTHED_OF = {OURS: SMOOTHED, BODY: BODY_SMOOTHED, BODY_TEMPLATE: BODY_TEMPLATE_SMOOTHED}  # a method -> its poses
# smoothed (the same replay)
WITH_BODY = (BODY, BODY_TEMPLATE, BODY_TEMPLATE_LAG)  # the methods tracked with the calibrated body
TRUSTING_FILTER = {"corner_noise_px": 0.05, "angular_accel_noise": 5.0}  # for template corners and a calibrated body
LABELS = {
    OURS: "ours (filter, robust cal)",
    SMOOTHED: "ours smoothed (offline)",
    LAGGED: "ours, fixed lag (--lag)",
    REFINED: "ours + refine",
    BODY: "ours + calibrate-body",
    BODY_SMOOTHED: "ours + body, smoothed",
    TEMPLATE: "ours + template",
    BODY_TEMPLATE: "ours + body + template",
    BODY_TEMPLATE_SMOOTHED: "ours + body + tmpl, smoothed",
    BODY_TEMPLATE_LAG: "ours + body + tmpl, lag",
    WORKFLOW: "README workflow",
    WORKFLOW_BASE: "README workflow, baseline",
    PAPER: "paper mean (CMA, arrival)",
    OUR_MEAN: "our mean (robust, capture)",
}
RATIO_KEYS = ((OURS, "ratio"), (SMOOTHED, "ratio_smoothed"), (LAGGED, "ratio_lag"), (REFINED, "ratio_refined"),
              (BODY, "ratio_body"), (BODY_SMOOTHED, "ratio_body_smoothed"), (TEMPLATE, "ratio_template"),
              (BODY_TEMPLATE, "ratio_body_template"), (BODY_TEMPLATE_SMOOTHED, "ratio_body_template_smoothed"),
              (BODY_TEMPLATE_LAG, "ratio_body_template_lag"), (WORKFLOW, "ratio_workflow"),
              (WORKFLOW_BASE, "ratio_workflow_baseline"))  # our methods with targets, their RMSE ratio's key
COMPLETE_FILE = "bench-complete.json"
REPORT_FILE = "accuracy_report.json"
ROBUST_EXTRINSICS_FILE = "extrinsics_robust.toml"


def code_version() -> str:
    """The commit the run's code is at, and the host files changed since (the code moves)."""
    import subprocess

    root = Path(__file__).resolve().parents[1]
    try:
        head = subprocess.run(["git", "-C", str(root), "rev-parse", "--short", "HEAD"], capture_output=True,
                              text=True, timeout=10).stdout.strip()
        dirty = subprocess.run(["git", "-C", str(root), "status", "--porcelain", "--", "host"], capture_output=True,
                               text=True, timeout=10).stdout.split("\n")
    except (OSError, subprocess.SubprocessError):
        return "unknown (no git)"
    changed = [line[3:].removeprefix("host/cubetrack/") for line in dirty if line.strip()]
    return f"git {head or '?'}" + (f" + uncommitted {', '.join(changed)}" if changed else "")


def commit_host(commit: str, into: Path) -> str:
    """``host/`` of ``commit`` extracted (``git archive``) under ``into`` (emptied first); its path."""
    import subprocess

    shutil.rmtree(into, ignore_errors=True)
    into.mkdir(parents=True)
    root = Path(__file__).resolve().parents[1]
    archive = subprocess.run(["git", "-C", str(root), "archive", commit, "host"], capture_output=True, check=True)
    subprocess.run(["tar", "-x", "-C", str(into)], input=archive.stdout, check=True)
    return str(into / "host")


def refine_available() -> bool:
    return importlib.util.find_spec("cubetrack.calib.bundle") is not None


# --------------------------------------------------------------------------------- scenes


def sim_params(preset: str, cameras: int, height: float, tilt: float, seed: int, duration: float,
               calibration_frames: int):
    from cubetrack.simulate import SimulationParams

    common = {"cameras": cameras, "height_m": height, "tilt_deg": tilt, "seed": seed, "duration_s": duration,
              "drop_rate": DROP_RATE, "jpeg_quality": 80, "cube_size_m": 0.11, "marker_size_m": 0.08,
              "calibration_frames": calibration_frames}
    if preset == RIG:   # its own frame rate, image size, inverted markers with distinct ids
        return SimulationParams.rig(**common)
    if preset == HAND:  # the same, carried by hand
        return SimulationParams.rig(**common, path="handheld", speed_m_s=HAND_SPEED_M_S)
    make = SimulationParams.realistic if preset == REALISTIC else SimulationParams
    return make(**common, fps=FPS, distinct_ids=False)


def scene_dir(work: Path, config_index: int, seed: int, preset: str = CLEAN) -> Path:
    _, cameras, height, tilt, _ = CONFIGS[config_index]
    prefix = {REALISTIC: "real_", RIG: "rig_", HAND: "hand_"}.get(preset, "")
    return work / f"{prefix}c{cameras}_h{height:g}_t{tilt:g}_s{seed}"


def ensure_recording(params, rec: Path, workers: int) -> tuple[float, bool]:
    """Render ``rec`` unless it already holds a complete recording of ``params``; (seconds, reused)."""
    from cubetrack.core.params import params_to_table
    from cubetrack.simulate import simulate

    want = json.loads(json.dumps(params_to_table(params)))
    marker = rec / COMPLETE_FILE
    if marker.exists():
        try:
            if json.loads(marker.read_text(encoding="utf-8")) == want:
                return 0.0, True
        except (OSError, json.JSONDecodeError):
            pass
        marker.unlink()
    t0 = time.monotonic()
    simulate(params, rec, overwrite=True, workers=workers)
    marker.write_text(json.dumps(want), encoding="utf-8")
    return time.monotonic() - t0, False


def camera_distances(rec: Path) -> tuple[float, float, float]:
    """(min, median, max) distance from a camera to the cube centre over the session, metres."""
    import tomllib

    from cubetrack.io.trajectory import read_tum

    sim = tomllib.loads((rec / "simulation.toml").read_text(encoding="utf-8"))
    cams = np.array([c["position"] for c in sim["cameras"].values()])
    truth = read_tum(rec / "ground_truth.tum").positions_m
    d = np.linalg.norm(truth[:, None, :] - cams[None, :, :], axis=2)
    return float(d.min()), float(np.median(d)), float(d.max())


# a method that produced nothing
MISSING = {"pos_cm": math.nan, "rot_deg": math.nan, "pos_cm_eq7": math.nan, "rot_deg_eq7": math.nan, "dr": 0.0,
           "far": math.nan, "far_count": 0, "poses": 0, "scored": 0, "rate_hz": 0.0, "max_cm": math.nan}


def score(tum: Path, truth) -> dict:
    """The scores of one TUM trajectory against the truth."""
    from cubetrack.evaluate.metrics import evaluate
    from cubetrack.io.trajectory import read_tum

    traj = read_tum(tum)
    if len(traj) == 0:
        return dict(MISSING)
    s = evaluate(traj, truth)
    far = int(np.sum(s.position_errors_m > FAR_M))
    return {
        "pos_cm": s.position_rmse_m * 100.0,
        "rot_deg": s.rotation_rmse_deg,
        "pos_cm_eq7": s.position_rmse_nearest_m * 100.0,
        "rot_deg_eq7": s.rotation_rmse_nearest_deg,
        "dr": s.detection_ratio,
        "far": far / s.poses_scored if s.poses_scored else math.nan,
        "far_count": far,
        "poses": s.poses_total,
        "scored": s.poses_scored,
        "rate_hz": s.output_rate_hz,
        "max_cm": float(np.max(s.position_errors_m)) * 100.0 if s.poses_scored else math.nan,
    }


def calibration_error(extrinsics: dict, truth: dict) -> tuple[float, float]:
    """Mean over cameras of (position error mm, rotation error deg) of calibrated extrinsics."""
    from cubetrack.calib.extrinsics import extrinsics_errors

    errs = list(extrinsics_errors(extrinsics, truth).values())
    return float(np.mean([e[0] for e in errs]) * 1000.0), float(np.mean([e[1] for e in errs]))


def run_scene(work: str, preset: str, config_index: int, seed: int, duration: float, calibration_frames: int,
              workers: int, refine: bool, body_drive_s: float = 0.0, lag_s: float = 0.0,
              template: bool = False, workflow: dict[str, str] | None = None, body: bool = True) -> dict:
    """Simulate (or reuse) one scene, calibrate it both ways, track it every way, score it
    (``body_drive_s`` > 0: also with the body calibrated from a drive of that many seconds;
    ``lag_s`` > 0: also with that fixed lag; ``template``: also with template corners;
    ``workflow``: also the README workflow by each tree, method -> its ``host/``, with that drive;
    ``body`` False: the drive for the workflow only)."""
    from cubetrack.app.calibrate import calibrate_recording
    from cubetrack.app.track import track_recording
    from cubetrack.app.tracker import StageParams, Timestamps
    from cubetrack.calib.extrinsics import CalibrationMethod, CalibrationParams
    from cubetrack.detect.detector import CornerRefinement
    from cubetrack.fuse.fusion import FusionMethod
    from cubetrack.io.config import read_extrinsics, read_tracker_config, write_extrinsics
    from cubetrack.io.recording import Recording
    from cubetrack.io.trajectory import read_tum

    name, cameras, height, tilt, _ = CONFIGS[config_index]
    rec = scene_dir(Path(work), config_index, seed, preset)
    t0 = time.monotonic()
    render_s, reused = ensure_recording(sim_params(preset, cameras, height, tilt, seed, duration, calibration_frames),
                                        rec, workers)
    t1 = time.monotonic()
    config = read_tracker_config(rec / "config.toml")
    robot = config.robots[0].name
    truth = read_tum(rec / "ground_truth.tum")
    true_extrinsics = read_extrinsics(rec / "true_extrinsics.toml")
    calibration = Recording.open(rec / "calibration")
    ours_ext = calibrate_recording(config, calibration).extrinsics  # the config's default: robust
    (rec / "track").mkdir(exist_ok=True)
    write_extrinsics(ours_ext, rec / "track" / ROBUST_EXTRINSICS_FILE)  # for the speed measurement
    cma_ext = calibrate_recording(config, calibration, CalibrationParams(method=CalibrationMethod.CMA)).extrinsics
    t2 = time.monotonic()

    base = StageParams.from_config(config)
    paper = dataclasses.replace(base, fusion=dataclasses.replace(base.fusion, method=FusionMethod.MEAN),
                                track=dataclasses.replace(base.track, timestamps=Timestamps.ARRIVAL))
    our_mean = dataclasses.replace(base, fusion=dataclasses.replace(base.fusion, method=FusionMethod.MEAN))
    variants = {OURS: (base, ours_ext), PAPER: (paper, cma_ext), OUR_MEAN: (our_mean, ours_ext)}
    out: dict = {"preset": preset, "config": config_index, "seed": seed, "methods": {}, "calibration": {}}
    if refine:
        t_refine = time.monotonic()
        try:
            refined_ext, refine_info = refine_extrinsics(config, rec, ours_ext)
        except Exception as exc:  # a failing refinement is reported, not fatal to the whole run
            refined_ext, refine_info = None, {"error": f"{type(exc).__name__}: {exc}"}
        refine_info["seconds"] = time.monotonic() - t_refine
        out["refine"] = refine_info
        if refined_ext is not None:
            variants[REFINED] = (base, refined_ext)
            out["calibration"][REFINED] = calibration_error(refined_ext, true_extrinsics)
    if body_drive_s > 0:
        t_body = time.monotonic()
        full = rec.with_name(rec.name + "_drive")
        ensure_recording(sim_params(preset, cameras, height, tilt, seed, duration + body_drive_s, 0), full, workers)
        drive = later_part(full, rec.with_name(rec.name + "_drive_after"),
                           read_sim_start_s(full) + duration)
        for method, host in (workflow or {}).items():
            out["methods"][method] = score(readme_workflow(host, rec, drive, rec / "track" / method, robot), truth)
        if body:
            config_body, out["body"] = calibrated_body(config, drive, rec, ours_ext, robot)
            out["body"].update(seconds=time.monotonic() - t_body, drive_s=body_drive_s)
    out["calibration"]["robust"] = calibration_error(ours_ext, true_extrinsics)
    out["calibration"]["cma"] = calibration_error(cma_ext, true_extrinsics)
    body = body and body_drive_s > 0
    if body:
        variants[BODY] = (base, ours_ext)
    if lag_s > 0:
        variants[LAGGED] = (dataclasses.replace(base, filter=dataclasses.replace(base.filter, smooth_lag_s=lag_s)),
                            ours_ext)
    if template:
        templated = dataclasses.replace(  # as a config saying corner_refinement = "template" resolves (app.config)
            base, detector=dataclasses.replace(base.detector, corner_refinement=CornerRefinement.TEMPLATE),
            filter=dataclasses.replace(base.filter, corner_noise_by_width=False))
        variants[TEMPLATE] = (templated, ours_ext)
        if body:
            trusting = dataclasses.replace(templated, filter=dataclasses.replace(templated.filter, **TRUSTING_FILTER))
            variants[BODY_TEMPLATE] = (trusting, ours_ext)
            if lag_s > 0:
                variants[BODY_TEMPLATE_LAG] = (dataclasses.replace(trusting, filter=dataclasses.replace(
                    trusting.filter, smooth_lag_s=lag_s)), ours_ext)
    for key, (params, extrinsics) in variants.items():
        result = track_recording(config_body if key in WITH_BODY else config, Recording.open(rec), extrinsics,
                                 rec / "track" / key, params, smooth=key in SMOOTHED_OF)
        out["methods"][key] = score(result.outputs[robot][0], truth)
        if key in SMOOTHED_OF:
            out["methods"][SMOOTHED_OF[key]] = score(result.smoothed[robot][0], truth)
    t3 = time.monotonic()
    out["distance_m"] = camera_distances(rec)
    out["seconds"] = {"render": render_s, "reused": reused, "calibrate": t2 - t1, "track": t3 - t2,
                      "total": t3 - t0}
    return out


def readme_workflow(host: str, rec: Path, drive: Path, out: Path, robot: str) -> Path:
    """The README's real-camera workflow by the code in ``host`` (``PYTHONPATH``), as commands:
    ``calibrate --refine-with`` the ``drive``, then ``track`` the session ``rec`` into ``out``;
    the robot's TUM file (empty when a command failed: the method then scores as missing)."""
    import subprocess

    env = dict(os.environ, PYTHONPATH=host)
    cli = [sys.executable, "-m", "cubetrack.cli.main"]
    config, extrinsics = rec / "config.toml", out / "extrinsics.toml"
    out.mkdir(parents=True, exist_ok=True)
    tum = out / f"{robot}.tum"
    tum.unlink(missing_ok=True)
    for args in (["calibrate", "--config", config, "--recording", rec / "calibration", "--refine-with", drive,
                  "--out", extrinsics],
                 ["track", "--config", config, "--extrinsics", extrinsics, "--recording", rec, "--out", out]):
        proc = subprocess.run([*cli, *map(str, args)], env=env, capture_output=True, text=True, check=False)
        (out / f"{args[0]}.log").write_text(proc.stdout + proc.stderr, encoding="utf-8")
        if proc.returncode != 0:
            tum.write_text("", encoding="utf-8")
            break
    return tum


def refine_extrinsics(config, rec: Path, extrinsics: dict) -> tuple[dict, dict]:
    """Our extrinsics refined from the cube observations of the tracking recording and the world
    marker of the calibration recording (:func:`cubetrack.app.calibrate.adjust_recording_extrinsics`, default
    parameters); (extrinsics, what the refinement reported)."""
    from cubetrack.app.calibrate import adjust_recording_extrinsics as refine
    from cubetrack.io.recording import Recording

    report = refine(config, Recording.open(rec), extrinsics, calibration=Recording.open(rec / "calibration"))
    info = {"instants": report.instants, "moved": list(report.moved), "warnings": list(report.warnings),
            "rms_px": {c: r.rms_px for c, r in report.cameras.items()}}
    return report.extrinsics, info


def read_sim_start_s(rec: Path) -> float:
    """The host clock at the start of a simulated recording (its ``simulation.toml``), Unix seconds."""
    import tomllib

    return float(tomllib.loads((rec / "simulation.toml").read_text(encoding="utf-8"))["params"]["start_unix_s"])


def later_part(rec: Path, out: Path, after_host_s: float) -> Path:
    """A copy of recording ``rec`` at ``out`` with only the frames that arrived at least 1 s after
    ``after_host_s`` (host clock: a frame captured before it would have taken over 1 s to arrive),
    every /time round trip and the camera_info files: a drive of its own, after the session that
    ends at ``after_host_s``."""
    from cubetrack.io.recording import CameraEntry, Recording, RecordingWriter

    src = Recording.open(rec)
    shutil.rmtree(out, ignore_errors=True)
    with RecordingWriter(out, [CameraEntry(c) for c in src.camera_names]) as w:
        for c in src.camera_names:
            for frame in src.frames(c):
                if frame.host_time_s >= after_host_s + 1.0:
                    w.add_frame(c, frame.seq, frame.device_time_s, frame.host_time_s, frame.jpeg)
            for sample in src.clock_samples(c):
                w.add_clock_sample(c, sample)
            info = src.camera_info_path(c)
            if info is not None:
                shutil.copyfile(info, w.camera_info_path(c))
    return out


def calibrated_body(config, drive: Path, rec: Path, extrinsics: dict, robot: str):
    """``config`` with ``robot``'s layout calibrated from the recording ``drive``
    (:func:`cubetrack.app.calibrate.calibrate_recording_body`, default parameters), and the worst
    marker placement errors (mm, degrees) of the nominal and the calibrated layout against the
    cube as built (``rec``'s ``true_cube.toml``)."""
    from cubetrack.app.calibrate import calibrate_recording_body
    from cubetrack.calib.body import placement_errors
    from cubetrack.core.layout import read_layout, write_layout
    from cubetrack.io.recording import Recording

    cached, key = rec / "track" / BODY_CACHE_FILE, body_cache_key(drive, extrinsics)
    key_file = cached.with_suffix(".key")
    if cached.exists() and key_file.exists() and key_file.read_text(encoding="utf-8") == key:
        layout, reused = read_layout(cached), True
    else:
        layout, reused = calibrate_recording_body(config, Recording.open(drive), extrinsics, robot).layout, False
        write_layout(layout, cached)
        key_file.write_text(key, encoding="utf-8")
    robots = tuple(dataclasses.replace(r, layout=layout) if r.name == robot else r for r in config.robots)
    truth = read_layout(rec / "true_cube.toml")
    nominal = next(r.layout for r in config.robots if r.name == robot)
    worst = {name: (max(e[0] for e in errs.values()) * 1000.0, max(e[1] for e in errs.values()))
             for name, errs in (("nominal", placement_errors(nominal, truth)),
                                ("calibrated", placement_errors(layout, truth)))}
    return dataclasses.replace(config, robots=robots), {"placement_worst_mm_deg": worst, "reused": reused}


BODY_CACHE_FILE = "calibrated_body.toml"


def body_cache_key(drive: Path, extrinsics: dict) -> str:
    """What a cached calibrated body depends on: the drive (its completeness marker), the
    extrinsics it started from and the package code that calibrates it (every module of calib/,
    detect/, estimate/, core/, fuse/, app/calibrate.py and io/), as one SHA-256."""
    import hashlib

    host = Path(__file__).resolve().parents[1] / "host" / "cubetrack"
    digest = hashlib.sha256()
    for name in sorted(extrinsics):
        digest.update(name.encode() + np.asarray(extrinsics[name].T_world_cam, float).tobytes())
    for path in sorted((*(p for d in ("calib", "detect", "estimate", "core", "fuse", "io")
                          for p in (host / d).glob("*.py")), host / "app" / "calibrate.py")):
        digest.update(path.read_bytes())
    marker = drive.parent / drive.name.removesuffix("_after") / COMPLETE_FILE
    digest.update(marker.read_bytes() if marker.exists() else b"")
    return digest.hexdigest()


# --------------------------------------------------------------------------------- speed


def _load_events(rec: Path, max_frames: int | None):
    """The recording's frames (in memory, arrival order) interleaved with its /time round trips
    exactly as :func:`cubetrack.app.track.track_recording` feeds them."""
    from cubetrack.io.recording import Recording

    recording = Recording.open(rec)
    frames = []
    for frame in recording.merged_frames():
        frames.append(frame)
        if max_frames and len(frames) >= max_frames:
            break
    trips = sorted(((s.host_recv_s, c, s) for c in recording.camera_names for s in recording.clock_samples(c)),
                   key=lambda item: (item[0], item[1]))
    events, k = [], 0
    for frame in frames:
        while k < len(trips) and trips[k][0] <= frame.host_time_s:
            events.append((trips[k][1], trips[k][2]))
            k += 1
        events.append(frame)
    synced = frozenset(c for c in recording.camera_names if recording.clock_samples(c))
    return recording, frames, events, synced


class SpeedCase:
    """One recording's frames, ready for both loops."""

    def __init__(self, rec: Path, max_frames: int | None):
        import cv2

        from cubetrack.app.calibrate import calibrate_recording
        from cubetrack.app.track import recording_intrinsics
        from cubetrack.app.tracker import StageParams
        from cubetrack.core.layout import marker_corners_m
        from cubetrack.io.config import read_extrinsics, read_tracker_config
        from cubetrack.io.recording import Recording

        self.config = read_tracker_config(rec / "config.toml")
        recording, self.frames, self.events, self.synced = _load_events(rec, max_frames)
        self.intrinsics = recording_intrinsics(self.config, recording)
        saved = rec / "track" / ROBUST_EXTRINSICS_FILE
        self.extrinsics = (read_extrinsics(saved) if saved.exists()
                           else calibrate_recording(self.config, Recording.open(rec / "calibration")).extrinsics)
        self.params = StageParams.from_config(self.config)
        sizes = {self.config.world.marker_id: self.config.world.marker_size_m}
        for robot in self.config.robots:
            for m in robot.layout.markers:
                sizes.setdefault(m.marker_id, m.size_m)
        self.objects = {i: np.ascontiguousarray(marker_corners_m(s), dtype=np.float64) for i, s in sizes.items()}
        self.K = {c: (i.K, i.dist) for c, i in self.intrinsics.items()}
        self.naive_detector = cv2.aruco.ArucoDetector(cv2.aruco.getPredefinedDictionary(cv2.aruco.DICT_4X4_50))

    def naive(self, limit: int | None = None) -> tuple[float, float, int]:
        """(wall s, CPU s, marker poses) of the naive loop over the frames (the first ``limit``)."""
        import cv2

        det, objects, K = self.naive_detector, self.objects, self.K
        poses = 0
        w0, c0 = time.perf_counter(), time.process_time()
        for frame in self.frames[:limit]:
            img = cv2.imdecode(np.frombuffer(frame.jpeg, np.uint8), cv2.IMREAD_COLOR)
            corners, ids, _ = det.detectMarkers(img)
            if ids is None:
                continue
            k, dist = K[frame.camera]
            for c, marker_id in zip(corners, ids.reshape(-1), strict=True):
                obj = objects.get(int(marker_id))
                if obj is None:
                    continue
                ok, _, _ = cv2.solvePnP(obj, c.reshape(4, 2), k, dist, flags=cv2.SOLVEPNP_IPPE_SQUARE)
                poses += bool(ok)
        return time.perf_counter() - w0, time.process_time() - c0, poses

    def ours(self, limit: int | None = None) -> tuple[float, float, int]:
        """(wall s, CPU s, robot poses) of the tracker over the same frames (plus the round trips)."""
        from cubetrack.app.tracker import Tracker

        tracker = Tracker(self.intrinsics, self.config.world, self.config.robots, self.extrinsics, self.params,
                          self.synced)
        poses = 0
        w0, c0 = time.perf_counter(), time.process_time()
        for event in self.events[:limit]:
            if isinstance(event, tuple):
                poses += len(tracker.add_clock_sample(*event))
            else:
                poses += len(tracker.process(event))
        poses += len(tracker.finish())
        return time.perf_counter() - w0, time.process_time() - c0, poses


def measure_speed(recs: list[Path], rounds: int, max_frames: int | None, warmup_frames: int = 40) -> dict:
    """Interleaved single-core timing of both loops over the recordings; medians over rounds."""
    import cv2

    cv2.setNumThreads(1)
    pinned = None
    if hasattr(os, "sched_getaffinity"):
        pinned = os.sched_getaffinity(0)
        os.sched_setaffinity(0, {min(pinned)})
    try:
        cases = [SpeedCase(r, max_frames) for r in recs]
        for case in cases:  # warm-up: first-call costs (imports, allocations, caches) out of the timing
            case.naive(warmup_frames)
            case.ours(warmup_frames)
        frames = sum(len(c.frames) for c in cases)
        rows = []  # per round: naive wall, ours wall, naive cpu, ours cpu
        outputs = {"naive": 0, "ours": 0}
        for r in range(rounds):
            order = ("naive", "ours") if r % 2 == 0 else ("ours", "naive")
            t = {"naive": [0.0, 0.0], "ours": [0.0, 0.0]}
            for case in cases:
                for which in order:
                    wall, cpu, count = getattr(case, which)()
                    t[which][0] += wall
                    t[which][1] += cpu
                    outputs[which] += count if r == 0 else 0
            rows.append((t["naive"][0], t["ours"][0], t["naive"][1], t["ours"][1]))
    finally:
        if pinned is not None:
            os.sched_setaffinity(0, pinned)
    naive_fps = [frames / r[0] for r in rows]
    ours_fps = [frames / r[1] for r in rows]
    ratio = [r[0] / r[1] for r in rows]
    ratio_cpu = [r[2] / r[3] for r in rows]
    return {
        "frames": frames,
        "recordings": [str(r.name) for r in recs],
        "rounds": rounds,
        "naive_fps": statistics.median(naive_fps),
        "ours_fps": statistics.median(ours_fps),
        "ratio": statistics.median(ratio),
        "ratio_cpu": statistics.median(ratio_cpu),
        "ratio_min": min(ratio),
        "ratio_max": max(ratio),
        "per_round": rows,
        "naive_marker_poses": outputs["naive"],
        "ours_robot_poses": outputs["ours"],
    }


# --------------------------------------------------------------------------------- report


def _agg(values: list[float]) -> tuple[float, float, float]:
    v = np.array(values, dtype=float)
    return float(np.mean(v)), float(np.min(v)), float(np.max(v))


def build_report(scenes: list[dict], seeds: list[int], methods: list[str]) -> dict:
    """Rows per configuration and preset (``"<preset> <configuration>"``), configurations in
    order, clean before realistic: each method's mean / best / worst over the seeds."""
    rows = {}
    for ci, preset in ((ci, preset) for ci in range(len(CONFIGS)) for preset in PRESETS):
        name, published = CONFIGS[ci][0], CONFIGS[ci][4]
        mine = sorted((s for s in scenes if s["config"] == ci and s["preset"] == preset), key=lambda s: s["seed"])
        if not mine:
            continue
        row = {"name": name, "preset": preset, "published_paper_mean_cm": published, "seeds": [s["seed"] for s in mine],
               "methods": {}, "distance_m": (min(s["distance_m"][0] for s in mine),
                                             float(np.median([s["distance_m"][1] for s in mine])),
                                             max(s["distance_m"][2] for s in mine)),
               "calibration": {k: tuple(np.mean([s["calibration"][k] for s in mine if k in s["calibration"]], axis=0))
                               for k in dict.fromkeys(k for s in mine for k in s["calibration"])},
               "refine": [s.get("refine") for s in mine], "body": [s.get("body") for s in mine]}
        for m in methods:
            per = [s["methods"].get(m, MISSING) for s in mine]
            row["methods"][m] = {k: _agg([p[k] for p in per])
                                 for k in ("pos_cm", "rot_deg", "pos_cm_eq7", "rot_deg_eq7",
                                           "dr", "far", "rate_hz", "max_cm")}
            row["methods"][m]["per_seed"] = per
        ratios = [s["methods"][PAPER]["pos_cm"] / s["methods"][OURS]["pos_cm"] for s in mine]
        row["ratio"] = _agg(ratios)
        row["ratio_per_seed"] = ratios
        for method, key in RATIO_KEYS[1:]:
            if method in methods:
                row[key] = _agg([s["methods"][PAPER]["pos_cm"] / s["methods"].get(method, MISSING)["pos_cm"]
                                 for s in mine])
        rows[f"{preset} {name}"] = row
    return {"seeds": seeds, "configs": rows}


def _worst_failures(report: dict, method: str, ratio_key: str) -> tuple[list[str], list[tuple]]:
    """Target checks for one of our methods: (failing target names, printable rows)."""
    failures, lines = [], []
    for name, row in report["configs"].items():
        m = row["methods"][method]
        pos, rot, dr, far, ratio = m["pos_cm"][2], m["rot_deg"][2], m["dr"][1], m["far"][2], row[ratio_key][1]
        target_pos, target_rot = TARGETS[row["preset"]]
        checks = [
            (f"pos ≤ {target_pos:g} cm", f"{pos:.2f}", pos <= target_pos),
            (f"rot ≤ {target_rot:g}°", f"{rot:.2f}", rot <= target_rot),
            (f"DR ≥ {TARGET_DR:g}", f"{dr:.3f}", dr >= TARGET_DR),
            (f">{FAR_M * 100:g} cm = 0", f"{far:.4f}", far == 0.0),
            (f"ratio ≥ {TARGET_RATIO:g}", f"{ratio:.1f}", ratio >= TARGET_RATIO),
        ]
        lines.append((name, checks))
        failures += [f"{name}: {label} (worst {value})" for label, value, ok in checks if not ok]
    return failures, lines


def fmt(v: float, spec: str) -> str:
    return "nan" if v is None or (isinstance(v, float) and math.isnan(v)) else format(v, spec)


def print_report(report: dict, speed: dict | None, methods: list[str], duration: float, wall_s: float,
                 work: Path, kept: bool) -> list[str]:
    p = print
    seeds = report["seeds"]
    p()
    p(f"accuracy benchmark (issues 5, 15): seeds {' '.join(map(str, seeds))}, {duration:g} s per session, "
      f"{FPS:g} fps, {DROP_RATE:.0%} dropped, VGA JPEG q80, one id on five 8 cm faces of an 11 cm cube; "
      f"presets {', '.join(sorted({r['preset'] for r in report['configs'].values()}, key=PRESETS.index))}")
    p(f"code: {report['code']}")
    p("mean / worst over seeds; worst = max for errors, min for detection ratio and RMSE ratio")
    p()
    head = (f"{'configuration':<18} {'preset':<9} {'method':<27} {'pos RMSE cm':>13} {'rot RMSE °':>13} "
            f"{'det. ratio':>13} {'>5cm':>7} {'max cm':>7} {'poses/s':>7}")
    p(head)
    p(f"{'':<18} {'':<9} {'':<27} {'mean  worst':>13} {'mean  worst':>13} {'mean  worst':>13} {'worst':>7} "
      f"{'worst':>7} {'mean':>7}")
    p("-" * len(head))
    shown = set()
    for row in report["configs"].values():
        name = row["name"]
        first = True
        for m in methods:
            s = row["methods"][m]
            p(f"{name if name not in shown else '':<18} {row['preset'] if first else '':<9} {LABELS[m]:<27} "
              f"{fmt(s['pos_cm'][0], '6.2f')} {fmt(s['pos_cm'][2], '6.2f')} "
              f"{fmt(s['rot_deg'][0], '6.2f')} {fmt(s['rot_deg'][2], '6.2f')} "
              f"{fmt(s['dr'][0], '6.3f')} {fmt(s['dr'][1], '6.3f')} "
              f"{fmt(s['far'][2], '7.4f')} {fmt(s['max_cm'][2], '7.2f')} {fmt(s['rate_hz'][0], '7.1f')}")
            first = False
            shown.add(name)
        r = row["ratio"]
        extra = ""
        if "ratio_refined" in row:
            extra = f"; with refine {row['ratio_refined'][0]:.1f} (worst {row['ratio_refined'][1]:.1f})"
        d = row["distance_m"]
        cal = row["calibration"]
        cal_text = ", ".join(f"{k} {v[0]:.1f} mm/{v[1]:.2f}°" for k, v in cal.items())
        p(f"{'':<18} RMSE ratio paper mean / ours: {r[0]:.1f} (worst {r[1]:.1f}){extra}; "
          f"published paper mean {row['published_paper_mean_cm']:.1f} cm")
        p(f"{'':<18} camera-cube {d[0]:.1f}-{d[2]:.1f} m (median {d[1]:.1f}); calibration error {cal_text}")
        per = " ".join(f"s{sd}: {o['pos_cm']:.2f}/{pm['pos_cm']:.2f}"
                       for sd, o, pm in zip(row["seeds"], row["methods"][OURS]["per_seed"],
                                            row["methods"][PAPER]["per_seed"], strict=True))
        p(f"{'':<18} per seed, ours/paper-mean cm: {per}")
        eq7 = row["methods"][OURS]
        p(f"{'':<18} ours against the nearest ground-truth sample (eq. 7), worst: "
          f"{fmt(eq7['pos_cm_eq7'][2], '.2f')} cm / {fmt(eq7['rot_deg_eq7'][2], '.2f')}°")
        for sd, info in zip(row["seeds"], row["refine"], strict=True):
            if info is None:
                continue
            if "error" in info:
                p(f"{'':<18} refine FAILED on seed {sd}: {info['error']}")
            else:
                moved = f", moved: {', '.join(info['moved'])}" if info["moved"] else ""
                p(f"{'':<18} refine seed {sd}: {info['instants']} instants, {info['seconds']:.0f} s, "
                  f"{len(info['warnings'])} warning(s){moved}")
        for sd, info in zip(row["seeds"], row["body"], strict=True):
            if info is not None:
                worst = info["placement_worst_mm_deg"]
                (n_mm, n_deg), (c_mm, c_deg) = worst["nominal"], worst["calibrated"]
                how = "reused" if info.get("reused") else f"{info['seconds']:.0f} s"
                p(f"{'':<18} calibrate-body seed {sd} (a separate {info['drive_s']:g} s drive): {how}; "
                  f"worst marker placement nominal "
                  f"{n_mm:.2f} mm / {n_deg:.2f}°, calibrated {c_mm:.2f} mm / {c_deg:.2f}°")
    p()
    failures = []
    for method, ratio_key in RATIO_KEYS:
        if method not in methods:
            continue
        fails, lines = _worst_failures(report, method, ratio_key)
        p(f"targets for {LABELS[method]} (worst seed):")
        for name, checks in lines:
            cells = "  ".join(f"{label} {value} {'PASS' if ok else 'FAIL'}" for label, value, ok in checks)
            p(f"  {name:<28} {cells}")
        failures += [f"[{LABELS[method]}] {f}" for f in fails] if method != OURS else fails
    p()
    if speed is not None:
        ok = speed["ratio"] >= TARGET_SPEED
        p(f"speed (one core, {speed['frames']} frames of {', '.join(speed['recordings'])}, "
          f"median of {speed['rounds']} interleaved rounds): naive loop {speed['naive_fps']:.1f} frames/s, "
          f"ours {speed['ours_fps']:.1f} frames/s, ratio ours/naive {speed['ratio']:.2f} "
          f"(range {speed['ratio_min']:.2f}-{speed['ratio_max']:.2f}; CPU-time ratio {speed['ratio_cpu']:.2f}) "
          f"target ≥ {TARGET_SPEED:g}: {'PASS' if ok else 'FAIL'}")
        if not ok:
            failures.append(f"speed: ours/naive {speed['ratio']:.2f} < {TARGET_SPEED:g}")
    p(f"total {wall_s:.0f} s; recordings {'kept in ' + str(work) if kept else 'deleted'}")
    if failures:
        p(f"SUMMARY: {len(failures)} target(s) FAIL: " + "; ".join(failures))
    else:
        p("SUMMARY: all targets PASS")
    return failures


# --------------------------------------------------------------------------------- main


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--duration", type=float, default=None, help="seconds per simulated session (default 30; "
                    "--quick: 8)")
    ap.add_argument("--seeds", type=int, nargs="+", default=list(DEFAULT_SEEDS),
                    help=f"scene seeds (default {' '.join(map(str, DEFAULT_SEEDS))}: none used by the tests)")
    ap.add_argument("--out", type=Path, help="keep recordings and accuracy_report.json here (default: a temporary "
                    "folder, deleted); complete recordings with the same parameters are reused")
    ap.add_argument("--quick", action="store_true", help="smoke run: the first seed only, short sessions, "
                    "12 calibration frames, a short speed measurement")
    ap.add_argument("--jobs", type=int, default=1, help="scenes rendered and tracked in parallel processes "
                    "(default 1)")
    ap.add_argument("--refine", action="store_true", help="also report ours with extrinsics refined from cube "
                    "observations (cubetrack.calib.bundle)")
    ap.add_argument("--body", action="store_true", help="also report ours with the body calibrated (cubetrack "
                    "calibrate-body) from a separate drive of the same robot (out of sample: the frames after the "
                    "session's end of the scene rendered for --duration + --body-drive seconds)")
    ap.add_argument("--body-drive", type=float, default=60.0, help="seconds of driving that --body calibrates the body "
                    "from (default 60)")
    ap.add_argument("--lag", type=float, default=0.0, metavar="S", help="also report ours with [filter] "
                    "smooth_lag_s = S (each pose smoothed over the next S seconds of sightings, as "
                    "live; default 0: not)")
    ap.add_argument("--template", action="store_true", help="also report ours with [detector] corner_refinement = "
                    "template (and, with --body, the calibrated body, template corners and a filter that trusts them)")
    ap.add_argument("--workflow", action="store_true", help="also report the README workflow: cubetrack calibrate "
                    "--refine-with a separate drive of --body-drive seconds, then cubetrack track, as commands")
    ap.add_argument("--workflow-baseline", metavar="COMMIT", help="with --workflow: also that workflow by this "
                    "commit's code (git archive of its host/, PYTHONPATH), e.g. main")
    ap.add_argument("--speed-rounds", type=int, default=None, help="interleaved speed rounds (default 5; "
                    "--quick: 2)")
    ap.add_argument("--speed-frames", type=int, default=None, help="frames per recording in the speed "
                    "measurement (default: all; --quick: 30)")
    ap.add_argument("--no-speed", action="store_true", help="skip the speed measurement")
    ap.add_argument("--configs", type=int, nargs="+", choices=range(len(CONFIGS)), default=None, metavar="I",
                    help="only these configurations (0-3, in the table's order: " + "; ".join(
                        f"{i} {c[0]}" for i, c in enumerate(CONFIGS)) + "; default: all)")
    ap.add_argument("--presets", nargs="+", choices=PRESETS, default=list(DEFAULT_PRESETS),
                    help="simulator presets (default: clean and realistic; rig: the realistic preset with 1280x720 "
                    "webcams at 6 fps and inverted markers with distinct ids, SimulationParams.rig(); hand: the rig "
                    "preset's body carried by hand, free 6-DoF at 0.2 m/s RMS (path handheld); --quick: "
                    "the presets other than clean in the 3 cams 1.0 m and 5 cams configurations only)")
    args = ap.parse_args(argv)

    duration = args.duration if args.duration is not None else (8.0 if args.quick else 30.0)
    seeds = args.seeds[:1] if args.quick else list(dict.fromkeys(args.seeds))
    calibration_frames = 12 if args.quick else 200
    rounds = args.speed_rounds or (2 if args.quick else 5)
    speed_frames = args.speed_frames if args.speed_frames is not None else (30 if args.quick else None)
    if args.refine and not refine_available():
        ap.error("--refine needs cubetrack.calib.bundle, which is not installed")
    if args.lag < 0:
        ap.error(f"--lag must not be negative, got {args.lag}")
    if args.workflow_baseline and not args.workflow:
        ap.error("--workflow-baseline goes with --workflow")
    methods = ([OURS, SMOOTHED] + ([LAGGED] if args.lag > 0 else []) + ([REFINED] if args.refine else [])
               + ([BODY, BODY_SMOOTHED] if args.body else []) + ([TEMPLATE] if args.template else [])
               + ([BODY_TEMPLATE, BODY_TEMPLATE_SMOOTHED] if args.template and args.body else [])
               + ([BODY_TEMPLATE_LAG] if args.template and args.body and args.lag > 0 else [])
               + ([WORKFLOW] if args.workflow else []) + ([WORKFLOW_BASE] if args.workflow_baseline else [])
               + [PAPER, OUR_MEAN])

    kept = args.out is not None
    work = args.out if kept else Path(tempfile.mkdtemp(prefix="cubetrack-accuracy-"))
    work.mkdir(parents=True, exist_ok=True)
    t0 = time.monotonic()
    code = code_version()  # at the start: the scenes import the code as it is now
    presets = [p for p in PRESETS if p in args.presets]
    jobs = [(preset, ci, seed) for seed in seeds for preset in presets for ci in range(len(CONFIGS))
            if not (args.quick and preset != CLEAN and ci not in QUICK_REALISTIC)
            and (args.configs is None or ci in args.configs)]
    jobs.sort(key=lambda j: (-CONFIGS[j[1]][1], j[0] == CLEAN))  # the longest first: 5 cameras, realistic
    n_jobs = max(1, min(args.jobs, len(jobs)))
    workers = max(1, (os.cpu_count() or 1) // n_jobs)
    scenes = []
    try:
        def done(result: dict) -> None:
            scenes.append(result)
            name = CONFIGS[result["config"]][0]
            sec = result["seconds"]
            how = "reused" if sec["reused"] else f"rendered {sec['render']:.0f} s"
            print(f"  [{len(scenes)}/{len(jobs)}] {name} {result['preset']} seed {result['seed']}: {how}, calibrated "
                  f"{sec['calibrate']:.0f} s, tracked {sec['track']:.0f} s; ours "
                  f"{result['methods'][OURS]['pos_cm']:.2f} cm, paper mean {result['methods'][PAPER]['pos_cm']:.2f} cm",
                  file=sys.stderr, flush=True)

        trees = {WORKFLOW: str(Path(__file__).resolve().parents[1] / "host")} if args.workflow else None
        if args.workflow_baseline:
            trees[WORKFLOW_BASE] = commit_host(args.workflow_baseline, work / "workflow_baseline")
        call = [(str(work), preset, ci, seed, duration, calibration_frames, workers, args.refine,
                 args.body_drive if args.body or args.workflow else 0.0, args.lag, args.template, trees, args.body)
                for preset, ci, seed in jobs]
        print(f"{len(jobs)} scenes, {n_jobs} at a time, in {work} ...", file=sys.stderr, flush=True)
        if n_jobs == 1:
            for c in call:
                done(run_scene(*c))
        else:
            import multiprocessing

            with ProcessPoolExecutor(n_jobs, mp_context=multiprocessing.get_context("fork")) as pool:
                for fut in as_completed([pool.submit(run_scene, *c) for c in call]):
                    done(fut.result())
        speed = None
        if not args.no_speed:
            print(f"speed: {rounds} rounds on seed {seeds[0]}'s recordings ...", file=sys.stderr, flush=True)
            speed = measure_speed([scene_dir(work, ci, seeds[0], presets[0]) for ci in range(len(CONFIGS))
                                   if (presets[0], ci, seeds[0]) in jobs], rounds,
                                  speed_frames, warmup_frames=10 if args.quick else 40)
        report = build_report(scenes, seeds, methods)
        report["code"] = code
        failures = print_report(report, speed, methods, duration, time.monotonic() - t0, work, kept)
        if kept:
            doc = {"report": report, "speed": speed, "failures": failures, "duration_s": duration,
                   "scenes": scenes, "methods": methods}
            (work / REPORT_FILE).write_text(json.dumps(doc, indent=1, default=float), encoding="utf-8")
    finally:
        if not kept:
            shutil.rmtree(work, ignore_errors=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
