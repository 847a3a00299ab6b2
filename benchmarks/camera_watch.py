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


def scene(work: Path, cameras: int, seed: int, duration_s: float, bump_camera: int, bump_at_s: float,
          bumped: bool) -> Path:
    """Render (once) a realistic session; the unbumped twin has no calibration recording (it is the same)."""
    from cubetrack.simulate import SimulationParams, simulate

    name = f"c{cameras}_s{seed}_d{duration_s:g}_" + (f"bump{bump_camera}at{bump_at_s:g}" if bumped else "still")
    rec = work / name
    if (rec / "done").exists():
        return rec
    changes = {"bump_camera": (bump_camera,), "bump_at_s": (bump_at_s,), "bump_step_m": BUMP_STEP_M,
               "bump_turn_deg": BUMP_TURN_DEG} if bumped else {"calibration_frames": 0}
    params = SimulationParams.realistic(cameras=cameras, seed=seed, duration_s=duration_s, **changes)
    simulate(params, rec, overwrite=True, workers=min(4, os.cpu_count() or 1))
    (rec / "done").write_text("", encoding="utf-8")
    return rec


def replay(rec: Path, extrinsics: dict, watch: bool, config_path: Path | None = None) -> tuple[list, list, float]:
    """Replay a recording through a Tracker (frames and /time round trips in arrival order);
    returns its poses, the watcher's events and the CPU seconds it took."""
    from cubetrack.app.track import recording_intrinsics
    from cubetrack.app.tracker import StageParams, Tracker
    from cubetrack.calib.recalibrate import WatchedFusion
    from cubetrack.io.config import read_tracker_config
    from cubetrack.io.recording import Recording

    config = read_tracker_config(config_path or rec / "config.toml")
    recording = Recording.open(rec)
    params = StageParams.from_config(config)
    params = dataclasses.replace(params, camera_watch=dataclasses.replace(params.camera_watch, enabled=watch))
    synced = frozenset(c for c in recording.camera_names if recording.clock_samples(c))
    tracker = Tracker(recording_intrinsics(config, recording), config.world, config.robots, extrinsics, params,
                      synced)
    trips = sorted(((s.host_recv_s, c, s) for c in recording.camera_names for s in recording.clock_samples(c)),
                   key=lambda item: (item[0], item[1]))
    poses, k = [], 0
    c0 = time.process_time()
    for frame in recording.merged_frames():
        while k < len(trips) and trips[k][0] <= frame.host_time_s:
            poses += tracker.add_clock_sample(trips[k][1], trips[k][2])
            k += 1
        poses += tracker.process(frame)
    poses += tracker.finish()
    events = list(tracker.fusion.events) if isinstance(tracker.fusion, WatchedFusion) else []
    return poses, events, time.process_time() - c0


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


def new_pose_error(rec: Path, camera: str, T_world_cam: np.ndarray) -> tuple[float, float]:
    """The re-calibrated pose against the camera's true pose at the end of the session (m, deg)."""
    from cubetrack.core.geometry import R_from_quat_xyzw, rotation_angle
    from cubetrack.io.trajectory import read_tum

    truth = read_tum(rec / "true_camera_poses" / f"{camera}.tum")
    return (float(np.linalg.norm(truth.positions_m[-1] - T_world_cam[:3, 3])),
            rotation_angle(R_from_quat_xyzw(truth.quats_xyzw[-1]), T_world_cam[:3, :3], unit="deg"))


def rmse(err: np.ndarray) -> float:
    return float(np.sqrt(np.mean(err**2))) if len(err) else math.nan


def run_scene(work: Path, cameras: int, seed: int, duration_s: float, bump_camera: int, bump_at_s: float,
              still: bool = True) -> dict:
    """One scene's replays (see the module doc); ``still``: also render and replay the unbumped twin
    (doubles the rendering; without it there is no RMSE ratio nor false-alarm count)."""
    from cubetrack.app.calibrate import calibrate_recording
    from cubetrack.io.config import read_tracker_config
    from cubetrack.io.recording import Recording

    bumped_rec = scene(work, cameras, seed, duration_s, bump_camera, bump_at_s, True)
    still_rec = scene(work, cameras, seed, duration_s, bump_camera, bump_at_s, False) if still else None
    config = read_tracker_config(bumped_rec / "config.toml")
    extrinsics = calibrate_recording(config, Recording.open(bumped_rec / "calibration")).extrinsics
    start = float(read_tracker_start(bumped_rec))
    camera = f"cam{bump_camera}"
    out: dict = {"cameras": cameras, "seed": seed, "duration_s": duration_s, "bump": f"{camera} at {bump_at_s:g} s"}
    runs = [("watched", bumped_rec, True), ("unwatched", bumped_rec, False)]
    if still_rec is not None:
        runs += [("still", still_rec, True), ("still_unwatched", still_rec, False)]
    for key, rec, watch in runs:
        poses, events, cpu_s = replay(rec, extrinsics, watch)
        times, err = errors_m(poses, rec)
        row: dict = {"rmse_m": rmse(err), "max_m": float(err.max()), "poses": len(err), "cpu_s": cpu_s,
                     "events": [(e.kind.value, e.camera, round(e.time_s - start, 2)) for e in events]}
        if key == "watched":
            moved = [e for e in events if e.kind.value == "moved" and e.camera == camera]
            rejoined = [e for e in events if e.kind.value == "rejoined" and e.camera == camera]
            row["moved_after_s"] = moved[0].time_s - start - bump_at_s if moved else None
            row["rejoined_after_s"] = rejoined[0].time_s - start - bump_at_s if rejoined else None
            if rejoined:
                row["new_pose_error"] = new_pose_error(rec, camera, rejoined[0].T_world_cam)
                row["sightings"] = rejoined[0].sightings
            row["false_alarms"] = [e.camera for e in events if e.kind.value == "moved" and e.camera != camera]
        out[key] = row
    out["rmse_ratio"] = out["watched"]["rmse_m"] / out["still_unwatched"]["rmse_m"] if still_rec else math.nan
    return out


def real_footage(work: Path) -> dict:
    """The caliscope-4cam footage imported as benchmarks/real_footage.py does, replayed with the
    watching on: its events (there should be none: nobody bumped those cameras)."""
    from cubetrack.app.import_rig import import_caliscope
    from cubetrack.io.config import read_extrinsics

    data = Path(__file__).resolve().parents[1] / ".." / "shared" / "data" / "real" / "caliscope-4cam"
    if not (work / "config.toml").exists():
        import_caliscope(data, work)
    poses, events, cpu_s = replay(work / "recording", read_extrinsics(work / "extrinsics.toml"), True,
                                  work / "config.toml")
    return {"poses": len(poses), "events": [(e.kind.value, e.camera, e.time_s) for e in events], "cpu_s": cpu_s}


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
    parser.add_argument("--bump-camera", type=int, default=2, help="the camera bumped (default: 2)")
    parser.add_argument("--bump-at", type=float, default=20.0, help="when, seconds after the start (default: 20)")
    parser.add_argument("--report", type=Path, default=None, help="write the JSON report here")
    parser.add_argument("--no-still", action="store_true", help="skip the unbumped twin (half the rendering)")
    parser.add_argument("--real", action="store_true", help="also replay the caliscope-4cam real footage watched")
    args = parser.parse_args(argv)
    args.work.mkdir(parents=True, exist_ok=True)
    if args.real:
        print("real footage (caliscope-4cam), watched:", real_footage(args.work / "caliscope-4cam"), flush=True)
    rows = []
    for cameras in args.cameras:
        for seed in args.seeds:
            rows.append(run_scene(args.work, cameras, seed, args.duration, args.bump_camera, args.bump_at,
                                  not args.no_still))
            print(json.dumps(rows[-1], indent=1, default=float), flush=True)
    print(f"\n{os.cpu_count()} cores, load {os.getloadavg()[0]:.1f}")
    print("cams seed  moved after  rejoined after  new pose error   max err  RMSE watched/still  still: alarms")
    for r in rows:
        w = r["watched"]
        pose_err = w.get("new_pose_error")
        print(f"{r['cameras']:4d} {r['seed']:4d}  {_s(w['moved_after_s']):>11}  {_s(w['rejoined_after_s']):>14}  "
              f"{_pose(pose_err):>14}  {100 * w['max_m']:6.1f} cm  {r['rmse_ratio']:18.3f}  "
              f"{len([e for e in r['still']['events'] if e[0] == 'moved']) if 'still' in r else '-'}")
    if args.report:
        args.report.write_text(json.dumps(rows, indent=1, default=float), encoding="utf-8")
    return 0


def _s(value: float | None) -> str:
    return "never" if value is None else f"{value:.1f} s"


def _pose(value: tuple[float, float] | None) -> str:
    return "-" if value is None else f"{1000 * value[0]:.1f} mm {value[1]:.3f} deg"


if __name__ == "__main__":
    sys.exit(main())
