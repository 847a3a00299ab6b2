"""Rigid-body maths as plain functions on numpy arrays (the function layer).

Conventions, used everywhere in cubetrack:

- A pose ``T_a_b`` is a 4x4 homogeneous matrix that maps points from frame *b* to frame *a*:
  ``p_a = T_a_b @ p_b``. So ``T_world_cam`` is the camera's pose in the world frame.
- Lengths are metres, angles radians unless a ``unit`` argument says otherwise, times seconds.
- Quaternions are scalar-last ``(x, y, z, w)`` (ROS, TUM, scipy) and are returned with ``w >= 0``.
- Camera optical frame: x right, y down, z forward (OpenCV). Marker frame: origin at the
  marker centre, x right, y up, z out of the face (OpenCV ArUco). World frame: the world
  marker's frame, z up (ENU).
- Image coordinates: pixels, x right, y down, ``(0, 0)`` the centre of the top-left pixel
  (OpenCV's convention); the top-left pixel covers ``[-0.5, 0.5] x [-0.5, 0.5]``.
"""

from __future__ import annotations

import math

import cv2
import numpy as np
from numpy.typing import ArrayLike
from scipy.spatial.transform import Rotation

_ANGLE_UNITS = {"rad": 1.0, "deg": np.pi / 180.0}
_EYE4 = np.eye(4)
_EYE4.setflags(write=False)


def to_radians(angle: float | np.ndarray, unit: str = "rad") -> float | np.ndarray:
    """Convert ``angle`` given in ``unit`` ("rad" or "deg") to radians."""
    try:
        return angle * _ANGLE_UNITS[unit]
    except KeyError:
        raise ValueError(f"unknown angle unit {unit!r}; use 'rad' or 'deg'") from None


def make_T(R: np.ndarray, t: ArrayLike) -> np.ndarray:
    """4x4 pose from a 3x3 rotation matrix and a translation (metres)."""
    T = _EYE4.copy()
    T[:3, :3] = R
    T[:3, 3] = np.asarray(t, dtype=float).reshape(3)
    return T


def invert_T(T: np.ndarray) -> np.ndarray:
    """Inverse of a rigid 4x4 pose: ``invert_T(T_a_b) == T_b_a``. (Runs many times per frame:
    a copied identity and one 3-vector negation, not ``np.eye`` and a negated matrix.)"""
    Rt = T[:3, :3].T
    out = _EYE4.copy()
    out[:3, :3] = Rt
    out[:3, 3] = -(Rt @ T[:3, 3])
    return out


def R_from_rotvec(rotvec: np.ndarray) -> np.ndarray:
    """3x3 rotation of a rotation vector (axis x angle, radians): OpenCV's Rodrigues.

    The same as ``Rotation.from_rotvec(v).as_matrix()``, about 30x cheaper for one vector (this
    runs several times per corner set in the filter and the joint fit).
    """
    return cv2.Rodrigues(np.asarray(rotvec, dtype=np.float64).reshape(3, 1))[0]


def so3_left_jacobian(rotvec: np.ndarray) -> np.ndarray:
    """Left Jacobian of SO(3) at ``rotvec`` (radians): ``R_from_rotvec(v + e) ~
    R_from_rotvec(J e) @ R_from_rotvec(v)`` for a small ``e``. The chain rule of a pose
    parametrised by a finite rotation vector applied on the left."""
    v = np.asarray(rotvec, dtype=float).reshape(3)
    theta2 = float(v @ v)
    K = np.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])
    if theta2 < 1e-12:
        return np.eye(3) + 0.5 * K + (K @ K) / 6.0
    theta = math.sqrt(theta2)
    return np.eye(3) + ((1.0 - math.cos(theta)) / theta2) * K + ((theta - math.sin(theta)) / (theta2 * theta)) * (K @ K)


def T_from_rvec_tvec(rvec: np.ndarray, tvec: np.ndarray) -> np.ndarray:
    """4x4 pose from OpenCV's Rodrigues rotation vector (radians) and translation (metres)."""
    return make_T(R_from_rotvec(rvec), tvec)


def rvec_tvec_from_T(T: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """OpenCV rotation vector (radians) and translation (metres) of a 4x4 pose, each (3, 1) as
    OpenCV's solvers take them (``cv2.Rodrigues``: ``solvePnPRefineLM`` treats (3,) vectors
    differently)."""
    return cv2.Rodrigues(np.asarray(T[:3, :3], dtype=np.float64))[0], T[:3, 3].reshape(3, 1).copy()


def quat_xyzw_from_R(R: np.ndarray) -> np.ndarray:
    """Unit quaternion (x, y, z, w) with w >= 0 of a 3x3 rotation matrix.

    Shepperd's method: the quaternion component of largest magnitude is found from the diagonal
    first, the others from the off-diagonal sums and differences, so no branch divides by a small
    number. Runs once per output pose: ``Rotation.from_matrix`` costs ~100 us for one matrix,
    this ~5 us; tests hold the two equal.
    """
    (r00, r01, r02), (r10, r11, r12), (r20, r21, r22) = np.asarray(R, dtype=float).tolist()
    trace = r00 + r11 + r22
    if trace > 0.0:
        s = 2.0 * math.sqrt(trace + 1.0)
        q = ((r21 - r12) / s, (r02 - r20) / s, (r10 - r01) / s, 0.25 * s)
    elif r00 >= r11 and r00 >= r22:
        s = 2.0 * math.sqrt(max(1.0 + r00 - r11 - r22, 1e-300))
        q = (0.25 * s, (r01 + r10) / s, (r02 + r20) / s, (r21 - r12) / s)
    elif r11 >= r22:
        s = 2.0 * math.sqrt(max(1.0 + r11 - r00 - r22, 1e-300))
        q = ((r01 + r10) / s, 0.25 * s, (r12 + r21) / s, (r02 - r20) / s)
    else:
        s = 2.0 * math.sqrt(max(1.0 + r22 - r00 - r11, 1e-300))
        q = ((r02 + r20) / s, (r12 + r21) / s, 0.25 * s, (r10 - r01) / s)
    out = np.array(q) / math.sqrt(sum(c * c for c in q))
    return out if out[3] >= 0.0 else -out


def R_from_quat_xyzw(q_xyzw: np.ndarray) -> np.ndarray:
    """3x3 rotation matrix of a quaternion (x, y, z, w); the quaternion is normalised first."""
    return Rotation.from_quat(np.asarray(q_xyzw, dtype=float)).as_matrix()


def T_from_position_quat(position_m: np.ndarray, q_xyzw: np.ndarray) -> np.ndarray:
    """4x4 pose from a position (metres) and a quaternion (x, y, z, w)."""
    return make_T(R_from_quat_xyzw(q_xyzw), position_m)


def position_quat_from_T(T: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Position (metres) and quaternion (x, y, z, w, w >= 0) of a 4x4 pose."""
    return T[:3, 3].copy(), quat_xyzw_from_R(T[:3, :3])


def transform_points(T_a_b: np.ndarray, points_b: np.ndarray) -> np.ndarray:
    """Map an (N, 3) array of points from frame b to frame a."""
    points_b = np.asarray(points_b, dtype=float).reshape(-1, 3)
    return points_b @ T_a_b[:3, :3].T + T_a_b[:3, 3]


def rotation_angle(R_a: np.ndarray, R_b: np.ndarray, unit: str = "rad") -> float:
    """Angle of the relative rotation between two 3x3 rotation matrices, in ``unit``."""
    R = R_a.T @ R_b
    cos = (np.trace(R) - 1.0) / 2.0
    sin = 0.5 * math.sqrt((R[2, 1] - R[1, 2]) ** 2 + (R[0, 2] - R[2, 0]) ** 2 + (R[1, 0] - R[0, 1]) ** 2)
    angle = math.atan2(sin, cos)  # accurate for small angles too, unlike arccos(cos)
    return angle / float(to_radians(1.0, unit))


def shoelace_area(points_px: np.ndarray) -> float:
    """Area (px^2) of a simple polygon from its (N, 2) vertices in order (paper eq. 3)."""
    p = np.asarray(points_px, dtype=float).reshape(-1, 2)
    x, y = p[:, 0], p[:, 1]
    nxt = np.concatenate((p[1:], p[:1]))  # the next vertex: np.roll(., -1)'s values, without its ~10 us per call
    return 0.5 * abs(float(np.dot(x, nxt[:, 1]) - np.dot(y, nxt[:, 0])))


def mean_rotation(Rs: np.ndarray, weights: np.ndarray | None = None) -> np.ndarray:
    """Chordal L2 mean of (N, 3, 3) rotations (Markley et al. 2007), optionally weighted.

    Insensitive to quaternion signs, unlike a component-wise quaternion mean.
    """
    return Rotation.from_matrix(np.asarray(Rs)).mean(weights=weights).as_matrix()


def is_finite_pose(T: np.ndarray) -> bool:
    """True for a finite 4x4 pose whose rotation part is a rotation (orthonormal to 1e-6, det > 0).
    In plain floats: it runs per camera frame."""
    T = np.asarray(T)
    if T.shape != (4, 4):
        return False
    (a, b, c, x), (d, e, f, y), (g, h, i, z), (p, q, r, w) = T.tolist()
    if not math.isfinite(a + b + c + d + e + f + g + h + i + x + y + z + p + q + r + w):
        return False
    gram = (a * a + d * d + g * g - 1.0, b * b + e * e + h * h - 1.0, c * c + f * f + i * i - 1.0,
            a * b + d * e + g * h, a * c + d * f + g * i, b * c + e * f + h * i)  # R^T R - I
    det = a * (e * i - f * h) - b * (d * i - f * g) + c * (d * h - e * g)
    return max(map(abs, gram)) <= 1e-6 and det > 0.0


# cv2.undistortPoints iterated to 1e-12 (OpenCV's default stops after five iterations)
_UNDISTORT_CRITERIA = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 50, 1e-12)


def undistort_points(points_px: np.ndarray, K: np.ndarray, dist: np.ndarray,
                     P: np.ndarray | None = None) -> np.ndarray:
    """Distorted image points (..., 2) px to ideal ones, iterated to 1e-12: normalised image
    coordinates (x/z, y/z), or with ``P`` (e.g. ``K``) pixels of that pinhole camera. Same shape."""
    pts = np.asarray(points_px, dtype=np.float64)
    out = cv2.undistortPoints(pts.reshape(-1, 1, 2), K, dist, None, P, criteria=_UNDISTORT_CRITERIA)
    return out.reshape(pts.shape)
