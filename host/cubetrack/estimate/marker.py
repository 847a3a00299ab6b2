"""Pose of one square marker from its four corners (planar PnP with both solutions kept).

Frames (docs/developing.md): camera optical (x right, y down, z forward); marker (origin at the
centre, x right, y up, z out of the face). Poses are 4x4 ``T_a_b`` mapping b-points into a.
Lengths are metres, pixel errors RMS pixels over a marker's corners.

:func:`marker_pose` runs ``SOLVEPNP_IPPE_SQUARE`` on the undistorted corners (in a virtual camera
that keeps IPPE away from its half-turn singularity) and keeps both planar solutions, sorted by
reprojection error (pixels, with the camera's distortion); non-finite, behind-camera,
back-facing or badly reprojecting solutions are dropped. Which solution (and which face of a
body) a marker is, is the matcher's question (:mod:`cubetrack.estimate.match`).
"""

from __future__ import annotations

import logging
import math

import cv2
import numpy as np

from cubetrack.core.cameras import CameraIntrinsics
from cubetrack.core.errors import EstimationError
from cubetrack.core.geometry import T_from_rvec_tvec, rvec_tvec_from_T, undistort_points
from cubetrack.core.layout import marker_corners_m
from cubetrack.core.records import Detection, MarkerPose

log = logging.getLogger(__name__)

_ZERO3 = np.zeros(3)
_EYE3 = np.eye(3)
_EYE4 = np.eye(4)
# Solutions whose rotations differ by less than this are one (cos of 1 degree).
_SAME_ROTATION_COS = math.cos(math.radians(1.0))


def reprojection_rms_px(obj_m: np.ndarray, img_px: np.ndarray, T_cam_obj: np.ndarray,
                        intrinsics: CameraIntrinsics) -> float:
    """RMS distance (px) between ``img_px`` and the object points projected at ``T_cam_obj``
    (points moved into the camera here: cv2.Rodrigues from a matrix is slow)."""
    proj, _ = cv2.projectPoints(obj_m @ T_cam_obj[:3, :3].T + T_cam_obj[:3, 3], _ZERO3, _ZERO3,
                                intrinsics.K, intrinsics.dist)
    d = proj.reshape(-1, 2) - img_px
    return math.sqrt(float((d * d).sum()) / len(d))


def in_front(obj_m: np.ndarray, T_cam_obj: np.ndarray) -> bool:
    """A finite pose (its rotation from cv2.Rodrigues, so orthonormal) with every object point
    in front of the camera."""
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
# An IPPE run whose best solution reprojects worse than this (px) is suspect (see below).
_IPPE_TRUSTED_PX = 2.0


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
    rays[:, :2] = undistort_points(img_px, intrinsics.K, intrinsics.dist)
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
        for rvec, tvec in zip(rvecs, tvecs, strict=True):
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
        rv, tv = cv2.solvePnPRefineLM(obj_m, img_px, intrinsics.K, intrinsics.dist, *rvec_tvec_from_T(T))
    except cv2.error:
        return T
    if math.isfinite(float(rv.sum() + tv.sum())):
        return T_from_rvec_tvec(rv, tv)
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
    closed-form solutions (exact for exact corners; what :func:`cubetrack.estimate.pose.estimate_cube`
    uses per frame).
    """
    if not size_m > 0.0:
        raise EstimationError(f"marker size must be positive metres, got {size_m!r}")
    obj = marker_corners_m(size_m)
    img = np.asarray(detection.corners_px, dtype=np.float64).reshape(4, 2)
    if not math.isfinite(float(img.sum())):
        return None

    def score(T: np.ndarray) -> float | None:
        if not in_front(obj, T) or float(T[:3, 2] @ T[:3, 3]) >= 0.0:  # back-facing
            return None
        err = reprojection_rms_px(obj, img, T, intrinsics)
        return err if math.isfinite(err) else None

    candidates = _ippe_square_candidates(obj, img, intrinsics)
    raw = [(e, T) for e, T in zip(_scores(candidates, obj, img, intrinsics), candidates, strict=True) if e < np.inf]
    solutions = []
    for raw_err, T in _distinct(sorted(raw, key=lambda s: s[0]))[:2]:
        err: float | None = raw_err
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


