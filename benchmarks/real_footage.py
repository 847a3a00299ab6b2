"""Real footage, scored: the caliscope-4cam recording (../shared/data/real, its README) imported with
``cubetrack import``, tracked with the default filter and with the paper's mean fusion, each scored
against the board's own ChArUco corners triangulated from the calibrated cameras.

The reference (:func:`charuco_reference`): in every camera frame OpenCV's ``CharucoDetector`` finds
the board's chessboard corners (on the negated image: the board is printed inverted); at each
instant (caliscope's ``sync_index``: one frame per camera, a few ms apart) every corner seen by two
or more cameras is triangulated (linear least squares on undistorted rays, the calibration's
cameras), and the board's corner grid is fitted to them rigidly (Kabsch). An instant counts when
at least 6 corners triangulate and the rigid fit's RMS residual is below 3 mm (typically ~1 mm);
every instant at which two or more cameras see board markers (ids of the board: a stray id of the
dictionary elsewhere in a frame, a false positive as the README names, is not the board) counts for
the share of instants with a pose.

Scoring (:func:`score`): an instant has a pose when the tracker output one between its first and
its last camera frame (1 ms slack); the instant's last such pose is compared with the reference
interpolated to that pose's time (linear in position, slerp in rotation, between neighbouring
instants). Position error in mm, rotation error in degrees.

Usage: python benchmarks/real_footage.py [--data DIR] [--work DIR]   (prints a table)
"""

from __future__ import annotations

import argparse
import csv
import os
import sys
import tempfile
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
from scipy.spatial.transform import Rotation, Slerp

DATA = Path(__file__).resolve().parents[1] / ".." / "shared" / "data" / "real" / "caliscope-4cam"
MIN_CORNERS = 6
MAX_FIT_RMS_M = 0.003
TIME_SLACK_S = 0.001


@dataclass(frozen=True)
class Instant:
    """One sync index at which two or more cameras see board markers: its frames' time span (s),
    the board's reference pose in the world (body frame of ``cubetrack import``'s board layout;
    None where too few corners triangulate or the rigid fit is off), how many cameras saw markers,
    the fit's RMS (m)."""

    t0_s: float
    t1_s: float
    T_world_body: np.ndarray | None
    cameras: int
    rms_m: float


def _frames(video: Path) -> list[np.ndarray]:
    capture = cv2.VideoCapture(str(video))
    out = []
    while True:
        ok, image = capture.read()
        if not ok:
            break
        out.append(cv2.cvtColor(image, cv2.COLOR_BGR2GRAY))
    capture.release()
    return out


def _triangulate(rays: Sequence[tuple[np.ndarray, np.ndarray]]) -> np.ndarray:
    """The point closest (least squares) to rays given as (origin, unit direction) in the world."""
    A = np.zeros((3, 3))
    b = np.zeros(3)
    for origin, d in rays:
        P = np.eye(3) - np.outer(d, d)
        A += P
        b += P @ origin
    return np.linalg.solve(A, b)


def _rigid_fit(model: np.ndarray, points: np.ndarray) -> tuple[np.ndarray, float]:
    """T (4x4) with points ~ T model (Kabsch), and the RMS residual (m)."""
    cm, cp = model.mean(axis=0), points.mean(axis=0)
    U, _, Vt = np.linalg.svd((model - cm).T @ (points - cp))
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(Vt.T @ U.T))])
    R = Vt.T @ D @ U.T
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, cp - R @ cm
    rms = float(np.sqrt(np.mean(np.sum((model @ R.T + T[:3, 3] - points) ** 2, axis=1))))
    return T, rms


def charuco_reference(data: Path = DATA) -> dict[int, Instant]:
    """Sync index -> the board's reference pose (module docstring)."""
    from cubetrack.io.caliscope import read_caliscope_rig

    rig = read_caliscope_rig(data)
    board = rig.board
    dictionary = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, board.dictionary))
    cv_board = cv2.aruco.CharucoBoard((board.squares_x, board.squares_y), board.square_size_m,
                                      board.marker_size_m, dictionary)
    detector = cv2.aruco.CharucoDetector(cv_board)
    grid_cv = np.asarray(cv_board.getChessboardCorners(), float).reshape(-1, 3)
    board_ids = set(np.asarray(cv_board.getIds()).ravel().tolist())
    T_body_cv = board.T_board_opencv  # OpenCV's board frame in the board (body) frame
    rows: dict[int, list[tuple[int, int, float]]] = {}
    with (data / "video" / "timestamps.csv").open(newline="") as f:
        for row in csv.DictReader(f):
            rows.setdefault(int(row["cam_id"]), []).append((int(row["sync_index"]), int(row["frame_index"]),
                                                            float(row["frame_time"])))
    seen: dict[int, dict[int, list[tuple[np.ndarray, np.ndarray]]]] = {}  # sync -> corner -> rays
    times: dict[int, list[float]] = {}
    cams: dict[int, set[int]] = {}
    for cam, cam_rows in rows.items():
        intr, T_world_cam = rig.intrinsics[cam], rig.extrinsics[cam].T_world_cam
        frames = _frames(data / "video" / f"cam_{cam}.mp4")
        for k, (sync, _index, t) in enumerate(sorted(cam_rows)):
            times.setdefault(sync, []).append(t)
            gray = frames[k]
            corners, ids, _, marker_ids = detector.detectBoard(255 - gray if rig.inverted else gray)
            if marker_ids is not None and board_ids.intersection(marker_ids.ravel().tolist()):  # not a stray id
                cams.setdefault(sync, set()).add(cam)
            if ids is None or len(ids) < 2:
                continue
            xy = cv2.undistortPoints(corners.reshape(-1, 1, 2), intr.K, intr.dist).reshape(-1, 2)
            dirs = np.column_stack([xy, np.ones(len(xy))]) @ T_world_cam[:3, :3].T
            dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
            for corner_id, d in zip(ids.ravel().tolist(), dirs, strict=True):
                seen.setdefault(sync, {}).setdefault(corner_id, []).append((T_world_cam[:3, 3], d))
    out = {}
    for sync, seen_by in cams.items():
        if len(seen_by) < 2:
            continue
        corners = seen.get(sync, {})
        ids = [c for c, rays in corners.items() if len(rays) >= 2]
        T_world_body, rms = None, float("nan")
        if len(ids) >= MIN_CORNERS:
            T_world_cv, rms = _rigid_fit(grid_cv[ids], np.array([_triangulate(corners[c]) for c in ids]))
            if rms <= MAX_FIT_RMS_M:
                T_world_body = T_world_cv @ np.linalg.inv(T_body_cv)
        out[sync] = Instant(min(times[sync]), max(times[sync]), T_world_body, len(seen_by), rms)
    return out


def read_tum(path: Path) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Times (n,), positions (n, 3), quaternions xyzw (n, 4) of a TUM file."""
    rows = np.loadtxt(path, ndmin=2)
    if rows.size == 0:
        return np.zeros(0), np.zeros((0, 3)), np.zeros((0, 4))
    return rows[:, 0], rows[:, 1:4], rows[:, 4:8]


@dataclass(frozen=True)
class Score:
    instants: int          # instants at which >= 2 cameras saw board markers
    with_pose: int         # of those, the ones with a pose (errors: where the reference has a pose)
    position_mm: np.ndarray
    rotation_deg: np.ndarray

    @property
    def fraction(self) -> float:
        return self.with_pose / max(self.instants, 1)

    def line(self, name: str) -> str:
        p, r = self.position_mm, self.rotation_deg
        if not len(p):
            return f"{name:<28} poses at 0/{self.instants} instants"
        return (f"{name:<28} poses at {self.with_pose}/{self.instants} instants ({100 * self.fraction:.1f} %); "
                f"position median {np.median(p):.2f} p95 {np.percentile(p, 95):.2f} max {p.max():.2f} mm; "
                f"rotation median {np.median(r):.3f} p95 {np.percentile(r, 95):.3f} max {r.max():.3f} deg")


def score(tum: Path, reference: Mapping[int, Instant], frame_times_s: np.ndarray | None = None) -> Score:
    """Score a TUM trajectory against ``reference`` (module docstring). ``frame_times_s``: per pose,
    the recorded time of the frame it was made from (NaN: none), which then places the pose in its
    instant instead of the pose's own time (a live run's clock is not the recording's); the errors
    are still taken at the pose's own time."""
    times, positions, quats = read_tum(tum)
    placed = times if frame_times_s is None else np.asarray(frame_times_s, float)
    syncs = sorted(s for s, i in reference.items() if i.T_world_body is not None)
    ref_t = np.array([0.5 * (reference[s].t0_s + reference[s].t1_s) for s in syncs])
    ref_T = np.array([reference[s].T_world_body for s in syncs])
    ref_p, slerp = ref_T[:, :3, 3], Slerp(ref_t, Rotation.from_matrix(ref_T[:, :3, :3]))
    pos_err, rot_err = [], []
    with_pose = 0
    for _sync, inst in sorted(reference.items()):
        inside = np.flatnonzero((placed >= inst.t0_s - TIME_SLACK_S) & (placed <= inst.t1_s + TIME_SLACK_S))
        if not len(inside):
            continue
        with_pose += 1
        if inst.T_world_body is None:
            continue
        i = inside[-1]
        t = float(np.clip(times[i], ref_t[0], ref_t[-1]))
        p_ref = np.array([np.interp(t, ref_t, ref_p[:, k]) for k in range(3)])
        pos_err.append(1000.0 * np.linalg.norm(positions[i] - p_ref))
        rot_err.append(np.degrees((slerp([t])[0].inv() * Rotation.from_quat(quats[i])).magnitude()))
    return Score(len(reference), with_pose, np.array(pos_err), np.array(rot_err))


def track(work: Path, name: str, sections: Mapping[str, Mapping[str, object]] | None = None) -> Path:
    """Track the imported recording in ``work`` with the config's settings plus ``sections``
    (extra TOML tables); the TUM file written."""
    import tomllib

    from cubetrack.app.config import config_params
    from cubetrack.app.track import track_recording
    from cubetrack.io.config import read_extrinsics, read_tracker_config, write_toml
    from cubetrack.io.recording import Recording

    with (work / "config.toml").open("rb") as f:
        doc = tomllib.load(f)
    for section, table in (sections or {}).items():
        doc[section] = {**doc.get(section, {}), **table}
    config_path = work / f"config-{name}.toml"
    write_toml(doc, config_path)
    config = read_tracker_config(config_path)
    out = work / f"track-{name}"
    track_recording(config, Recording.open(work / "recording"), read_extrinsics(work / "extrinsics.toml"), out,
                    config_params(config).stages, workers=0)
    return out / "board.tum"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--data", type=Path, default=DATA, help="the caliscope project folder")
    parser.add_argument("--work", type=Path, help="where to import and track (default: a temporary folder)")
    parser.add_argument("--set", action="append", default=[], metavar="SECTION.KEY=VALUE",
                        help="an extra setting for the 'custom' run (TOML value), e.g. filter.corner_noise_px=2.0")
    args = parser.parse_args(argv)
    from cubetrack.app.import_rig import import_caliscope

    work = args.work or Path(tempfile.mkdtemp(prefix="real-footage-"))
    if not (work / "config.toml").exists():
        import_caliscope(args.data, work)
    reference = charuco_reference(args.data)
    rms = np.array([i.rms_m for i in reference.values() if i.T_world_body is not None]) * 1000.0
    print(f"{len(reference)} instants with >= 2 cameras seeing the board, {len(rms)} with a reference pose: rigid-fit "
          f"RMS median {np.median(rms):.2f} mm, max {rms.max():.2f} mm; "
          f"cores {os.cpu_count()}")
    runs: dict[str, dict] = {"default (filter)": {}, "mean fusion": {"fusion": {"method": "mean"}}}
    if args.set:
        import tomllib

        custom: dict[str, dict] = {}
        for item in args.set:
            key, value = item.split("=", 1)
            section, name = key.split(".", 1)
            custom.setdefault(section, {})[name] = tomllib.loads(f"v = {value}")["v"]
        runs["custom " + " ".join(args.set)] = custom
    for i, (name, sections) in enumerate(runs.items()):
        print(score(track(work, f"run{i}", sections), reference).line(name), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
