"""Body poses from detections: the world marker's pose, and one cube pose per camera frame.

Frames (docs/developing.md): camera optical (x right, y down, z forward); marker (origin at the
centre, x right, y up, z out of the face); cube (origin at the centre, x forward, y left, z up);
world (the world marker's frame, z up). Poses are 4x4 ``T_a_b`` mapping b-points into a.
Lengths are metres, pixel errors RMS pixels over a marker's corners.

Pipeline of :func:`estimate_cube` for one camera frame and one robot:

1. :func:`cubetrack.estimate.match.match_faces` without a prediction: the robot's detections,
   each one's single-marker poses (:func:`cubetrack.estimate.marker.marker_pose`, IPPE's two
   closed-form solutions: no Levenberg-Marquardt polish per frame, which changed per-face errors
   by < 2 % on simulated frames), and the face and solution each is by the upright prior;
   faces that disagree on the cube's centre dropped.
2. With two or more faces, one joint PnP over all their corners (``solvePnPRefineLM`` seeded from
   the largest face's pose; only when that fit is worse than 2 x ``corner_noise_px`` RMS, from
   every other face's pose and ``SOLVEPNP_SQPNP`` too): two non-coplanar faces remove the planar
   ambiguity. The lowest-cost upright solution within ``max_joint_reprojection_error_px`` wins.
   If no solution passes, the subsets one face smaller are tried (a misidentified or foreign
   face is left out), down to the largest face alone.

The per-face observations (``CameraEstimate.faces``) are what the paper's fusion methods
average; ``CameraEstimate.T_world_cube`` is the joint estimate.
"""

from __future__ import annotations

import itertools
import logging
import math
from collections.abc import Iterable, Sequence

import cv2
import numpy as np

from cubetrack.core.cameras import CameraIntrinsics
from cubetrack.core.geometry import T_from_rvec_tvec, invert_T, rvec_tvec_from_T
from cubetrack.core.layout import CubeLayout
from cubetrack.core.records import CameraEstimate, Detection, FaceObservation, MarkerPose
from cubetrack.estimate.marker import in_front, marker_pose, reprojection_rms_px
from cubetrack.estimate.match import FaceMatch, detections_of, match_faces, uses_upright_prior
from cubetrack.estimate.params import EstimatorParams

log = logging.getLogger(__name__)

WORLD_UP = np.array([0.0, 0.0, 1.0])


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
    found = detections_of(detections, dictionary, (marker_id,))
    if not found:
        return None
    best = max(found, key=lambda d: d.area_px2)
    return marker_pose(best, size_m, intrinsics, params.max_reprojection_error_px)


# --------------------------------------------------------------------------- cube pose


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


def _joint_pose(faces: Sequence[FaceMatch], intrinsics: CameraIntrinsics, T_world_cam: np.ndarray,
                params: EstimatorParams, with_prior: bool) -> tuple[np.ndarray, float, float] | None:
    """One PnP over all matched faces' corners: (T_world_cube, RMS px, cost per corner) or None
    when no solution passes the reprojection and upright gates (``with_prior``: the upright one).

    Levenberg-Marquardt starts from each face's cube pose in turn (largest face first); the
    first result within ``2 x corner_noise_px`` RMS is taken at once (two non-coplanar faces
    that fit that well leave no ambiguity). Otherwise every face's seed and ``SOLVEPNP_SQPNP``
    are tried and the cheapest acceptable result wins."""
    obj = np.concatenate([f.points_body_m for f in faces])
    img = np.concatenate([f.detection.corners_px for f in faces]).astype(np.float64)
    T_cam_world = invert_T(T_world_cam)
    good_enough_px = 2.0 * params.corner_noise_px

    def seeds():
        for f in faces:
            yield T_cam_world @ _observed(f).T_world_cube
        try:
            ok, rvec, tvec = cv2.solvePnP(obj, img, intrinsics.K, intrinsics.dist, flags=cv2.SOLVEPNP_SQPNP)
        except cv2.error:
            return
        if ok:
            yield T_from_rvec_tvec(rvec, tvec)

    best = None
    for T_seed in seeds():
        if not math.isfinite(float(T_seed.sum())):
            continue
        try:
            rvec, tvec = cv2.solvePnPRefineLM(obj, img, intrinsics.K, intrinsics.dist, *rvec_tvec_from_T(T_seed))
        except cv2.error:
            continue
        if not math.isfinite(float(rvec.sum() + tvec.sum())):
            continue
        T_cam_cube = T_from_rvec_tvec(rvec, tvec)
        if not in_front(obj, T_cam_cube):
            continue
        err = reprojection_rms_px(obj, img, T_cam_cube, intrinsics)
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
    :func:`~cubetrack.estimate.marker.marker_pose` does by default: on simulated frames the refinement changed the
    per-face errors by under 2 % (position median 6.8 vs 6.9 mm, p95 25.5 vs 25.2 mm) at about
    a quarter of the per-frame cost. The joint multi-face fit is a Levenberg-Marquardt fit.
    """
    params = params or EstimatorParams()
    T_world_cam = np.asarray(T_world_cam, dtype=float)
    faces = match_faces(detections, layout, intrinsics, T_world_cam, params=params)
    if not faces:
        return None
    first = _observed(faces[0])
    T_world_cube, err = first.T_world_cube, first.marker_pose.reprojection_error_px
    used = faces[:1]
    if len(faces) >= 2 and params.joint_pnp:
        with_prior = uses_upright_prior(layout, params)
        # all faces first; if their joint fit fails, the best subset one face smaller, ...
        for n in range(len(faces), 1, -1):
            fits = []
            for subset in itertools.combinations(faces, n):
                joint = _joint_pose(subset, intrinsics, T_world_cam, params, with_prior)
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
        area_px2=float(sum(_observed(f).area_px2 for f in used)), faces=tuple(_observed(f) for f in used),
        reprojection_error_px=float(err),
    )


def _observed(face: FaceMatch) -> FaceObservation:
    """The face's own single-marker observation, which every face matched without a prediction has."""
    assert face.observation is not None, f"face {face.face} was matched by a prediction"
    return face.observation
