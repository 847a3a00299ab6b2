"""Where each marker really sits on a body, calibrated from a recording of it driving about
(``cubetrack calibrate-body``).

A hand-built cube is not its layout file: each printed marker is shifted by a millimetre or two,
turned by a degree, printed slightly small, and the faces are not quite square. The tracker
takes the layout as exact, so every such error becomes a pose error that changes with the face
in view. :func:`calibrate_body` estimates each marker's pose on the body and its size from the
body's sightings in a tracking recording — a bundle adjustment (:mod:`cubetrack.calib.solver`)
over multi-camera instants as in the extrinsics refinement (:mod:`cubetrack.calib.bundle`) but of
frames closer in time (``body_max_span_s``), each corner's noise growing with its frame's time from
its instant (``body_motion_noise_px_per_s``: the constant-velocity motion between the frames misses
turns and vibration), the corners measured by the template fit (:mod:`cubetrack.calib.marker_fit`),
with the markers free, held near the nominal layout by priors (``body_position_sigma_m``,
``body_rotation_sigma_deg``, ``body_size_sigma``), the cameras refined too but held near the given
extrinsics (``body_camera_sigma_m``, ``body_camera_sigma_deg``), and (``refine_intrinsics``) the
intrinsics near camera_info.

Gauge: the body frame of the result is the nominal layout's best fit — the rigid transform that
brings the calibrated marker corners closest (least squares over all corners) to the nominal
ones is applied to the result, so the body frame moves with no marker in particular and the
tracked pose of a perfectly built body is unchanged. Markers never seen keep their nominal pose
(in that frame) and are named in a warning.
"""

from __future__ import annotations

import dataclasses
import logging
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field

import numpy as np

from cubetrack.calib.bundle import BundleAdjustmentParams, Refinement, layout_with, rms_px, start_refinement
from cubetrack.calib.solver import PosePrior
from cubetrack.core.cameras import CameraExtrinsics, CameraIntrinsics, ClockSample
from cubetrack.core.errors import CalibrationError
from cubetrack.core.geometry import invert_T, make_T, rotation_angle
from cubetrack.core.layout import CubeLayout
from cubetrack.core.progress import Progress
from cubetrack.core.records import Frame
from cubetrack.detect.detector import DetectorParams

log = logging.getLogger(__name__)

METHOD = "body-refined"  # CameraExtrinsics.method of the cameras a body calibration refined


@dataclass(frozen=True, slots=True)
class MarkerResult:
    """One calibrated marker: ``corners`` observed (in ``instants`` instants), their RMS
    reprojection error (px), and how far the result is from the nominal layout (both in the
    result's body frame): ``shift_m`` (centre), ``turn_deg`` (orientation), ``size_m`` against
    ``nominal_size_m``."""

    face: str
    marker_id: int
    corners: int
    instants: int
    rms_px: float
    shift_m: float
    turn_deg: float
    size_m: float
    nominal_size_m: float


@dataclass(frozen=True, slots=True, eq=False)
class BodyCalibrationReport:
    """What :func:`calibrate_body` found: the calibrated ``layout`` of ``robot`` (body frame = the
    ``nominal`` layout's best fit), per-marker results, the cameras as refined alongside
    (``extrinsics``, ``intrinsics``), the instants used and the warnings issued."""

    robot: str
    layout: CubeLayout
    nominal: CubeLayout
    markers: tuple[MarkerResult, ...]
    instants: int
    extrinsics: dict[str, CameraExtrinsics]
    intrinsics: dict[str, CameraIntrinsics]
    warnings: tuple[str, ...] = field(default_factory=tuple)


def best_fit_transform(points_from: np.ndarray, points_to: np.ndarray) -> np.ndarray:
    """The rigid transform T (4x4) minimising sum |T p - q|^2 over (n, 3) point pairs (Kabsch)."""
    a, b = np.asarray(points_from, float), np.asarray(points_to, float)
    ca, cb = a.mean(axis=0), b.mean(axis=0)
    U, _s, Vt = np.linalg.svd((a - ca).T @ (b - cb))
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(Vt.T @ U.T))])
    R = Vt.T @ D @ U.T
    return make_T(R, cb - R @ ca)


def moved_layout(layout: CubeLayout, T_new_old: np.ndarray) -> CubeLayout:
    """``layout`` expressed in another body frame: every marker pose becomes ``T_new_old @ T``."""
    return layout_with(layout, np.array([T_new_old @ m.T_cube_marker for m in layout.markers]), layout.sizes_m)


def _check_same_markers(a: CubeLayout, b: CubeLayout, what: str) -> None:
    if [(m.face, m.marker_id) for m in a.markers] != [(m.face, m.marker_id) for m in b.markers]:
        raise CalibrationError(f"{what} has other markers (faces and ids) than the layout: "
                               f"{[(m.face, m.marker_id) for m in b.markers]} vs {[(m.face, m.marker_id) for m in a.markers]}")


def placement_errors(layout: CubeLayout, truth: CubeLayout, aligned: bool = True
                     ) -> dict[str, tuple[float, float, float]]:
    """Per face: (position error m, rotation error deg, size error m) of ``layout``'s markers
    against ``truth``'s (same faces and ids). ``aligned``: first express ``layout`` in the body
    frame that fits ``truth`` best (the body frame is a choice, the markers' placement on the
    body is not); else compare as written."""
    _check_same_markers(layout, truth, "the true layout")
    if aligned:
        layout = moved_layout(layout, best_fit_transform(layout.corners_m.reshape(-1, 3), truth.corners_m.reshape(-1, 3)))
    return {m.face: (float(np.linalg.norm(m.T_cube_marker[:3, 3] - t.T_cube_marker[:3, 3])),
                     rotation_angle(m.T_cube_marker[:3, :3], t.T_cube_marker[:3, :3], "deg"), m.size_m - t.size_m)
            for m, t in zip(layout.markers, truth.markers)}


def calibrate_body(frames: Mapping[str, Iterable[Frame]], extrinsics: Mapping[str, CameraExtrinsics],
                   intrinsics: Mapping[str, CameraIntrinsics], layout: CubeLayout, robot: str = "robot", *,
                   clock_samples: Mapping[str, Sequence[ClockSample]] | None = None,
                   params: BundleAdjustmentParams | None = None,
                   detector_params: DetectorParams | None = None, progress: Progress | None = None,
                   frame_count: int = 0, readout_s: Mapping[str, float] | None = None,
                   edge_corners: bool = False) -> BodyCalibrationReport:
    """Calibrate the placement of every marker of ``layout`` (the nominal body of ``robot``) from
    the tracking ``frames`` (camera -> its frames, stamped with ``clock_samples``) of cameras
    with ``extrinsics`` and ``intrinsics``; see the module docstring. ``params``: the
    ``[bundle_adjustment]`` settings (None: the defaults; instants, their span
    ``body_max_span_s``, noise, rounds, the body_* and intrinsics priors); ``readout_s``: each
    camera's rolling-shutter readout (seconds; a corner is moved to the time its row was
    exposed; None: the intrinsics' ``readout_s``, from camera_info); ``edge_corners``:
    re-measure the corners by the calibration's edge fit and template fit
    (:mod:`cubetrack.calib.marker_fit`).

    CalibrationError when fewer than two calibrated cameras saw the body at once.
    """
    params = params or BundleAdjustmentParams()
    warnings: list[str] = []

    def warn(message: str) -> None:
        warnings.append(message)
        log.warning("%s", message)

    ref, _cameras = start_refinement(frames, extrinsics, intrinsics, {robot: layout}, clock_samples=clock_samples,
                                     params=dataclasses.replace(params, max_span_s=params.body_max_span_s),
                                     detector_params=detector_params, progress=progress,
                                     frame_count=frame_count, warn=warn, readout_s=readout_s,
                                     calibration_corners=edge_corners)
    T_given = ref.model.T_cams.copy()
    camera_prior = PosePrior(T_given, params.body_camera_sigma_m, np.radians(params.body_camera_sigma_deg))
    for done in range(params.rounds + 1):
        if progress is not None:
            progress("body calibration: solves", done, params.rounds + 1)
        if done:
            ref.update_velocities()
            ref.rematch()
        ref.solve(ref.freedom(camera_prior=camera_prior, intrinsics=params.refine_intrinsics, body=True))
    _fix_gauge(ref, layout)
    ref.update_velocities()
    return _report(ref, robot, layout, extrinsics, intrinsics, warn, warnings)


def _fix_gauge(ref: Refinement, nominal: CubeLayout) -> None:
    """Move the body frame to the nominal layout's best fit (markers and body poses together, so
    every projection stays as it is)."""
    calibrated = ref.layout(ref.robots[0])
    G = best_fit_transform(calibrated.corners_m.reshape(-1, 3), nominal.corners_m.reshape(-1, 3))
    ref.model = ref.model.replace(T_body_markers=np.einsum("ij,gjk->gik", G, ref.model.T_body_markers),
                                  T_bodies=np.einsum("kij,jl->kil", ref.model.T_bodies, invert_T(G)))


def _report(ref: Refinement, robot: str, nominal: CubeLayout, extrinsics: Mapping[str, CameraExtrinsics],
            intrinsics: Mapping[str, CameraIntrinsics], warn, warnings: list[str]) -> BodyCalibrationReport:
    obs, r, _rw = ref.residuals()
    calibrated = ref.layout(robot)
    results = []
    for g, (m, n) in enumerate(zip(calibrated.markers, nominal.markers)):
        mine = obs.marker == g
        if not mine.any():
            warn(f"marker {m.face} (id {m.marker_id}) was never seen by two cameras at once: kept as the layout has it")
        results.append(MarkerResult(
            m.face, m.marker_id, int(mine.sum()), len(np.unique(obs.inst[mine])), rms_px(r[mine]),
            float(np.linalg.norm(m.T_cube_marker[:3, 3] - n.T_cube_marker[:3, 3])),
            rotation_angle(m.T_cube_marker[:3, :3], n.T_cube_marker[:3, :3], "deg"), m.size_m, n.size_m))
    refined = dict(extrinsics)
    for c, T in ref.T_world_cam().items():
        n_inst = len(np.unique(obs.inst[obs.cam == ref.cameras.index(c)]))
        refined[c] = CameraExtrinsics(T, n_inst, 0.0, 0.0, METHOD)
    return BodyCalibrationReport(robot, calibrated, nominal, tuple(results), len(ref.instants), refined,
                                 {**dict(intrinsics), **ref.intrinsics()}, tuple(warnings))
