"""Camera watching (issue 27, docs/calibration.md "Watching the cameras"): simulated realistic
sessions with one camera bumped, tracked with the watcher on, and the same sessions unbumped.

For each scene (cameras, seed) the script renders (once; reused from --work) a bumped session
(``--bump-camera``, 2 cm / 1 deg at ``--bump-at``) and the same session unbumped, calibrates
the cameras from the calibration recording, then replays:

- the bumped session with the watching on: time to declare moved, the largest position error of
  any pose, time to rejoin, the new pose's error against the truth, position RMSE;
- the bumped session with the watching off (what happens today);
- the unbumped session with the watching on: false alarms, and the RMSE it is compared with.

Prints one table and writes a JSON report. Rendering dominates (minutes per scene on 2 cores):
run it with ``nice``. Example::

    nice -n 10 .venv/bin/python benchmarks/camera_watch.py --work /tmp/watch --cameras 3 5 --seeds 31
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import os
import sys
import time
from pathlib import Path

import numpy as np

BUMP_STEP_M = 0.02
BUMP_TURN_DEG = 1.0


@dataclasses.dataclass(frozen=True)
class Moves:
    """What happens to the cameras in a scene: bumped cameras (numbers) and when (s after the
    start), 2 cm / 1 deg each; a drifting camera (0: none) and its rate (mm per minute)."""

    bump_cameras: tuple[int, ...] = ()
    bump_at_s: tuple[float, ...] = ()
    drift_camera: int = 0
    drift_mm_per_min: float = 0.0

    @property
    def name(self) -> str:
        bumps = "_".join(f"bump{c}at{t:g}" for c, t in zip(self.bump_cameras, self.bump_at_s, strict=True))
        drift = f"drift{self.drift_camera}at{self.drift_mm_per_min:g}" if self.drift_camera else ""
        return "_".join(part for part in (bumps, drift) if part) or "still"


def scene(work: Path, cameras: int, seed: int, duration_s: float, moves: Moves, calibration: bool = True) -> Path:
    """Render (once) a realistic session; without ``calibration`` (an unbumped twin: its calibration
    recording would be the bumped session's) no calibration recording."""
    from cubetrack.simulate import SimulationParams, simulate

    rec = work / f"c{cameras}_s{seed}_d{duration_s:g}_{moves.name}{'' if calibration else '_nocal'}"
    if (rec / "done").exists():
        return rec
    changes: dict = {"bump_camera": moves.bump_cameras, "bump_at_s": moves.bump_at_s, "bump_step_m": BUMP_STEP_M,
                     "bump_turn_deg": BUMP_TURN_DEG, "drift_camera": moves.drift_camera,
                     "drift_mm_per_min": moves.drift_mm_per_min}
    if not calibration:
        changes["calibration_frames"] = 0
    params = SimulationParams.realistic(cameras=cameras, seed=seed, duration_s=duration_s, **changes)
    simulate(params, rec, overwrite=True, workers=min(4, os.cpu_count() or 1))
    (rec / "done").write_text("", encoding="utf-8")
    return rec


def replay(rec: Path, extrinsics: dict, watch: bool, config_path: Path | None = None,
           camera: str | None = None, keep_samples: bool = False, follow_m: float | None = None) -> dict:
    """Replay a recording through a Tracker (frames and /time round trips in arrival order);
    returns its ``poses``, the watcher's ``events`` and ``stats``, the ``cpu_s`` it took, with
    ``keep_samples`` every checked sighting the watcher kept (``samples``, in time order: its
    samples are read every 5 s, before they leave its ``baseline_s`` span) and, for ``camera``,
    ``camera_poses``: (host time, the pose the fusion uses, the watcher's settled pose or None)
    every 5 s. ``follow_m``: the watcher's ``follow_m`` (None: the config's; 0: no drift followed)."""
    from cubetrack.app.track import recording_intrinsics
    from cubetrack.app.tracker import StageParams, Tracker
    from cubetrack.calib.recalibrate import WatchedFusion
    from cubetrack.io.config import read_tracker_config
    from cubetrack.io.recording import Recording

    config = read_tracker_config(config_path or rec / "config.toml")
    recording = Recording.open(rec)
    params = StageParams.from_config(config)
    follow = {} if follow_m is None else {"follow_m": follow_m}
    params = dataclasses.replace(params, camera_watch=dataclasses.replace(params.camera_watch, enabled=watch, **follow))
    synced = frozenset(c for c in recording.camera_names if recording.clock_samples(c))
    tracker = Tracker(recording_intrinsics(config, recording), config.world, config.robots, extrinsics, params,
                      synced)
    fusion = tracker.fusion if isinstance(tracker.fusion, WatchedFusion) else None
    trips = sorted(((s.host_recv_s, c, s) for c in recording.camera_names for s in recording.clock_samples(c)),
                   key=lambda item: (item[0], item[1]))
    poses, k, camera_poses, next_s, kept = [], 0, [], -math.inf, {}
    c0 = time.process_time()
    for frame in recording.merged_frames():
        while k < len(trips) and trips[k][0] <= frame.host_time_s:
            poses += tracker.add_clock_sample(trips[k][1], trips[k][2])
            k += 1
        poses += tracker.process(frame)
        if fusion is not None and frame.host_time_s >= next_s:
            next_s = frame.host_time_s + 5.0
            if keep_samples:
                kept.update((id(s), s) for samples in fusion.watch.samples.values() for s in samples)
            if camera is not None:
                camera_poses.append((frame.host_time_s, fusion.watch.T_world_cam[camera].copy(),
                                     fusion.watch.settled.get(camera)))
    poses += tracker.finish()
    if fusion is not None and keep_samples:
        kept.update((id(s), s) for samples in fusion.watch.samples.values() for s in samples)
    return {"poses": poses, "events": list(fusion.events) if fusion else [], "cpu_s": time.process_time() - c0,
            "follows": list(fusion.watch.follows) if fusion else [],
            "in_use": {c: T.copy() for c, T in fusion.watch.T_world_cam.items()} if fusion else {},
            "stats": {**fusion.stats, **fusion.watch.stats} if fusion else {}, "camera_poses": camera_poses,
            "samples": sorted(kept.values(), key=lambda s: s.time_s)}


def errors_m(poses: list, rec: Path) -> tuple[np.ndarray, np.ndarray]:
    """Each measured pose's capture time and position error (m) against the nearest ground truth sample."""
    from cubetrack.io.trajectory import read_tum

    truth = read_tum(rec / "ground_truth.tum")
    measured = [p for p in poses if not p.predicted]
    times = np.array([p.time_s for p in measured])
    idx = np.clip(np.searchsorted(truth.times_s, times), 1, len(truth.times_s) - 1)
    nearer = np.where(np.abs(truth.times_s[idx - 1] - times) < np.abs(truth.times_s[idx] - times), idx - 1, idx)
    err = np.linalg.norm(np.array([p.position_m for p in measured]) - truth.positions_m[nearer], axis=1)
    return times, err


def true_camera_pose(rec: Path, camera: str, time_s: float | None = None) -> np.ndarray:
    """The camera's true pose at host time ``time_s`` (the nearest sample; None: the session's end)."""
    from cubetrack.core.geometry import T_from_position_quat
    from cubetrack.io.trajectory import read_tum

    truth = read_tum(rec / "true_camera_poses" / f"{camera}.tum")
    i = len(truth.times_s) - 1 if time_s is None else int(np.argmin(np.abs(truth.times_s - time_s)))
    return T_from_position_quat(truth.positions_m[i], truth.quats_xyzw[i])


def pose_error(T_a: np.ndarray, T_b: np.ndarray) -> tuple[float, float]:
    """Distance (m) and angle (deg) between two camera poses."""
    from cubetrack.core.geometry import rotation_angle

    return float(np.linalg.norm(T_a[:3, 3] - T_b[:3, 3])), rotation_angle(T_a[:3, :3], T_b[:3, :3], unit="deg")


def move_error(T_new: np.ndarray, T_calibrated: np.ndarray, T_true_after: np.ndarray, T_true_before: np.ndarray
               ) -> tuple[float, float]:
    """How far (m, deg) the move the re-calibration found (its new pose against the calibrated
    one, in the camera's frame) is from the true move: the new pose's error without what the
    calibration left (the other cameras' calibration error that every re-fit inherits)."""
    from cubetrack.core.geometry import invert_T

    return pose_error(invert_T(T_calibrated) @ T_new, invert_T(T_true_before) @ T_true_after)


def rmse(err: np.ndarray) -> float:
    return float(np.sqrt(np.mean(err**2))) if len(err) else math.nan


def principal_point_floor_deg(rec: Path, camera: str) -> float:
    """The turn (deg) that the camera's principal point error (its camera_info against
    true_camera_info) amounts to: no pose fitted to its images gets closer to the true rotation."""
    from cubetrack.io.camera_info import read_camera_info

    told = read_camera_info(rec / "camera_info" / f"{camera}.yaml").K
    true = read_camera_info(rec / "true_camera_info" / f"{camera}.yaml").K
    return math.degrees(math.atan(math.hypot(*(told[:2, 2] - true[:2, 2])) / true[0, 0]))


def calibrated_world(rec: Path, extrinsics: dict, still: list[str]) -> tuple[np.ndarray, float]:
    """The rigid motion ``G`` (4x4) that best maps the ``still`` cameras' true poses onto their
    calibrated ones (each pose as :func:`pose_points`), and the RMS (m) of what it leaves: the
    world the calibration put those cameras in, and how far they are from any rigid copy of the truth."""
    true = np.vstack([pose_points(true_camera_pose(rec, c)) for c in still])
    calibrated = np.vstack([pose_points(extrinsics[c].T_world_cam) for c in still])
    R, _, a, b = similarity(true, calibrated, False)
    G = np.eye(4)
    G[:3, :3], G[:3, 3] = R, b - R @ a
    return G, float(np.sqrt(np.mean(np.sum((true @ R.T + G[:3, 3] - calibrated) ** 2, axis=1))))


def bump_rows(rec: Path, events: list, moves: Moves, start: float, extrinsics: dict) -> dict:
    """Per bumped camera: moved declared and rejoined (s after its bump), the new pose's error,
    and what bounds it: the camera's calibrated pose against its true pose before the bump, and its
    principal point's error as a turn. The new pose is also compared with its true pose mapped into
    the calibrated world (:func:`calibrated_world` of the cameras never moved): what a re-calibration
    against the other cameras can reach, their calibration error left out (``new_pose_error_in_world``,
    ``world_rms_m``)."""
    out: dict = {}
    if not moves.bump_cameras:  # a still or drifting session: no camera was bumped, no true poses over time to read
        return out
    moved = {f"cam{c}" for c in moves.bump_cameras} | ({f"cam{moves.drift_camera}"} if moves.drift_camera else set())
    still = sorted(c for c in extrinsics if c not in moved)
    G, world_rms_m = calibrated_world(rec, extrinsics, still) if len(still) >= 2 else (None, math.nan)
    for number, at_s in zip(moves.bump_cameras, moves.bump_at_s, strict=True):
        camera = f"cam{number}"
        moved = [e for e in events if e.kind.value == "moved" and e.camera == camera]
        rejoined = [e for e in events if e.kind.value == "rejoined" and e.camera == camera]
        true_before = true_camera_pose(rec, camera, start + at_s - 1.0)
        row: dict = {"moved_after_s": moved[0].time_s - start - at_s if moved else None,
                     "rejoined_after_s": rejoined[0].time_s - start - at_s if rejoined else None,
                     "calibrated_error": pose_error(true_before, extrinsics[camera].T_world_cam),
                     "principal_point_floor_deg": principal_point_floor_deg(rec, camera)}
        if rejoined:
            row["new_pose_error"] = pose_error(true_camera_pose(rec, camera), rejoined[0].T_world_cam)
            row["move_error"] = move_error(rejoined[0].T_world_cam, extrinsics[camera].T_world_cam,
                                           true_camera_pose(rec, camera), true_before)
            row["sightings"] = rejoined[0].sightings
            if G is not None:
                row["new_pose_error_in_world"] = pose_error(G @ true_camera_pose(rec, camera), rejoined[0].T_world_cam)
                row["world_rms_m"] = world_rms_m
        out[camera] = row
    return out


def drift_rows(rec: Path, camera: str, camera_poses: list, start: float) -> list:
    """The drifting camera every 5 s: seconds after the start, the error (mm) of the pose the
    fusion uses and of the watcher's settled pose against its true pose then."""
    rows = []
    for t, in_use, settled in camera_poses:
        truth = true_camera_pose(rec, camera, t)
        rows.append((round(t - start, 1), round(1000 * pose_error(in_use, truth)[0], 2),
                     None if settled is None else round(1000 * pose_error(settled, truth)[0], 2)))
    return rows


REACH_M = 2.0  # a camera pose as its centre and a point this far along each axis: a turn weighs as its sideways move


def pose_points(T_world_cam: np.ndarray) -> np.ndarray:
    """(4, 3): the camera's optical centre and a point REACH_M along each of its axes."""
    return T_world_cam[:3, 3] + np.vstack([np.zeros(3), REACH_M * T_world_cam[:3, :3].T])


def similarity(src: np.ndarray, dst: np.ndarray, scale: bool) -> tuple[np.ndarray, float, np.ndarray, np.ndarray]:
    """(R, s, a, b): the rotation, scale (1 unless ``scale``) and centroids with ``s R (src - a) + b`` ~ ``dst``."""
    a, b = src.mean(axis=0), dst.mean(axis=0)
    U, S, Vt = np.linalg.svd((src - a).T @ (dst - b))
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(Vt.T @ U.T))])
    s = float((S * np.diag(D)).sum() / ((src - a) ** 2).sum()) if scale else 1.0
    return Vt.T @ D @ U.T, s, a, b


def joint_poses(samples: list, T_world_cams: dict, rounds: int = 30) -> tuple[dict, int]:
    """Every camera's pose fitted with every sample's cube pose (a bundle adjustment by alternation:
    each sample's cube pose from all its corners, the cameras where the last round put them, then each
    camera's resection against its own samples' corners placed by those cube poses), the world held
    where ``T_world_cams`` put it (after each round the cameras are moved back by the rigid motion
    that best maps them onto it), until a round moves every camera by under 0.2 mm / 0.005 deg.
    Returns the poses and the rounds taken."""
    import dataclasses as dc

    from cubetrack.core.geometry import invert_T, rotation_angle, transform_points
    from cubetrack.estimate.reprojection import moved_pose
    from cubetrack.fuse.camera_watch import FIT_ITERATIONS, VELOCITY_SIGMA, refit_camera
    from cubetrack.fuse.multi_view_fit import solve_joint

    T = {c: np.asarray(t, float).copy() for c, t in T_world_cams.items()}
    cubes = {id(s): s.T_world_cube for s in samples}
    anchor = np.vstack([pose_points(T[c]) for c in T])
    done = 0
    while done < rounds:
        done += 1
        seen: dict = {c: ([], [], []) for c in T}
        for s in samples:
            sets = [dc.replace(x, T_cam_world=invert_T(T[x.camera])) for x in (*s.own_sets, *s.reference_sets)]
            fit = solve_joint(sets, cubes[id(s)], s.time_s, velocity_sigma=VELOCITY_SIGMA, iterations=FIT_ITERATIONS)
            if fit is None:
                continue
            cubes[id(s)] = fit.T_world_cube
            for x in s.own_sets:
                T_world_cube = moved_pose(fit.T_world_cube, fit.velocity_m_s, fit.angular_velocity_rad_s,
                                          x.time_s - s.time_s)
                seen[x.camera][0].append(transform_points(T_world_cube, x.points_cube_m))
                seen[x.camera][1].append(x.normalized)
                seen[x.camera][2].append(np.full(len(x.normalized), x.focal_px))
        new = {}
        for c, (points, normalized, focal) in seen.items():
            fit_c = refit_camera(np.concatenate(points), np.concatenate(normalized), np.concatenate(focal), T[c]) \
                if points else None
            new[c] = T[c] if fit_c is None else fit_c.T_world_cam
        R, _, a, b = similarity(np.vstack([pose_points(new[c]) for c in T]), anchor, False)
        G = np.eye(4)
        G[:3, :3], G[:3, 3] = R, b - R @ a
        new = {c: G @ t for c, t in new.items()}
        small = all(np.linalg.norm(new[c][:3, 3] - T[c][:3, 3]) < 2e-4
                    and rotation_angle(new[c][:3, :3], T[c][:3, :3], unit="deg") < 0.005 for c in T)
        T = new
        if small:
            break
    return T, done


def drift_joint_rows(rec: Path, samples: list, extrinsics: dict, start: float, span_s: float, every_s: float) -> list:
    """Whether a camera's slow drift shows in the joint fit of all cameras (docs/calibration.md):
    :func:`joint_poses` over each ``span_s`` of the watcher's samples, ending every ``every_s``;
    each span's poses against the first span's, one camera left out at a time: the others aligned
    onto the first span's (rigid, and with scale free), how far the left-out camera then moved
    (mm, its pose points' RMS) and the largest of the others'. Per span: its end (s after the
    start), rounds, each camera's true move since the first span's end (mm), and per left-out camera
    (its move, the others' largest) rigid and with scale."""
    cams = sorted(extrinsics)
    T0 = {c: extrinsics[c].T_world_cam for c in cams}
    rows, first, end = [], None, span_s
    last = samples[-1].time_s - start if samples else 0.0
    while end <= last + 1e-6:
        poses, done = joint_poses([s for s in samples if end - span_s <= s.time_s - start < end], T0)
        first = first or (end, poses)
        row: dict = {"end_s": end, "rounds": done, "true_mm": {c: round(1000 * float(np.linalg.norm(
            true_camera_pose(rec, c, start + end)[:3, 3] - true_camera_pose(rec, c, start + first[0])[:3, 3])), 2)
            for c in cams}}
        for scale in (False, True):
            out = {}
            for left in cams:
                others = [c for c in cams if c != left]
                R, s, a, b = similarity(np.vstack([pose_points(poses[c]) for c in others]),
                                        np.vstack([pose_points(first[1][c]) for c in others]), scale)
                moved = {c: 1000 * float(np.sqrt(np.mean(np.sum(
                    ((s * (pose_points(poses[c]) - a) @ R.T + b) - pose_points(first[1][c])) ** 2, axis=1))))
                    for c in cams}
                out[left] = (round(moved[left], 2), round(max(moved[c] for c in others), 2))
            row["scaled" if scale else "rigid"] = out
        rows.append(row)
        print(json.dumps(row), flush=True)
        end += every_s
    return rows


def run_scene(work: Path, cameras: int, seed: int, duration_s: float, moves: Moves, still: bool = True,
              joint: tuple[float, float] | None = None, follow_m: float | None = None) -> dict:
    """One scene's replays (see the module doc). An unmoved scene (``--long``) is replayed watched
    and unwatched; a scene with moves also, with ``still``, its unmoved twin (doubles the rendering;
    without it there is no RMSE ratio nor false-alarm count on the twin). ``joint``: (span, every), seconds:
    the drift scene's :func:`drift_joint_rows` too. ``follow_m``: the watcher's (None: the config's); with
    one set, a drifting scene is also replayed watched with no drift followed (``watched_no_follow``)."""
    from cubetrack.app.calibrate import calibrate_recording
    from cubetrack.io.config import read_tracker_config
    from cubetrack.io.recording import Recording

    moved_rec = scene(work, cameras, seed, duration_s, moves)
    still_rec = scene(work, cameras, seed, duration_s, Moves(), False) if still and moves != Moves() else None
    config = read_tracker_config(moved_rec / "config.toml")
    extrinsics = calibrate_recording(config, Recording.open(moved_rec / "calibration")).extrinsics
    start = float(read_tracker_start(moved_rec))
    first_move_s = min(moves.bump_at_s, default=duration_s)
    drifting = f"cam{moves.drift_camera}" if moves.drift_camera else None
    bumped = {f"cam{c}" for c in moves.bump_cameras} | ({drifting} if drifting else set())
    out: dict = {"cameras": cameras, "seed": seed, "duration_s": duration_s, "moves": moves.name}
    runs = [("watched", moved_rec, True), ("unwatched", moved_rec, False)]
    if drifting and follow_m:
        runs.append(("watched_no_follow", moved_rec, True))
    if still_rec is not None:
        runs += [("still", still_rec, True), ("still_unwatched", still_rec, False)]
    for key, rec, watch in runs:
        run = replay(rec, extrinsics, watch, camera=drifting, keep_samples=bool(joint) and key == "watched",
                     follow_m=0.0 if key == "watched_no_follow" else follow_m)
        times, err = errors_m(run["poses"], rec)
        after = times - start >= first_move_s
        row: dict = {"rmse_m": rmse(err), "max_m": float(err.max()), "poses": len(err), "cpu_s": run["cpu_s"],
                     "max_before_m": float(err[~after].max()) if (~after).any() else math.nan,
                     "max_after_m": float(err[after].max()) if after.any() else math.nan,
                     "events": [(e.kind.value, e.camera, round(e.time_s - start, 2)) for e in run["events"]],
                     "suspect": run["stats"].get("suspect", 0),
                     "suspect_sightings": run["stats"].get("suspect sighting", 0),
                     "false_alarms": [e.camera for e in run["events"] if e.kind.value == "moved"
                                      and (key.startswith("still") or e.camera not in bumped)],
                     "follows": [(f.camera, round(f.time_s - start, 1), round(1000 * f.offset_m, 2),
                                  round(f.shift_px, 2), round(f.others_px, 2), round(f.others_after_px, 2))
                                 for f in run["follows"]],
                     # a drift followed in a camera that never moved: how far its pose in use went from its calibration
                     "false_follows_mm": {c: round(1000 * pose_error(T, extrinsics[c].T_world_cam)[0], 2)
                                          for c, T in run["in_use"].items() if c not in bumped
                                          and any(f.camera == c for f in run["follows"])}}
        if drifting and key.startswith("watched"):
            row["drift"] = drift_rows(rec, drifting, run["camera_poses"], start)
        if key == "watched":
            row["bumps"] = bump_rows(rec, run["events"], moves, start, extrinsics)
            if joint:
                row["joint"] = drift_joint_rows(rec, run["samples"], extrinsics, start, *joint)
        out[key] = row
    base = out["still_unwatched"] if still_rec is not None else out["unwatched"]
    out["rmse_ratio"] = out["watched"]["rmse_m"] / base["rmse_m"]
    return out


def real_footage(work: Path) -> dict:
    """The caliscope-4cam footage imported as benchmarks/real_footage.py does, replayed with the
    watching on and off: its events (there should be none: nobody bumped those cameras), and how
    far the watched poses are from the unwatched ones (there is no ground truth)."""
    from cubetrack.app.import_rig import import_caliscope
    from cubetrack.io.config import read_extrinsics

    data = Path(__file__).resolve().parents[1] / ".." / "shared" / "data" / "real" / "caliscope-4cam"
    if not (work / "config.toml").exists():
        import_caliscope(data, work)
    extrinsics = read_extrinsics(work / "extrinsics.toml")
    on = replay(work / "recording", extrinsics, True, work / "config.toml")
    off = replay(work / "recording", extrinsics, False, work / "config.toml")
    a = {(p.robot, round(p.time_s, 4)): p.position_m for p in on["poses"] if not p.predicted}
    b = {(p.robot, round(p.time_s, 4)): p.position_m for p in off["poses"] if not p.predicted}
    common = sorted(set(a) & set(b))
    apart = np.array([np.linalg.norm(np.subtract(a[k], b[k])) for k in common])
    return {"poses": len(on["poses"]), "events": [(e.kind.value, e.camera, e.time_s) for e in on["events"]],
            "suspect": on["stats"].get("suspect", 0), "suspect_sightings": on["stats"].get("suspect sighting", 0),
            "checked": on["stats"].get("checked", 0), "cpu_s": on["cpu_s"], "poses_compared": len(common),
            "on_vs_off_median_mm": 1000 * float(np.median(apart)) if len(apart) else math.nan,
            "on_vs_off_max_mm": 1000 * float(apart.max()) if len(apart) else math.nan}


def read_tracker_start(rec: Path) -> float:
    """The simulated session's start (host clock), from simulation.toml."""
    import tomllib

    return tomllib.loads((rec / "simulation.toml").read_text(encoding="utf-8"))["params"]["start_unix_s"]


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--work", type=Path, required=True, help="folder for the rendered sessions (reused)")
    parser.add_argument("--cameras", type=int, nargs="+", default=[3], help="camera counts (default: 3)")
    parser.add_argument("--seeds", type=int, nargs="+", default=[31], help="scene seeds (default: 31)")
    parser.add_argument("--duration", type=float, default=50.0, help="session length, seconds (default: 50)")
    parser.add_argument("--bump-camera", type=int, nargs="*", default=[2],
                        help="the cameras bumped, 2 cm / 1 deg each (default: 2; none: no bump)")
    parser.add_argument("--bump-at", type=float, nargs="*", default=[20.0],
                        help="when, seconds after the start, one per bumped camera (default: 20)")
    parser.add_argument("--drift-camera", type=int, default=0, help="a camera drifting from the start (default: none)")
    parser.add_argument("--drift-mm-per-min", type=float, default=2.0, help="its drift, mm per minute (default: 2)")
    parser.add_argument("--long", action="store_true",
                        help="no bump, no drift: --duration 600 unless given (10 minutes), the false-alarm run")
    parser.add_argument("--joint-span", type=float, default=0.0,
                        help="also fit all cameras jointly over spans of this many seconds of the watched replay's "
                             "checked sightings and say which camera moved since the first span, one left out at a "
                             "time (docs/calibration.md, the drift's observability; 0: not)")
    parser.add_argument("--joint-every", type=float, default=30.0, help="a joint-fit span ending every this many "
                        "seconds (default: 30)")
    parser.add_argument("--report", type=Path, default=None, help="write the JSON report here")
    parser.add_argument("--no-still", action="store_true", help="skip the unbumped twin (half the rendering)")
    parser.add_argument("--real", action="store_true", help="also replay the caliscope-4cam real footage watched")
    parser.add_argument("--follow-m", type=float, default=None,
                        help="the watcher's follow_m, metres (default: the config's; 0: no drift followed)")
    args = parser.parse_args(argv)
    if args.long:
        args.bump_camera, args.bump_at, args.drift_camera = [], [], 0
        if "--duration" not in (argv if argv is not None else sys.argv[1:]):
            args.duration = 600.0
    if len(args.bump_camera) != len(args.bump_at):
        parser.error(f"--bump-at needs one time per bumped camera ({len(args.bump_camera)}), got {len(args.bump_at)}")
    moves = Moves(tuple(args.bump_camera), tuple(args.bump_at), args.drift_camera,
                  args.drift_mm_per_min if args.drift_camera else 0.0)
    args.work.mkdir(parents=True, exist_ok=True)
    if args.real:
        print("real footage (caliscope-4cam), watched:", real_footage(args.work / "caliscope-4cam"), flush=True)
    rows = []
    for cameras in args.cameras:
        for seed in args.seeds:
            rows.append(run_scene(args.work, cameras, seed, args.duration, moves, not args.no_still,
                                  (args.joint_span, args.joint_every) if args.joint_span > 0 else None,
                                  args.follow_m))
            print(json.dumps(rows[-1], indent=1, default=float), flush=True)
    print_table(rows)
    if args.report:
        args.report.write_text(json.dumps(rows, indent=1, default=float), encoding="utf-8")
    return 0


def print_table(rows: list[dict]) -> None:
    print(f"\n{os.cpu_count()} cores, load {os.getloadavg()[0]:.1f}")
    print("cams seed moves              camera  moved after  rejoined after  new pose error    calibrated before    "
          "pp floor  max err (before/after the first move)  RMSE watched/base  alarms (still)")
    for r in rows:
        w = r["watched"]
        alarms = f"{len(w['false_alarms'])} ({len(r['still']['false_alarms']) if 'still' in r else '-'})"
        head = (f"{r['cameras']:4d} {r['seed']:4d} {r['moves']:<18} ")
        tail = (f"{100 * w['max_before_m']:5.1f} / {100 * w['max_after_m']:5.1f} cm"
                f"{r['rmse_ratio']:27.3f}  {alarms}")
        for camera, b in (w.get("bumps") or {"-": {}}).items():
            print(f"{head}{camera:>6}  {_s(b.get('moved_after_s')):>11}  {_s(b.get('rejoined_after_s')):>14}  "
                  f"{_pose(b.get('new_pose_error')):>16}  {_pose(b.get('calibrated_error')):>18}  "
                  f"{_deg(b.get('principal_point_floor_deg')):>9}  {tail}")
            if b.get("move_error"):
                print(f"{'':29}the move found against the true move: {_pose(b['move_error'])}")
            if b.get("new_pose_error_in_world"):
                print(f"{'':29}the new pose against its true pose in the calibrated world of the unmoved cameras: "
                      f"{_pose(b['new_pose_error_in_world'])} (those cameras {1000 * b['world_rms_m']:.1f} mm RMS "
                      f"from a rigid copy of their truth)")
        print(f"    drift followed: {len(w['follows'])} steps {sorted({f[0] for f in w['follows']})}; cameras that "
              f"never moved followed (mm from their calibration at the end): {w['false_follows_mm']} "
              f"(still twin: {r['still']['false_follows_mm'] if 'still' in r else '-'})")
        plain = {t: in_use for t, in_use, _ in r.get("watched_no_follow", {}).get("drift", [])}
        for t, in_use, settled in w.get("drift", []):
            print(f"    drift at {t:6.1f} s: pose in use {in_use:6.2f} mm off ({plain.get(t, math.nan):6.2f} with no "
                  f"follow), settled pose {'-' if settled is None else f'{settled:.2f} mm'} off")
        if "watched_no_follow" in r:
            plain_rmse = r["watched_no_follow"]["rmse_m"]
            print(f"    RMSE watched {100 * w['rmse_m']:.3f} cm, with no follow {100 * plain_rmse:.3f} cm, "
                  f"unwatched {100 * r['unwatched']['rmse_m']:.3f} cm")


def _s(value: float | None) -> str:
    return "never" if value is None else f"{value:.1f} s"


def _deg(value: float | None) -> str:
    return "-" if value is None else f"{value:.3f} deg"


def _pose(value: tuple[float, float] | None) -> str:
    return "-" if value is None else f"{1000 * value[0]:.1f} mm {value[1]:.3f} deg"


if __name__ == "__main__":
    sys.exit(main())
