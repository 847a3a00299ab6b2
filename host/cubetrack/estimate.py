"""Pose estimation from detections: single markers, the world marker, and one cube pose per camera frame.

Frames (docs/developing.md): camera optical (x right, y down, z forward); marker (origin at the
centre, x right, y up, z out of the face); cube (origin at the centre, x forward, y left, z up);
world (the world marker's frame, z up). Poses are 4x4 ``T_a_b`` mapping b-points into a.
Lengths are metres, pixel errors RMS pixels over a marker's corners.

Pipeline of :func:`estimate_cube` for one camera frame and one robot:

1. :func:`marker_pose` per detection of the cube's dictionary and ids: ``SOLVEPNP_IPPE_SQUARE``
   with the camera's K and distortion, both planar solutions kept, sorted by reprojection
   error; non-finite, behind-camera, back-facing or badly reprojecting solutions dropped.
2. :func:`identify_faces`: for every detection, every layout face with that id and every IPPE
   solution, the implied ``T_world_cube = T_world_cam @ T_cam_marker @ inv(T_cube_marker)``
   is scored by a MAP cost: reprojection (``corner_noise_px``) plus an upright prior on the cube's
   z axis against world up (``upright_sigma_deg``, hard gate ``upright_tolerance_deg``). With one
   id on five faces (the paper's cube) the prior is what tells the faces apart (they differ by
   90° in the implied cube tilt) and what resolves IPPE's planar flip; with distinct ids the
   face is given by the id and the prior only resolves the flip. Faces are then checked for
   consistency: each must imply a cube centre within ``max_face_spread_m`` of the largest face's.
3. With two or more faces, one joint PnP over all their corners (``solvePnPRefineLM`` seeded from
   every face's pose, plus ``SOLVEPNP_SQPNP``): two non-coplanar faces remove the planar
   ambiguity. The lowest-cost upright solution within ``max_joint_reprojection_error_px`` wins.
   If no solution passes, the subsets one face smaller are tried (a misidentified or foreign
   face is left out), down to the largest face alone.

The per-face observations (``CameraEstimate.faces``) are what the paper's fusion methods
average; ``CameraEstimate.T_world_cube`` is the joint estimate.
"""

from __future__ import annotations

import itertools
import logging
from collections.abc import Iterable, Sequence
from dataclasses import dataclass

import cv2
import numpy as np

from cubetrack.errors import EstimationError
from scipy.spatial.transform import Rotation

from cubetrack.geometry import invert_T, is_finite_pose, make_T, rotation_angle
from cubetrack.io.camera_info import CameraIntrinsics
from cubetrack.layout import CubeLayout, LayoutMarker, marker_corners_m
from cubetrack.params import param
from cubetrack.records import CameraEstimate, Detection, FaceObservation, MarkerPose

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


def _reprojection_rms_px(obj_m: np.ndarray, img_px: np.ndarray, T_cam_obj: np.ndarray,
                         intrinsics: CameraIntrinsics) -> float:
    rvec, _ = cv2.Rodrigues(T_cam_obj[:3, :3])
    proj, _ = cv2.projectPoints(obj_m.reshape(-1, 1, 3), rvec, T_cam_obj[:3, 3].reshape(3, 1),
                                intrinsics.K, intrinsics.dist)
    return float(np.sqrt(np.mean(np.sum((proj.reshape(-1, 2) - img_px.reshape(-1, 2)) ** 2, axis=1))))


def _valid_solution(T_cam_obj: np.ndarray, obj_m: np.ndarray) -> bool:
    """Finite (rotation from cv2.Rodrigues, so orthonormal), every object point in front."""
    if not np.all(np.isfinite(T_cam_obj)):
        return False
    z = obj_m @ T_cam_obj[2, :3] + T_cam_obj[2, 3]
    return bool(np.all(z > 1e-6))


# Virtual camera rotations for extra IPPE runs (see _ippe_square_candidates).
_VIRTUAL_ROTATIONS = (
    Rotation.from_euler("x", 30.0, degrees=True).as_matrix(),
    Rotation.from_euler("y", 30.0, degrees=True).as_matrix(),
)
# IPPE results with a rotation-vector norm above this are distrusted (see below).
_SUSPECT_ANGLE_RAD = np.radians(170.0)


def _T_from_rvec(rvec: np.ndarray, tvec: np.ndarray) -> np.ndarray:
    """4x4 pose from an OpenCV rotation vector and translation (cv2.Rodrigues: fast)."""
    T = np.eye(4)
    T[:3, :3] = cv2.Rodrigues(np.asarray(rvec, float).reshape(3, 1))[0]
    T[:3, 3] = np.asarray(tvec, float).reshape(3)
    return T


def _ippe_square_candidates(obj_m: np.ndarray, img_px: np.ndarray,
                            intrinsics: CameraIntrinsics) -> list[np.ndarray]:
    """Finite IPPE-square solutions ``T_cam_marker`` (unsorted, possibly repeated).

    OpenCV's IPPE breaks when the true rotation is within ~1e-3° of a half turn: it returns NaN
    or a finite but wrong pose (measured: 43° and 83° off for an upside-down marker squarely
    facing the camera; an upright marker facing the camera is exactly such a half turn, Rx(180°),
    common in simulation). Such outputs always include a rotation-vector norm above ~176° (or a
    NaN), so when any output exceeds 170° the problem is solved again in virtual cameras rotated
    by 30° about x and about y (the rays rotated, the results rotated back). A half turn about
    axis a stays one under the x rotation only when a is perpendicular to x, under the y rotation
    only when a is perpendicular to y, and no visible marker's axis is perpendicular to both
    (that would be a = z: a marker facing away). ``marker_pose`` ranks the pooled results.
    """
    norm = cv2.undistortPoints(img_px.reshape(-1, 1, 2), intrinsics.K, intrinsics.dist,
                               criteria=(cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 50, 1e-12))
    rays = np.column_stack([norm.reshape(-1, 2), np.ones(len(img_px))])
    found: list[np.ndarray] = []
    for Q in (np.eye(3),) + _VIRTUAL_ROTATIONS:
        r = rays @ Q.T
        if np.any(r[:, 2] <= 1e-6):
            continue
        try:
            _n, rvecs, tvecs, _errs = cv2.solvePnPGeneric(
                obj_m, r[:, :2] / r[:, 2:3], np.eye(3), None, flags=cv2.SOLVEPNP_IPPE_SQUARE)
        except cv2.error as exc:
            log.debug("IPPE failed: %s", exc)
            continue
        suspect = len(rvecs) < 2
        for rvec, tvec in zip(rvecs, tvecs):
            rvec, tvec = np.asarray(rvec, float).reshape(3), np.asarray(tvec, float).reshape(3)
            if not (np.all(np.isfinite(rvec)) and np.all(np.isfinite(tvec))):
                suspect = True
                continue
            suspect |= bool(np.linalg.norm(rvec) > _SUSPECT_ANGLE_RAD)
            T_virtual = _T_from_rvec(rvec, tvec)
            found.append(make_T(Q.T @ T_virtual[:3, :3], Q.T @ tvec))
        if not suspect:
            break
    return found


def _polish(obj_m: np.ndarray, img_px: np.ndarray, T: np.ndarray,
            intrinsics: CameraIntrinsics) -> np.ndarray:
    """Levenberg-Marquardt refinement of a pose in real pixels (with distortion)."""
    try:
        rv, tv = cv2.solvePnPRefineLM(obj_m, img_px, intrinsics.K, intrinsics.dist,
                                      cv2.Rodrigues(T[:3, :3])[0], T[:3, 3].reshape(3, 1).copy())
    except cv2.error:
        return T
    if np.all(np.isfinite(rv)) and np.all(np.isfinite(tv)):
        return _T_from_rvec(rv, tv)
    return T


def _distinct(solutions: list[tuple[float, np.ndarray]]) -> list[tuple[float, np.ndarray]]:
    """Drop solutions (sorted by error) whose rotation repeats an earlier one's within 1°.

    The planar ambiguity's two solutions differ in rotation; IPPE run in different virtual
    cameras returns the same rotation with translations a few millimetres apart."""
    kept: list[tuple[float, np.ndarray]] = []
    for err, T in solutions:
        if all(rotation_angle(T[:3, :3], T2[:3, :3], "deg") > 1.0 for _e, T2 in kept):
            kept.append((err, T))
    return kept


def marker_pose(detection: Detection, size_m: float, intrinsics: CameraIntrinsics,
                max_reprojection_error_px: float = np.inf) -> MarkerPose | None:
    """Pose ``T_cam_marker`` of one square marker of side ``size_m`` (metres) in the camera frame.

    Both IPPE-square solutions are kept (each polished by Levenberg-Marquardt on the distorted
    pixels), sorted by RMS reprojection error (pixels, with the camera's distortion). A solution is dropped when it is non-finite (IPPE returns NaN near
    fronto-parallel views), puts a corner behind the camera, shows the marker's back to the
    camera, or reprojects worse than ``max_reprojection_error_px``. None when none survives.
    Rotation vectors are not kept: poses are rebuilt from them as 4x4 matrices, which also
    normalises OpenCV's occasional huge-norm rotation vectors.
    """
    if not size_m > 0.0:
        raise EstimationError(f"marker size must be positive metres, got {size_m!r}")
    obj = marker_corners_m(size_m)
    img = np.asarray(detection.corners_px, dtype=np.float64).reshape(4, 2)
    if not np.all(np.isfinite(img)):
        return None
    def score(T: np.ndarray) -> float | None:
        if not _valid_solution(T, obj) or float(T[:3, 2] @ T[:3, 3]) >= 0.0:  # back-facing
            return None
        err = _reprojection_rms_px(obj, img, T, intrinsics)
        return err if np.isfinite(err) else None

    raw = [(e, T) for T in _ippe_square_candidates(obj, img, intrinsics) if (e := score(T)) is not None]
    solutions = []
    for _e, T in _distinct(sorted(raw, key=lambda s: s[0]))[:2]:
        T = _polish(obj, img, T, intrinsics)
        err = score(T)
        if err is not None and err <= max_reprojection_error_px:
            solutions.append((err, T))
    if not solutions:
        return None
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
    if not is_finite_pose(T_world_cam):
        raise EstimationError("T_world_cam must be a finite rigid 4x4 pose")
    with_prior = params.use_upright_prior or layout.has_repeated_ids
    chosen: list[tuple[float, FaceObservation]] = []
    for mp in marker_poses:
        mp = mp[1] if isinstance(mp, tuple) else mp
        det = mp.detection
        if not _dictionary_matches(det, layout.dictionary):
            continue
        best: tuple[float, FaceObservation] | None = None
        for face in layout.markers_with_id(det.marker_id):
            if not np.isclose(face.size_m, mp.size_m, rtol=1e-6):
                continue
            T_marker_cube = invert_T(face.T_cube_marker)
            for T_cam_marker, err, T_alt, err_alt in (
                (mp.T_cam_marker, mp.reprojection_error_px, mp.T_cam_marker_alt,
                 mp.reprojection_error_alt_px),
                (mp.T_cam_marker_alt, mp.reprojection_error_alt_px, mp.T_cam_marker,
                 mp.reprojection_error_px),
            ):
                if T_cam_marker is None or not err <= params.max_reprojection_error_px:
                    continue
                T_world_cube = T_world_cam @ T_cam_marker @ T_marker_cube
                tilt = cube_tilt_deg(T_world_cube)
                if with_prior and tilt > params.upright_tolerance_deg:
                    continue
                cost = _cost(err, 4, tilt, params, with_prior)
                if best is None or cost < best[0]:
                    pose = MarkerPose(det, mp.size_m, T_cam_marker, err,
                                      T_alt if (T_alt is not None and np.isfinite(err_alt)) else None,
                                      err_alt if T_alt is not None else float("inf"))
                    best = (cost, FaceObservation(face.face, pose, T_world_cube, det.area_px2))
        if best is not None:
            chosen.append(best)
    # One detection per face (the larger), then consistency with the largest face.
    chosen.sort(key=lambda c: -c[1].area_px2)
    out: list[FaceObservation] = []
    for _cost_value, obs in chosen:
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
    no solution passes the reprojection and upright gates."""
    by_face = {m.face: m for m in layout.markers}
    obj = np.concatenate([by_face[f.face].corners_cube_m() for f in faces])
    img = np.concatenate([np.asarray(f.marker_pose.detection.corners_px, float) for f in faces])
    T_cam_world = invert_T(T_world_cam)
    seeds = [T_cam_world @ f.T_world_cube for f in faces]
    try:
        ok, rvec, tvec = cv2.solvePnP(obj, img, intrinsics.K, intrinsics.dist, flags=cv2.SOLVEPNP_SQPNP)
        if ok:
            seeds.append(_T_from_rvec(rvec, tvec))
    except cv2.error:
        pass
    with_prior = params.use_upright_prior or layout.has_repeated_ids
    best = None
    for T_seed in seeds:
        if not np.all(np.isfinite(T_seed)):
            continue
        rvec, _ = cv2.Rodrigues(T_seed[:3, :3])
        tvec = T_seed[:3, 3].reshape(3, 1).copy()
        try:
            rvec, tvec = cv2.solvePnPRefineLM(obj, img, intrinsics.K, intrinsics.dist, rvec, tvec)
        except cv2.error:
            continue
        rvec, tvec = np.asarray(rvec, float).reshape(3), np.asarray(tvec, float).reshape(3)
        if not (np.all(np.isfinite(rvec)) and np.all(np.isfinite(tvec))):
            continue
        T_cam_cube = _T_from_rvec(rvec, tvec)
        if not _valid_solution(T_cam_cube, obj):
            continue
        err = _reprojection_rms_px(obj, img, T_cam_cube, intrinsics)
        T_world_cube = T_world_cam @ T_cam_cube
        tilt = cube_tilt_deg(T_world_cube)
        if not np.isfinite(err) or err > params.max_joint_reprojection_error_px:
            continue
        if with_prior and tilt > params.upright_tolerance_deg:
            continue
        cost = _cost(err, len(obj), tilt, params, with_prior) / len(obj)
        if best is None or cost < best[0]:
            best = (cost, T_world_cube, err)
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
    """
    params = params or EstimatorParams()
    T_world_cam = np.asarray(T_world_cam, dtype=float)
    poses: list[MarkerPose] = []
    for det in detections:
        if det.marker_id not in layout.ids or not _dictionary_matches(det, layout.dictionary):
            continue
        for size_m in sorted({m.size_m for m in layout.markers_with_id(det.marker_id)}):
            mp = marker_pose(det, size_m, intrinsics, params.max_reprojection_error_px)
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
