"""The corner filter's numeric kernels, compiled (numba): the Gauss-Newton update of
:meth:`cubetrack.fuse.corner_filter.PoseFilter.update` and the prediction of
:meth:`cubetrack.fuse.corner_filter.PoseFilter.predict`.

As numpy, one update was about forty small array operations per Gauss-Newton step (a Jacobian
per corner set, the Huber weights, the calibration discount, two LU solves), each paying
numpy's per-call cost on 8-24 rows; here it is one call over plain loops. The mathematics is
that of :mod:`cubetrack.estimate.reprojection` (residuals and Jacobian, motion-compensated per
corner set) and :mod:`cubetrack.fuse.corner_filter` (the update's steps, in the same order);
the small inverses and solves are an LU with partial pivoting, as OpenCV's ``DECOMP_LU`` that
the numpy version called (singular when a pivot is below ``100 * DBL_EPSILON``). Results agree
with the numpy version to rounding (tests/unit/fuse/test_filter_kernels.py). The multi-camera fit that
starts a track (:mod:`cubetrack.fuse.multi_view_fit`) is compiled too (:func:`joint_fit`).

A corner set's arrays are passed packed (:func:`packed_sets`): one row per corner
(``points_cube_m``, ``normalized``, its set's index, its capture instant) and one per set
(``R_cam_world``, ``t_cam_world``, ``focal_px``). :func:`compile_filter_kernels` compiles them (or
loads them from numba's on-disk cache) before the first sighting.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numba
import numpy as np

from cubetrack.detect.detector import compile_kernels
from cubetrack.estimate.corner_noise import corner_noise_factors
from cubetrack.estimate.kernels import exp_and_left_jacobian
from cubetrack.estimate.match import compile_match_kernels
from cubetrack.estimate.reprojection import CornerSet

SINGULAR = 1.0e2 * np.finfo(np.float64).eps  # OpenCV's LU: a pivot below this is a singular matrix
_LARGEST = float(np.finfo(np.float64).max)
_EPS = float(np.finfo(np.float64).eps)
BEHIND_PX = 1.0e3  # the residual of a corner behind its camera (or one that did not undistort)

# status of solve_update: the prior's or a step's matrix was singular (np.linalg.LinAlgError in the numpy version)
OK, SINGULAR_PRIOR, SINGULAR_STEP = 0, 1, 2


Packed = tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]


def packed_sets(sets: Sequence[CornerSet]) -> Packed:
    """The kernels' arrays of ``sets``: ``(points_cube_m (N, 3), normalized (N, 2), set of each
    corner (N,), R_cam_world (S, 3, 3), t_cam_world (S, 3), focal_px (S,), each corner's capture
    instant (N,))`` (:meth:`CornerSet.corner_times_s`)."""
    if len(sets) == 1:   # most sightings (per call: numpy's cost of making each array is most of it)
        T_cw, which = sets[0].T_cam_world[None], np.zeros(len(sets[0].points_cube_m), dtype=np.int64)
        points, normalized = sets[0].points_cube_m, sets[0].normalized
        times = sets[0].corner_times_s()
    else:
        T_cw = np.array([s.T_cam_world for s in sets], dtype=np.float64)
        which = np.repeat(np.arange(len(sets)), [len(s.points_cube_m) for s in sets])
        points = np.concatenate([s.points_cube_m for s in sets])
        normalized = np.concatenate([s.normalized for s in sets])
        times = np.concatenate([s.corner_times_s() for s in sets])
    return (np.array(points, dtype=np.float64), np.array(normalized, dtype=np.float64), which,
            np.array(T_cw[:, :3, :3], dtype=np.float64), np.array(T_cw[:, :3, 3], dtype=np.float64),
            np.array([s.focal_px for s in sets], dtype=np.float64), times)


def taken_at(sets: Sequence[CornerSet], time_s: float) -> bool:
    """Whether every corner of ``sets`` was taken at ``time_s`` (else a fit at ``time_s`` moves
    them to their own instants at the body's velocities: a rolling shutter's rows)."""
    return all(s.time_s == time_s and s.row_offsets_s is None for s in sets)


@numba.njit(cache=True, nogil=True)
def _lu_solve(A: np.ndarray, B: np.ndarray) -> bool:  # pragma: no cover
    """Solve ``A X = B`` in place (``B`` becomes ``X``; ``A`` is overwritten): Gaussian
    elimination with partial pivoting, as OpenCV's ``LU``. False when ``A`` is singular."""
    n, m = A.shape[0], B.shape[1]
    for i in range(n):
        k = i
        for j in range(i + 1, n):
            if abs(A[j, i]) > abs(A[k, i]):
                k = j
        if abs(A[k, i]) < SINGULAR:
            return False
        if k != i:
            for j in range(i, n):
                A[i, j], A[k, j] = A[k, j], A[i, j]
            for j in range(m):
                B[i, j], B[k, j] = B[k, j], B[i, j]
        d = -1.0 / A[i, i]
        for j in range(i + 1, n):
            alpha = A[j, i] * d
            for c in range(i + 1, n):
                A[j, c] += alpha * A[i, c]
            for c in range(m):
                B[j, c] += alpha * B[i, c]
    for i in range(n - 1, -1, -1):
        for j in range(m):
            s = B[i, j]
            for c in range(i + 1, n):
                s -= A[i, c] * B[c, j]
            B[i, j] = s / A[i, i]
    return True


@numba.njit(cache=True, nogil=True)
def _inverse(M: np.ndarray, out: np.ndarray) -> bool:  # pragma: no cover
    """``out`` = the inverse of ``M`` (``M`` kept); False when singular."""
    out[:] = 0.0
    for i in range(M.shape[0]):
        out[i, i] = 1.0
    return _lu_solve(M.copy(), out)


@numba.njit(cache=True, nogil=True)
def _moved_corners(R0: np.ndarray, p0: np.ndarray, times: np.ndarray, t_ref: float, v: np.ndarray, w: np.ndarray,
                   moving: bool) -> tuple[np.ndarray, np.ndarray, np.ndarray]:  # pragma: no cover
    """The body's rotation and position at each corner's instant (the pose moved from ``t_ref`` to
    it at ``v``, ``w`` when ``moving``) and its ``[Exp(ω dt) | J_l(ω dt) dt]``; corners of one
    instant (a set without row offsets) share them."""
    N = times.shape[0]
    R, p, chain = np.empty((N, 3, 3)), np.empty((N, 3)), np.zeros((N, 3, 6))
    for i in range(N):
        if not moving:
            R[i] = R0
            p[i] = p0
        elif i > 0 and times[i] == times[i - 1]:
            R[i], p[i], chain[i] = R[i - 1], p[i - 1], chain[i - 1]
        else:
            dt = times[i] - t_ref
            exp_and_left_jacobian(w[0], w[1], w[2], dt, chain[i])
            for a in range(3):
                for b in range(3):
                    R[i, a, b] = chain[i, a, 0] * R0[0, b] + chain[i, a, 1] * R0[1, b] + chain[i, a, 2] * R0[2, b]
                p[i, a] = p0[a] + v[a] * dt
    return R, p, chain


@numba.njit(cache=True, nogil=True)
def reprojection(T: np.ndarray, points: np.ndarray, normalized: np.ndarray, which: np.ndarray, R_cw: np.ndarray,
                 t_cw: np.ndarray, focal: np.ndarray, times: np.ndarray, t_ref: float, v: np.ndarray, w: np.ndarray,
                 moving: bool, jacobian: bool) -> tuple[np.ndarray, np.ndarray]:  # pragma: no cover
    """Residuals (2N,) px of the packed corner sets and (``jacobian``) their Jacobian (2N, 12
    when ``moving`` else 6; each corner moved to its own instant ``times[i]``), as
    ``reprojection_jacobian_px`` / ``reprojection_residuals_px``: a
    corner behind its camera gets ``BEHIND_PX`` and a zero row; without the Jacobian, a non-finite
    residual becomes ``BEHIND_PX`` too."""
    N = points.shape[0]
    cols = 12 if moving else 6
    R, p, chain = _moved_corners(T[:3, :3], T[:3, 3], times, t_ref, v, w, moving)
    r = np.empty(2 * N)
    H = np.zeros((2 * N if jacobian else 0, cols))
    q, pw, pc, d_pw, d_th = np.empty(3), np.empty(3), np.empty(3), np.empty((2, 3)), np.empty((2, 3))
    for i in range(N):
        k = which[i]
        X, Ri, Rc = points[i], R[i], R_cw[k]
        for a in range(3):
            q[a] = Ri[a, 0] * X[0] + Ri[a, 1] * X[1] + Ri[a, 2] * X[2]
        for a in range(3):
            pw[a] = q[a] + p[i, a]
        for a in range(3):
            pc[a] = Rc[a, 0] * pw[0] + Rc[a, 1] * pw[1] + Rc[a, 2] * pw[2] + t_cw[k, a]
        z, f = pc[2], focal[k]
        if not z > 1e-6:
            r[2 * i], r[2 * i + 1] = BEHIND_PX, BEHIND_PX
            continue
        u, vv = pc[0] / z, pc[1] / z
        r[2 * i], r[2 * i + 1] = (u - normalized[i, 0]) * f, (vv - normalized[i, 1]) * f
        if not jacobian:
            continue
        scale = f / z
        for a in range(3):
            d_pw[0, a] = (Rc[0, a] - u * Rc[2, a]) * scale
            d_pw[1, a] = (Rc[1, a] - vv * Rc[2, a]) * scale
        for b in range(2):   # q x d_pw[b]: the rotation's columns
            d_th[b, 0] = q[1] * d_pw[b, 2] - q[2] * d_pw[b, 1]
            d_th[b, 1] = q[2] * d_pw[b, 0] - q[0] * d_pw[b, 2]
            d_th[b, 2] = q[0] * d_pw[b, 1] - q[1] * d_pw[b, 0]
        dt = times[i] - t_ref
        for b in range(2):
            row = H[2 * i + b]
            for a in range(3):
                row[a] = d_pw[b, a]
                if moving:
                    row[6 + a] = d_pw[b, a] * dt
                    row[3 + a] = d_th[b, 0] * chain[i, 0, a] + d_th[b, 1] * chain[i, 1, a] + d_th[b, 2] * chain[i, 2, a]
                    row[9 + a] = (d_th[b, 0] * chain[i, 0, 3 + a] + d_th[b, 1] * chain[i, 1, 3 + a]
                                  + d_th[b, 2] * chain[i, 2, 3 + a])
                else:
                    row[3 + a] = d_th[b, a]
    if not jacobian:
        for i in range(2 * N):   # as np.nan_to_num(r, nan=BEHIND_PX)
            if math.isnan(r[i]):
                r[i] = BEHIND_PX
            elif math.isinf(r[i]):
                r[i] = _LARGEST if r[i] > 0 else -_LARGEST
    return r, H


@numba.njit(cache=True, nogil=True)
def _perturbed(T0: np.ndarray, delta: np.ndarray, out: np.ndarray) -> None:  # pragma: no cover
    """``out`` (4x4) = ``T0`` moved by the world-frame increment ``delta[:6] = [δp, δθ]``
    (``reprojection.perturbed``)."""
    chain = np.empty((3, 6))
    exp_and_left_jacobian(delta[3], delta[4], delta[5], 1.0, chain)
    out[:] = 0.0
    out[3, 3] = 1.0
    for a in range(3):
        for b in range(3):
            out[a, b] = chain[a, 0] * T0[0, b] + chain[a, 1] * T0[1, b] + chain[a, 2] * T0[2, b]
        out[a, 3] = T0[a, 3] + delta[a]


@numba.njit(cache=True, nogil=True)
def calibration_discount(T: np.ndarray, R_cw: np.ndarray, t_cw: np.ndarray, info_add: np.ndarray, sigma_t: float,
                         sigma_phi: float, sigma_s: float, sigma_w: float, K: np.ndarray) -> bool:  # pragma: no cover
    """What one camera frame's corners tell about the pose, less what its camera's calibration
    error could make them say: ``K`` (written into ``K``, 6x6), with the corners' information
    becoming ``H^T W H - C K C^T`` (``C = H^T W H_pose``); False with the camera taken as exact
    (``sigma_t`` or ``sigma_phi`` zero, or a singular matrix). ``T``: the body's pose (4x4);
    ``R_cw``, ``t_cw``: the packed sets' cameras (the first one's is used: all sets of one update
    come from one camera frame); ``info_add``: the corners' information (its 6x6 pose block is
    ``H_pose^T W H_pose``); ``sigma_t`` (m), ``sigma_phi`` (rad): the camera's position and
    orientation error, 1 sigma per axis; ``sigma_s``: its scale error (a fraction, 1 sigma; 0: none);
    ``sigma_w`` (rad): the body's wobble, 1 sigma per axis (0: none).

    A camera whose true pose is off from its extrinsics by ``ε = (δt, δφ)`` (world frame,
    rotation about its centre ``c``) sees the body as if it had moved by ``δp = -δt + [p - c]× δφ``,
    ``δθ = -δφ``: so every corner of its frame shares the error ``H_pose e``, ``e ~ N(0, Σ)`` with
    ``Σ = σ_t² diag(I, 0) + σ_φ² A Aᵀ``, ``A = [[p - c]×; -I]``. The corners' covariance is then
    ``W⁻¹ + H_pose Σ H_poseᵀ``, whose inverse (Woodbury) is ``W - W H_pose K H_poseᵀ W`` with
    ``K = (Σ⁻¹ + H_poseᵀ W H_pose)⁻¹``; ``K H_poseᵀ W r`` is the error ``e`` that best explains
    residuals ``r``. ``Σ⁻¹`` in closed form (its Schur complement on the rotation block is
    ``σ_t² I``): ``[[I, D], [Dᵀ, σ_t²/σ_φ² I + DᵀD]] / σ_t²`` with ``D = [p - c]×``. A scale error
    ``s`` of the camera (its focal length off by that fraction) moves the body along the camera's
    optical axis ``z`` by ``s`` times its depth: ``Σ`` gains ``σ_s² u uᵀ`` with ``u = [z (z · (p - c)); 0]``,
    taken into ``Σ⁻¹`` by Sherman-Morrison. A wobble of the body (a robot on an uneven floor: roll
    and pitch ``δθ`` about the world's x and y, about the floor point ``h`` below it, ``h`` the body's
    height above the world's z = 0) adds ``σ_w² (u_x u_xᵀ + u_y u_yᵀ)`` with ``u_x = [-h y; x]``,
    ``u_y = [h x; y]`` (``δp = δθ × h z``), two more Sherman-Morrison updates."""
    if sigma_t <= 0.0 or sigma_phi <= 0.0:
        return False
    d = np.empty(3)
    for a in range(3):   # p - c, with c = -R_cwᵀ t_cw
        d[a] = T[a, 3] + R_cw[0, 0, a] * t_cw[0, 0] + R_cw[0, 1, a] * t_cw[0, 1] + R_cw[0, 2, a] * t_cw[0, 2]
    D = np.array([[0.0, -d[2], d[1]], [d[2], 0.0, -d[0]], [-d[1], d[0], 0.0]])
    M = np.zeros((6, 6))
    ratio2, scale = (sigma_t / sigma_phi) ** 2, 1.0 / sigma_t**2
    for a in range(3):
        M[a, a] = 1.0
        for b in range(3):
            M[a, 3 + b] = D[a, b]
            M[3 + a, b] = D[b, a]
            M[3 + a, 3 + b] = D[0, a] * D[0, b] + D[1, a] * D[1, b] + D[2, a] * D[2, b]
        M[3 + a, 3 + a] += ratio2
    M *= scale
    if sigma_s > 0.0:   # Σ⁻¹ - (Σ⁻¹u)(Σ⁻¹u)ᵀ σ_s² / (1 + σ_s² uᵀΣ⁻¹u), u = [z (z · d); 0]
        u = np.zeros(6)
        depth = R_cw[0, 2, 0] * d[0] + R_cw[0, 2, 1] * d[1] + R_cw[0, 2, 2] * d[2]
        for a in range(3):
            u[a] = R_cw[0, 2, a] * depth
        v = _matvec(M, u)
        factor = sigma_s**2 / (1.0 + sigma_s**2 * (u[0] * v[0] + u[1] * v[1] + u[2] * v[2]))
        for a in range(6):
            for b in range(6):
                M[a, b] -= v[a] * v[b] * factor
    if sigma_w > 0.0:   # Σ⁻¹ less the wobble's two directions, u_x = [-h y; x], u_y = [h x; y]
        for axis in range(2):
            u = np.zeros(6)
            u[1 - axis] = T[2, 3] if axis else -T[2, 3]
            u[3 + axis] = 1.0
            v = _matvec(M, u)
            factor = sigma_w**2 / (1.0 + sigma_w**2 * (u[0] * v[0] + u[1] * v[1] + u[3] * v[3] + u[4] * v[4]))
            for a in range(6):
                for b in range(6):
                    M[a, b] -= v[a] * v[b] * factor
    M += info_add[:6, :6]
    return _inverse(M, K)


@numba.njit(cache=True, nogil=True)
def _matvec(A: np.ndarray, x: np.ndarray) -> np.ndarray:  # pragma: no cover
    """``A x[:A.shape[1]]``."""
    out = np.zeros(A.shape[0])
    for i in range(A.shape[0]):
        for a in range(A.shape[1]):
            out[i] += A[i, a] * x[a]
    return out


@numba.njit(cache=True, nogil=True)
def _discounted(info_add: np.ndarray, grad: np.ndarray, K: np.ndarray) -> None:  # pragma: no cover
    """In place: ``info_add - C K Cᵀ`` and ``grad - C K grad[:6]``, with ``C = info_add[:, :6]``
    (the corners' information less what the camera's calibration error could explain)."""
    n = info_add.shape[0]
    CK = np.zeros((n, 6))
    for i in range(n):
        for a in range(6):
            for b in range(6):
                CK[i, a] += info_add[i, b] * K[b, a]
    g6 = grad[:6].copy()
    update = np.zeros((n, n))
    for i in range(n):
        for a in range(6):
            grad[i] -= CK[i, a] * g6[a]
            for j in range(n):
                update[i, j] += CK[i, a] * info_add[j, a]
    for i in range(n):
        for j in range(n):
            info_add[i, j] -= update[i, j]


@numba.njit(cache=True, nogil=True)
def _explained(H: np.ndarray, WH: np.ndarray, K: np.ndarray, x: np.ndarray) -> np.ndarray:  # pragma: no cover
    """``H[:, :6] K WH[:, :6]ᵀ x``: the part of residuals ``x`` that the camera's calibration
    error explains."""
    g = np.zeros(6)
    for i in range(H.shape[0]):
        for a in range(6):
            g[a] += WH[i, a] * x[i]
    e = _matvec(K, g)
    out = np.zeros(H.shape[0])
    for i in range(H.shape[0]):
        for a in range(6):
            out[i] += H[i, a] * e[a]
    return out


@numba.njit(cache=True, nogil=True)
def _normal_equations(H: np.ndarray, r: np.ndarray, explained: np.ndarray, delta: np.ndarray, huber: float,
                      inv_var: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:  # pragma: no cover
    """Huber weights on ``r - explained`` times each corner's inverse variance ``inv_var`` (N,),
    rows ``2i`` and ``2i + 1`` being corner ``i``: ``(W H, Hᵀ W H, (W H)ᵀ (H δ - r))``."""
    rows, n = H.shape
    WH = np.empty((rows, n))
    Hd_r = np.empty(rows)
    for i in range(rows):
        e = abs(r[i] - explained[i])
        weight = e if math.isnan(e) else min(huber / max(e, 1e-12), 1.0) * inv_var[i // 2]
        s = 0.0
        for a in range(n):
            WH[i, a] = weight * H[i, a]
            s += H[i, a] * delta[a]
        Hd_r[i] = s - r[i]
    info = np.zeros((n, n))
    grad = np.zeros(n)
    for i in range(rows):
        for a in range(n):
            grad[a] += WH[i, a] * Hd_r[i]
            for b in range(n):
                info[a, b] += H[i, a] * WH[i, b]
    return WH, info, grad


@numba.njit(cache=True, nogil=True)
def solve_update(T0: np.ndarray, P: np.ndarray, t_ref: float, v0: np.ndarray, w0: np.ndarray, points: np.ndarray,
                 normalized: np.ndarray, which: np.ndarray, R_cw: np.ndarray, t_cw: np.ndarray, focal: np.ndarray,
                 times: np.ndarray, moving: bool, iterations: int, huber: float, inv_var: np.ndarray, sigma_t: float,
                 sigma_phi: float, sigma_s: float, sigma_w: float) -> tuple:  # pragma: no cover
    """``PoseFilter._solve`` on packed corner sets: Gauss-Newton on the prior (``P``, the state at
    ``T0``, ``v0``, ``w0``, time ``t_ref``) plus the Huber-weighted corner residuals less what the
    camera's calibration error explains. Returns ``(status, δ (12,), information (12x12), the pose
    moved by δ (4x4), residuals px there (2N,), the posterior covariance (the information's
    inverse, symmetrised), whether that inverse exists)``; ``status`` is ``OK`` or which matrix
    was singular (the other results are then zeros)."""
    n = 12 if moving else 6
    rows = 2 * points.shape[0]
    delta, rhs, info = np.zeros(12), np.zeros(12), np.zeros((12, 12))
    T, P_post, r = T0.copy(), np.zeros((12, 12)), np.zeros(rows)
    info_prior = np.empty((12, 12))
    if not _inverse(P, info_prior):
        return SINGULAR_PRIOR, delta, info, T, r, P_post, False
    explained = np.zeros(rows)
    K = np.zeros((6, 6))
    have_K = False
    H, WH = np.zeros((rows, n)), np.zeros((rows, n))
    for _ in range(iterations):
        r, H = reprojection(T, points, normalized, which, R_cw, t_cw, focal, times, t_ref, v0 + delta[6:9],
                            w0 + delta[9:12], moving, True)
        WH, info_add, grad = _normal_equations(H, r, explained, delta, huber, inv_var)
        have_K = calibration_discount(T, R_cw, t_cw, info_add, sigma_t, sigma_phi, sigma_s, sigma_w, K)
        if have_K:
            _discounted(info_add, grad, K)
        info[:] = info_prior
        info[:n, :n] += info_add
        rhs[:n] = grad
        step = rhs.reshape(12, 1).copy()
        if not _lu_solve(info.copy(), step):
            return SINGULAR_STEP, np.zeros(12), np.zeros((12, 12)), T0.copy(), np.zeros(rows), P_post, False
        step = step.ravel() - delta
        delta = delta + step
        _perturbed(T0, delta, T)
        if have_K:   # the calibration error that explains the residuals there
            explained = _explained(H, WH, K, r + _matvec(H, step))
    r, _ = reprojection(T, points, normalized, which, R_cw, t_cw, focal, times, t_ref, v0 + delta[6:9],
                        w0 + delta[9:12], moving, False)
    if have_K:
        r = r - _explained(H, WH, K, r)
    post_ok = _inverse(info, P_post)
    P_post = (P_post + P_post.T) / 2.0
    return OK, delta, info, T, r, P_post, post_ok


@numba.njit(cache=True, nogil=True)
def _joint_residuals(T_init: np.ndarray, x: np.ndarray, points: np.ndarray, normalized: np.ndarray,
                     which: np.ndarray, R_cw: np.ndarray, t_cw: np.ndarray, focal: np.ndarray, times: np.ndarray,
                     t_ref: float, noise_px: float, sigma_v: float, sigma_w: float,
                     jacobian: bool) -> tuple[np.ndarray, np.ndarray]:  # pragma: no cover
    """The joint fit's residuals at the increment ``x`` (6: pose; 12: and velocities), in units of their
    noise (the corners' over ``noise_px``, then with velocities ``v / sigma_v``, ``w / sigma_w``), and
    (``jacobian``) their Jacobian in ``x``: the rotation columns chained through the left Jacobian of the
    finite increment ``x[3:6]`` (``multi_view_fit.solve_joint``)."""
    n = x.shape[0]
    moving = n == 12
    T = np.empty((4, 4))
    _perturbed(T_init, x, T)
    v, w = np.zeros(3), np.zeros(3)
    if moving:
        v[:], w[:] = x[6:9], x[9:12]
    r, H = reprojection(T, points, normalized, which, R_cw, t_cw, focal, times, t_ref if moving else 0.0, v, w,
                        moving, jacobian)
    rows = r.shape[0]
    f = np.empty(rows + (6 if moving else 0))
    for i in range(rows):   # as reprojection without its Jacobian: a NaN residual becomes BEHIND_PX
        e = r[i]
        if math.isnan(e):
            e = BEHIND_PX
        elif math.isinf(e):
            e = _LARGEST if e > 0 else -_LARGEST
        f[i] = e / noise_px
    if moving:
        for a in range(3):
            f[rows + a], f[rows + 3 + a] = v[a] / sigma_v, w[a] / sigma_w
    J = np.zeros((f.shape[0] if jacobian else 0, n))
    if jacobian:
        chain = np.empty((3, 6))
        exp_and_left_jacobian(x[3], x[4], x[5], 1.0, chain)   # chain[:, 3:] = J_l(x[3:6])
        for i in range(rows):
            for a in range(n):
                J[i, a] = H[i, a] / noise_px
            for a in range(3):
                J[i, 3 + a] = (H[i, 3] * chain[0, 3 + a] + H[i, 4] * chain[1, 3 + a]
                               + H[i, 5] * chain[2, 3 + a]) / noise_px
        if moving:
            for a in range(3):
                J[rows + a, 6 + a], J[rows + 3 + a, 9 + a] = 1.0 / sigma_v, 1.0 / sigma_w
    return f, J


@numba.njit(cache=True, nogil=True)
def _soft_l1_cost(f: np.ndarray, f_scale: float) -> float:  # pragma: no cover
    """``Σ f_scale² (sqrt(1 + (f / f_scale)²) - 1)``: the soft-L1 cost (scipy's ``least_squares``, halved)."""
    cost = 0.0
    for e in f:
        cost += math.sqrt(1.0 + (e / f_scale) ** 2) - 1.0
    return cost * f_scale * f_scale


@numba.njit(cache=True, nogil=True)
def joint_fit(T_init: np.ndarray, n: int, points: np.ndarray, normalized: np.ndarray, which: np.ndarray,
              R_cw: np.ndarray, t_cw: np.ndarray, focal: np.ndarray, times: np.ndarray, t_ref: float, noise_px: float,
              f_scale: float, sigma_v: float, sigma_w: float, max_steps: int) -> tuple:  # pragma: no cover
    """The soft-L1 least-squares fit of ``multi_view_fit.solve_joint`` (the minimum scipy's
    ``least_squares(method="trf", loss="soft_l1")`` finds): Gauss-Newton on the increment ``x`` (``n`` = 6:
    the pose; 12: and velocities) from zero, with the loss's curvature in the normal equations as scipy
    puts it (``ρ' + 2 ρ'' f²`` weighting each row of ``JᵀJ``), each step halved while it does not lower
    the cost (or, at the cost's rounding, keeps it with a step under half the last), until no step does
    (or ``max_steps``). Returns
    ``(ok, x, covariance, residuals)``: the covariance ``(JsᵀJs)⁻¹`` with ``Js`` the Jacobian scaled as
    scipy scales it for the loss (each row by ``(1 + (f / f_scale)²)^-3/4``), the residuals in units of
    their noise; ``ok`` False when a matrix is singular or the fit is not finite."""
    x = np.zeros(n)
    f, J = _joint_residuals(T_init, x, points, normalized, which, R_cw, t_cw, focal, times, t_ref, noise_px,
                            sigma_v, sigma_w, True)
    cost, last_size = _soft_l1_cost(f, f_scale), math.inf
    for _ in range(max_steps):
        A, step = np.zeros((n, n)), np.zeros((n, 1))
        for i in range(f.shape[0]):   # the gradient Jᵀ ρ' f, the loss's curvature ρ' + 2 ρ'' f² on JᵀJ
            t = 1.0 + (f[i] / f_scale) ** 2
            gradient, curvature = f[i] / math.sqrt(t), max(t**-1.5, _EPS)
            for a in range(n):
                step[a, 0] -= gradient * J[i, a]
                for b in range(n):
                    A[a, b] += curvature * J[i, a] * J[i, b]
        if not _lu_solve(A, step):
            return False, x, np.zeros((n, n)), f
        scale, moved = 1.0, False
        for _halving in range(30):
            x_new = x + scale * step[:, 0]
            if np.all(x_new == x):
                break
            f_new, _ = _joint_residuals(T_init, x_new, points, normalized, which, R_cw, t_cw, focal, times, t_ref,
                                        noise_px, sigma_v, sigma_w, False)
            cost_new = _soft_l1_cost(f_new, f_scale)
            # at the cost's rounding a full step that keeps it is taken while the steps still shrink fast
            size = np.abs(step).max()
            if cost_new < cost or (cost_new == cost and scale == 1.0 and size < 0.5 * last_size):
                x, cost, moved, last_size = x_new, cost_new, True, size
                break
            scale *= 0.5
        if not moved:
            break
        f, J = _joint_residuals(T_init, x, points, normalized, which, R_cw, t_cw, focal, times, t_ref, noise_px,
                                sigma_v, sigma_w, True)
    if not np.all(np.isfinite(x)):
        return False, x, np.zeros((n, n)), f
    information = np.zeros((n, n))
    for i in range(f.shape[0]):   # JsᵀJs, Js: scipy's scaling of the Jacobian for the loss, at the solution
        s2 = max((1.0 + (f[i] / f_scale) ** 2) ** -1.5, _EPS)
        for a in range(n):
            for b in range(n):
                information[a, b] += s2 * J[i, a] * J[i, b]
    covariance = np.empty((n, n))
    ok = _inverse(information, covariance)
    return ok, x, covariance, f


@numba.njit(cache=True, nogil=True)
def moved_pose(T: np.ndarray, v: np.ndarray, w: np.ndarray, dt: float) -> np.ndarray:  # pragma: no cover
    """The pose after ``dt`` seconds at constant world-frame velocities ``v``, ``w``
    (``reprojection.moved_pose``)."""
    delta = np.empty(6)
    for a in range(3):
        delta[a] = v[a] * dt
        delta[3 + a] = w[a] * dt
    out = np.empty((4, 4))
    _perturbed(T, delta, out)
    return out


@numba.njit(cache=True, nogil=True)
def predicted_covariance(P: np.ndarray, dt: float, A: np.ndarray, B: np.ndarray,
                         C: np.ndarray) -> np.ndarray:  # pragma: no cover
    """``F P Fᵀ + A |dt|³/3 + B dt²/2 + C |dt|`` with ``F = I + dt [[0, I], [0, 0]]`` (the
    constant-velocity transition of ``corner_filter.PoseFilter.predict``)."""
    out = P.copy()
    for a in range(6):
        for b in range(12):
            out[a, b] += dt * P[6 + a, b]
    for a in range(12):
        for b in range(6):
            out[a, b] += dt * out[a, 6 + b]
    adt = abs(dt)
    ka, kb, kc = adt**3 / 3.0, dt * dt / 2.0, adt
    for a in range(12):
        for b in range(12):
            out[a, b] += ka * A[a, b] + kb * B[a, b] + kc * C[a, b]
    return out


@numba.njit(cache=True, nogil=True)
def largest_eigenvalue(A: np.ndarray, at: int) -> float:  # pragma: no cover
    """The largest eigenvalue of the symmetric 3x3 block ``A[at:at+3, at:at+3]`` (closed form: the
    trigonometric solution of its characteristic cubic)."""
    a, b, c = A[at, at], A[at + 1, at + 1], A[at + 2, at + 2]
    d, e, f = A[at, at + 1], A[at, at + 2], A[at + 1, at + 2]
    off = d * d + e * e + f * f
    if off == 0.0:
        return max(a, b, c)
    q = (a + b + c) / 3.0
    p = math.sqrt(((a - q) ** 2 + (b - q) ** 2 + (c - q) ** 2 + 2.0 * off) / 6.0)
    a, b, c = (a - q) / p, (b - q) / p, (c - q) / p   # B = (A - q I) / p
    d, e, f = d / p, e / p, f / p
    half_det = (a * (b * c - f * f) - d * (d * c - f * e) + e * (d * f - b * e)) / 2.0
    return q + 2.0 * p * math.cos(math.acos(min(1.0, max(-1.0, half_det))) / 3.0)


@numba.njit(cache=True, nogil=True)
def spread_m(covariance: np.ndarray, reach_m: float) -> float:  # pragma: no cover
    """How far (1 sigma, metres) a body's corners may be from where a pose of ``covariance`` (6x6
    or more, ``[δp (m), δθ (rad)]`` first) puts them: the largest position spread plus the largest
    rotation spread times ``reach_m``, the body's farthest corner from its origin."""
    return (math.sqrt(max(largest_eigenvalue(covariance, 0), 0.0))
            + reach_m * math.sqrt(max(largest_eigenvalue(covariance, 3), 0.0)))


@numba.njit(cache=True, nogil=True)
def projected_spread_px(covariance: np.ndarray, T_world_cube: np.ndarray, T_world_cam: np.ndarray, focal_px: float,
                        reach_m: float) -> float:  # pragma: no cover
    """:func:`spread_m` seen from the camera at ``T_world_cam``, pixels: over the body's depth there (its
    origin's, at ``T_world_cube``) times ``focal_px``; 0 for a body less than a millimetre in front."""
    depth_m = 0.0
    for a in range(3):
        depth_m += T_world_cam[a, 2] * (T_world_cube[a, 3] - T_world_cam[a, 3])
    if depth_m <= 1e-3:
        return 0.0
    return focal_px * spread_m(covariance, reach_m) / depth_m


def compile_filter_kernels() -> None:
    """Compile the kernels (or load them from numba's on-disk cache, ``__pycache__``) for the
    argument types the filter passes, on a made-up sighting, so that no sighting pays it: called
    before the first sighting (:class:`cubetrack.fuse.fusion.FilterFusion` does; once loaded, a
    call costs microseconds), with the association's (:func:`cubetrack.estimate.match.compile_match_kernels`),
    as the detector's (:func:`cubetrack.detect.detector.compile_kernels`: a first compile logged at INFO,
    Ctrl-C while numba loads them a KeyboardInterrupt)."""
    compile_kernels("filter's kernels", _run_kernels, compile_match_kernels)


def _run_kernels() -> None:
    """Each kernel once, with the argument types the filter passes."""
    T, P, noise = np.eye(4), np.eye(12), np.eye(12)
    T[2, 3] = 2.0
    T.setflags(write=False)      # the filter's pose and process noise are read-only arrays (another numba type)
    noise.setflags(write=False)
    points = np.array([[-0.02, -0.02, 0.0], [0.02, -0.02, 0.0], [0.02, 0.02, 0.0], [-0.02, 0.02, 0.0]])
    normalized = points[:, :2] / 2.0
    which, R_cw, t_cw = np.zeros(4, dtype=np.int64), np.eye(3)[None].copy(), np.zeros((1, 3))
    for moving in (False, True):
        solve_update(T, P, 0.0, np.zeros(3), np.zeros(3), points, normalized, which, R_cw, t_cw, np.ones(1),
                     np.full(4, 0.01 if moving else 0.0), moving, 2, 1.5, np.full(4, 4.0), 0.002, 0.002, 0.005, 0.01)
    for n in (6, 12):   # the joint fit's start pose (multi_view_fit) is a writable array
        joint_fit(T.copy(), n, points, normalized, which, R_cw, t_cw, np.ones(1), np.zeros(4), 0.0, 0.5, 3.0, 1.0,
                  1.0, 2)
    moved_pose(T, np.zeros(3), np.zeros(3), 0.01)
    corner_noise_factors(points[:, :2] * 1000.0 + 100.0, [6])   # each corner's noise (the association's corner sets)
    for moving in (False, True):   # as a camera's term sample calls it (fuse.camera_corrections.term_observed)
        reprojection(T.copy(), points, normalized, which, R_cw, t_cw, np.ones(1), np.zeros(4), 0.0, np.zeros(3),
                     np.zeros(3), moving, True)
    exp_and_left_jacobian(0.0, 0.0, 1.0, 0.01, np.empty((3, 6)))   # as estimate.reprojection calls it
    spread_m(P, 0.1)
    for pose in (T, T.copy()):   # the filter's read-only pose, a corrected camera's array
        projected_spread_px(P, T, pose, 500.0, 0.1)
    predicted_covariance(P, 0.01, noise, noise, noise)
