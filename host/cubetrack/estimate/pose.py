"""Pose estimation from detections: single markers, the world marker, and one cube pose per camera frame.

Frames (docs/developing.md): camera optical (x right, y down, z forward); marker (origin at the
centre, x right, y up, z out of the face); cube (origin at the centre, x forward, y left, z up);
world (the world marker's frame, z up). Poses are 4x4 ``T_a_b`` mapping b-points into a.
Lengths are metres, pixel errors RMS pixels over a marker's corners.

Pipeline of :func:`estimate_cube` for one camera frame and one robot:

1. :func:`marker_pose` per detection of the cube's dictionary and ids: ``SOLVEPNP_IPPE_SQUARE``
   on the undistorted corners (in a virtual camera that keeps IPPE away from its half-turn
   singularity), both planar solutions kept, sorted by reprojection error (pixels, with the
   camera's distortion); non-finite, behind-camera, back-facing or badly reprojecting solutions
   dropped. Per frame the closed-form solutions are used as they are (no Levenberg-Marquardt
   polish: it changed per-face errors by < 2 % on simulated frames).
2. :func:`identify_faces`: for every detection, every layout face with that id and every IPPE
   solution, the implied ``T_world_cube = T_world_cam @ T_cam_marker @ inv(T_cube_marker)``
   is scored by a MAP cost: reprojection (``corner_noise_px``) plus an upright prior on the cube's
   z axis against world up (``upright_sigma_deg``, hard gate ``upright_tolerance_deg``). With one
   id on five faces (the paper's cube) the prior is what tells the faces apart (they differ by
   90° in the implied cube tilt) and what resolves IPPE's planar flip; with distinct ids the
   face is given by the id and the prior only resolves the flip. Faces are then checked for
   consistency: each must imply a cube centre within ``max_face_spread_m`` of the largest face's.
3. With two or more faces, one joint PnP over all their corners (``solvePnPRefineLM`` seeded from
   the largest face's pose; only when that fit is worse than 2 x ``corner_noise_px`` RMS, from
   every other face's pose and ``SOLVEPNP_SQPNP`` too): two non-coplanar faces remove the planar
   ambiguity. The lowest-cost upright solution within ``max_joint_reprojection_error_px`` wins.
   If no solution passes, the subsets one face smaller are tried (a misidentified or foreign
   face is left out), down to the largest face alone.

The per-face observations (``CameraEstimate.faces``) are what the paper's fusion methods
average; ``CameraEstimate.T_world_cube`` is the joint estimate.
"""

from __future__ import annotations

import functools
import itertools
import logging
import math
from collections.abc import Iterable, Sequence
from dataclasses import dataclass

import cv2
import numpy as np

from cubetrack.core.cameras import CameraIntrinsics
from cubetrack.core.errors import EstimationError
from cubetrack.core.geometry import invert_T
from cubetrack.core.layout import CubeLayout, LayoutMarker, marker_corners_m
from cubetrack.core.params import param
from cubetrack.core.records import CameraEstimate, Detection, FaceObservation, MarkerPose

log = logging.getLogger(__name__)

WORLD_UP = np.array([0.0, 0.0, 1.0])


@dataclass(frozen=True, slots=True)
class EstimatorParams:
    """Estimator thresholds; the ``[estimator]`` TOML table maps 1:1 onto these fields."""

    max_reprojection_error_px: float = param(
        3.0, "a single-marker PnP solution whose RMS reprojection error exceeds this is dropped, pixels",
    )
    corner_noise_px: float = param(
        0.5, "assumed corner noise (1 sigma), pixels: weighs reprojection error against the "
        "upright prior when choosing a face and an IPPE solution",
    )
    use_upright_prior: bool = param(
        True, "assume the cube stands upright (ground robot): its z axis near world up. Needed to "
        "tell apart faces that share an id; with distinct ids, false picks solutions by "
        "reprojection error alone",
    )
    upright_sigma_deg: float = param(
        10.0, "spread (1 sigma) of the cube's tilt from world up in the upright prior, degrees",
    )
    upright_tolerance_deg: float = param(
        35.0, "a face/solution implying a cube tilted more than this from world up is rejected, degrees",
    )
    max_face_spread_m: float = param(
        0.25, "faces implying a cube centre farther than this from the largest face's are dropped, metres",
    )
    joint_pnp: bool = param(
        True, "refine one cube pose over all identified faces' corners (else: the largest face's pose)",
    )
    max_joint_reprojection_error_px: float = param(
        3.0, "a joint multi-face solution above this RMS reprojection error is rejected (then "
        "subsets one face smaller are tried, down to the largest face alone), pixels",
    )

    def __post_init__(self) -> None:
        for name in ("max_reprojection_error_px", "corner_noise_px", "upright_sigma_deg",
                     "upright_tolerance_deg", "max_face_spread_m", "max_joint_reprojection_error_px"):
            if not getattr(self, name) > 0.0:
                raise ValueError(f"{name} must be positive, got {getattr(self, name)}")


# --------------------------------------------------------------------------- single markers

_ZERO3 = np.zeros(3)
_EYE3 = np.eye(3)
_EYE4 = np.eye(4)
# Solutions whose rotations differ by less than this are one (cos of 1 degree).
_SAME_ROTATION_COS = math.cos(math.radians(1.0))


def _reprojection_rms_px(obj_m: np.ndarray, img_px: np.ndarray, T_cam_obj: np.ndarray,
                         intrinsics: CameraIntrinsics) -> float:
    """RMS distance (px) between ``img_px`` and the object points projected at ``T_cam_obj``
    (points moved into the camera here: cv2.Rodrigues from a matrix is slow)."""
    proj, _ = cv2.projectPoints(obj_m @ T_cam_obj[:3, :3].T + T_cam_obj[:3, 3], _ZERO3, _ZERO3,
                                intrinsics.K, intrinsics.dist)
    d = proj.reshape(-1, 2) - img_px
    return math.sqrt(float((d * d).sum()) / len(d))


def _valid_solution(T_cam_obj: np.ndarray, obj_m: np.ndarray) -> bool:
    """Finite (rotation from cv2.Rodrigues, so orthonormal), every object point in front."""
    z = obj_m @ T_cam_obj[2, :3] + T_cam_obj[2, 3]
    return math.isfinite(float(T_cam_obj.sum())) and float(z.min()) > 1e-6


def _axis_rotation(axis: tuple[float, float, float], angle_deg: float) -> np.ndarray:
    """Rotation by ``angle_deg`` about ``axis``."""
    v = np.asarray(axis, dtype=np.float64)
    return cv2.Rodrigues(v / np.linalg.norm(v) * math.radians(angle_deg))[0]


# The cameras IPPE runs in (see _ippe_square_candidates): rotated by 30° about two axes of the
# image plane 22.5° from x and from y, then the real camera.
_VIRTUAL_ROTATIONS = (
    _axis_rotation((math.cos(math.radians(22.5)), math.sin(math.radians(22.5)), 0.0), 30.0),
    _axis_rotation((-math.sin(math.radians(22.5)), math.cos(math.radians(22.5)), 0.0), 30.0),
    np.eye(3),
)
# IPPE results with a rotation-vector norm above this are distrusted (see below).
_SUSPECT_ANGLE_RAD = math.radians(170.0)
_UNDISTORT_CRITERIA = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 50, 1e-12)
# An IPPE run whose best solution reprojects worse than this (px) is suspect (see below).
_IPPE_TRUSTED_PX = 2.0


def _T_from_rvec(rvec: np.ndarray, tvec: np.ndarray) -> np.ndarray:
    """4x4 pose from an OpenCV rotation vector and translation (cv2.Rodrigues: fast)."""
    T = _EYE4.copy()
    T[:3, :3] = cv2.Rodrigues(np.asarray(rvec, dtype=np.float64).reshape(3, 1))[0]
    T[:3, 3] = np.asarray(tvec, dtype=np.float64).reshape(3)
    return T


def _ippe_square_candidates(obj_m: np.ndarray, img_px: np.ndarray,
                            intrinsics: CameraIntrinsics) -> list[np.ndarray]:
    """Finite IPPE-square solutions ``T_cam_marker`` (unsorted, possibly repeated).

    OpenCV's IPPE breaks near rotations by a half turn, and every marker squarely facing the
    camera is one (a half turn about an axis in the image plane: an upright marker ahead is
    Rx(180°)). Measured on exact corners: NaN; a solution facing away; or poses 14-65° off that
    reproject within 0.3 px (the planar flip) or 14 px, the true pose missing; and within ~5° of
    a half turn results a few degrees off. So IPPE runs first in a virtual camera rotated by 30°
    about an image-plane axis 22.5° from x (the rays rotated, the results rotated back), where
    only markers whose half-turn axis is perpendicular to that axis stay half turns. A run is
    suspect when a solution is missing, non-finite, facing away or has a rotation-vector norm
    above 170°, or the better one reprojects worse than ``_IPPE_TRUSTED_PX``; then it runs
    again about the perpendicular image-plane axis (no visible marker's axis is perpendicular
    to both: that would be a marker facing away), then in the real camera. The first unsuspect
    run's solutions are returned (every run's when all are suspect).
    """
    rays = np.ones((len(img_px), 3))
    rays[:, :2] = cv2.undistortPoints(img_px.reshape(-1, 1, 2), intrinsics.K, intrinsics.dist,
                                      criteria=_UNDISTORT_CRITERIA).reshape(-1, 2)
    trusted = _IPPE_TRUSTED_PX * 2.0 / (float(intrinsics.K[0, 0]) + float(intrinsics.K[1, 1]))
    found: list[np.ndarray] = []
    for Q in _VIRTUAL_ROTATIONS:
        r = rays @ Q.T
        if float(r[:, 2].min()) <= 1e-6:
            continue
        try:
            _n, rvecs, tvecs, errs = cv2.solvePnPGeneric(
                obj_m, r[:, :2] / r[:, 2:3], _EYE3, None, flags=cv2.SOLVEPNP_IPPE_SQUARE)
        except cv2.error as exc:
            log.debug("IPPE failed: %s", exc)
            continue
        # errs: RMS reprojection errors of the solutions in normalised image units
        suspect = len(rvecs) < 2 or errs is None or not float(np.min(errs)) <= trusted
        run: list[np.ndarray] = []
        for rvec, tvec in zip(rvecs, tvecs):
            rx, ry, rz = rvec.ravel().tolist()
            tx, ty, tz = tvec.ravel().tolist()
            if not math.isfinite(rx + ry + rz + tx + ty + tz):
                suspect = True
                continue
            R = cv2.Rodrigues(rvec)[0]
            # facing away: the marker's z axis along the line of sight (same in either camera)
            suspect |= (math.sqrt(rx * rx + ry * ry + rz * rz) > _SUSPECT_ANGLE_RAD
                        or float(R[0, 2] * tx + R[1, 2] * ty + R[2, 2] * tz) >= 0.0)
            T = _EYE4.copy()
            T[:3, :3] = Q.T @ R  # back from the virtual camera
            T[:3, 3] = Q.T @ tvec.ravel()
            run.append(T)
        if not suspect:
            return run
        found += run
    return found


def _polish(obj_m: np.ndarray, img_px: np.ndarray, T: np.ndarray,
            intrinsics: CameraIntrinsics) -> np.ndarray:
    """Levenberg-Marquardt refinement of a pose in real pixels (with distortion)."""
    try:
        rv, tv = cv2.solvePnPRefineLM(obj_m, img_px, intrinsics.K, intrinsics.dist,
                                      cv2.Rodrigues(T[:3, :3])[0], T[:3, 3].reshape(3, 1).copy())
    except cv2.error:
        return T
    if math.isfinite(float(rv.sum() + tv.sum())):
        return _T_from_rvec(rv, tv)
    return T


def _scores(poses: list[np.ndarray], obj_m: np.ndarray, img_px: np.ndarray,
            intrinsics: CameraIntrinsics) -> list[float]:
    """RMS reprojection errors (px) of candidate poses ``T_cam_obj`` of a planar object seen
    from its front (one projectPoints call for all); inf for a pose that is non-finite, puts a
    point behind the camera or shows the object's back."""
    if not poses:
        return []
    T = np.array(poses)                                                    # (C, 4, 4)
    pts = obj_m @ T[:, :3, :3].transpose(0, 2, 1) + T[:, None, :3, 3]      # (C, N, 3) in the camera
    proj, _ = cv2.projectPoints(pts.reshape(-1, 3), _ZERO3, _ZERO3, intrinsics.K, intrinsics.dist)
    d = proj.reshape(pts.shape[0], -1, 2) - img_px
    err = np.sqrt((d * d).sum(axis=-1).mean(axis=-1))
    facing = (T[:, :3, 2] * T[:, :3, 3]).sum(axis=-1) < 0.0
    ok = facing & (pts[..., 2].min(axis=-1) > 1e-6) & np.isfinite(err)
    return np.where(ok, err, np.inf).tolist()


def _distinct(solutions: list[tuple[float, np.ndarray]]) -> list[tuple[float, np.ndarray]]:
    """Drop solutions (sorted by error) whose rotation repeats an earlier one's within 1°.

    The planar ambiguity's two solutions differ in rotation; IPPE run in different virtual
    cameras returns the same rotation with translations a few millimetres apart."""
    kept: list[tuple[float, np.ndarray]] = []
    for err, T in solutions:
        # cos of the relative rotation's angle = (trace(R1^T R2) - 1) / 2
        if all(0.5 * (float((T[:3, :3] * T2[:3, :3]).sum()) - 1.0) < _SAME_ROTATION_COS for _e, T2 in kept):
            kept.append((err, T))
    return kept


def marker_pose(detection: Detection, size_m: float, intrinsics: CameraIntrinsics,
                max_reprojection_error_px: float = np.inf, *, polish: bool = True) -> MarkerPose | None:
    """Pose ``T_cam_marker`` of one square marker of side ``size_m`` (metres) in the camera frame.

    Both IPPE-square solutions are kept (with ``polish``, each refined by Levenberg-Marquardt on
    the distorted pixels: the maximum-likelihood pose near it), sorted by RMS reprojection error
    (pixels, with the camera's distortion). A solution is dropped when it is non-finite (IPPE
    returns NaN near fronto-parallel views), puts a corner behind the camera, shows the marker's
    back to the camera, or reprojects worse than ``max_reprojection_error_px``. None when none
    survives. Rotation vectors are not kept: poses are rebuilt from them as 4x4 matrices, which
    also normalises OpenCV's occasional huge-norm rotation vectors. ``polish=False`` keeps IPPE's
    closed-form solutions (exact for exact corners; what :func:`estimate_cube` uses per frame).
    """
    if not size_m > 0.0:
        raise EstimationError(f"marker size must be positive metres, got {size_m!r}")
    obj = marker_corners_m(size_m)
    img = np.asarray(detection.corners_px, dtype=np.float64).reshape(4, 2)
    if not math.isfinite(float(img.sum())):
        return None

    def score(T: np.ndarray) -> float | None:
        if not _valid_solution(T, obj) or float(T[:3, 2] @ T[:3, 3]) >= 0.0:  # back-facing
            return None
        err = _reprojection_rms_px(obj, img, T, intrinsics)
        return err if math.isfinite(err) else None

    candidates = _ippe_square_candidates(obj, img, intrinsics)
    raw = [(e, T) for e, T in zip(_scores(candidates, obj, img, intrinsics), candidates) if e < np.inf]
    solutions = []
    for err, T in _distinct(sorted(raw, key=lambda s: s[0]))[:2]:
        if polish:
            T = _polish(obj, img, T, intrinsics)
            err = score(T)
        if err is not None and err <= max_reprojection_error_px:
            solutions.append((err, T))
    if not solutions:
        return None
    if polish:
        solutions = _distinct(sorted(solutions, key=lambda s: s[0]))
    (err, T), alt = solutions[0], (solutions[1] if len(solutions) > 1 else (float("inf"), None))
    return MarkerPose(detection=detection, size_m=float(size_m), T_cam_marker=T,
                      reprojection_error_px=err, T_cam_marker_alt=alt[1],
                      reprojection_error_alt_px=alt[0])


def _dictionary_matches(detection: Detection, dictionary: str) -> bool:
    return detection.dictionary in ("", dictionary)


def world_marker_pose(detections: Iterable[Detection], *, dictionary: str, marker_id: int,
                      size_m: float, intrinsics: CameraIntrinsics,
                      params: EstimatorParams | None = None) -> MarkerPose | None:
    """Pose of the world marker in the camera: the returned ``T_cam_marker`` is ``T_cam_world``.

    Uses the largest detection with ``marker_id`` in ``dictionary`` (a floor marker of
    ``size_m`` metres); the lower-reprojection IPPE solution is kept first (the other stays in
    ``T_cam_marker_alt``). ``invert_T(pose.T_cam_marker)`` is ``T_world_cam``: the camera
    calibration sample, and the paper's uncalibrated "raw world-marker pose" mode.
    """
    params = params or EstimatorParams()
    matches = [d for d in detections
               if d.marker_id == marker_id and _dictionary_matches(d, dictionary)]
    if not matches:
        return None
    best = max(matches, key=lambda d: d.area_px2)
    return marker_pose(best, size_m, intrinsics, params.max_reprojection_error_px)


# --------------------------------------------------------------------------- cube faces


def cube_tilt_deg(T_world_cube: np.ndarray) -> float:
    """Angle between the cube's z axis and world up, degrees."""
    return float(np.degrees(np.arccos(np.clip(T_world_cube[:3, 2] @ WORLD_UP, -1.0, 1.0))))


def _cost(rms_px: float, n_points: int, tilt_deg: float, params: EstimatorParams,
          with_prior: bool) -> float:
    """Negative log posterior (up to a constant) of one pose hypothesis."""
    cost = n_points * rms_px ** 2 / (2.0 * params.corner_noise_px ** 2)
    if with_prior:
        cost += tilt_deg ** 2 / (2.0 * params.upright_sigma_deg ** 2)
    return cost


@dataclass(frozen=True, slots=True, eq=False)
class _LayoutTables:
    """What the per-frame estimation needs from a layout, computed once per layout: the sizes
    per id; per id its faces, their ``T_marker_cube`` stacked (F, 4, 4) and sizes (F,); per face
    its corners in the cube frame (4, 3)."""

    repeated_ids: bool
    sizes: dict[int, tuple[float, ...]]
    faces_by_id: dict[int, tuple[tuple[LayoutMarker, ...], np.ndarray, np.ndarray]]
    corners_cube_m: dict[str, np.ndarray]


@functools.lru_cache(maxsize=32)
def _tables(layout: CubeLayout) -> _LayoutTables:
    """The layout's tables (cached by layout object: layouts are frozen and never mutated)."""
    markers = layout.markers
    faces_by_id = {}
    for marker_id in dict.fromkeys(m.marker_id for m in markers):
        faces = tuple(m for m in markers if m.marker_id == marker_id)
        T_marker_cube = np.stack([invert_T(m.T_cube_marker) for m in faces])
        sizes = np.array([m.size_m for m in faces])
        T_marker_cube.setflags(write=False)
        sizes.setflags(write=False)
        faces_by_id[marker_id] = (faces, T_marker_cube, sizes)
    corners = {m.face: m.corners_cube_m() for m in markers}
    for a in corners.values():
        a.setflags(write=False)
    return _LayoutTables(layout.has_repeated_ids,
                         {i: tuple(sorted(set(s.tolist()))) for i, (_f, _T, s) in faces_by_id.items()},
                         faces_by_id, corners)


def _is_rigid(T: np.ndarray) -> bool:
    """``geometry.is_finite_pose`` in plain floats (a per-frame check)."""
    if T.shape != (4, 4) or not math.isfinite(float(T.sum())):
        return False
    R = T[:3, :3]
    (a, b, c), (d, e, f), (g, h, i) = R.tolist()
    det = a * (e * i - f * h) - b * (d * i - f * g) + c * (d * h - e * g)
    return float(np.abs(R.T @ R - _EYE3).max()) <= 1e-6 and det > 0.0


def identify_faces(marker_poses: Iterable[tuple[LayoutMarker, MarkerPose]] | Iterable[MarkerPose],
                   layout: CubeLayout, T_world_cam: np.ndarray,
                   params: EstimatorParams | None = None) -> tuple[FaceObservation, ...]:
    """Assign marker poses to cube faces and give each the cube pose it implies.

    ``marker_poses`` are MarkerPoses of markers in ``layout`` (ids of other markers are ignored).
    For each, every face of the layout with that id (and the same size) and each of its IPPE
    solutions is a hypothesis; the lowest MAP cost (reprojection + upright prior) within
    ``upright_tolerance_deg`` wins. Repeated faces keep their larger detection; faces implying
    a cube centre farther than ``max_face_spread_m`` from the largest face's are dropped.
    Result: one FaceObservation per identified face, largest area first, whose
    ``marker_pose.T_cam_marker`` is the chosen solution.
    """
    params = params or EstimatorParams()
    T_world_cam = np.asarray(T_world_cam, dtype=float)
    if not _is_rigid(T_world_cam):
        raise EstimationError("T_world_cam must be a finite rigid 4x4 pose")
    tables = _tables(layout)
    with_prior = params.use_upright_prior or tables.repeated_ids
    reprojection_weight = 4.0 / (2.0 * params.corner_noise_px ** 2)   # 4 corners
    tilt_weight = 1.0 / (2.0 * params.upright_sigma_deg ** 2)
    chosen: list[FaceObservation] = []
    for mp in marker_poses:
        mp = mp[1] if isinstance(mp, tuple) else mp
        det = mp.detection
        entry = tables.faces_by_id.get(det.marker_id)
        if entry is None or det.dictionary not in ("", layout.dictionary):
            continue
        faces, T_marker_cube, sizes = entry
        size_ok = np.abs(sizes - mp.size_m) <= 1e-6 * abs(mp.size_m)
        # hypotheses: each solution (with the other as its alternative) x each face with the id
        options = [(mp.T_cam_marker, mp.reprojection_error_px, mp.T_cam_marker_alt, mp.reprojection_error_alt_px)]
        if mp.T_cam_marker_alt is not None:
            options.append((mp.T_cam_marker_alt, mp.reprojection_error_alt_px, mp.T_cam_marker, mp.reprojection_error_px))
        options = [o for o in options if o[1] <= params.max_reprojection_error_px]
        if not options or not size_ok.any():
            continue
        T_world_cube = (T_world_cam @ np.array([o[0] for o in options]))[:, None] @ T_marker_cube  # (S, F, 4, 4)
        cost = reprojection_weight * np.array([[o[1] ** 2] for o in options])          # (S, 1)
        allowed = size_ok
        if with_prior:
            tilt = np.degrees(np.arccos(np.clip(T_world_cube[:, :, 2, 2], -1.0, 1.0)))  # cube z vs world up
            cost = cost + tilt_weight * tilt * tilt
            allowed = allowed & (tilt <= params.upright_tolerance_deg)
        cost = np.where(allowed, cost, np.inf)
        k = int(cost.argmin())
        if not cost.flat[k] < np.inf:
            continue
        s, f = divmod(k, cost.shape[1])
        T_cam_marker, err, T_alt, err_alt = options[s]
        if T_cam_marker is mp.T_cam_marker and (T_alt is None or math.isfinite(err_alt)):
            pose = mp  # the solution it already has first
        else:
            pose = MarkerPose(det, mp.size_m, T_cam_marker, err,
                              T_alt if (T_alt is not None and math.isfinite(err_alt)) else None,
                              err_alt if T_alt is not None else float("inf"))
        chosen.append(FaceObservation(faces[f].face, pose, T_world_cube[s, f], det.area_px2))
    # One detection per face (the larger), then consistency with the largest face.
    chosen.sort(key=lambda obs: -obs.area_px2)
    out: list[FaceObservation] = []
    for obs in chosen:
        if any(o.face == obs.face for o in out):
            continue
        if out and np.linalg.norm(obs.T_world_cube[:3, 3] - out[0].T_world_cube[:3, 3]) > params.max_face_spread_m:
            log.debug("face %s dropped: disagrees with face %s by more than %.3f m",
                      obs.face, out[0].face, params.max_face_spread_m)
            continue
        out.append(obs)
    return tuple(out)


def _joint_pose(faces: Sequence[FaceObservation], layout: CubeLayout, intrinsics: CameraIntrinsics,
                T_world_cam: np.ndarray, params: EstimatorParams) -> tuple[np.ndarray, float, float] | None:
    """One PnP over all faces' corners: (T_world_cube, RMS px, cost per corner) or None when
    no solution passes the reprojection and upright gates.

    Levenberg-Marquardt starts from each face's cube pose in turn (largest face first); the
    first result within ``2 x corner_noise_px`` RMS is taken at once (two non-coplanar faces
    that fit that well leave no ambiguity). Otherwise every face's seed and ``SOLVEPNP_SQPNP``
    are tried and the cheapest acceptable result wins."""
    tables = _tables(layout)
    obj = np.concatenate([tables.corners_cube_m[f.face] for f in faces])
    img = np.concatenate([f.marker_pose.detection.corners_px for f in faces]).astype(np.float64)
    T_cam_world = invert_T(T_world_cam)
    with_prior = params.use_upright_prior or tables.repeated_ids
    good_enough_px = 2.0 * params.corner_noise_px

    def seeds():
        for f in faces:
            yield T_cam_world @ f.T_world_cube
        try:
            ok, rvec, tvec = cv2.solvePnP(obj, img, intrinsics.K, intrinsics.dist, flags=cv2.SOLVEPNP_SQPNP)
        except cv2.error:
            return
        if ok:
            yield _T_from_rvec(rvec, tvec)

    best = None
    for T_seed in seeds():
        if not math.isfinite(float(T_seed.sum())):
            continue
        rvec, _ = cv2.Rodrigues(T_seed[:3, :3])
        tvec = T_seed[:3, 3].reshape(3, 1).copy()
        try:
            rvec, tvec = cv2.solvePnPRefineLM(obj, img, intrinsics.K, intrinsics.dist, rvec, tvec)
        except cv2.error:
            continue
        if not math.isfinite(float(rvec.sum() + tvec.sum())):
            continue
        T_cam_cube = _T_from_rvec(rvec, tvec)
        if not _valid_solution(T_cam_cube, obj):
            continue
        err = _reprojection_rms_px(obj, img, T_cam_cube, intrinsics)
        if not err <= params.max_joint_reprojection_error_px:
            continue
        T_world_cube = T_world_cam @ T_cam_cube
        tilt = math.degrees(math.acos(min(1.0, max(-1.0, float(T_world_cube[2, 2])))))
        if with_prior and tilt > params.upright_tolerance_deg:
            continue
        cost = _cost(err, len(obj), tilt, params, with_prior) / len(obj)
        if best is None or cost < best[0]:
            best = (cost, T_world_cube, err)
        if err <= good_enough_px:
            break
    return None if best is None else (best[1], best[2], best[0])


def estimate_cube(detections: Iterable[Detection], layout: CubeLayout, intrinsics: CameraIntrinsics,
                  T_world_cam: np.ndarray, *, camera: str, robot: str, seq: int,
                  capture_time_s: float, arrival_time_s: float,
                  params: EstimatorParams | None = None) -> CameraEstimate | None:
    """One cube pose (``T_world_cube``) from one camera frame's detections, or None.

    ``detections``: everything the detector found in the frame (other markers are ignored);
    ``layout``: the robot's cube; ``T_world_cam``: the camera's pose in the world (calibrated
    extrinsics, or the inverse of this frame's world-marker pose in the paper's raw mode).
    ``area_px2`` is the summed pixel area of the faces used (paper eq. 3); ``faces`` the
    per-face observations consistent with the result; ``reprojection_error_px`` the RMS over
    the corners used.

    Per-face poses are IPPE's closed-form solutions, not refined by Levenberg-Marquardt as
    :func:`marker_pose` does by default: on simulated frames the refinement changed the
    per-face errors by under 2 % (position median 6.8 vs 6.9 mm, p95 25.5 vs 25.2 mm) at about
    a quarter of the per-frame cost. The joint multi-face fit is a Levenberg-Marquardt fit.
    """
    params = params or EstimatorParams()
    T_world_cam = np.asarray(T_world_cam, dtype=float)
    tables = _tables(layout)
    poses: list[MarkerPose] = []
    for det in detections:
        if det.marker_id not in tables.sizes or not _dictionary_matches(det, layout.dictionary):
            continue
        for size_m in tables.sizes[det.marker_id]:
            mp = marker_pose(det, size_m, intrinsics, params.max_reprojection_error_px, polish=False)
            if mp is not None:
                poses.append(mp)
    if not poses:
        return None
    faces = identify_faces(poses, layout, T_world_cam, params)
    if not faces:
        return None
    T_world_cube, err = faces[0].T_world_cube, faces[0].marker_pose.reprojection_error_px
    used = faces[:1]
    if len(faces) >= 2 and params.joint_pnp:
        # all faces first; if their joint fit fails, the best subset one face smaller, ...
        for n in range(len(faces), 1, -1):
            fits = []
            for subset in itertools.combinations(faces, n):
                joint = _joint_pose(subset, layout, intrinsics, T_world_cam, params)
                if joint is not None:
                    fits.append((joint[2], joint[0], joint[1], subset))
            if fits:
                _cost_value, T_world_cube, err, used = min(fits, key=lambda f: f[0])
                break
        if len(used) < len(faces):
            log.debug("%s/%s seq %d: %d of %d faces fit one cube pose (%s)", camera, robot, seq,
                      len(used), len(faces), ", ".join(f.face for f in used))
    elif len(faces) >= 2:
        used = faces
    return CameraEstimate(
        camera=camera, robot=robot, seq=int(seq), capture_time_s=float(capture_time_s),
        arrival_time_s=float(arrival_time_s), T_world_cube=T_world_cube,
        area_px2=float(sum(f.area_px2 for f in used)), faces=tuple(used),
        reprojection_error_px=float(err),
    )
