"""Issue 15: what better corners would buy. Replays every sighting of realistic scenes through
``FilterFusion`` with each detection's corners replaced, and scores the poses as
``benchmarks/accuracy.py`` does (:func:`cubetrack.evaluate.evaluate`: the truth interpolated to
each pose's time).

Scenes: ``benchmarks/accuracy.py``'s realistic preset (``--configs``: its configuration indices,
default 1 and 3 = 3 cameras and 5 cameras at 1.0 m / 30°), seed 101, ``--duration`` seconds; a
complete recording of the same parameters under ``--out`` is reused (accuracy.py's own rule).
Each scene is tracked once with the default configuration (robust calibration, the filter) and
its sightings are kept (the same detections, camera poses, intrinsics and capture stamps as the
tracker had); then they are replayed with their corners replaced by:

- **oracle** corners: the cube as built (the simulator's ``true_cube``) at the true pose at each
  corner's own capture instant (its row's mid-exposure time under the rolling shutter, iterated
  to the corner's row), projected through the camera's true intrinsics (lens distortion) and
  pose with the simulator's own projection, plus Gaussian noise of ``--sigmas`` px per
  coordinate. Everything else stays as the tracker has it (camera_info, calibrated extrinsics,
  estimated capture stamps), so only the corners improve. The residual detected - oracle is the
  edge fit's real error: its RMS per corner coordinate is reported by the face's view angle;
- **template** corners: the detected corners refined by the body calibration's template fit of
  the whole marker image (:func:`cubetrack.calib.marker_fit.template_fitted_corners`, default
  parameters, the camera_info the tracker has; its failures keep the edge fit's corners), with
  its thread CPU per marker (``--no-template`` skips it).

Each set is tracked with the nominal layout (``cube.toml``), the cube as built
(``true_cube.toml``) and, with ``--body``, the layout ``calibrate-body`` gives from a separate
drive (accuracy.py's ``--body``: the scene rendered for ``--duration`` + ``--body-drive`` s, only
the frames after the session's end used), with the default filter settings and with the best setting of a small grid
(``corner_noise_px`` x ``angular_accel_noise`` x ``yaw_accel_noise``, one setting per row chosen
on the mean over the scenes: in-sample, so an upper bound on what retuning buys). Reported per
row: rotation RMSE, its roll/pitch (RMS of the world-frame error about x and y) and yaw (about z)
parts, position RMSE, each the mean over the scenes, and per scene in the JSON report.

``--floor`` (issue 26) also measures the floor each accuracy target is stated against: every
sighting's camera frame alone, fitted (``cv2.solvePnP``, Levenberg-Marquardt from the true pose,
so never a flipped solution) with the true camera (true intrinsics and lens, true pose) and the
body as built, to the detected corners, the oracle corners and the template corners; scored
against the truth at the instant the fitted corners' rows were exposed (their mean row under the
rolling shutter), RMS over sightings, all and split by one marker / two or more. The tracker's
filter pools several frames and cameras, so it can go below this floor; a per-instant fit cannot.
``--preset`` picks accuracy.py's preset of the scenes (default realistic). ``--decompose --split``
(issue 26) adds the first and last ladder rows with one corner noise for every corner (the filter
without :mod:`cubetrack.estimate.corner_noise`) and which sightings carry the filter's error over
the floor. Every run also tables the edge fit's corner error by the border module's width in
pixels (the per-corner noise model's evidence).

    nice -n 19 .venv/bin/python benchmarks/corner_ceiling.py [--out /tmp/corner_ceiling] [--duration 15]
                                                              [--configs 1 3] [--sigmas 0 0.02 0.05 0.1 0.2]
                                                              [--body] [--no-template] [--no-tune] [--json FILE]
                                                              [--floor] [--preset clean|realistic|rig]

The process lowers its own priority (``os.nice``). The exit code is 0 for a completed run.
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import itertools
import json
import math
import os
import pickle
import sys
import time
from pathlib import Path

import numpy as np

ACCURACY = Path(__file__).resolve().with_name("accuracy.py")
SEED = 101
CONFIGS = (1, 3)  # accuracy.py's configuration indices: 3 cameras 1.0 m / 30°, 5 cameras 1.0 m / 30°
SIGMAS_PX = (0.0, 0.02, 0.05, 0.1, 0.2)
TUNE_GRID = {"corner_noise_px": (0.05, 0.1, 0.2, 0.5), "angular_accel_noise": (0.5, 2.0, 5.0, 10.0),
             "yaw_accel_noise": (5.0, 10.0)}
VIEW_BINS_DEG = (0.0, 30.0, 45.0, 60.0, 70.0, 90.0)
MATCH_PX = 3.0  # a detection whose nearest true marker projects farther off (RMS) keeps its corners
NOMINAL, TRUE, BODY = "nominal", "true cube", "calibrate-body"
CACHE = "corner_ceiling"  # per-scene folder of sightings, oracle and template corners


def load_accuracy():
    """benchmarks/accuracy.py as a module (its scenes, rendering and reuse rule)."""
    if str(ACCURACY.parent) not in sys.path:
        sys.path.insert(0, str(ACCURACY.parent))
    import accuracy

    return accuracy


def say(text: str) -> None:
    print(text, file=sys.stderr, flush=True)


# --------------------------------------------------------------------------------- sightings


def capture_sightings(rec: Path) -> dict:
    """Track ``rec`` with the default configuration and keep every sighting the fusion got, with
    the host time it got it; also the layouts and the fusion's parameters."""
    from unittest import mock

    from cubetrack.app import tracker as tracker_module
    from cubetrack.app.calibrate import calibrate_recording
    from cubetrack.app.track import track_recording
    from cubetrack.io.config import read_tracker_config
    from cubetrack.io.recording import Recording

    config = read_tracker_config(rec / "config.toml")
    extrinsics = calibrate_recording(config, Recording.open(rec / "calibration")).extrinsics
    params = stage_params(rec)
    got: list = []

    class Recorded(tracker_module.FilterFusion):
        def add(self, sighting, now_s):
            got.append((sighting, now_s))
            return super().add(sighting, now_s)

    with mock.patch.object(tracker_module, "FilterFusion", Recorded):
        track_recording(config, Recording.open(rec), extrinsics, rec / CACHE / "track", params, workers=0)
    return {"sightings": got, "layouts": {r.name: r.layout for r in config.robots}}


def stage_params(rec: Path):
    """The default configuration's stage parameters for ``rec`` (its config.toml)."""
    from cubetrack.app.tracker import StageParams
    from cubetrack.io.config import read_tracker_config

    return StageParams.from_config(read_tracker_config(rec / "config.toml"))


def cached(path: Path, make):
    if path.exists():
        return pickle.loads(path.read_bytes())
    value = make()
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_bytes(pickle.dumps(value))
    return value


# --------------------------------------------------------------------------------- oracle


class Truth:
    """The simulated scene behind a recording, rebuilt from its ``simulation.toml``: true cameras,
    the cube as built, the true capture instant of every frame."""

    def __init__(self, rec: Path):
        import tomllib

        from cubetrack.core.params import params_from_table
        from cubetrack.simulate import SimulationParams
        from cubetrack.simulate.scenario import STREAM_TIMING, build_scene, rng_for
        from cubetrack.simulate.timing import plan_captures

        table = tomllib.loads((rec / "simulation.toml").read_text(encoding="utf-8"))
        p = params_from_table(SimulationParams, table["params"], f"{rec}/simulation.toml")
        self.params = p
        self.scene = build_scene(p)
        self.cameras = {c.name: c for c in self.scene.cameras}
        start, end = p.start_unix_s, p.start_unix_s + p.duration_s
        self.capture_s = {}  # (camera, seq) -> capture instant, scene seconds
        for i, c in enumerate(self.scene.cameras):
            for cap in plan_captures(p, c.clock, c.capture_phase_s, rng_for(p.seed, STREAM_TIMING, i), start, end):
                self.capture_s[(c.name, cap.seq)] = cap.capture_host_s - start
        self.markers = self.scene.robots[0].true_layout.markers

    def corners(self, camera: str, seq: int, marker, iterations: int = 3) -> tuple[np.ndarray, float]:
        """(4, 2) pixels of a true marker's corners, each at its own row's instant, and the face's
        view angle (degrees between its normal and the ray to the camera)."""
        from cubetrack.core.geometry import transform_points
        from cubetrack.core.layout import marker_corners_m
        from cubetrack.simulate.render import project_points

        cam = self.cameras[camera]
        t0 = self.capture_s[(camera, seq)]
        local = marker_corners_m(marker.size_m)
        times = np.full(4, t0)
        for _ in range(iterations):
            world = np.array([transform_points(self.scene.T_world_cube(t) @ marker.T_cube_marker, local[k:k + 1])[0]
                              for k, t in enumerate(times)])
            uv = project_points(cam.intrinsics, cam.T_world_cam, world)
            times = t0 + (uv[:, 1] - cam.reference_row) * cam.row_s
        T = self.scene.T_world_cube(t0) @ marker.T_cube_marker
        ray = cam.T_world_cam[:3, 3] - T[:3, 3]
        angle = math.degrees(math.acos(np.clip(np.dot(T[:3, 2], ray) / np.linalg.norm(ray), -1.0, 1.0)))
        return uv, angle

    def nearest(self, camera: str, seq: int, detection) -> tuple[float, np.ndarray | None, float, object]:
        """The true marker a detection shows (the nearest one of its id in front of the camera):
        the RMS distance (px) of its oracle corners from the detected ones, those corners, its view
        angle and the marker (``inf, None, nan, None`` when no marker of that id faces the camera)."""
        best: tuple[float, np.ndarray | None, float, object] = (math.inf, None, math.nan, None)
        for m in self.markers:
            if m.marker_id != detection.marker_id:
                continue
            uv, angle = self.corners(camera, seq, m)
            if angle >= 90.0:
                continue
            rms = float(np.sqrt(np.mean(np.sum((uv - detection.corners_px) ** 2, axis=1))))
            if rms < best[0]:
                best = (rms, uv, angle, m)
        return best

    def match(self, camera: str, seq: int, detection) -> tuple[np.ndarray | None, float]:
        """The oracle corners of the true marker a detection shows (:meth:`nearest`), and its view
        angle; None when none is within ``MATCH_PX`` (RMS)."""
        rms, uv, angle, _ = self.nearest(camera, seq, detection)
        return (uv, angle) if rms <= MATCH_PX else (None, angle)


def oracle_corners(rec: Path, sightings: list) -> dict:
    """Per sighting, per detection: (oracle corners or None, view angle)."""
    truth = Truth(rec)
    out = {}
    for k, (s, _) in enumerate(sightings):
        out[k] = [truth.match(s.camera, s.seq, d) for d in s.detections]
        if k % 50 == 0:
            say(f"  oracle {rec.name}: {k}/{len(sightings)} sightings")
    return out


def template_corners(rec: Path, sightings: list) -> dict:
    """Per sighting, per detection: (template-fitted corners or None on failure, thread CPU s)."""
    from cubetrack.calib.marker_fit import template_fitted_corners
    from cubetrack.detect.detector import decode_gray
    from cubetrack.detect.template_fit import LensMap
    from cubetrack.io.recording import Recording

    recording = Recording.open(rec)
    wanted = {(s.camera, s.seq) for s, _ in sightings}
    jpegs = {(c, f.seq): f.jpeg for c in recording.camera_names for f in recording.frames(c) if (c, f.seq) in wanted}
    layouts = {}
    lenses = {}  # camera -> its lens map (built once)
    out = {}
    for k, (s, _) in enumerate(sightings):
        gray = decode_gray(jpegs[(s.camera, s.seq)])
        if s.camera not in lenses:
            lenses[s.camera] = LensMap(s.intrinsics)
        row = []
        for d in s.detections:
            dictionary = d.dictionary or layouts.setdefault(s.robot, _dictionary(rec))
            c0 = time.thread_time()
            fitted = template_fitted_corners(gray, d.corners_px, dictionary, d.marker_id, lenses[s.camera])
            cpu = time.thread_time() - c0
            row.append((fitted if np.isfinite(fitted).all() else None, cpu))
        out[k] = row
        if k % 50 == 0:
            say(f"  template fit {rec.name}: {k}/{len(sightings)} sightings")
    return out


def _dictionary(rec: Path) -> str:
    from cubetrack.core.layout import read_layout

    return read_layout(rec / "cube.toml").dictionary


# --------------------------------------------------------------------------------- replay


def replaced(sightings: list, corners: dict, sigma_px: float, seed: int, params) -> list:
    """The sightings with each detection's corners replaced (``corners[k][i][0]``; None keeps
    the detected ones) plus Gaussian noise of ``sigma_px``; a sighting that carried a per-camera
    estimate gets one from its new corners."""
    from cubetrack.core.geometry import shoelace_area
    from cubetrack.core.records import Detection
    from cubetrack.estimate.pose import estimate_cube

    rng = np.random.default_rng(seed)
    out = []
    for k, (s, now_s) in enumerate(sightings):
        detections = []
        for d, (c, _) in zip(s.detections, corners[k], strict=True):
            c = d.corners_px if c is None else c
            if sigma_px > 0:
                c = c + rng.normal(0.0, sigma_px, c.shape)
            detections.append(Detection(d.marker_id, c, shoelace_area(c), d.dictionary))
        detections = tuple(detections)
        estimate = s.estimate
        if estimate is not None:
            estimate = estimate_cube(detections, params["layouts"][s.robot], s.intrinsics, s.T_world_cam,
                                     camera=s.camera, robot=s.robot, seq=s.seq, capture_time_s=s.capture_time_s,
                                     arrival_time_s=s.arrival_time_s, params=params["params"].estimator)
        out.append((dataclasses.replace(s, detections=detections, estimate=estimate), now_s))
    return out


def replay(sightings: list, layouts: dict, stage_params, filter_overrides: dict, smooth: bool = False) -> list:
    """The sightings through ``FilterFusion``: its poses as live (causal), or (``smooth``) smoothed
    over the whole replay as ``cubetrack track --smooth`` does (one robot)."""
    from cubetrack.fuse.fusion import FilterFusion
    from cubetrack.fuse.smoother import smoothed_poses

    fusion = FilterFusion(layouts, stage_params.fusion, dataclasses.replace(stage_params.filter, **filter_overrides))
    if smooth:
        fusion.keep_trail()
    poses = []
    for s, now_s in sightings:
        poses += fusion.add(s, now_s)
    end_s = sightings[-1][1]
    poses += fusion.flush(end_s)
    if smooth:
        return smoothed_poses(fusion.trail(next(iter(layouts)), end_s), end_s)
    return poses


def score(poses: list, truth) -> dict:
    """accuracy.py's scoring (:func:`cubetrack.evaluate.evaluate`) and the world-frame split of
    the rotation error into roll/pitch (about x and y) and yaw (about z)."""
    from scipy.spatial.transform import Rotation

    from cubetrack.evaluate.metrics import evaluate, truth_at
    from cubetrack.io.trajectory import Trajectory

    poses = sorted(poses, key=lambda p: p.time_s)
    traj = Trajectory(np.array([p.time_s for p in poses]), np.array([p.position_m for p in poses]),
                      np.array([p.quaternion_xyzw for p in poses]))
    s = evaluate(traj, truth)
    inside = (traj.times_s >= truth.times_s[0]) & (traj.times_s <= truth.times_s[-1])
    _, r_truth = truth_at(truth, traj.times_s[inside])
    e = np.degrees((Rotation.from_quat(traj.quats_xyzw[inside]) * r_truth.inv()).as_rotvec())
    return {"rot_deg": s.rotation_rmse_deg, "rollpitch_deg": float(np.sqrt(np.mean(np.sum(e[:, :2] ** 2, axis=1)))),
            "yaw_deg": float(np.sqrt(np.mean(e[:, 2] ** 2))), "pos_cm": 100.0 * s.position_rmse_m,
            "dr": s.detection_ratio, "poses": s.poses_scored}


KEYS = ("rot_deg", "rollpitch_deg", "yaw_deg", "pos_cm")


def mean_scores(per_scene: list[dict]) -> dict:
    return {k: float(np.mean([s[k] for s in per_scene])) for k in KEYS}


# --------------------------------------------------------------------------------- floor


def true_markers(truth: Truth, sightings: list) -> list[list]:
    """Per sighting, per detection: the true marker it shows (:meth:`Truth.nearest`), None when
    none is within ``MATCH_PX``."""
    out = []
    for s, _ in sightings:
        row = []
        for d in s.detections:
            rms, _, _, marker = truth.nearest(s.camera, s.seq, d)
            row.append(marker if rms <= MATCH_PX else None)
        out.append(row)
    return out


def floor_errors(truth: Truth, sightings: list, markers: list[list],
                 corners: dict | None) -> list[tuple[float, float, int]]:
    """The floor (issue 26): per sighting that shows true markers, the error of a per-instant fit
    of that camera frame alone with the true camera (its true intrinsics, lens included, and true
    pose) and the body as built, started from the truth: position (m), rotation (°) against the
    truth at the instant the fitted corners' rows were exposed (their mean row under the rolling
    shutter; the frame's capture instant without one), and the markers fitted. ``corners``: per sighting, per
    detection, the corners to fit (None, or a None entry: the detected ones); ``markers``: the
    true marker of each detection (:func:`true_markers`; None: left out)."""
    import cv2

    from cubetrack.core.geometry import invert_T, make_T, rotation_angle, transform_points
    from cubetrack.core.layout import marker_corners_m

    out = []
    for k, (s, _) in enumerate(sightings):
        obj, img = [], []
        for i, (d, marker) in enumerate(zip(s.detections, markers[k], strict=True)):
            if marker is None:
                continue
            given = None if corners is None else corners[k][i][0]
            obj.append(transform_points(marker.T_cube_marker, marker_corners_m(marker.size_m)))
            img.append(d.corners_px if given is None else given)
        if not obj:
            continue
        cam = truth.cameras[s.camera]
        rows_s = (float(np.concatenate(img)[:, 1].mean()) - cam.reference_row) * cam.row_s  # the markers' rows
        T_true = truth.scene.T_world_cube(truth.capture_s[(s.camera, s.seq)] + rows_s)
        T_cam_cube = invert_T(cam.T_world_cam) @ T_true
        rvec = cv2.Rodrigues(T_cam_cube[:3, :3])[0]
        tvec = T_cam_cube[:3, 3].reshape(3, 1).copy()
        _, rvec, tvec = cv2.solvePnP(np.concatenate(obj), np.concatenate(img).astype(np.float64),
                                     cam.intrinsics.K, cam.intrinsics.dist, rvec, tvec, useExtrinsicGuess=True,
                                     flags=cv2.SOLVEPNP_ITERATIVE)
        T_fit = cam.T_world_cam @ make_T(cv2.Rodrigues(rvec)[0], tvec.ravel())
        out.append((float(np.linalg.norm(T_fit[:3, 3] - T_true[:3, 3])),
                    rotation_angle(T_fit[:3, :3], T_true[:3, :3], unit="deg"), len(obj)))
    return out


def floor_summary(errors: list[tuple[float, float, int]]) -> dict:
    """RMS position (cm) and rotation (°) of :func:`floor_errors`, over all sightings and split by
    one marker / two or more."""
    out = {}
    for name, keep in (("all", lambda n: True), ("1 marker", lambda n: n == 1), ("2+ markers", lambda n: n > 1)):
        e = np.array([(p, r) for p, r, n in errors if keep(n)]).reshape(-1, 2)
        out[name] = {"pos_cm": 100.0 * float(np.sqrt(np.mean(e[:, 0] ** 2))) if len(e) else math.nan,
                     "rot_deg": float(np.sqrt(np.mean(e[:, 1] ** 2))) if len(e) else math.nan,
                     "sightings": len(e)}
    return out


def floor_report(scenes: list[dict], corner_sets: list[str]) -> dict:
    """:func:`floor_summary` per scene and corner set (``edge``: as detected, ``oracle``,
    ``template``)."""
    out = {}
    for sc in scenes:
        truth = Truth(sc["rec"])
        markers = true_markers(truth, sc["sightings"])
        out[sc["name"]] = {which: floor_summary(floor_errors(truth, sc["sightings"], markers,
                                                              None if which == "edge" else sc[which]))
                           for which in corner_sets}
        say(f"  floor {sc['name']}: done")
    return out


# --------------------------------------------------------------------------------- decomposition

# --decompose's rows: which of the tracker's inputs are replaced by the truth (cumulative towards
# the last row, the filter with nothing left to get wrong: its own floor)
LADDER = ((), ("body",), ("cameras",), ("body", "cameras"), ("body", "cameras", "stamps"),
          ("body", "cameras", "stamps", "corners"))
ONE_NOISE = ", one corner noise"  # a row with every corner at the nominal corner_noise_px (no per-corner model)


def with_truth(sc: dict, truth: Truth, true: tuple[str, ...], start: dict) -> tuple[list, dict]:
    """The scene's sightings and layouts with the inputs named in ``true`` replaced by the truth:
    ``body`` the cube as built, ``cameras`` each camera's true pose and intrinsics (lens and readout),
    ``stamps`` each frame's true capture instant, ``corners`` the oracle's corners; the others
    as ``start`` has them (``extrinsics``: camera -> T_world_cam or None for the tracker's own,
    ``layouts``). A sighting that carried a per-camera estimate gets one from what it now has."""
    from cubetrack.core.geometry import shoelace_area
    from cubetrack.core.records import Detection
    from cubetrack.estimate.pose import estimate_cube
    from cubetrack.io.camera_info import read_camera_info
    from cubetrack.io.config import read_extrinsics

    rec = sc["rec"]
    layouts = sc["layout_sets"][TRUE] if "body" in true else start["layouts"]
    poses = start["extrinsics"]
    if "cameras" in true:
        poses = {c: e.T_world_cam for c, e in read_extrinsics(rec / "true_extrinsics.toml").items()}
        lenses = {c: dataclasses.replace(read_camera_info(rec / "true_camera_info" / f"{c}.yaml"),
                                         readout_s=truth.cameras[c].readout_s) for c in poses}  # the file has none
    start_s = truth.params.start_unix_s
    out = []
    for k, (s, now_s) in enumerate(sc["sightings"]):
        change: dict = {}
        if poses is not None:
            change["T_world_cam"] = poses[s.camera]
        if "cameras" in true:
            change["intrinsics"] = lenses[s.camera]
        if "stamps" in true:
            change["capture_time_s"] = start_s + truth.capture_s[(s.camera, s.seq)]
        if "corners" in true:
            change["detections"] = tuple(d if c is None else Detection(d.marker_id, c, shoelace_area(c), d.dictionary)
                                         for d, (c, _) in zip(s.detections, sc["oracle"][k], strict=True))
        s = dataclasses.replace(s, **change)
        if s.estimate is not None:
            s = dataclasses.replace(s, estimate=estimate_cube(
                s.detections, layouts[s.robot], s.intrinsics, s.T_world_cam, camera=s.camera, robot=s.robot, seq=s.seq,
                capture_time_s=s.capture_time_s, arrival_time_s=s.arrival_time_s, params=sc["params"].estimator))
        out.append((s, now_s))
    return out, layouts


def decompose_report(scenes: list[dict], starts: dict[str, dict], split: bool = False) -> dict:
    """Per start (``starts``: name -> ``extrinsics`` and ``layouts`` the tracker starts from) and
    scene: the default filter's :func:`score` (causal and smoothed) on each :data:`LADDER` row;
    with ``split`` also on the first and last rows with every corner given the nominal noise
    (:data:`ONE_NOISE`: the filter before each corner's own noise, :mod:`cubetrack.estimate.corner_noise`)
    and, under ``"split"``, :func:`excess_split` per start and scene."""
    from unittest import mock

    import cubetrack.estimate.reprojection as reprojection

    out: dict = {}
    for sc in scenes:
        truth = Truth(sc["rec"])
        for name, start in starts.items():
            rows = {}
            one_noise = [(LADDER[0], True), (LADDER[-1], True)] if split else []
            for true, nominal in [(t, False) for t in LADDER] + one_noise:
                sightings, layouts = with_truth(sc, truth, true, start(sc) if callable(start) else start)
                with mock.patch.object(reprojection, "corner_noise_factors", lambda c, m: np.ones(len(c))) \
                        if nominal else contextlib.nullcontext():
                    rows[(" + ".join(true) or "nothing") + (ONE_NOISE if nominal else "")] = {
                        "causal": score(replay(sightings, layouts, sc["params"], {}), sc["truth"]),
                        "smoothed": score(replay(sightings, layouts, sc["params"], {}, smooth=True), sc["truth"])}
            out.setdefault(name, {})[sc["name"]] = rows
            if split:
                out.setdefault("split", {}).setdefault(name, {})[sc["name"]] = excess_split(
                    sc, truth, start(sc) if callable(start) else start)
            say(f"  decomposition {sc['name']}, {name}: done")
    return out


def pose_errors_deg(poses: list, truth) -> dict[float, float]:
    """Each pose's rotation error (°) against the truth at its time, by its time (host seconds)."""
    from scipy.spatial.transform import Rotation

    from cubetrack.evaluate.metrics import truth_at

    times = np.array([p.time_s for p in poses])
    inside = (times >= truth.times_s[0]) & (times <= truth.times_s[-1])
    _, r_truth = truth_at(truth, times[inside])
    r = Rotation.from_quat(np.array([p.quaternion_xyzw for p in poses])[inside])
    return dict(zip(times[inside].tolist(), np.degrees((r * r_truth.inv()).magnitude()).tolist(), strict=True))


# --decompose's split of the excess over the floor: each bin of a sighting's (and the pose it makes) conditions
SPLITS = {"turn rate < 0.5 rad/s": lambda c: c["turn"] < 0.5, "turn rate 0.5-2 rad/s": lambda c: 0.5 <= c["turn"] < 2,
          "turn rate >= 2 rad/s": lambda c: c["turn"] >= 2.0, "first 2 s": lambda c: c["time"] < 2.0,
          "after 2 s": lambda c: c["time"] >= 2.0, "stamp error < 2 ms": lambda c: abs(c["stamp_ms"]) < 2.0,
          "stamp error >= 2 ms": lambda c: abs(c["stamp_ms"]) >= 2.0, "1 marker": lambda c: c["markers"] == 1,
          "2+ markers": lambda c: c["markers"] > 1}


def excess_split(sc: dict, truth: Truth, start: dict) -> dict:
    """Which sightings carry the filter's excess over the floor: per :data:`SPLITS` bin (the true turn
    rate about the world's z at the sighting, its time in the session, its capture stamp's error, the
    markers it shows), the RMS rotation error of the poses the filter makes at those sightings (from
    ``start``, nothing true; and with body, cameras and stamps true) and of their per-instant floor
    fits, and the bin's share of the filter's squared error."""
    markers = true_markers(truth, sc["sightings"])
    floors = floor_errors(truth, sc["sightings"], markers, None)
    start_s = truth.params.start_unix_s
    conditions = {}
    for s, _ in sc["sightings"]:
        t = truth.capture_s[(s.camera, s.seq)]
        R0, R1 = truth.scene.T_world_cube(t - 0.005)[:3, :3], truth.scene.T_world_cube(t + 0.005)[:3, :3]
        turn = abs(float(np.arctan2((R1 @ R0.T)[1, 0], (R1 @ R0.T)[0, 0]))) / 0.01
        conditions[s.capture_time_s] = {"turn": turn, "time": t, "stamp_ms": 1000.0 * (s.capture_time_s - start_s - t),
                                        "markers": len(s.detections)}
    floor_by_time = {}  # the floor's fits are of the sightings with a true marker, in order
    fitted = [s for k, (s, _) in enumerate(sc["sightings"]) if any(m is not None for m in markers[k])]
    for s, (_, rot, _) in zip(fitted, floors, strict=True):
        floor_by_time[s.capture_time_s] = rot
    errors = {}
    for name, true in (("nothing", ()), ("body + cameras + stamps", ("body", "cameras", "stamps"))):
        sightings, layouts = with_truth(sc, truth, true, start)
        errors[name] = pose_errors_deg(replay(sightings, layouts, sc["params"], {}), sc["truth"])
    stamps = {start_s + truth.capture_s[(s.camera, s.seq)]: s.capture_time_s for s, _ in sc["sightings"]}
    errors["body + cameras + stamps"] = {stamps.get(t, t): e for t, e in errors["body + cameras + stamps"].items()}
    total = sum(e * e for e in errors["nothing"].values())
    out = {}
    for name, keep in SPLITS.items():
        times = [t for t, c in conditions.items() if keep(c)]
        cell = {}
        for row, by_time in (*errors.items(), ("floor", floor_by_time)):
            e = np.array([by_time[t] for t in times if t in by_time])
            cell[row] = {"n": len(e), "rms_deg": float(np.sqrt(np.mean(e**2))) if len(e) else math.nan}
        cell["share"] = sum(errors["nothing"].get(t, 0.0) ** 2 for t in times) / total if total else math.nan
        out[name] = cell
    return out


def workflow_start(sc: dict) -> dict:
    """The start the README workflow gave a scene (accuracy.py ``--workflow``'s files under the
    scene's ``track/readme_workflow``: ``calibrate --refine-with``'s extrinsics and body)."""
    from cubetrack.core.layout import read_layout
    from cubetrack.io.config import read_extrinsics

    folder = sc["rec"] / "track" / "readme_workflow"
    robot = next(iter(sc["layouts"]))
    body = folder / f"extrinsics.{robot}.body.toml"
    return {"extrinsics": {c: e.T_world_cam for c, e in read_extrinsics(folder / "extrinsics.toml").items()},
            "layouts": {robot: read_layout(body)} if body.exists() else sc["layouts"]}


# --------------------------------------------------------------------------------- report


def error_parts(got: np.ndarray, oracle: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """One marker's corner error ``got - oracle`` (4, 2) split: per corner, along the ray from the
    oracle quad's centre (radial, + outward) and across it (tangential); per side (corner i to
    i + 1), the error of its line's offset along its outward normal (+ outward; the mean of its two
    corners' errors there)."""
    z = oracle[:, 0] + 1j * oracle[:, 1]
    e = (got[:, 0] - oracle[:, 0]) + 1j * (got[:, 1] - oracle[:, 1])
    ray = (z - z.mean()) / np.abs(z - z.mean())
    parts = e * ray.conjugate()
    side = np.roll(z, -1) - z
    normal = side * -1j / np.abs(side)   # outward for a clockwise quad (y down)
    offset = 0.5 * ((e * normal.conjugate()).real + (np.roll(e, -1) * normal.conjugate()).real)
    return parts.real, parts.imag, offset


def residual_table(scenes: list[dict], which: str) -> dict:
    """Per view-angle bin: RMS per corner coordinate of (``which`` corners - oracle), and whether
    that error is bias or noise (:func:`error_parts`' mean and standard deviation: radial and
    tangential per corner, the sides' outward offsets), with counts."""
    out = {}
    for lo, hi in itertools.pairwise(VIEW_BINS_DEG):
        d, parts = [], []
        for sc in scenes:
            for k, (s, _) in enumerate(sc["sightings"]):
                for i, det in enumerate(s.detections):
                    oracle, angle = sc["oracle"][k][i]
                    if oracle is None or not lo <= angle < hi:
                        continue
                    got = det.corners_px if which == "edge" else sc["template"][k][i][0]
                    if got is not None:
                        d.append(got - oracle)
                        parts.append(error_parts(got, oracle))
        d = np.array(d).reshape(-1, 2)
        cell = {"rms_px": float(np.sqrt(np.mean(d ** 2))) if len(d) else math.nan, "corners": len(d)}
        for n, name in enumerate(("radial", "tangential", "side_offset")):
            v = np.concatenate([p[n] for p in parts]) if parts else np.full(1, math.nan)
            cell[f"{name}_mean_px"], cell[f"{name}_sd_px"] = float(np.mean(v)), float(np.std(v))
        out[f"{lo:g}-{hi:g}"] = cell
    return out


MODULE_BINS_PX = (0.0, 1.5, 2.0, 2.5, 3.0, 4.0, math.inf)


def module_table(scenes: list[dict]) -> dict:
    """Per bin of a corner's border module width in pixels (read off the detected quad by
    :func:`cubetrack.estimate.corner_noise.border_module_px`): RMS per coordinate of (edge corners -
    oracle), the mean view angle, and the noise factor the tracker gives those corners
    (:func:`cubetrack.estimate.corner_noise.corner_noise_scale`), with counts (the model's evidence)."""
    from cubetrack.detect.predicted import modules_of
    from cubetrack.estimate.corner_noise import border_module_px, corner_noise_scale

    rows = []
    for sc in scenes:
        for k, (s, _) in enumerate(sc["sightings"]):
            for i, det in enumerate(s.detections):
                oracle, angle = sc["oracle"][k][i]
                if oracle is None:
                    continue
                modules = modules_of(det.dictionary or "DICT_4X4_50")
                e2 = np.sum((det.corners_px - oracle) ** 2, axis=1) / 2.0
                rows += zip(border_module_px(det.corners_px, modules), e2, [angle] * 4,
                            corner_noise_scale(det.corners_px, modules), strict=True)
    table = np.array(rows).reshape(-1, 4)
    out = {}
    for lo, hi in itertools.pairwise(MODULE_BINS_PX):
        t = table[(table[:, 0] >= lo) & (table[:, 0] < hi)]
        out[f"{lo:g}-{hi:g}"] = {"corners": len(t), "rms_px": float(np.sqrt(t[:, 1].mean())) if len(t) else math.nan,
                                 "width_px": float(t[:, 0].mean()) if len(t) else math.nan,
                                 "view_deg": float(t[:, 2].mean()) if len(t) else math.nan,
                                 "scale": float(t[:, 3].mean()) if len(t) else math.nan}
    return out


def run_rows(scenes: list[dict], label: str, corners_key: str, sigma: float, tune: bool) -> list[dict]:
    """Rows for one corner set (both layouts, default and tuned filter), means over the scenes."""
    rows = []
    for layout_name in scenes[0]["layout_sets"]:
        sets = []
        for n, sc in enumerate(scenes):
            corners = sc[corners_key] if corners_key else {k: [(None, 0.0)] * len(s.detections)
                                                            for k, (s, _) in enumerate(sc["sightings"])}
            layouts = sc["layout_sets"][layout_name]
            new = replaced(sc["sightings"], corners, sigma, 1000 + n, sc)
            sets.append((new, layouts, sc))
        grid = [{}]
        if tune:
            names = list(TUNE_GRID)
            grid += [dict(zip(names, values, strict=True)) for values in itertools.product(*TUNE_GRID.values())]
        results = []
        for overrides in grid:
            per_scene = [score(replay(new, layouts, sc["params"], overrides), sc["truth"]) for new, layouts, sc in sets]
            results.append((overrides, per_scene))
        default = results[0]
        best = min(results, key=lambda r: mean_scores(r[1])["rot_deg"])
        rows.append({"corners": label, "sigma_px": sigma, "layout": layout_name,
                     "default": {"mean": mean_scores(default[1]), "scenes": default[1]},
                     "tuned": {"setting": best[0], "mean": mean_scores(best[1]), "scenes": best[1]},
                     "grid": [{"setting": o, "mean": mean_scores(per)} for o, per in results]})
        say(f"  {label} sigma {sigma:g} {layout_name}: rotation {rows[-1]['default']['mean']['rot_deg']:.3f}° "
            f"(tuned {rows[-1]['tuned']['mean']['rot_deg']:.3f}° with {best[0] or 'the defaults'})")
    return rows


def print_floor(report: dict) -> None:
    """The floor's table: RMS position / rotation of the per-instant fits per scene and corner set."""
    print("\nfloor: per-instant fit of each camera frame, true camera and body (RMS over sightings)")
    print("| scene | corners | all: position cm / rotation ° | 1 marker | 2+ markers | sightings (1 / 2+) |")
    print("| --- | --- | --- | --- | --- | --- |")
    for scene, sets in report["floor"].items():
        for which, f in sets.items():
            cells = " | ".join(f"{f[k]['pos_cm']:.3f} / {f[k]['rot_deg']:.3f}"
                               for k in ("all", "1 marker", "2+ markers"))
            print(f"| {scene} | {which} | {cells} | {f['1 marker']['sightings']} / {f['2+ markers']['sightings']} |")


def print_decomposition(report: dict) -> None:
    """The decomposition's table: per start and scene, each ladder row's errors, causal and smoothed."""
    print("\ndecomposition: the tracker's filter (default settings) with inputs replaced by the truth")
    print("| start | scene | true | position cm | rotation ° | roll/pitch ° | yaw ° | smoothed: position cm / "
          "rotation ° |")
    print("| --- | --- | --- | --- | --- | --- | --- | --- |")
    for start, scenes in report["decomposition"].items():
        if start == "split":
            continue
        for scene, rows in scenes.items():
            for true, r in rows.items():
                c, m = r["causal"], r["smoothed"]
                print(f"| {start} | {scene} | {true} | {c['pos_cm']:.3f} | {c['rot_deg']:.3f} | "
                      f"{c['rollpitch_deg']:.3f} | {c['yaw_deg']:.3f} | {m['pos_cm']:.3f} / {m['rot_deg']:.3f} |")
    if "split" not in report["decomposition"]:
        return
    print("\nwhich sightings carry the filter's excess over the floor: rotation RMS (°) of the poses the filter makes "
          "at them and of their per-instant floor fits, and their share of the filter's squared error")
    print("| start | scene | sightings | poses | filter ° | filter, body + cameras + stamps true ° | floor ° | "
          "filter / floor | share of the filter's error |")
    print("| --- | --- | --- | --- | --- | --- | --- | --- | --- |")
    for start, scenes in report["decomposition"]["split"].items():
        for scene, bins in scenes.items():
            for name, c in bins.items():
                f, t, fl = c["nothing"], c["body + cameras + stamps"], c["floor"]
                print(f"| {start} | {scene} | {name} | {f['n']} | {f['rms_deg']:.3f} | {t['rms_deg']:.3f} | "
                      f"{fl['rms_deg']:.3f} | {f['rms_deg'] / fl['rms_deg']:.2f}x | {100 * c['share']:.0f} % |")


def print_report(report: dict) -> None:
    print(f"corner ceiling: {report['scenes']} (load average {report['load']}, {report['cores']} cores)")
    print(f"oracle corners for {report['oracle_matched']} of {report['detections']} detections "
          f"(the others, no true marker within {MATCH_PX:g} px, keep their detected corners)")
    for which, table in report["residuals"].items():
        print(f"\n{which} corners - oracle by view angle: RMS per coordinate; bias (mean) and noise (sd) of the "
              "corners' radial (+ outward) and tangential errors and of the sides' outward offsets, px")
        print("| view angle | corners | RMS | radial mean / sd | tangential mean / sd | side offset mean / sd |")
        print("| --- | --- | --- | --- | --- | --- |")
        for name, v in table.items():
            print(f"| {name}° | {v['corners']} | {v['rms_px']:.3f} | " + " | ".join(
                f"{v[f'{p}_mean_px']:+.3f} / {v[f'{p}_sd_px']:.3f}" for p in ("radial", "tangential", "side_offset"))
                + " |")
    print("\nedge corners - oracle by the border module's width across the corner's sides (px, from the detected "
          "quad): RMS per coordinate, and the noise factor the tracker gives them (estimate/corner_noise.py)")
    print("| module width px | corners | mean width px | mean view angle ° | RMS px | noise factor |")
    print("| --- | --- | --- | --- | --- | --- |")
    for name, v in report["modules"].items():
        print(f"| {name} | {v['corners']} | {v['width_px']:.2f} | {v['view_deg']:.1f} | {v['rms_px']:.3f} | "
              f"{v['scale']:.2f} |")
    if "template_cpu_ms" in report:
        t = report["template_cpu_ms"]
        print(f"\ntemplate fit CPU per marker: median {t['median']:.1f} ms, mean {t['mean']:.1f} ms, "
              f"p90 {t['p90']:.1f} ms over {t['markers']} markers ({t['failed']} failed, edge corners kept)")
    if "floor" in report:
        print_floor(report)
    if "decomposition" in report:
        print_decomposition(report)
    print("\n| corners | sigma px | layout | rotation | roll/pitch | yaw | position cm | tuned: rotation / roll-pitch "
          "/ yaw | tuned setting |")
    print("| --- | --- | --- | --- | --- | --- | --- | --- | --- |")
    for r in report["rows"]:
        d, t = r["default"]["mean"], r["tuned"]["mean"]
        setting = ", ".join(f"{k} {v:g}" for k, v in r["tuned"]["setting"].items()) or "defaults"
        print(f"| {r['corners']} | {r['sigma_px']:g} | {r['layout']} | {d['rot_deg']:.3f}° | "
              f"{d['rollpitch_deg']:.3f}° | {d['yaw_deg']:.3f}° | {d['pos_cm']:.3f} | {t['rot_deg']:.3f}° / "
              f"{t['rollpitch_deg']:.3f}° / {t['yaw_deg']:.3f}° | {setting} |")


def parse_args(argv: list[str] | None) -> argparse.Namespace:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter, epilog=__doc__)
    ap.add_argument("--out", type=Path, default=Path("/tmp/corner_ceiling"),
                    help="folder of the recordings (reused when complete) and accuracy caches")
    ap.add_argument("--seed", type=int, default=SEED)
    ap.add_argument("--preset", choices=("clean", "realistic", "rig"), default="realistic",
                    help="accuracy.py's simulation preset of the scenes")
    ap.add_argument("--floor", action="store_true",
                    help="also the floor: a per-instant fit of each camera frame with the true camera and body")
    ap.add_argument("--decompose", action="store_true",
                    help="also replay the tracker's filter with its inputs replaced by the truth, a row per step")
    ap.add_argument("--workflow", action="store_true",
                    help="with --decompose: also start from the README workflow's extrinsics and body (accuracy.py "
                         "--workflow's files in the scene's track/readme_workflow)")
    ap.add_argument("--split", action="store_true",
                    help="with --decompose: also the first and last rows with one corner noise for every corner, and "
                         "which sightings carry the filter's error over the floor (turn rate, time, stamp error, "
                         "markers)")
    ap.add_argument("--duration", type=float, default=15.0, help="seconds per scene")
    ap.add_argument("--configs", type=int, nargs="+", default=list(CONFIGS),
                    help="accuracy.py's configuration indices (0-3)")
    ap.add_argument("--sigmas", type=float, nargs="+", default=list(SIGMAS_PX), help="oracle corner noise, px")
    ap.add_argument("--no-template", action="store_true", help="skip the template fit")
    ap.add_argument("--no-tune", action="store_true", help="only the default filter settings")
    ap.add_argument("--body", action="store_true",
                    help="also track with the body calibrated (calibrate-body) from a separate drive")
    ap.add_argument("--body-drive", type=float, default=60.0, help="seconds of the --body drive")
    ap.add_argument("--calibration-frames", type=int, default=200)
    ap.add_argument("--json", type=Path, help="also write the report here")
    args = ap.parse_args(argv)
    bench = load_accuracy()
    if any(not 0 <= c < len(bench.CONFIGS) for c in args.configs):
        ap.error(f"--configs: indices 0..{len(bench.CONFIGS) - 1}")
    if any(s < 0 for s in args.sigmas) or args.duration <= 0:
        ap.error("--sigmas must not be negative and --duration must be positive")
    return args


def load_scene(bench, args, config_index: int) -> dict:
    from cubetrack.core.layout import read_layout
    from cubetrack.io.trajectory import read_tum

    name, cameras, height, tilt, _ = bench.CONFIGS[config_index]
    rec = bench.scene_dir(args.out, config_index, args.seed, args.preset)
    say(f"{name}: {rec}")
    seconds, reused = bench.ensure_recording(
        bench.sim_params(args.preset, cameras, height, tilt, args.seed, args.duration, args.calibration_frames),
        rec, 2)
    say(f"  recording {'reused' if reused else f'rendered in {seconds:.0f} s'}")
    cache = rec / CACHE
    if not reused:
        for f in cache.glob("*.pkl"):
            f.unlink()
    sc = cached(cache / "sightings.pkl", lambda: capture_sightings(rec))
    sc["params"] = stage_params(rec)  # the current code's (a cached older one may lack new fields)
    say(f"  {len(sc['sightings'])} sightings")
    sc["oracle"] = cached(cache / "oracle.pkl", lambda: oracle_corners(rec, sc["sightings"]))
    if not args.no_template:
        sc["template"] = cached(cache / "template.pkl", lambda: template_corners(rec, sc["sightings"]))
    robot = next(iter(sc["layouts"]))
    sc["layout_sets"] = {NOMINAL: sc["layouts"], TRUE: {robot: read_layout(rec / "true_cube.toml")}}
    if args.body:
        body = cached(cache / "body.pkl", lambda: calibrated_body(bench, args, rec, config_index, robot))
        sc["layout_sets"][BODY] = body["layouts"]
        sc["body"] = body["info"]
        say(f"  body calibrated from a separate {args.body_drive:g} s drive: worst marker {body['info']}")
    sc["truth"] = read_tum(rec / "ground_truth.tum")
    sc["name"] = name
    sc["rec"] = rec
    return sc


def calibrated_body(bench, args, rec: Path, config_index: int, robot: str) -> dict:
    """The layout ``calibrate-body`` gives from a separate drive, as accuracy.py's ``--body`` makes
    it (the scene rendered for ``--duration`` + ``--body-drive`` s, only the frames after the
    session's end used), and its worst marker placement errors."""
    from cubetrack.app.calibrate import calibrate_recording
    from cubetrack.io.config import read_tracker_config
    from cubetrack.io.recording import Recording

    _, cameras, height, tilt, _ = bench.CONFIGS[config_index]
    full = rec.with_name(rec.name + "_drive")
    bench.ensure_recording(bench.sim_params(args.preset, cameras, height, tilt, args.seed,
                                            args.duration + args.body_drive, 0), full, 2)
    drive = bench.later_part(full, rec.with_name(rec.name + "_drive_after"),
                             bench.read_sim_start_s(full) + args.duration)
    config = read_tracker_config(rec / "config.toml")
    extrinsics = calibrate_recording(config, Recording.open(rec / "calibration")).extrinsics
    config_body, info = bench.calibrated_body(config, drive, rec, extrinsics, robot)
    return {"layouts": {r.name: r.layout for r in config_body.robots}, "info": info["placement_worst_mm_deg"]}


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    try:
        os.nice(19)
    except OSError:
        pass
    bench = load_accuracy()
    args.out.mkdir(parents=True, exist_ok=True)
    scenes = [load_scene(bench, args, c) for c in args.configs]
    report = {"scenes": ", ".join(f"{sc['name']} {args.preset} seed {args.seed} {args.duration:g} s" for sc in scenes),
              "load": " ".join(f"{v:.1f}" for v in os.getloadavg()), "cores": os.cpu_count(),
              "residuals": {"edge": residual_table(scenes, "edge")}, "modules": module_table(scenes), "rows": [],
              "oracle_matched": [sum(o is not None for row in sc["oracle"].values() for o, _ in row) for sc in scenes],
              "detections": [sum(len(row) for row in sc["oracle"].values()) for sc in scenes]}
    tune = not args.no_tune
    report["rows"] += run_rows(scenes, "detected (edge fit)", "", 0.0, tune)
    for sigma in args.sigmas:
        report["rows"] += run_rows(scenes, "oracle", "oracle", sigma, tune)
    if not args.no_template:
        report["residuals"]["template"] = residual_table(scenes, "template")
        cpu = np.array([c for sc in scenes for row in sc["template"].values() for _, c in row]) * 1000.0
        failed = sum(f is None for sc in scenes for row in sc["template"].values() for f, _ in row)
        report["template_cpu_ms"] = {"median": float(np.median(cpu)), "mean": float(np.mean(cpu)),
                                     "p90": float(np.percentile(cpu, 90)), "markers": len(cpu), "failed": failed}
        report["rows"] += run_rows(scenes, "template fit", "template", 0.0, tune)
    if args.floor:
        report["floor"] = floor_report(scenes, ["edge", "oracle"] + ([] if args.no_template else ["template"]))
    if args.decompose:
        starts = {"as tracked": lambda sc: {"extrinsics": None, "layouts": sc["layouts"]}}
        if args.workflow:
            starts["README workflow"] = workflow_start
        report["decomposition"] = decompose_report(scenes, starts, args.split)
    report["load_end"] = " ".join(f"{v:.1f}" for v in os.getloadavg())
    print_report(report)
    if args.json:
        args.json.write_text(json.dumps(report, indent=1), encoding="utf-8")
    return 0


if __name__ == "__main__":
    sys.exit(main())
