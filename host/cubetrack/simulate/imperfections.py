"""What real hardware gets wrong, drawn per seed: each camera's own lens (principal point and
focal length off the nominal ones), the intrinsics a calibration gives the tracker (close to
the truth, not equal), a hand-built cube (markers shifted, turned, printed under size, faces not
quite square) and auto-exposure steps.

Each function returns the truth unchanged when its effect is off, so the clean preset renders
exactly what it always did.
"""

from __future__ import annotations

import math

import numpy as np
from scipy.spatial.transform import Rotation

from cubetrack.core.cameras import CameraIntrinsics
from cubetrack.core.geometry import make_T
from cubetrack.core.layout import CubeLayout, LayoutMarker
from cubetrack.simulate.params import SimulationParams

# A calibration's k1 and k2 errors trade against each other: the fitted distortion is right
# where the calibration board was seen most (mid-field), so dk2 ~ -dk1 / r_mid^2.
K2_PER_K1_ERROR = -3.4
_K2_INDEPENDENT = 0.15   # the part of the k2 error not explained by k1 (relative)
_FOCAL_INDEPENDENT = 0.3  # the part of the fx, fy errors that is not shared (relative)
_UNDERSIZE_SPREAD = 0.2   # each marker's undersize varies by this fraction of the mean
_AE_SETTLE_S = 0.25       # an auto-exposure step settles linearly over this time
_AE_RANGE = (0.6, 1.6)    # auto-exposure gain limits


def true_intrinsics(p: SimulationParams, name: str, rng: np.random.Generator) -> CameraIntrinsics:
    """A camera's true intrinsics: ``focal_px`` and the image centre, moved by the lens's own
    ``focal_spread`` and ``principal_offset_px`` (pixel-centre convention)."""
    f = p.focal_px * (1.0 + rng.normal(0.0, p.focal_spread)) if p.focal_spread > 0 else p.focal_px
    c = rng.normal(0.0, p.principal_offset_px, 2) if p.principal_offset_px > 0 else np.zeros(2)
    K = np.array([[f, 0.0, (p.image_width_px - 1) / 2.0 + c[0]],
                  [0.0, f, (p.image_height_px - 1) / 2.0 + c[1]],
                  [0.0, 0.0, 1.0]])
    return CameraIntrinsics(p.image_width_px, p.image_height_px, K, np.array(p.distortion, float), name)


def calibrated_intrinsics(truth: CameraIntrinsics, p: SimulationParams, rng: np.random.Generator) -> CameraIntrinsics:
    """The intrinsics a ChArUco calibration would give for ``truth`` (what camera_info holds):
    fx, fy off by a mostly shared fraction (``info_focal_error``), the principal point by a few
    pixels (``info_principal_error_px``), k1 by ``info_k1_error`` and k2 correlated with it."""
    if p.info_focal_error == 0 and p.info_principal_error_px == 0 and p.info_k1_error == 0:
        return truth
    K = truth.K.copy()
    shared = rng.normal(0.0, p.info_focal_error)
    own = rng.normal(0.0, _FOCAL_INDEPENDENT * p.info_focal_error, 2)
    K[0, 0] *= 1.0 + shared + own[0]
    K[1, 1] *= 1.0 + shared + own[1]
    K[:2, 2] += rng.normal(0.0, p.info_principal_error_px, 2)
    dist = np.array(truth.dist, float)
    dk1 = rng.normal(0.0, p.info_k1_error)
    dist[0] += dk1
    dist[1] += K2_PER_K1_ERROR * dk1 + rng.normal(0.0, _K2_INDEPENDENT * abs(K2_PER_K1_ERROR) * p.info_k1_error)
    return CameraIntrinsics(truth.width, truth.height, K, dist, truth.camera_name)


def built_layout(nominal: CubeLayout, p: SimulationParams, rng: np.random.Generator) -> CubeLayout:
    """The cube as built: each marker of ``nominal`` shifted (``marker_shift_mm`` per in-plane
    axis, half of it along the face normal), turned in its plane (``marker_turn_deg``), tilted
    out of it (``face_tilt_deg``: faces not quite square) and printed ``marker_undersize`` small."""
    if p.marker_shift_mm == 0 and p.marker_turn_deg == 0 and p.face_tilt_deg == 0 and p.marker_undersize == 0:
        return nominal
    markers = []
    for m in nominal.markers:
        shift = rng.normal(0.0, 1e-3 * p.marker_shift_mm, 3) * np.array([1.0, 1.0, 0.5])
        angles = np.radians([rng.normal(0.0, p.face_tilt_deg), rng.normal(0.0, p.face_tilt_deg),
                             rng.normal(0.0, p.marker_turn_deg)])
        scale = 1.0 - p.marker_undersize * (1.0 + _UNDERSIZE_SPREAD * float(np.clip(rng.normal(), -1.0, 1.0)))
        T_marker_built = make_T(Rotation.from_rotvec(angles).as_matrix(), shift)
        markers.append(LayoutMarker(m.face, m.marker_id, m.size_m * scale, m.T_cube_marker @ T_marker_built))
    return CubeLayout(nominal.dictionary, tuple(markers), nominal.motion)


def auto_exposure_gains(p: SimulationParams, times_s: np.ndarray, start_s: float, end_s: float,
                        rng: np.random.Generator) -> np.ndarray:
    """Auto-exposure gain at each of ``times_s`` (host seconds in ``[start_s, end_s]``): steps at
    random instants (``exposure_steps_per_s``), each changing the gain by a log-normal factor
    (``exposure_step``) within 0.6-1.6, settling linearly over 0.25 s. All ones when off."""
    times_s = np.asarray(times_s, float)
    if p.exposure_steps_per_s <= 0:
        return np.ones(len(times_s))
    count = int(rng.poisson(p.exposure_steps_per_s * (end_s - start_s)))
    step_times = np.sort(rng.uniform(start_s, end_s, count))
    levels = [1.0]
    for _ in range(count):
        levels.append(float(np.clip(levels[-1] * math.exp(rng.normal(0.0, p.exposure_step)), *_AE_RANGE)))
    gains = np.ones(len(times_s))
    for k, t0 in enumerate(step_times):
        u = np.clip((times_s - t0) / _AE_SETTLE_S, 0.0, 1.0)
        gains = np.where(times_s >= t0, levels[k] + u * (levels[k + 1] - levels[k]), gains)
    return gains
