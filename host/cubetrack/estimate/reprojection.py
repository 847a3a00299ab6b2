"""The reprojection model of a body's matched corners in calibrated cameras (used by the filter,
the multi-camera fit and the bundle adjustment).

A :class:`CornerSet` is one camera frame's corners matched to the body's faces
(:func:`cubetrack.estimate.match.match_faces`, made into a set by :func:`corner_set`), with the
camera's known ``T_world_cam``, ``K`` and distortion. The residual of a body pose is the
reprojection error of every corner; frames taken at different times are motion-compensated with
a velocity: the body at time ``t_i`` is ``p_i = p + v (t_i - t)``, ``R_i = exp(ω (t_i - t)) R``.

Pose increments are world-frame: ``R = exp(δθ) R0``, ``p = p0 + δp``; covariances are ordered
``[δp, δθ]`` (metres, radians). Pixel residuals are computed on undistorted, normalised points
scaled by the camera's focal length, so they are in pixels.
"""

from __future__ import annotations

import warnings
from collections.abc import Sequence
from dataclasses import dataclass

import cv2
import numpy as np

from cubetrack.core.cameras import CameraIntrinsics
from cubetrack.core.geometry import R_from_rotvec, invert_T, make_T
from cubetrack.core.layout import DEFAULT_DICTIONARY, CubeLayout
from cubetrack.core.records import Detection
from cubetrack.detect.predicted import modules_of
from cubetrack.estimate.corner_noise import corner_noise_factors
from cubetrack.estimate.kernels import exp_and_left_jacobian
from cubetrack.estimate.match import FaceMatch, match_faces


@dataclass(frozen=True, slots=True, eq=False)
class CornerSet:
    """One camera frame's cube corners matched to the cube's faces (made by :func:`corner_set`).

    ``points_cube_m`` (N, 3) in the cube frame; ``normalized`` (N, 2) the detected corners
    undistorted to normalised image coordinates; ``focal_px`` scales them back to pixels;
    ``T_cam_world`` the camera's extrinsics; ``time_s`` its capture time (host clock); ``faces``
    the matched faces' names, four rows each, in order; ``noise_scale`` (N,) each corner's
    measurement noise over the nominal one (:func:`cubetrack.estimate.corner_noise.corner_noise_scale`;
    None: 1 for every corner); ``row_offsets_s`` (N,) each corner's own capture instant after
    ``time_s``, seconds (under a rolling shutter the rows of one face are exposed one after the
    other: a moving body's face is seen sheared; None: every corner at ``time_s``).
    """

    camera: str
    time_s: float
    T_cam_world: np.ndarray
    focal_px: float
    points_cube_m: np.ndarray
    normalized: np.ndarray
    faces: tuple[str, ...]
    noise_scale: np.ndarray | None = None
    row_offsets_s: np.ndarray | None = None

    def corner_times_s(self) -> np.ndarray:
        """(N,) each corner's capture instant (host clock, seconds)."""
        if self.row_offsets_s is None:
            return np.full(len(self.points_cube_m), self.time_s)
        return np.add(self.time_s, self.row_offsets_s, dtype=np.float64)  # a host clock needs float64


def normalize_px(corners_px: np.ndarray, K: np.ndarray, dist: np.ndarray) -> np.ndarray:
    """Undistort (N, 2) pixel points to normalised image coordinates (x/z, y/z)."""
    pts = np.asarray(corners_px, dtype=np.float64).reshape(-1, 1, 2)
    return cv2.undistortPoints(pts, K, dist).reshape(-1, 2)


def corner_set(matches: Sequence[FaceMatch], intrinsics: CameraIntrinsics, T_world_cam: np.ndarray,
               camera: str, time_s: float, T_cam_world: np.ndarray | None = None) -> CornerSet | None:
    """The corner set of one camera frame's matched faces (in the order of ``matches``), or
    None when nothing matched. ``T_cam_world``: ``T_world_cam``'s inverse if the caller holds it."""
    if not matches:
        return None
    K, dist = intrinsics.K, intrinsics.dist
    corners_px = np.concatenate([m.detection.corners_px for m in matches])
    return CornerSet(camera, time_s, invert_T(T_world_cam) if T_cam_world is None else T_cam_world,
                     float((K[0, 0] + K[1, 1]) / 2.0),
                     np.concatenate([m.points_body_m for m in matches]), normalize_px(corners_px, K, dist),
                     tuple(m.face for m in matches), noise_scales(matches, corners_px))


def noise_scales(matches: Sequence[FaceMatch], corners_px: np.ndarray) -> np.ndarray:
    """(4 x len(matches),) each matched corner's noise over the nominal one, in the matches' order
    (:func:`cubetrack.estimate.corner_noise.corner_noise_scale`: from each marker's own quad);
    ``corners_px`` their corners stacked (4 x len(matches), 2)."""
    return corner_noise_factors(corners_px, [modules_of(m.detection.dictionary or DEFAULT_DICTIONARY)
                                             for m in matches])


def associate(detections: Sequence[Detection], layout: CubeLayout, T_world_cube: np.ndarray,
              T_world_cam: np.ndarray, intrinsics: CameraIntrinsics, camera: str, time_s: float,
              gate_px: float, max_view_angle_deg: float = 80.0) -> CornerSet | None:
    """Deprecated: ``corner_set(match_faces(detections, layout, intrinsics, T_world_cam,
    T_world_cube, gate_px=...), intrinsics, T_world_cam, camera, time_s)``."""
    warnings.warn("cubetrack.estimate.reprojection.associate is deprecated; use corner_set(match_faces(...), ...)",
                  DeprecationWarning, stacklevel=2)
    matches = match_faces(detections, layout, intrinsics, T_world_cam, T_world_cube, gate_px=gate_px,
                          max_view_angle_deg=max_view_angle_deg)
    return corner_set(matches, intrinsics, T_world_cam, camera, time_s)


def moved_pose(T_world_cube: np.ndarray, velocity_m_s: np.ndarray, angular_velocity_rad_s: np.ndarray,
               dt_s: float) -> np.ndarray:
    """The pose after ``dt_s`` seconds of constant world-frame linear and angular velocity."""
    R = R_from_rotvec(angular_velocity_rad_s * dt_s) @ T_world_cube[:3, :3]
    return make_T(R, T_world_cube[:3, 3] + velocity_m_s * dt_s)


def perturbed(T0: np.ndarray, delta: np.ndarray) -> np.ndarray:
    """``T0`` moved by a world-frame increment ``delta = [δp (m), δθ (rad)]``."""
    R = R_from_rotvec(delta[3:6]) @ T0[:3, :3]
    return make_T(R, T0[:3, 3] + delta[:3])


def _residuals(s: CornerSet, R: np.ndarray, p: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The set's corners with the body at rotation ``R``, position ``p`` (world; one for the set,
    or one per corner: (N, 3, 3), (N, 3)): ``q`` rotated
    (world axes, (N, 3)), their normalised image points ``uv`` (N, 2), ``focal/z`` (N,) and the
    pixel residuals (N, 2). A corner behind the camera (z <= 1e-6 m) gets a 1000 px residual
    and a zero ``focal/z``."""
    R_cw, t_cw = s.T_cam_world[:3, :3], s.T_cam_world[:3, 3]
    q = s.points_cube_m @ R.T if R.ndim == 2 else np.einsum("nij,nj->ni", R, s.points_cube_m)
    pc = q @ R_cw.T + ((R_cw @ p + t_cw) if p.ndim == 1 else (p @ R_cw.T + t_cw))
    z = pc[:, 2]
    ok = z > 1e-6
    if ok.all():
        uv = pc[:, :2] / z[:, None]
        scale = s.focal_px / z
        return q, uv, scale, (uv - s.normalized) * s.focal_px
    zs = np.where(ok, z, 1.0)
    uv = pc[:, :2] / zs[:, None]
    r = (uv - s.normalized) * s.focal_px
    r[~ok] = 1e3
    return q, uv, np.where(ok, s.focal_px / zs, 0.0), r


def reprojection_residuals_px(T_world_cube: np.ndarray, sets: Sequence[CornerSet], t_ref_s: float = 0.0,
                              velocity_m_s: np.ndarray | None = None,
                              angular_velocity_rad_s: np.ndarray | None = None) -> np.ndarray:
    """Stacked (x, y) reprojection residuals in pixels of every corner set, motion-compensated
    from ``t_ref_s`` to each set's time, or each corner's with the set's ``row_offsets_s`` (without
    velocities: the still cube). Corners behind a
    camera give a large residual (1000 px; a NaN one, e.g. of a corner that did not undistort,
    too)."""
    out = []
    for s in sets:
        R, p, _, _ = _moved(T_world_cube, s, t_ref_s, velocity_m_s, angular_velocity_rad_s)
        out.append(_residuals(s, R, p)[3].ravel())
    if not out:
        return np.zeros(0)
    r = out[0] if len(out) == 1 else np.concatenate(out)
    return r if np.isfinite(r).all() else np.nan_to_num(r, nan=1e3)


# (q @ _NEG_SKEW).reshape(3, 3) is -[q]x: a row vector a times it is q x a
_NEG_SKEW: np.ndarray = np.zeros((3, 3, 3))
_NEG_SKEW[0, 1, 2], _NEG_SKEW[0, 2, 1] = 1.0, -1.0
_NEG_SKEW[1, 2, 0], _NEG_SKEW[1, 0, 2] = 1.0, -1.0
_NEG_SKEW[2, 0, 1], _NEG_SKEW[2, 1, 0] = 1.0, -1.0
_NEG_SKEW = _NEG_SKEW.reshape(3, 9)
_NEG_SKEW.setflags(write=False)


def _exp_and_left_jacobian(omega: list[float], dt: float) -> np.ndarray:
    """``[Exp(ω dt) | J_l(ω dt) dt]`` (3, 6) for an angular velocity ``omega`` (rad/s, 3 floats): the
    rotation of a body turning at ``omega`` for ``dt`` seconds and its left Jacobian times ``dt``
    (:func:`cubetrack.estimate.kernels.exp_and_left_jacobian`, which the filter's kernels use too)."""
    out = np.empty((3, 6))
    exp_and_left_jacobian(omega[0], omega[1], omega[2], dt, out)
    return out


def _moved(T_world_cube: np.ndarray, s: CornerSet, t_ref_s: float, velocity_m_s: np.ndarray | None,
           angular_velocity_rad_s: np.ndarray | None) -> tuple[np.ndarray, np.ndarray, np.ndarray | None, np.ndarray]:
    """The body's rotation and position when the set's corners were taken, moved from
    ``T_world_cube`` at ``t_ref_s`` at the velocities (without them: the still body), one for the
    set or, with its ``row_offsets_s``, one per corner; with ``[Exp(ω dt) | J_l(ω dt) dt]`` (None
    when still) and ``dt`` (a scalar, or (N,) per corner)."""
    R0, p0 = T_world_cube[:3, :3], T_world_cube[:3, 3]
    if velocity_m_s is None or angular_velocity_rad_s is None:
        return R0, p0, None, np.asarray(0.0)
    omega = angular_velocity_rad_s.tolist()
    if s.row_offsets_s is None:
        dt = s.time_s - t_ref_s
        chain = _exp_and_left_jacobian(omega, dt)  # [S | J_l(ω dt) dt]
        return chain[:, :3] @ R0, p0 + velocity_m_s * dt, chain, np.asarray(dt)
    dts = s.corner_times_s() - t_ref_s
    chains = np.array([_exp_and_left_jacobian(omega, float(dt)) for dt in dts])
    return chains[:, :, :3] @ R0, p0 + velocity_m_s * dts[:, None], chains, dts


def reprojection_jacobian_px(T_world_cube: np.ndarray, sets: Sequence[CornerSet], t_ref_s: float = 0.0,
                             velocity_m_s: np.ndarray | None = None,
                             angular_velocity_rad_s: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Residuals (2N,) in pixels and their analytic Jacobian.

    Without velocities: the still cube at ``T_world_cube``, Jacobian (2N, 6) with respect to a
    world-frame increment ``[δp, δθ]`` (see :func:`perturbed`). With them: the cube moving from
    ``T_world_cube`` at ``t_ref_s`` (see :func:`moved_pose`), Jacobian (2N, 12) with respect to
    ``[δp, δθ, δv, δω]`` — the residuals of :func:`reprojection_residuals_px`.

    With ``q`` the corner rotated to its moved pose, ``S = Exp(ω dt)`` and ``J_l`` the left
    Jacobian of SO(3): ``d(pw)/d[δp, δθ, δv, δω] = [I | -[q]× S | dt I | -[q]× J_l(ω dt) dt]``;
    the pinhole gives ``d(x/z, y/z)/d(pc) = [[1/z, 0, -x/z²], [0, 1/z, -y/z²]]``;
    ``pc = R_cw pw + t_cw``. Corners behind a camera get a 1000 px residual and a zero row. A set
    with ``row_offsets_s`` is moved per corner, each to its own instant (``dt`` per corner).
    """
    moving = velocity_m_s is not None and angular_velocity_rad_s is not None
    residuals, jacobians = [], []
    for s in sets:
        R, p, chain, dt = _moved(T_world_cube, s, t_ref_s, velocity_m_s, angular_velocity_rad_s)
        q, uv, scale, r = _residuals(s, R, p)
        R_cw = s.T_cam_world[:3, :3]
        # d(pixels)/d(pw) = focal/z [[1, 0, -x/z], [0, 1, -y/z]] R_cw, one (2, 3) block per corner
        d_pw = (R_cw[:2] - uv[:, :, None] * R_cw[2]) * scale[:, None, None]
        d_theta = d_pw @ (q @ _NEG_SKEW).reshape(-1, 3, 3)  # a^T (-[q]x) = q x a, row by row
        if chain is not None:  # moving
            d_rot = d_theta @ chain
            blocks = [d_pw, d_rot[:, :, :3], d_pw * (dt if dt.ndim == 0 else dt[:, None, None]), d_rot[:, :, 3:]]
        else:
            blocks = [d_pw, d_theta]
        residuals.append(r.ravel())
        jacobians.append(np.concatenate(blocks, axis=2).reshape(2 * len(q), -1))
    if not residuals:
        return np.zeros(0), np.zeros((0, 12 if moving else 6))
    if len(residuals) == 1:
        return residuals[0], jacobians[0]
    return np.concatenate(residuals), np.vstack(jacobians)
