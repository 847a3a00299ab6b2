"""Real footage, scored: the caliscope-4cam recording (../shared/data/real, its README) imported with
``cubetrack import``, tracked with the default filter and with the paper's mean fusion, each scored
against the board's own ChArUco corners triangulated from the calibrated cameras.

The reference (:func:`charuco_reference`): in every camera frame OpenCV's ``CharucoDetector`` finds
the board's chessboard corners (on the negated image: the board is printed inverted); at each
instant (caliscope's ``sync_index``: one frame per camera, a few ms apart) every corner seen by two
or more cameras is triangulated (linear least squares on undistorted rays, the calibration's
cameras), and the board's corner grid is fitted to them rigidly (Kabsch). A camera's frame is part
of it only if it agrees with the others: while three frames or more are in, the one whose corners
are furthest from the reference of the others (RMS reprojection) is left out if that is over
``MAX_VIEW_RMS_PX`` (3 px: 2-3 times what agreeing cameras show on this footage, docs/tracking.md
"Real footage"); a camera left out still counts for the instant and the tracker still uses it. An
instant has a reference pose when at least 6 corners triangulate and the rigid fit's RMS residual
is below 3 mm (typically ~1 mm); its time is the mean stamp of the frames in it. Every instant at
which two or more cameras see board markers (ids of the board: a stray id of the dictionary
elsewhere in a frame, a false positive as the README names, is not the board) counts for the share
of instants with a pose. What the reference is worth is printed first (:func:`reference_report`):
per camera its corners' RMS against the other cameras' reference, the frames left out, and how far
the board moves when that camera is left out; each camera's stamp offset that best fits it to the
board the others see (:func:`camera_time_offsets`); and how far the reference of every corner is.

Scoring (:func:`score`): an instant has a pose when the tracker output one between its first and
its last camera frame (1 ms slack); the instant's last such pose is compared with the reference
interpolated to that pose's time (linear in position, slerp in rotation, between neighbouring
instants). Position error in mm, rotation error in degrees.

What the scoring allows (:func:`instant_fits`, printed last): the corners the default run's filter got,
one fit per instant, scored the same way — every camera taken as exact (a triangulation, as the reference
is), the reference's own cameras only, and weighed by the calibration term as set (the filter's
measurement model without its motion model).

Runs: the default filter (the import's board: ``motion = "free"``, a hand-held body: docs/tracking.md "A motion
switch per body"), the mean fusion, the default filter with the board's ``motion = "floor"`` (the robot body's
default), and ``--set``'s.

Usage: python benchmarks/real_footage.py [--data DIR] [--work DIR] [--reference-only]   (prints a table)
"""

from __future__ import annotations

import argparse
import csv
import os
import sys
import tempfile
from collections.abc import Callable, Iterator, Mapping, Sequence
from contextlib import contextmanager, nullcontext
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING

import cv2
import numpy as np
from scipy.spatial.transform import Rotation, Slerp

if TYPE_CHECKING:
    from cubetrack.core.cameras import CameraIntrinsics
    from cubetrack.core.layout import CubeLayout
    from cubetrack.core.records import CubeSighting
    from cubetrack.estimate.reprojection import CornerSet
    from cubetrack.fuse.corner_filter import FilterParams

DATA = Path(__file__).resolve().parents[1] / ".." / "shared" / "data" / "real" / "caliscope-4cam"
MIN_CORNERS = 6
MAX_FIT_RMS_M = 0.003
TIME_SLACK_S = 0.001
MAX_VIEW_RMS_PX = 3.0


@dataclass(frozen=True, eq=False)
class View:
    """One camera frame's ChArUco corners: the camera id, its stamp (s), the corners' ids and pixels,
    their rays' unit directions in the world (from the camera's centre, ``T_world_cam``'s translation) and
    the camera that projects into the frame (intrinsics, ``T_world_cam``). Compared by identity."""

    camera: int
    t_s: float
    ids: np.ndarray
    corners_px: np.ndarray
    dirs: np.ndarray
    intrinsics: CameraIntrinsics
    T_world_cam: np.ndarray


@dataclass(frozen=True)
class Instant:
    """One sync index at which two or more cameras see board markers: its frames' time span (s),
    the board's reference pose in the world (body frame of ``cubetrack import``'s board layout;
    None where too few corners triangulate or the rigid fit is off), how many cameras saw markers,
    the fit's RMS (m). ``t_s``: the mean stamp of the frames in the reference; ``used`` / ``dropped``:
    the cameras whose corners made it / were left out for disagreeing with the others;
    ``reprojection_px``: per camera with corners, the RMS (px) of its corners against the reference
    of the other used cameras (against the reference itself where they make none); ``loo_mm``: per
    used camera, how far (mm) the board's centre moves when that camera is left out (three cameras or
    more); ``all_cameras_mm``: how far the reference of every camera's corners, agreeing or not, is;
    ``views``: every camera's corners at the instant; ``grid_m``: the board's corners (OpenCV's board frame)."""

    t0_s: float
    t1_s: float
    T_world_body: np.ndarray | None
    cameras: int
    rms_m: float
    t_s: float = float("nan")
    used: tuple[int, ...] = ()
    dropped: tuple[int, ...] = ()
    reprojection_px: Mapping[int, float] = field(default_factory=dict)
    loo_mm: Mapping[int, float] = field(default_factory=dict)
    all_cameras_mm: float = float("nan")
    views: tuple[View, ...] = ()
    grid_m: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))


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


def _fit(views: Sequence[View], grid: np.ndarray) -> tuple[np.ndarray | None, float]:
    """The board's grid (OpenCV's board frame) fitted rigidly to its corners triangulated from
    ``views`` (those seen in two views or more): T_world_board, or None where fewer than
    ``MIN_CORNERS`` triangulate or the fit's RMS is over ``MAX_FIT_RMS_M``; the RMS (m)."""
    rays: dict[int, list[tuple[np.ndarray, np.ndarray]]] = {}
    for view in views:
        for corner_id, d in zip(view.ids.tolist(), view.dirs, strict=True):
            rays.setdefault(corner_id, []).append((view.T_world_cam[:3, 3], d))
    ids = [c for c, r in rays.items() if len(r) >= 2]
    if len(ids) < MIN_CORNERS:
        return None, float("nan")
    T, rms = _rigid_fit(grid[ids], np.array([_triangulate(rays[c]) for c in ids]))
    return (T if rms <= MAX_FIT_RMS_M else None), rms


def _reprojection_px(view: View, T_world_board: np.ndarray, grid: np.ndarray) -> float:
    """RMS (px) of the view's corners against the board's corners at ``T_world_board`` projected."""
    T_cam_world = np.linalg.inv(view.T_world_cam) @ T_world_board
    rvec, _ = cv2.Rodrigues(T_cam_world[:3, :3])
    px, _ = cv2.projectPoints(grid[view.ids], rvec, T_cam_world[:3, 3], view.intrinsics.K, view.intrinsics.dist)
    return float(np.sqrt(np.mean(np.sum((px.reshape(-1, 2) - view.corners_px) ** 2, axis=1))))


def _agreeing(views: Sequence[View], grid: np.ndarray, max_view_rms_px: float) -> tuple[list[View], dict[int, float]]:
    """The views that agree: while three or more are left, the view whose corners are furthest
    (RMS px) from the reference of the others goes if that is over ``max_view_rms_px``. Returns the
    views kept and, per view's camera, its RMS against the others' reference (the last one
    computed; a camera whose others made no reference: none)."""
    kept, rms_px = list(views), {}
    while len(kept) >= 3:
        for view in kept:
            T_others, _ = _fit([v for v in kept if v is not view], grid)
            if T_others is not None:
                rms_px[view.camera] = _reprojection_px(view, T_others, grid)
        worst = max(kept, key=lambda v: rms_px.get(v.camera, 0.0))
        if rms_px.get(worst.camera, 0.0) <= max_view_rms_px:
            break
        kept.remove(worst)
    return kept, rms_px


def _position_mm(A: np.ndarray, B: np.ndarray, T_body_cv: np.ndarray) -> float:
    """How far apart (mm) the board's centre is at the OpenCV board poses ``A`` and ``B``."""
    return 1000.0 * float(np.linalg.norm((A @ np.linalg.inv(T_body_cv))[:3, 3] - (B @ np.linalg.inv(T_body_cv))[:3, 3]))


def _instant(views: Sequence[View], times: Sequence[float], cameras: int, grid: np.ndarray,
             T_body_cv: np.ndarray, max_view_rms_px: float) -> Instant:
    """The reference pose of one instant from its views (module docstring)."""
    kept, rms_px = _agreeing(views, grid, max_view_rms_px)
    T_cv, rms = _fit(kept, grid)
    t0, t1 = min(times), max(times)
    if T_cv is None:
        return Instant(t0, t1, None, cameras, rms, views=tuple(views), grid_m=grid)
    for view in views:  # a camera left out keeps its RMS against the others that left it out
        if view.camera not in rms_px or (len(kept) < 3 and view in kept):
            rms_px[view.camera] = _reprojection_px(view, T_cv, grid)
    loo = {}
    for view in kept if len(kept) >= 3 else ():
        T_others, _ = _fit([v for v in kept if v is not view], grid)
        if T_others is not None:
            loo[view.camera] = _position_mm(T_others, T_cv, T_body_cv)
    T_all, _ = _fit(views, grid)
    return Instant(t0, t1, T_cv @ np.linalg.inv(T_body_cv), cameras, rms, float(np.mean([v.t_s for v in kept])),
                   tuple(v.camera for v in kept), tuple(v.camera for v in views if v not in kept), rms_px, loo,
                   _position_mm(T_all, T_cv, T_body_cv) if T_all is not None else float("nan"), tuple(views), grid)


def charuco_reference(data: Path = DATA, max_view_rms_px: float = MAX_VIEW_RMS_PX) -> dict[int, Instant]:
    """Sync index -> the board's reference pose (module docstring; ``max_view_rms_px`` inf: every
    camera's corners, agreeing or not)."""
    from cubetrack.io.caliscope import read_caliscope_rig

    rig = read_caliscope_rig(data)
    board = rig.board
    dictionary = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, board.dictionary))
    cv_board = cv2.aruco.CharucoBoard((board.squares_x, board.squares_y), board.square_size_m,
                                      board.marker_size_m, dictionary)
    detector = cv2.aruco.CharucoDetector(cv_board)
    grid_cv = np.asarray(cv_board.getChessboardCorners(), float).reshape(-1, 3)
    board_ids = set(np.asarray(cv_board.getIds()).ravel().tolist())
    rows: dict[int, list[tuple[int, int, float]]] = {}
    with (data / "video" / "timestamps.csv").open(newline="") as f:
        for row in csv.DictReader(f):
            rows.setdefault(int(row["cam_id"]), []).append((int(row["sync_index"]), int(row["frame_index"]),
                                                            float(row["frame_time"])))
    views: dict[int, list[View]] = {}
    times: dict[int, list[float]] = {}
    cams: dict[int, set[int]] = {}
    for cam, cam_rows in rows.items():
        intr, T_world_cam = rig.intrinsics[cam], rig.extrinsics[cam].T_world_cam
        frames = _frames(data / "video" / f"cam_{cam}.mp4")
        for k, (sync, _index, t) in enumerate(sorted(cam_rows)):
            times.setdefault(sync, []).append(t)
            corners, ids, _, marker_ids = detector.detectBoard(255 - frames[k] if rig.inverted else frames[k])
            if marker_ids is not None and board_ids.intersection(marker_ids.ravel().tolist()):  # not a stray id
                cams.setdefault(sync, set()).add(cam)
            if ids is None or len(ids) < 2:
                continue
            xy = cv2.undistortPoints(corners.reshape(-1, 1, 2), intr.K, intr.dist).reshape(-1, 2)
            dirs = np.column_stack([xy, np.ones(len(xy))]) @ T_world_cam[:3, :3].T
            views.setdefault(sync, []).append(View(cam, t, ids.ravel(), corners.reshape(-1, 2),
                                                   dirs / np.linalg.norm(dirs, axis=1, keepdims=True), intr,
                                                   T_world_cam))
    return {sync: _instant(views.get(sync, []), times[sync], len(seen_by), grid_cv, board.T_board_opencv,
                           max_view_rms_px)
            for sync, seen_by in sorted(cams.items()) if len(seen_by) >= 2}


def reference_report(reference: Mapping[int, Instant]) -> list[str]:
    """What the reference is worth, in lines: per camera its corners' RMS (px) against the other
    cameras' reference, the frames left out, how far the board moves without it (leave-one-camera-out,
    mm); the reference against the one of every camera's corners."""
    posed = [i for i in reference.values() if i.T_world_body is not None]
    rms = np.array([i.rms_m for i in posed]) * 1000.0
    spread_ms = 1000.0 * np.array([i.t1_s - i.t0_s for i in reference.values()])
    lines = [f"{len(reference)} instants with >= 2 cameras seeing the board, {len(posed)} with a reference pose: "
             f"rigid-fit RMS median {np.median(rms):.2f} mm, max {rms.max():.2f} mm; an instant's frames stamped "
             f"within {np.median(spread_ms):.1f} ms (median), {np.percentile(spread_ms, 90):.1f} (p90), "
             f"{spread_ms.max():.1f} (max)"]
    for cam in sorted({c for i in posed for c in i.reprojection_px}):
        px = np.array([i.reprojection_px[cam] for i in posed if cam in i.reprojection_px])
        loo = np.array([i.loo_mm[cam] for i in posed if cam in i.loo_mm])
        dropped = sum(cam in i.dropped for i in posed)
        loo_text = f"median {np.median(loo):.2f} p95 {np.percentile(loo, 95):.2f} mm" if len(loo) else "-"
        lines.append(f"  cam{cam}: {len(px)} frames, corners against the others' reference RMS median "
                     f"{np.median(px):.2f} px (p95 {np.percentile(px, 95):.2f}); left out {dropped}; "
                     f"board moves without it {loo_text} ({len(loo)} instants)")
    loo_all = np.array([v for i in posed for v in i.loo_mm.values()])
    apart = np.array([i.all_cameras_mm for i in posed])
    offsets = camera_time_offsets(reference)
    lines.append("  stamps against the other cameras' board: " + "; ".join(
        f"cam{c} best {1000 * o:+.0f} ms ({at:.2f} px, at 0 ms {zero:.2f} px)" for c, (o, at, zero) in offsets.items()))
    lines.append(f"  leave-one-camera-out, every camera: median {np.median(loo_all):.2f} p95 "
                 f"{np.percentile(loo_all, 95):.2f} mm; the reference of all corners (none left out) is "
                 f"median {np.nanmedian(apart):.2f} p95 {np.nanpercentile(apart, 95):.2f} mm from it")
    return lines


def camera_time_offsets(reference: Mapping[int, Instant], step_s: float = 0.005,
                        span_s: float = 0.1) -> dict[int, tuple[float, float, float]]:
    """Per camera, how its stamps fit the board as the other cameras see it: the board's pose from
    the others' corners (instants where two or more others agree), interpolated to the camera's
    stamps moved by an offset (-``span_s`` to ``span_s`` in ``step_s`` steps), projected into its
    frames. (best offset s, the camera's corners' RMS px at it, at 0). No tracker involved."""
    out = {}
    for cam in sorted({v.camera for i in reference.values() for v in i.views}):
        times, poses = [], []
        for _sync, inst in sorted(reference.items()):
            others = [v for v in inst.views if v.camera != cam and v.camera in inst.used]
            T_cv = _fit(others, inst.grid_m)[0] if len(others) >= 2 else None
            if T_cv is not None:
                times.append(float(np.mean([v.t_s for v in others])))
                poses.append(T_cv)
        if len(times) < 2:
            continue
        t, T = np.array(times), np.array(poses)
        slerp = Slerp(t, Rotation.from_matrix(T[:, :3, :3]))
        offsets = np.round(np.arange(-span_s, span_s + step_s / 2, step_s), 6)
        sq, n = np.zeros(len(offsets)), np.zeros(len(offsets))
        for inst in reference.values():
            for view in (v for v in inst.views if v.camera == cam):
                at = view.t_s + offsets
                k = np.searchsorted(t, at)
                inside = np.flatnonzero((k > 0) & (k < len(t)))
                inside = inside[t[k[inside]] - t[k[inside] - 1] <= 0.4]  # a gap: not interpolated across
                if not len(inside):
                    continue
                rotations = slerp(at[inside]).as_matrix()
                for j, R in zip(inside, rotations, strict=True):
                    T_at = np.eye(4)
                    T_at[:3, :3], T_at[:3, 3] = R, [np.interp(at[j], t, T[:, m, 3]) for m in range(3)]
                    sq[j] += _reprojection_px(view, T_at, inst.grid_m) ** 2 * len(view.ids)
                    n[j] += len(view.ids)
        rms = np.sqrt(sq / np.maximum(n, 1))
        best, zero = int(np.argmin(np.where(n > 0, rms, np.inf))), int(np.argmin(np.abs(offsets)))
        out[cam] = (float(offsets[best]), float(rms[best]), float(rms[zero]))
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
    reference_cameras: np.ndarray = field(default_factory=lambda: np.zeros(0, int))  # per error: cameras in reference

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

    def by_reference(self, name: str) -> str:
        """The position errors grouped by how many agreeing cameras made the instant's reference (a reference
        of two cameras is the weakest: no camera can be checked against the others)."""
        groups = [f"{k} cameras: {n} instants, median {np.median(self.position_mm[self.reference_cameras == k]):.2f} mm"
                  for k, n in zip(*np.unique(self.reference_cameras, return_counts=True), strict=True)]
        return f"{name:<28} by reference: " + "; ".join(groups)


def _interpolated(reference: Mapping[int, Instant]) -> Callable[[float], tuple[np.ndarray, Rotation]]:
    """The reference as a function of time: t (s) -> the board's position (m) and rotation in the world,
    linear in position and slerp in rotation between neighbouring instants (held at either end)."""
    syncs = sorted(s for s, i in reference.items() if i.T_world_body is not None)
    ref_t = np.array([reference[s].t_s for s in syncs])
    ref_T = np.array([reference[s].T_world_body for s in syncs])
    ref_p, slerp = ref_T[:, :3, 3], Slerp(ref_t, Rotation.from_matrix(ref_T[:, :3, :3]))

    def at(t_s: float) -> tuple[np.ndarray, Rotation]:
        t = float(np.clip(t_s, ref_t[0], ref_t[-1]))
        return np.array([np.interp(t, ref_t, ref_p[:, k]) for k in range(3)]), slerp([t])[0]

    return at


def score(tum: Path, reference: Mapping[int, Instant], frame_times_s: np.ndarray | None = None) -> Score:
    """Score a TUM trajectory against ``reference`` (module docstring). ``frame_times_s``: per pose,
    the recorded time of the frame it was made from (NaN: none), which then places the pose in its
    instant instead of the pose's own time (a live run's clock is not the recording's); the errors
    are still taken at the pose's own time."""
    times, positions, quats = read_tum(tum)
    placed = times if frame_times_s is None else np.asarray(frame_times_s, float)
    reference_at = _interpolated(reference)
    pos_err, rot_err, used = [], [], []
    with_pose = 0
    for _sync, inst in sorted(reference.items()):
        inside = np.flatnonzero((placed >= inst.t0_s - TIME_SLACK_S) & (placed <= inst.t1_s + TIME_SLACK_S))
        if not len(inside):
            continue
        with_pose += 1
        if inst.T_world_body is None:
            continue
        i = inside[-1]
        p_ref, r_ref = reference_at(float(times[i]))
        pos_err.append(1000.0 * np.linalg.norm(positions[i] - p_ref))
        rot_err.append(np.degrees((r_ref.inv() * Rotation.from_quat(quats[i])).magnitude()))
        used.append(len(inst.used))
    return Score(len(reference), with_pose, np.array(pos_err), np.array(rot_err), np.array(used, dtype=int))


MATCH_GATE_PX = 30.0  # instant fits: a detection is the board's marker within this (px) of where the reference puts it
INSTANT_FITS = ("every camera as exact", "its cameras as exact", "the calibration term")


def instant_fits(reference: Mapping[int, Instant], sightings: Sequence[CubeSighting], layout: CubeLayout,
                 filter_params: FilterParams, max_view_angle_deg: float) -> dict[str, Score]:
    """What the scoring allows (its floor): one fit per instant of the corners the tracker got (its own
    detections, not the reference's ChArUco corners), scored as :func:`score` scores a tracker (the pose at
    the stamp of the instant's last frame). ``sightings``: the fusion's (:func:`track`'s ``sightings``).
    Each camera frame of the instant's span is matched to the board's markers where the reference puts
    the board (``MATCH_GATE_PX``; faces seen more obliquely than ``max_view_angle_deg`` left out, as the
    tracker does), then three fits, named in ``INSTANT_FITS``: every camera's corners in one multi-camera fit,
    each camera taken as exact (a triangulation, as the reference is); the same of the cameras the reference
    kept; and each camera's own fit weighed by its covariance plus the calibration term as ``filter_params``
    set it (the filter's measurement model at one instant, without its motion model: docs/tracking.md
    "Cameras that disagree")."""
    from cubetrack.core.geometry import make_T
    from cubetrack.estimate.match import match_faces
    from cubetrack.fuse.fusion import sighting_corner_sets

    reference_at = _interpolated(reference)
    errors: dict[str, list[tuple[float, float, int]]] = {name: [] for name in INSTANT_FITS}
    for inst in reference.values():
        inside = [s for s in sightings if inst.t0_s - TIME_SLACK_S <= s.capture_time_s <= inst.t1_s + TIME_SLACK_S]
        if inst.T_world_body is None or not inside:
            continue
        sets: dict[str, list[CornerSet]] = {}
        for s in inside:
            p, r = reference_at(s.capture_time_s)
            matches = match_faces(s.detections, layout, s.intrinsics, s.T_world_cam, make_T(r.as_matrix(), p),
                                  gate_px=MATCH_GATE_PX, max_view_angle_deg=max_view_angle_deg)
            sets.setdefault(s.camera, []).extend(sighting_corner_sets(matches, s.intrinsics, s.T_world_cam,
                                                                      s.camera, s.capture_time_s))
        t_s = max(s.capture_time_s for s in inside)
        p_ref, r_ref = reference_at(t_s)
        T_ref = make_T(r_ref.as_matrix(), p_ref)
        kept = {c: v for c, v in sets.items() if int(c.removeprefix("cam")) in inst.used}  # the import's names
        fitted = (_exact_fit(sets, T_ref, t_s, filter_params), _exact_fit(kept, T_ref, t_s, filter_params),
                  _term_fit(sets, T_ref, t_s, filter_params))
        for name, T in zip(INSTANT_FITS, fitted, strict=True):
            if T is not None:
                errors[name].append((1000.0 * float(np.linalg.norm(T[:3, 3] - p_ref)),
                                     float(np.degrees((r_ref.inv() * Rotation.from_matrix(T[:3, :3])).magnitude())),
                                     len(inst.used)))
    posed = sum(inst.T_world_body is not None for inst in reference.values())
    return {name: Score(posed, len(e), np.array([x[0] for x in e]), np.array([x[1] for x in e]),
                        np.array([x[2] for x in e], dtype=int)) for name, e in errors.items()}


def _exact_fit(sets: Mapping[str, Sequence[CornerSet]], T_init: np.ndarray, t_s: float,
               filter_params: FilterParams) -> np.ndarray | None:
    """T_world_body of one multi-camera fit of every corner set, every camera taken as exact (None: no fit)."""
    from cubetrack.fuse.multi_view_fit import solve_joint

    every = [cs for camera_sets in sets.values() for cs in camera_sets]
    fit = solve_joint(every, T_init, t_s, filter_params.corner_noise_px) if every else None
    return None if fit is None else fit.T_world_cube


def _term_fit(sets: Mapping[str, Sequence[CornerSet]], T_init: np.ndarray, t_s: float,
              filter_params: FilterParams) -> np.ndarray | None:
    """T_world_body of each camera's own fit (linearised at ``T_init``) weighed by the inverse of its
    covariance plus the calibration term's ``Σ`` (:func:`cubetrack.fuse.filter_kernels.calibration_discount`
    with no corner information gives ``Σ`` itself): the generalised least squares the filter's update
    makes of one instant's frames (None: no camera's fit)."""
    from cubetrack.estimate.reprojection import perturbed
    from cubetrack.fuse.filter_kernels import calibration_discount, packed_sets
    from cubetrack.fuse.multi_view_fit import solve_joint

    fp = filter_params
    information, weighted = np.zeros((6, 6)), np.zeros(6)
    for camera_sets in sets.values():
        fit = solve_joint(camera_sets, T_init, t_s, fp.corner_noise_px) if camera_sets else None
        if fit is None:
            continue
        _, _, _, R_cw, t_cw, _, _ = packed_sets(camera_sets)
        term = np.zeros((6, 6))
        if not calibration_discount(T_init, R_cw, t_cw, np.zeros((6, 6)), fp.camera_position_sigma_m,
                                    np.radians(fp.camera_rotation_sigma_deg), fp.camera_scale_sigma,
                                    np.radians(fp.wobble_sigma_deg), term):
            term[:] = 0.0  # the cameras taken as exact
        W = np.linalg.inv(fit.covariance[:6, :6] + term)
        T = fit.T_world_cube
        delta = np.concatenate([T[:3, 3] - T_init[:3, 3],
                                Rotation.from_matrix(T[:3, :3] @ T_init[:3, :3].T).as_rotvec()])
        information += W
        weighted += W @ delta
    return perturbed(T_init, np.linalg.solve(information, weighted)) if information.any() else None


@contextmanager
def _recorded(sightings: list[CubeSighting]) -> Iterator[None]:
    """Within it, every sighting a tracker's filter fusion gets is appended to ``sightings``."""
    from unittest import mock

    from cubetrack.app import tracker as tracker_module

    class Recorded(tracker_module.FilterFusion):
        def add(self, sighting: CubeSighting, now_s: float) -> list:
            sightings.append(sighting)
            return super().add(sighting, now_s)

    with mock.patch.object(tracker_module, "FilterFusion", Recorded):
        yield


def track(work: Path, name: str, sections: Mapping[str, Mapping[str, object]] | None = None,
          sightings: list[CubeSighting] | None = None, motion: str | None = None) -> Path:
    """Track the imported recording in ``work`` with the config's settings plus ``sections``
    (extra TOML tables); the TUM file written. ``sightings``: a list to which every sighting the
    filter fusion gets is appended (for :func:`instant_fits`). ``motion``: the board's body file's
    ``motion`` instead of the import's ("free")."""
    import dataclasses
    import tomllib

    from cubetrack.app.config import config_params
    from cubetrack.app.track import track_recording
    from cubetrack.core.layout import layout_to_table, read_layout
    from cubetrack.io.config import read_extrinsics, read_tracker_config, write_toml
    from cubetrack.io.recording import Recording

    with (work / "config.toml").open("rb") as f:
        doc = tomllib.load(f)
    for section, table in (sections or {}).items():
        doc[section] = {**doc.get(section, {}), **table}
    for robot in doc["robots"] if motion is not None else ():
        layout = dataclasses.replace(read_layout(work / robot["layout"]), motion=motion)
        robot["layout"] = f"{Path(robot['layout']).stem}-{name}.toml"
        write_toml(layout_to_table(layout), work / robot["layout"])
    config_path = work / f"config-{name}.toml"
    write_toml(doc, config_path)
    config = read_tracker_config(config_path)
    out = work / f"track-{name}"
    with _recorded(sightings) if sightings is not None else nullcontext():
        track_recording(config, Recording.open(work / "recording"), read_extrinsics(work / "extrinsics.toml"), out,
                        config_params(config).stages, workers=0)
    return out / "board.tum"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--data", type=Path, default=DATA, help="the caliscope project folder")
    parser.add_argument("--work", type=Path, help="where to import and track (default: a temporary folder)")
    parser.add_argument("--set", action="append", default=[], metavar="SECTION.KEY=VALUE",
                        help="an extra setting for the 'custom' run (TOML value), e.g. filter.corner_noise_px=2.0")
    parser.add_argument("--reference-only", action="store_true",
                        help="print what the reference is worth (per camera), track nothing")
    parser.add_argument("--max-view-rms-px", type=float, default=MAX_VIEW_RMS_PX,
                        help="a camera frame further than this (RMS px) from the others' reference is left out of "
                             "the reference (default %(default)s; inf: none)")
    args = parser.parse_args(argv)
    from cubetrack.app.import_rig import import_caliscope

    reference = charuco_reference(args.data, args.max_view_rms_px)
    print("\n".join(reference_report(reference)) + f"\ncores {os.cpu_count()}", flush=True)
    if args.reference_only:
        return 0
    work = args.work or Path(tempfile.mkdtemp(prefix="real-footage-"))
    if not (work / "config.toml").exists():
        import_caliscope(args.data, work)
    runs: dict[str, dict] = {"default (filter)": {}, "mean fusion": {"fusion": {"method": "mean"}},
                             "board motion = floor": {}}
    if args.set:
        import tomllib

        custom: dict[str, dict] = {}
        for item in args.set:
            key, value = item.split("=", 1)
            section, name = key.split(".", 1)
            custom.setdefault(section, {})[name] = tomllib.loads(f"v = {value}")["v"]
        runs["custom " + " ".join(args.set)] = custom
    sightings: list[CubeSighting] = []
    for i, (name, sections) in enumerate(runs.items()):
        result = score(track(work, f"run{i}", sections, sightings if i == 0 else None,
                             "floor" if name == "board motion = floor" else None), reference)
        print(result.line(name) + "\n" + result.by_reference(name), flush=True)
    print_instant_fits(work, reference, sightings)
    return 0


def print_instant_fits(work: Path, reference: Mapping[int, Instant], sightings: Sequence[CubeSighting]) -> None:
    """Print :func:`instant_fits` of the default run's sightings, with the config's settings."""
    from cubetrack.app.config import config_params
    from cubetrack.io.config import read_tracker_config

    config = read_tracker_config(work / "config.toml")
    stages = config_params(config).stages
    print("the scoring's floor: one fit per instant of the tracker's own corners (no motion model)")
    for name, result in instant_fits(reference, sightings, config.robots[0].layout, stages.filter,
                                     stages.fusion.max_view_angle_deg).items():
        print(result.line(name) + "\n" + result.by_reference(name), flush=True)


if __name__ == "__main__":
    sys.exit(main())
