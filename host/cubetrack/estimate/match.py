"""The one matcher: a frame's marker detections -> the faces of a body, as 2D-3D corner pairs.

It plays the role OpenCV's ``Board::matchImagePoints`` plays for a board (detected ids -> object
points), for a body whose faces may repeat one id (the paper's cube) and whose single markers
have two planar pose solutions. Everything that needs a body's corners matched calls it: the
per-camera estimate (:func:`cubetrack.estimate.pose.estimate_cube`), the filter and the
multi-camera fit (through :func:`cubetrack.estimate.reprojection.corner_set`) and the bundle
adjustment of the extrinsics.

:func:`match_faces` takes the detections, the body's layout, the camera (intrinsics and
``T_world_cam``) and, when there is one, a predicted body pose. Only the body's own detections
take part (:func:`body_detections`: one of its ids, in its dictionary). Which face a detection is
gets settled

- **by the predicted pose** when there is one (a running filter's prediction, a pose being
  refined): the layout's faces are projected with it and each detection takes the nearest
  unclaimed face with its id (mean corner distance under ``gate_px``, or half the detected
  marker's side), among the faces that face the camera at most ``max_view_angle_deg`` off the
  line of sight;
- **without one** (:func:`identify_faces`): each detection's single-marker poses (both IPPE
  solutions, :func:`cubetrack.estimate.marker.marker_pose`) for each face with its id imply a
  body pose, scored by a MAP cost: reprojection (``corner_noise_px``) plus an upright prior on
  the body's z axis against world up (``upright_sigma_deg``, hard gate
  ``upright_tolerance_deg``; :func:`uses_upright_prior`: floor bodies, or repeated ids). With one
  id on five faces the prior is what tells the faces apart
  (they differ by 90° in the implied tilt) and what resolves IPPE's planar flip; with distinct
  ids the face is given by the id and the prior only resolves the flip. A face seen twice keeps
  its larger detection; faces implying a body centre farther than ``max_face_spread_m`` from the
  largest face's are dropped.
"""

from __future__ import annotations

import itertools
import logging
import math
from collections.abc import Collection, Iterable, Sequence
from dataclasses import dataclass

import cv2
import numba
import numpy as np

from cubetrack.core.cameras import CameraIntrinsics
from cubetrack.core.errors import EstimationError
from cubetrack.core.geometry import is_finite_pose
from cubetrack.core.layout import CubeLayout
from cubetrack.core.records import Detection, FaceObservation, MarkerPose
from cubetrack.detect.predicted import COMPILED_DISTORTION, projected_px
from cubetrack.estimate.marker import marker_pose
from cubetrack.estimate.params import EstimatorParams

log = logging.getLogger(__name__)

_ZERO3 = np.zeros(3)


@dataclass(frozen=True, slots=True, eq=False)
class FaceMatch:
    """One detection matched to one face of a body. The 2D-3D corner pairs are
    ``detection.corners_px`` (4, 2) px and ``points_body_m`` (4, 3) in the body frame, both in
    detector order (TL, TR, BR, BL); ``marker`` indexes ``layout.markers``. ``observation``:
    matched without a prediction, the chosen single-marker pose and the body pose it implies
    (what the paper's fusions average); None when matched by a predicted pose."""

    marker: int
    face: str
    detection: Detection
    points_body_m: np.ndarray
    observation: FaceObservation | None = None


def detections_of(detections: Iterable[Detection], dictionary: str, ids: Collection[int]) -> tuple[Detection, ...]:
    """The detections with one of ``ids`` in ``dictionary`` (a detection with no dictionary named
    matches any), in their order: a body's, or the world marker's."""
    return tuple(d for d in detections if d.marker_id in ids and d.dictionary in ("", dictionary))


def body_detections(detections: Iterable[Detection], layout: CubeLayout) -> tuple[Detection, ...]:
    """The detections of ``layout``'s markers (:func:`detections_of` its dictionary and ids; a
    layout of several dictionaries: each marker's own)."""
    if len(layout.dictionaries) == 1:
        return detections_of(detections, layout.dictionary, layout.ids)
    return tuple(d for d in detections if len(layout.indices_of(d.marker_id, d.dictionary)))


def match_faces(detections: Iterable[Detection], layout: CubeLayout, intrinsics: CameraIntrinsics,
                T_world_cam: np.ndarray, T_world_cube: np.ndarray | None = None, *,
                params: EstimatorParams | None = None, gate_px: float = 12.0,
                max_view_angle_deg: float = 80.0, camera_checked: bool = False) -> tuple[FaceMatch, ...]:
    """Match one camera frame's detections to the faces of the body ``layout`` describes.

    ``T_world_cam``: the camera's pose; ``T_world_cube``: the predicted body pose, or None (see
    the module doc for how each settles repeated ids and flips). Without a prediction the matches
    come largest first, each with its ``observation`` (``params``: the estimator's thresholds);
    with one, in detection order (``gate_px``, ``max_view_angle_deg``). A face is matched at
    most once; detections of other bodies and of no face are left out. EstimationError when
    ``T_world_cam`` is not a finite rigid pose (``camera_checked``: the caller has found it one
    already, a float array, as the filter does once per camera pose).
    """
    mine = body_detections(detections, layout)
    if not mine:
        return ()
    if not camera_checked:
        T_world_cam = _checked_camera_pose(T_world_cam)
    if T_world_cube is not None:
        return _match_by_prediction(mine, layout, intrinsics, T_world_cam, np.asarray(T_world_cube, dtype=float),
                                    gate_px, max_view_angle_deg)
    params = params or EstimatorParams()
    poses: list[MarkerPose] = []
    for det in mine:
        for size_m in sorted(set(layout.sizes_m[layout.indices_of(det.marker_id, det.dictionary)].tolist())):
            mp = marker_pose(det, size_m, intrinsics, params.max_reprojection_error_px, polish=False)
            if mp is not None:
                poses.append(mp)
    return tuple(FaceMatch(k, obs.face, obs.marker_pose.detection, layout.corners_m[k], obs)
                 for k, obs in _identify(poses, layout, T_world_cam, params))


def identify_faces(marker_poses: Iterable[MarkerPose], layout: CubeLayout, T_world_cam: np.ndarray,
                   params: EstimatorParams | None = None) -> tuple[FaceObservation, ...]:
    """The matcher's step without a prediction, on single-marker poses already made: assign
    marker poses to faces and give each the body pose it implies.

    ``marker_poses`` are MarkerPoses of markers in ``layout`` (other ids and dictionaries are
    ignored). For each, every face with that id (and the same size) and each of its IPPE
    solutions is a hypothesis; the lowest MAP cost (reprojection + upright prior) within
    ``upright_tolerance_deg`` wins. Result: one FaceObservation per identified face, largest
    area first, whose ``marker_pose.T_cam_marker`` is the chosen solution.
    """
    return tuple(obs for _k, obs in _identify(marker_poses, layout, _checked_camera_pose(T_world_cam),
                                              params or EstimatorParams()))


def uses_upright_prior(layout: CubeLayout, params: EstimatorParams) -> bool:
    """Whether the upright prior (and its ``upright_tolerance_deg`` gate) applies to ``layout``'s body:
    ``use_upright_prior`` for a body on a floor robot (``motion = "floor"``); never for a free body (held by
    hand: any tilt), unless one id is on several faces, where the prior is the only way to tell them apart."""
    return layout.has_repeated_ids or (params.use_upright_prior and layout.motion == "floor")


def _checked_camera_pose(T_world_cam: np.ndarray) -> np.ndarray:
    T_world_cam = np.asarray(T_world_cam, dtype=float)
    if not is_finite_pose(T_world_cam):
        raise EstimationError("T_world_cam must be a finite rigid 4x4 pose")
    return T_world_cam


def _identify(marker_poses: Iterable[MarkerPose], layout: CubeLayout, T_world_cam: np.ndarray,
              params: EstimatorParams) -> list[tuple[int, FaceObservation]]:
    """:func:`identify_faces` with each face's index in ``layout.markers``."""
    with_prior = uses_upright_prior(layout, params)
    reprojection_weight = 4.0 / (2.0 * params.corner_noise_px ** 2)   # 4 corners
    tilt_weight = 1.0 / (2.0 * params.upright_sigma_deg ** 2)
    chosen: list[tuple[int, FaceObservation]] = []
    for mp in marker_poses:
        det = mp.detection
        faces = layout.indices_of(det.marker_id, det.dictionary)
        if not len(faces):
            continue
        T_marker_cube, sizes = layout.T_marker_cube[faces], layout.sizes_m[faces]
        size_ok = np.abs(sizes - mp.size_m) <= 1e-6 * abs(mp.size_m)
        # hypotheses: each solution (with the other as its alternative) x each face with the id
        first = (mp.T_cam_marker, mp.reprojection_error_px)
        second = (mp.T_cam_marker_alt, mp.reprojection_error_alt_px)
        options = [(*first, *second)] + ([(*second, *first)] if mp.T_cam_marker_alt is not None else [])
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
        marker = int(faces[f])
        chosen.append((marker, FaceObservation(layout.markers[marker].face, pose, T_world_cube[s, f], det.area_px2)))
    # One detection per face (the larger), then consistency with the largest face.
    chosen.sort(key=lambda c: -c[1].area_px2)
    out: list[tuple[int, FaceObservation]] = []
    for marker, obs in chosen:
        if any(o.face == obs.face for _m, o in out):
            continue
        if out and np.linalg.norm(obs.T_world_cube[:3, 3] - out[0][1].T_world_cube[:3, 3]) > params.max_face_spread_m:
            log.debug("face %s dropped: disagrees with face %s by more than %.3f m",
                      obs.face, out[0][1].face, params.max_face_spread_m)
            continue
        out.append((marker, obs))
    return out


def _match_by_prediction(detections: Sequence[Detection], layout: CubeLayout, intrinsics: CameraIntrinsics,
                         T_world_cam: np.ndarray, T_world_cube: np.ndarray, gate_px: float,
                         max_view_angle_deg: float) -> tuple[FaceMatch, ...]:
    """Each detection, in order, takes the nearest unclaimed visible face with its id where
    ``T_world_cube`` projects the faces (see the module doc). Runs per sighting in the filter: one
    compiled call (:func:`_nearest_faces`; with a lens model beyond the compiled one, OpenCV
    projects the faces and :func:`_claimed_faces` assigns them)."""
    cos_max = math.cos(math.radians(max_view_angle_deg))
    detected = np.array([det.corners_px for det in detections], dtype=np.float64)
    keys = np.array([(det.marker_id, max(gate_px, 0.5 * math.sqrt(det.area_px2))) for det in detections])
    if len(layout.dictionaries) > 1:   # a detection of a named dictionary takes only that dictionary's faces
        names = {name: code for code, name in enumerate(layout.dictionaries)}
        face_dictionaries = np.array([names[name] for name in layout.marker_dictionaries], dtype=np.int64)
        detection_dictionaries = np.array([names.get(det.dictionary, -2) if det.dictionary else -1
                                           for det in detections], dtype=np.int64)
    else:
        face_dictionaries = detection_dictionaries = _NO_CODES
    dist = intrinsics.dist.ravel()
    if len(dist) <= COMPILED_DISTORTION:   # OpenCV's model without its tilted sensor: compiled (the same pixels)
        chosen = _nearest_faces(layout.corners_m, layout.normals, T_world_cam, T_world_cube, cos_max, intrinsics.K,
                                dist, detected, keys, layout.marker_ids, face_dictionaries, detection_dictionaries)
    else:
        R_cb, t_cb = _body_in_camera(T_world_cam, T_world_cube)
        corners_cam, visible = _faces_in_camera(layout.corners_m, layout.normals, R_cb, t_cb, cos_max)
        found = _mean_corner_distances(
            cv2.projectPoints(corners_cam, _ZERO3, _ZERO3, intrinsics.K, dist)[0].reshape(-1, 2), detected)
        chosen = _claimed_faces(found, visible, keys, layout.marker_ids, face_dictionaries, detection_dictionaries)
    return tuple(FaceMatch(k, layout.markers[k].face, det, layout.corners_m[k])
                 for det, k in zip(detections, chosen.tolist(), strict=True) if k >= 0)


_NO_CODES = np.zeros(0, dtype=np.int64)   # a layout of one dictionary: no dictionary to check


# The prediction's numeric steps, compiled (numba: a dozen small numpy calls per sighting were most of the
# filter's association; compile_match_kernels compiles them before the first sighting).


@numba.njit(cache=True, nogil=True)
def _faces_in_camera(corners_m: np.ndarray, normals: np.ndarray, R_cb: np.ndarray, t_cb: np.ndarray,
                     cos_max: float) -> tuple[np.ndarray, np.ndarray]:  # pragma: no cover
    """The faces' corners (M, 4, 3) in the camera frame (body at ``R_cb``, ``t_cb`` there), as
    (4M, 3), and which faces are candidates: not facing away, nor seen more obliquely than the
    angle of cosine ``cos_max`` (the view angle's cosine ``-n.c / |c|``, with ``c`` twice the face's
    centre: its diagonal's midpoint)."""
    M = corners_m.shape[0]
    cam = np.empty((4 * M, 3))
    visible = np.empty(M, dtype=np.bool_)
    for j in range(M):
        for c in range(4):
            for a in range(3):
                cam[4 * j + c, a] = (R_cb[a, 0] * corners_m[j, c, 0] + R_cb[a, 1] * corners_m[j, c, 1]
                                     + R_cb[a, 2] * corners_m[j, c, 2] + t_cb[a])
        toward, length2 = 0.0, 0.0
        for a in range(3):
            centre = cam[4 * j, a] + cam[4 * j + 2, a]
            toward -= (R_cb[a, 0] * normals[j, 0] + R_cb[a, 1] * normals[j, 1] + R_cb[a, 2] * normals[j, 2]) * centre
            length2 += centre * centre
        visible[j] = toward >= cos_max * math.sqrt(length2)
    return cam, visible


@numba.njit(cache=True, nogil=True)
def _mean_corner_distances(projected: np.ndarray, detected: np.ndarray) -> np.ndarray:  # pragma: no cover
    """(D, M): each detection's (``detected`` (D, 4, 2)) mean corner distance to each face's
    projected corners (``projected`` (4M, 2)), pixels."""
    D, M = detected.shape[0], projected.shape[0] // 4
    out = np.empty((D, M))
    for i in range(D):
        for j in range(M):
            s = 0.0
            for c in range(4):
                dx, dy = projected[4 * j + c, 0] - detected[i, c, 0], projected[4 * j + c, 1] - detected[i, c, 1]
                s += math.sqrt(dx * dx + dy * dy)
            out[i, j] = s * 0.25
    return out


@numba.njit(cache=True, nogil=True)
def _body_in_camera(T_world_cam: np.ndarray,
                    T_world_cube: np.ndarray) -> tuple[np.ndarray, np.ndarray]:  # pragma: no cover
    """The body's rotation and position in the camera frame: ``R_wcᵀ R_wb``, ``R_wcᵀ (t_wb - t_wc)``."""
    R_cb, t_cb = np.empty((3, 3)), np.empty(3)
    for a in range(3):
        for b in range(3):
            R_cb[a, b] = (T_world_cam[0, a] * T_world_cube[0, b] + T_world_cam[1, a] * T_world_cube[1, b]
                          + T_world_cam[2, a] * T_world_cube[2, b])
        t_cb[a] = (T_world_cam[0, a] * (T_world_cube[0, 3] - T_world_cam[0, 3])
                   + T_world_cam[1, a] * (T_world_cube[1, 3] - T_world_cam[1, 3])
                   + T_world_cam[2, a] * (T_world_cube[2, 3] - T_world_cam[2, 3]))
    return R_cb, t_cb


@numba.njit(cache=True, nogil=True)
def _claimed_faces(distances: np.ndarray, visible: np.ndarray, keys: np.ndarray, face_ids: np.ndarray,
                   face_dictionaries: np.ndarray, detection_dictionaries: np.ndarray) -> np.ndarray:  # pragma: no cover
    """(D,): the face each detection takes, in order (-1: none): the nearest (``distances`` (D, M))
    unclaimed ``visible`` face with its id (``keys`` (D, 2): id, gate in pixels) within its gate; with
    dictionaries given (codes, a detection's -1: any), one of its dictionary."""
    D, M = distances.shape
    free = visible.copy()
    chosen = np.full(D, -1, dtype=np.int64)
    for i in range(D):
        best, k = math.inf, -1
        for j in range(M):
            if (distances[i, j] < best and free[j] and face_ids[j] == keys[i, 0]
                    and not (detection_dictionaries.shape[0] and detection_dictionaries[i] != -1
                             and face_dictionaries[j] != detection_dictionaries[i])):
                best, k = distances[i, j], j
        if k < 0 or best > keys[i, 1]:
            continue
        free[k] = False
        chosen[i] = k
    return chosen


@numba.njit(cache=True, nogil=True)
def _nearest_faces(corners_m: np.ndarray, normals: np.ndarray, T_world_cam: np.ndarray, T_world_cube: np.ndarray,
                   cos_max: float, K: np.ndarray, dist: np.ndarray, detected: np.ndarray, keys: np.ndarray,
                   face_ids: np.ndarray, face_dictionaries: np.ndarray,
                   detection_dictionaries: np.ndarray) -> np.ndarray:  # pragma: no cover
    """:func:`_body_in_camera`, :func:`_faces_in_camera`, :func:`~cubetrack.detect.predicted.projected_px`,
    :func:`_mean_corner_distances` and :func:`_claimed_faces` in one call from Python (each call costs
    a few microseconds of dispatch): the face each detection takes (-1: none)."""
    R_cb, t_cb = _body_in_camera(T_world_cam, T_world_cube)
    corners_cam, visible = _faces_in_camera(corners_m, normals, R_cb, t_cb, cos_max)
    distances = _mean_corner_distances(projected_px(corners_cam, K, dist), detected)
    return _claimed_faces(distances, visible, keys, face_ids, face_dictionaries, detection_dictionaries)


def compile_match_kernels() -> None:
    """Compile the matcher's kernels (or load them from numba's on-disk cache) for the argument
    types it passes (a layout's read-only arrays; poses read-only, as the filter's, or not), so that
    no sighting pays it."""
    corners = np.zeros((1, 4, 3))
    normals = np.array([[0.0, 0.0, 1.0]])
    ids = np.zeros(1, dtype=np.int64)
    for a in (corners, normals, ids):
        a.setflags(write=False)
    keys, detected = np.array([[0.0, 12.0]]), np.zeros((1, 4, 2))
    cam, visible = _faces_in_camera(corners, normals, np.eye(3), np.array([0.0, 0.0, 1.0]), 0.5)
    distances = _mean_corner_distances(projected_px(cam, np.eye(3), np.zeros(5)), detected)
    _claimed_faces(distances, visible, keys, ids, _NO_CODES, _NO_CODES)
    for cam_writable, cube_writable in itertools.product((False, True), repeat=2):
        T_world_cam, T_world_cube = np.eye(4), np.eye(4)
        T_world_cube[2, 3] = 1.0
        T_world_cam.setflags(write=cam_writable)
        T_world_cube.setflags(write=cube_writable)
        _body_in_camera(T_world_cam, T_world_cube)
        _nearest_faces(corners, normals, T_world_cam, T_world_cube, 0.5, np.eye(3), np.zeros(5), detected, keys, ids,
                       _NO_CODES, _NO_CODES)
