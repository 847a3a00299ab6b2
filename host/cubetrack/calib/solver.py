"""The bundle adjustment's least-squares core: camera poses, camera intrinsics, body poses and
the pose and size of every marker on a body, from marker corners observed in pixels.

Used by the extrinsics refinement (:mod:`cubetrack.calib.bundle`) and the body calibration
(:mod:`cubetrack.calib.body`); both build :class:`Observations` and a start :class:`Model`,
choose the free blocks and their priors (:class:`Freedom`) and call :func:`solve`.

The measurement model of one body corner ``u`` (a corner of a unit marker, TL TR BR BL) of
marker ``m`` seen by camera ``c`` at instant ``k``::

    P = R_m (s_m u) + t_m                     marker pose and size on the body (body frame)
    X = exp(ω dt) R_k (1 + σ_r) P + t_k + v dt    body pose at the instant, moved to the frame's
                                              time (the constant-velocity model of
                                              :mod:`cubetrack.estimate.reprojection`), σ_r the
                                              body's free scale (``free_cube_scale``)
    pixel = project(K_c, dist_c, R_c^T (X - t_c))   OpenCV's lens model (cv2.projectPoints)

and of a static world point ``X`` (a world marker's or a board's corner) just the last line.
With a continuous-time trajectory (``Observations.knot_alpha``, the body calibration's) the body
poses are knots on a time grid instead of instants, and a corner exposed at the fraction ``α``
of the way from knot ``k`` to knot ``k + 1`` sees the body at the interpolated pose::

    R = exp(α log(R_{k+1} R_k^T)) R_k,   t = (1 - α) t_k + α t_{k+1}

(no velocity assumed); the knots are tied by a smoothness prior on the second differences of
their positions and rotations (``Freedom.accel_sigma_m_s2``, ``angular_accel_sigma_rad_s2``),
which also carries the trajectory across knots no corner sees.
Residuals are pixel errors over their noise, a soft-L1 loss over all of them; for ground robots
the body's height against one height per robot and its tilt from world up (or, with
``Freedom.floor_tilt_sigma_rad``, against a plane per robot through that height and its
normal, the plane's tilt from world level held by that prior); and priors: camera
poses (a weak gauge prior, or the extrinsics a body calibration starts from), intrinsics (the
camera_info they start from: focal length, principal point, k1, k2) and marker poses and sizes
(the nominal layout). Every Jacobian is analytic (cv2.projectPoints gives the lens model's) and
sparse: a corner depends on one camera, one instant and one marker.

Increments: poses move by world-frame (cameras, bodies) or body-frame (markers) increments
``[δp, δθ]``: ``R = exp(δθ) R0``, ``p = p0 + δp``; focal lengths relatively, ``f = f0 (1 + δ)``;
the principal point in units of the focal length, ``c = c0 + f0 δ``; k1 and k2 as they are; a
marker's size relatively.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np
from scipy.optimize import least_squares
from scipy.sparse import coo_matrix, csr_matrix, diags
from scipy.sparse.linalg import splu
from scipy.spatial.transform import Rotation

from cubetrack.core.layout import marker_corners_m

UNIT_CORNERS = marker_corners_m(1.0)  # (4, 3) corners of a unit marker, TL TR BR BL
INTRINSIC_NAMES = ("fx", "fy", "cx", "cy", "k1", "k2")  # the refined intrinsics, in column order
_BEHIND_PX = 1e3  # residual (in noise units) of a point behind its camera


@dataclass(frozen=True, slots=True, eq=False)
class Observations:
    """Corner observations as flat arrays.

    Body corners (one row each): camera ``cam``, instant ``inst``, ``marker`` (index into the
    model's markers) and its ``corner`` (0..3: TL TR BR BL), ``pixels`` (N, 2) observed;
    ``motion_R`` (N, 3, 3), ``motion_t`` (N, 3): the body's motion from the instant's time to the
    frame's, ``exp(ω dt)`` and ``v dt``. ``robot`` (K,) of each instant, ``robots`` how many.
    World points: ``world_cam`` (M,), ``world_points`` (M, 3) metres, ``world_pixels`` (M, 2).
    ``dt_s`` (N,): each body corner's time from its instant (seconds; None: all at the instant).
    A continuous-time trajectory: ``knot_alpha`` (N,) where between knot ``inst`` and the next
    the corner was exposed (0..1; ``motion_R``/``motion_t`` are then unused), ``knot_triples``
    (S, 3) consecutive knots the smoothness prior ties, ``knot_spacing_s`` their spacing.
    """

    cam: np.ndarray
    inst: np.ndarray
    marker: np.ndarray
    corner: np.ndarray
    pixels: np.ndarray
    motion_R: np.ndarray
    motion_t: np.ndarray
    robot: np.ndarray
    robots: int
    world_cam: np.ndarray
    world_points: np.ndarray
    world_pixels: np.ndarray
    dt_s: np.ndarray | None = None
    knot_alpha: np.ndarray | None = None
    knot_triples: np.ndarray | None = None
    knot_spacing_s: float = 0.0


@dataclass(frozen=True, slots=True, eq=False)
class Model:
    """Everything the observations depend on: ``T_cams`` (C, 4, 4) camera poses in the world,
    ``K`` (C, 3, 3) and ``dist`` (C, D) their intrinsics, ``T_bodies`` (K, 4, 4) the body pose
    at each instant, ``T_body_markers`` (G, 4, 4) and ``sizes_m`` (G,) the markers on the bodies
    (``marker_robot`` (G,): whose body) and ``scales`` (robots,) each body's scale (1 unless
    ``free_cube_scale``)."""

    T_cams: np.ndarray
    K: np.ndarray
    dist: np.ndarray
    T_bodies: np.ndarray
    T_body_markers: np.ndarray
    sizes_m: np.ndarray
    marker_robot: np.ndarray
    scales: np.ndarray

    def replace(self, **changes: Any) -> Model:
        values = {name: getattr(self, name) for name in self.__slots__}
        values.update(changes)
        return Model(**values)


@dataclass(frozen=True, slots=True, eq=False)
class PosePrior:
    """Poses (n, 4, 4) held near ``T`` with ``sigma_m`` (position) and ``sigma_rad`` (rotation)."""

    T: np.ndarray
    sigma_m: float
    sigma_rad: float


@dataclass(frozen=True, slots=True, eq=False)
class IntrinsicsPrior:
    """Intrinsics held near ``K`` (C, 3, 3), ``dist`` (C, D): focal lengths within
    ``focal_rel`` (relative), the principal point within ``principal_px``, k1 and k2 within
    ``k1``, ``k2`` (1 sigma). Other distortion coefficients stay as they start."""

    K: np.ndarray
    dist: np.ndarray
    focal_rel: float
    principal_px: float
    k1: float
    k2: float


@dataclass(frozen=True, slots=True, eq=False)
class BodyPrior:
    """Markers held near their nominal poses ``T`` (G, 4, 4) and sizes ``sizes_m`` (G,):
    ``sigma_m``, ``sigma_rad`` and the relative size ``size_rel`` (1 sigma)."""

    T: np.ndarray
    sizes_m: np.ndarray
    sigma_m: float
    sigma_rad: float
    size_rel: float


@dataclass(frozen=True, slots=True, eq=False)
class Freedom:
    """What a solve may change and how it is held: cameras (``cameras``; ``camera_prior`` None =
    no prior), intrinsics (``intrinsics`` prior, None = fixed), markers (``body`` prior, None =
    fixed), each body's scale (``free_scale``); the body poses are always free. Noise and
    loss: ``corner_noise_px``, ``world_noise_px``, ``f_scale_px``, ``motion_noise_px_per_s`` (a body
    corner's noise grows with its time from the instant, ``sqrt(corner_noise_px^2 + (motion_noise_px_per_s
    dt)^2)``: the constant-velocity motion between an instant's frames misses turns and vibration);
    ground robots: ``height_sigma_m``
    (0 = no common height), ``upright_sigma_rad`` (0 = no upright prior), ``floor_tilt_sigma_rad``
    (the floor the robot drives on is a plane that may tilt from world level by this much, 1
    sigma: the height is taken along it and the upright prior holds the body to its normal; 0 =
    the floor is level in the world frame); ``max_nfev``; a
    continuous-time trajectory's smoothness: ``accel_sigma_m_s2``, ``angular_accel_sigma_rad_s2``
    (1 sigma of the second difference of the knots' positions and rotations over the squared
    knot spacing)."""

    cameras: bool = True
    camera_prior: PosePrior | None = None
    intrinsics: IntrinsicsPrior | None = None
    body: BodyPrior | None = None
    free_scale: bool = False
    corner_noise_px: float = 0.5
    world_noise_px: float = 0.5
    f_scale_px: float = 1.5
    height_sigma_m: float = 0.0
    upright_sigma_rad: float = 0.0
    floor_tilt_sigma_rad: float = 0.0
    max_nfev: int = 60
    motion_noise_px_per_s: float = 0.0
    accel_sigma_m_s2: float = 10.0
    angular_accel_sigma_rad_s2: float = 100.0


def apply_increments(T0: np.ndarray, x: np.ndarray) -> np.ndarray:
    """(n, 4, 4) poses moved by (n, 6) increments [δp, δθ]: ``R = exp(δθ) R0``, ``p = p0 + δp``."""
    out = T0.copy()
    out[:, :3, :3] = Rotation.from_rotvec(x[:, 3:6]).as_matrix() @ T0[:, :3, :3]
    out[:, :3, 3] = T0[:, :3, 3] + x[:, :3]
    return out


def pose_offsets(T: np.ndarray, T_ref: np.ndarray) -> np.ndarray:
    """(n, 6) [p - p_ref, log(R R_ref^T)] of (n, 4, 4) poses from their references."""
    rot = Rotation.from_matrix(T[:, :3, :3] @ np.transpose(T_ref[:, :3, :3], (0, 2, 1))).as_rotvec()
    return np.concatenate([T[:, :3, 3] - T_ref[:, :3, 3], rot], axis=1)


def skew(v: np.ndarray) -> np.ndarray:
    """(N, 3, 3) cross-product matrices of (N, 3) vectors."""
    out = np.zeros(v.shape[:-1] + (3, 3))
    out[..., 0, 1], out[..., 0, 2] = -v[..., 2], v[..., 1]
    out[..., 1, 0], out[..., 1, 2] = v[..., 2], -v[..., 0]
    out[..., 2, 0], out[..., 2, 1] = -v[..., 1], v[..., 0]
    return out


def padded_dist(dist: np.ndarray) -> np.ndarray:
    """Distortion coefficients as OpenCV takes them (at least k1 k2 p1 p2 k3)."""
    dist = np.asarray(dist, float).ravel()
    return np.concatenate([dist, np.zeros(max(0, 5 - len(dist)))])


def project(points_cam: np.ndarray, K: np.ndarray, dist: np.ndarray,
            with_jac: bool = False) -> tuple[np.ndarray, np.ndarray | None, np.ndarray]:
    """Pixels (N, 2) of points (N, 3) in a camera's frame through OpenCV's lens model; with
    ``with_jac`` also d pixel / d [point, fx, fy, cx, cy, dist...] (N, 2, 7 + D). Returns
    (pixels, jacobian or None, in front): points within 1 µm of the image plane or behind it
    get NaN pixels and a zero Jacobian."""
    n = len(points_cam)
    front = points_cam[:, 2] > 1e-6
    pixels = np.full((n, 2), np.nan)
    jac = np.zeros((n, 2, 7 + len(dist))) if with_jac else None
    if front.any():
        zero = np.zeros(3)
        uv, J = cv2.projectPoints(points_cam[front].astype(np.float64), zero, zero, K, dist)
        pixels[front] = uv.reshape(-1, 2)
        if jac is not None:  # with_jac
            J = J.reshape(-1, 2, J.shape[1])
            jac[front] = J[:, :, 3:]  # d/d tvec = d/d point; then f, c, dist
    return pixels, jac, front


def body_points(obs: Observations, model: Model) -> np.ndarray:
    """(N, 3) the observed corners in their body's frame (marker pose and size, body scale)."""
    T_m = model.T_body_markers[obs.marker]
    local = UNIT_CORNERS[obs.corner] * model.sizes_m[obs.marker][:, None]
    P = np.einsum("nij,nj->ni", T_m[:, :3, :3], local) + T_m[:, :3, 3]
    return P * model.scales[model.marker_robot[obs.marker]][:, None]


def corner_body_poses(obs: Observations, model: Model) -> tuple[np.ndarray, np.ndarray]:
    """(N, 3, 3) rotations and (N, 3) positions of the body when each corner was exposed: its
    instant's pose moved by ``motion_R``/``motion_t``, or (``knot_alpha``) interpolated between
    two knots of the trajectory."""
    R0, p0 = model.T_bodies[obs.inst, :3, :3], model.T_bodies[obs.inst, :3, 3]
    if obs.knot_alpha is None:
        return obs.motion_R @ R0, p0 + obs.motion_t
    return interpolated_poses(model.T_bodies[obs.inst], model.T_bodies[obs.inst + 1], obs.knot_alpha)


def interpolated_poses(T0: np.ndarray, T1: np.ndarray, alpha: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(n, 3, 3) rotations and (n, 3) positions the fractions ``alpha`` (n,) of the way from the
    poses T0 to T1 (n, 4, 4): ``exp(α log(R1 R0^T)) R0`` and ``(1 - α) p0 + α p1``."""
    al = np.asarray(alpha, float)[:, None]
    R0, p0 = T0[:, :3, :3], T0[:, :3, 3]
    step = Rotation.from_matrix(T1[:, :3, :3] @ np.transpose(R0, (0, 2, 1))).as_rotvec()
    return Rotation.from_rotvec(al * step).as_matrix() @ R0, (1 - al) * p0 + al * T1[:, :3, 3]


def corner_residuals_px(obs: Observations, model: Model) -> np.ndarray:
    """(N, 2) body-corner reprojection errors in pixels (NaN behind a camera)."""
    R, p = corner_body_poses(obs, model)
    X = np.einsum("nij,nj->ni", R, body_points(obs, model)) + p
    return _projected(model, obs.cam, X, False)[0] - obs.pixels


def world_residuals_px(obs: Observations, model: Model) -> np.ndarray:
    """(M, 2) world-point reprojection errors in pixels (NaN behind a camera)."""
    if not len(obs.world_cam):
        return np.zeros((0, 2))
    return _projected(model, obs.world_cam, obs.world_points, False)[0] - obs.world_pixels


def _projected(model: Model, cam: np.ndarray, X: np.ndarray,
               with_jac: bool) -> tuple[np.ndarray, np.ndarray | None, np.ndarray | None]:
    """Pixels (N, 2) of world points X seen by cameras ``cam``; with ``with_jac`` also
    d pixel / d X (N, 2, 3) and d pixel / d [fx, fy, cx, cy, dist...] (N, 2, 4 + D)."""
    Rc = model.T_cams[cam, :3, :3]
    pc = np.einsum("nji,nj->ni", Rc, X - model.T_cams[cam, :3, 3])
    n, D = len(X), model.dist.shape[1]
    pixels = np.full((n, 2), np.nan)
    dX = np.zeros((n, 2, 3)) if with_jac else None
    dI = np.zeros((n, 2, 4 + D)) if with_jac else None
    for c in np.unique(cam):
        rows = np.flatnonzero(cam == c)
        px, J, _front = project(pc[rows], model.K[c], model.dist[c], with_jac)
        pixels[rows] = px
        if dX is not None and dI is not None and J is not None:  # with_jac
            dX[rows] = J[:, :, :3] @ model.T_cams[c, :3, :3].T
            dI[rows] = J[:, :, 3:]
    return pixels, dX, dI


@dataclass(frozen=True, slots=True)
class _Layout:
    """Where each block's columns start in the parameter vector, and its size."""

    C: int
    K: int
    G: int
    R: int
    cams: int
    intr: int
    bodies: int
    heights: int
    slopes: int
    scales: int
    markers: int
    n: int


def _columns(obs: Observations, model: Model, free: Freedom) -> _Layout:
    C, K, G, R = len(model.T_cams), len(model.T_bodies), len(model.T_body_markers), obs.robots
    ground = free.height_sigma_m > 0 or free.upright_sigma_rad > 0
    sizes = [6 * C if free.cameras else 0, 6 * C if free.intrinsics is not None else 0, 6 * K,
             R if free.height_sigma_m > 0 else 0, 2 * R if ground and free.floor_tilt_sigma_rad > 0 else 0,
             R if free.free_scale else 0, 7 * G if free.body is not None else 0]
    starts = np.concatenate([[0], np.cumsum(sizes)])
    cams, intr, bodies, heights, slopes, scales, markers, n = (int(s) for s in starts)
    return _Layout(C, K, G, R, cams, intr, bodies, heights, slopes, scales, markers, n)


def solve(obs: Observations, model: Model, free: Freedom) -> Model:
    """Least-squares ``model`` for ``obs`` with the blocks and priors ``free`` gives (see the
    module docstring); returns the solved model (fixed blocks as they came)."""
    problem = _Problem(obs, model, free)
    L, sigma = problem.L, free.corner_noise_px
    if obs.knot_alpha is not None:  # thousands of knots: sparse direct steps (lsmr would crawl)
        knots = np.arange(L.bodies, L.bodies + 6 * L.K)
        order = np.r_[knots, np.setdiff1d(np.arange(L.n), knots)]  # the banded knots first, the few shared last
        return problem.unpack(levenberg_marquardt(problem.evaluate, np.zeros(L.n), free.f_scale_px / sigma,
                                                  free.max_nfev, order))

    def residuals(x: np.ndarray) -> np.ndarray:
        return problem.evaluate(x, False)[0]

    def jacobian(x: np.ndarray) -> csr_matrix:
        J = problem.evaluate(x, True)[1]
        assert J is not None  # with_jac
        return J

    result = least_squares(residuals, np.zeros(L.n), jac=jacobian,
                           method="trf", loss="soft_l1", f_scale=free.f_scale_px / sigma,
                           x_scale=np.full(L.n, 1e-3), max_nfev=free.max_nfev, tr_solver="lsmr")
    return problem.unpack(result.x)


class _Blocks:
    """The residuals of one evaluation and, ``with_jac``, their sparse Jacobian, block by block."""

    def __init__(self, with_jac: bool):
        self.with_jac = with_jac
        self.res: list[np.ndarray] = []
        self.rows: list[np.ndarray] = []
        self.cols: list[np.ndarray] = []
        self.vals: list[np.ndarray] = []
        self.row = 0

    def add(self, r: np.ndarray, parts: list[tuple[np.ndarray, np.ndarray]]) -> None:
        """Residuals r (n, k) and their Jacobian parts: (columns (n, w), values (n, k, w))."""
        n, k = r.shape
        self.res.append(r.ravel())
        if self.with_jac:
            base = self.row + k * np.arange(n)[:, None] + np.arange(k)[None, :]  # (n, k)
            for c, v in parts:
                w = c.shape[1]
                self.rows.append(np.broadcast_to(base[:, :, None], (n, k, w)).ravel())
                self.cols.append(np.broadcast_to(c[:, None, :], (n, k, w)).ravel())
                self.vals.append(v.ravel())
        self.row += n * k

    def result(self, columns: int) -> tuple[np.ndarray, csr_matrix | None]:
        r_all = np.concatenate(self.res)
        if not self.with_jac:
            return r_all, None
        J = coo_matrix((np.concatenate(self.vals), (np.concatenate(self.rows), np.concatenate(self.cols))),
                       shape=(self.row, columns))
        return r_all, J.tocsr()


class _Problem:
    """One solve's least-squares problem: the parameter vector's layout (:class:`_Layout`), the
    model it moves (:meth:`unpack`) and its weighted residuals and Jacobian (:meth:`evaluate`)."""

    def __init__(self, obs: Observations, model: Model, free: Freedom):
        self.obs, self.model, self.free = obs, model, free
        self.L = L = _columns(obs, model, free)
        sigma = free.corner_noise_px
        self.heights0 = np.array([np.median(model.T_bodies[obs.robot == j, 2, 3]) if (obs.robot == j).any() else 0.0
                                  for j in range(L.R)])
        # each robot's floor plane turns about the middle of its path (so its height and tilt are apart)
        self.xy0 = np.array([model.T_bodies[obs.robot == j, :2, 3].mean(axis=0) if (obs.robot == j).any()
                             else np.zeros(2) for j in range(L.R)])
        corner_sigma = np.full((len(obs.cam), 1), sigma)  # (N, 1) each body corner's noise
        if free.motion_noise_px_per_s > 0 and obs.dt_s is not None:
            corner_sigma = np.hypot(sigma, free.motion_noise_px_per_s * obs.dt_s)[:, None]
        self.corner_sigma = corner_sigma
        self.f0 = model.K[:, [0, 1], [0, 1]]  # (C, 2)
        self.fmean0 = self.f0.mean(axis=1)

    def unpack(self, x: np.ndarray) -> Model:
        model, free, L, f0, fmean0 = self.model, self.free, self.L, self.f0, self.fmean0
        changes = {"T_bodies": apply_increments(model.T_bodies, x[L.bodies:L.bodies + 6 * L.K].reshape(L.K, 6))}
        if free.cameras:
            changes["T_cams"] = apply_increments(model.T_cams, x[L.cams:L.cams + 6 * L.C].reshape(L.C, 6))
        if free.intrinsics is not None:
            d = x[L.intr:L.intr + 6 * L.C].reshape(L.C, 6)
            K = model.K.copy()
            K[:, 0, 0], K[:, 1, 1] = f0[:, 0] * (1 + d[:, 0]), f0[:, 1] * (1 + d[:, 1])
            K[:, 0, 2], K[:, 1, 2] = model.K[:, 0, 2] + fmean0 * d[:, 2], model.K[:, 1, 2] + fmean0 * d[:, 3]
            dist = model.dist.copy()
            dist[:, :2] += d[:, 4:6]
            changes.update(K=K, dist=dist)
        if free.free_scale:
            changes["scales"] = model.scales + x[L.scales:L.scales + L.R]
        if free.body is not None:
            d = x[L.markers:L.markers + 7 * L.G].reshape(L.G, 7)
            changes["T_body_markers"] = apply_increments(model.T_body_markers, d[:, :6])
            changes["sizes_m"] = model.sizes_m * (1 + d[:, 6])
        return model.replace(**changes)

    def evaluate(self, x: np.ndarray, with_jac: bool) -> tuple[np.ndarray, csr_matrix | None]:
        """The weighted residuals at ``x`` and, ``with_jac``, their sparse Jacobian."""
        m = self.unpack(x)
        blocks = _Blocks(with_jac)
        self._body_corners(m, blocks)
        self._world_points(m, blocks)
        self._trajectory(m, blocks)
        self._ground(m, x, blocks)
        self._priors(m, blocks)
        return blocks.result(self.L.n)

    def _cam_parts(self, m: Model, cam: np.ndarray, X: np.ndarray, A: np.ndarray, dI: np.ndarray,
                   scale: float | np.ndarray) -> list:
        """Jacobian parts of the cameras' poses and intrinsics (those that are free)."""
        free, L, f0, fmean0 = self.free, self.L, self.f0, self.fmean0
        parts = []
        if free.cameras:
            y = X - m.T_cams[cam, :3, 3]
            parts.append((L.cams + 6 * cam[:, None] + np.arange(6), np.concatenate([-A, A @ skew(y)], axis=2)))
        if free.intrinsics is not None:
            Jd = np.stack([dI[:, :, 0] * f0[cam, 0, None], dI[:, :, 1] * f0[cam, 1, None],
                           dI[:, :, 2] * fmean0[cam, None], dI[:, :, 3] * fmean0[cam, None],
                           dI[:, :, 4], dI[:, :, 5]], axis=2) / scale
            parts.append((L.intr + 6 * cam[:, None] + np.arange(6), Jd))
        return parts

    def _body_corners(self, m: Model, blocks: _Blocks) -> None:
        obs, free, L, corner_sigma = self.obs, self.free, self.L, self.corner_sigma
        if not len(obs.cam):
            return
        T_m = m.T_body_markers[obs.marker]
        local = UNIT_CORNERS[obs.corner] * m.sizes_m[obs.marker][:, None]
        q = np.einsum("nij,nj->ni", T_m[:, :3, :3], local)  # R_m s u
        scale = m.scales[m.marker_robot[obs.marker]]
        P = (q + T_m[:, :3, 3]) * scale[:, None]
        Rt, pt = corner_body_poses(obs, m)
        a = np.einsum("nij,nj->ni", Rt, P)  # the body corner, world axes
        X = a + pt
        px, dX, dI = _projected(m, obs.cam, X, blocks.with_jac)
        front = np.isfinite(px[:, 0])
        r = np.where(front[:, None], (px - obs.pixels) / corner_sigma, _BEHIND_PX)
        parts = []
        if dX is not None and dI is not None:  # with_jac
            A = dX / corner_sigma[:, :, None] * front[:, None, None]
            dI = dI * front[:, None, None]
            parts = self._cam_parts(m, obs.cam, X, A, dI, corner_sigma[:, :, None])
            if obs.knot_alpha is None:  # X = exp(ω dt) R_k P + ...: d X / d δθ_k = -exp(ω dt) [R_k P]x
                a_k = np.einsum("nji,nj->ni", obs.motion_R, a)
                parts.append((L.bodies + 6 * obs.inst[:, None] + np.arange(6),
                              np.concatenate([A, -(A @ obs.motion_R) @ skew(a_k)], axis=2)))
            else:  # the interpolated pose takes (1 - α) of knot k's increment and α of knot k + 1's (first order)
                dpose = np.concatenate([A, -A @ skew(a)], axis=2)
                al = obs.knot_alpha[:, None, None]
                parts.append((L.bodies + 6 * obs.inst[:, None] + np.arange(6), (1 - al) * dpose))
                parts.append((L.bodies + 6 * (obs.inst[:, None] + 1) + np.arange(6), al * dpose))
            B = A @ Rt  # d r / d P
            if free.free_scale:
                unscaled = P / scale[:, None]
                parts.append((L.scales + obs.robot[obs.inst][:, None], B @ unscaled[:, :, None]))
            if free.body is not None:
                Bs = B * scale[:, None, None]
                unit = np.einsum("nij,nj->ni", T_m[:, :3, :3], UNIT_CORNERS[obs.corner])
                size0 = self.model.sizes_m[obs.marker]
                Jm = np.concatenate([Bs, -Bs @ skew(q), (Bs @ unit[:, :, None]) * size0[:, None, None]], axis=2)
                parts.append((L.markers + 7 * obs.marker[:, None] + np.arange(7), Jm))
        blocks.add(r, parts)

    def _world_points(self, m: Model, blocks: _Blocks) -> None:
        obs, free, sigma_w = self.obs, self.free, self.free.world_noise_px
        if not (len(obs.world_cam) and (free.cameras or free.intrinsics is not None)):
            return
        px, dX, dI = _projected(m, obs.world_cam, obs.world_points, blocks.with_jac)
        front = np.isfinite(px[:, 0])
        r = np.where(front[:, None], (px - obs.world_pixels) / sigma_w, _BEHIND_PX)
        parts = []
        if dX is not None and dI is not None:  # with_jac
            parts = self._cam_parts(m, obs.world_cam, obs.world_points, dX / sigma_w * front[:, None, None],
                                    dI * front[:, None, None], sigma_w)
        blocks.add(r, parts)

    def _trajectory(self, m: Model, blocks: _Blocks) -> None:
        """A continuous-time trajectory: its knots' second differences."""
        obs, free, L = self.obs, self.free, self.L
        if obs.knot_triples is None or not len(obs.knot_triples):
            return
        i, j, k = obs.knot_triples.T
        s = np.r_[np.full(3, free.accel_sigma_m_s2), np.full(3, free.angular_accel_sigma_rad_s2)]
        s = s * obs.knot_spacing_s ** 2
        Tb = m.T_bodies
        step_ij = pose_offsets(Tb[j], Tb[i])
        step_jk = pose_offsets(Tb[k], Tb[j])
        eye = np.broadcast_to(np.diag(1.0 / s), (len(i), 6, 6))
        blocks.add((step_jk - step_ij) / s, [(L.bodies + 6 * i[:, None] + np.arange(6), eye),
                                              (L.bodies + 6 * j[:, None] + np.arange(6), -2 * eye),
                                              (L.bodies + 6 * k[:, None] + np.arange(6), eye)])

    def _ground(self, m: Model, x: np.ndarray, blocks: _Blocks) -> None:
        """Ground robots: one height per robot, body z near world up; with a floor tilt, both
        taken against each robot's floor plane ``z = h + s . (xy - xy0)`` (normal ``(-s, 1)``,
        small slopes ``s`` held near level by ``floor_tilt_sigma_rad``)."""
        obs, free, L = self.obs, self.free, self.L
        k_idx = np.arange(L.K)
        tilted = L.slopes < L.scales
        s = x[L.slopes:L.scales].reshape(L.R, 2) if tilted else np.zeros((L.R, 2))
        s_cols = L.slopes + 2 * obs.robot[:, None] + np.arange(2)  # (K, 2)
        if free.height_sigma_m > 0:
            h = self.heights0 + x[L.heights:L.heights + L.R]
            xy = m.T_bodies[:, :2, 3] - self.xy0[obs.robot]
            sk = s[obs.robot]
            r = ((m.T_bodies[:, 2, 3] - h[obs.robot] - np.sum(sk * xy, axis=1)) / free.height_sigma_m)[:, None]
            ones = np.full((L.K, 1, 1), 1.0 / free.height_sigma_m)
            parts = [(L.bodies + 6 * k_idx[:, None] + 2, ones), (L.heights + obs.robot[:, None], -ones)]
            if tilted:
                parts += [(L.bodies + 6 * k_idx[:, None] + np.arange(2), -sk[:, None, :] / free.height_sigma_m),
                          (s_cols, -xy[:, None, :] / free.height_sigma_m)]
            blocks.add(r, parts)
        if free.upright_sigma_rad > 0:
            up = m.T_bodies[:, :3, 2]
            parts = [(L.bodies + 6 * k_idx[:, None] + 3 + np.arange(3), -skew(up)[:, :2, :] / free.upright_sigma_rad)]
            if tilted:
                parts.append((s_cols, np.broadcast_to(np.eye(2) / free.upright_sigma_rad, (L.K, 2, 2))))
            blocks.add((up[:, :2] + s[obs.robot]) / free.upright_sigma_rad, parts)
        if tilted:
            blocks.add(s / free.floor_tilt_sigma_rad,
                       [(L.slopes + 2 * np.arange(L.R)[:, None] + np.arange(2),
                         np.broadcast_to(np.eye(2) / free.floor_tilt_sigma_rad, (L.R, 2, 2)))])

    def _priors(self, m: Model, blocks: _Blocks) -> None:
        """The priors on the cameras' poses, their intrinsics and the markers on the body."""
        free, L = self.free, self.L
        if free.cameras and free.camera_prior is not None:
            cp = free.camera_prior
            s = np.r_[np.full(3, cp.sigma_m), np.full(3, cp.sigma_rad)]
            c_idx = np.arange(L.C)
            blocks.add(pose_offsets(m.T_cams, cp.T) / s,
                       [(L.cams + 6 * c_idx[:, None] + np.arange(6), np.broadcast_to(np.diag(1.0 / s), (L.C, 6, 6)))])
        if free.intrinsics is not None:
            ip = free.intrinsics
            fp = ip.K[:, [0, 1], [0, 1]]
            s = np.column_stack([ip.focal_rel * fp, np.full((L.C, 2), ip.principal_px), np.full(L.C, ip.k1),
                                 np.full(L.C, ip.k2)])
            value = np.column_stack([m.K[:, 0, 0], m.K[:, 1, 1], m.K[:, 0, 2], m.K[:, 1, 2], m.dist[:, :2]])
            prior = np.column_stack([fp, ip.K[:, 0, 2], ip.K[:, 1, 2], ip.dist[:, :2]])
            d = np.column_stack([self.f0, self.fmean0, self.fmean0, np.ones(L.C), np.ones(L.C)]) / s
            c_idx = np.arange(L.C)
            blocks.add((value - prior) / s, [(L.intr + 6 * c_idx[:, None] + np.arange(6), d[:, :, None] * np.eye(6))])
        if free.body is not None:
            bp = free.body
            s = np.r_[np.full(3, bp.sigma_m), np.full(3, bp.sigma_rad), bp.size_rel]
            offsets = np.column_stack([pose_offsets(m.T_body_markers, bp.T), m.sizes_m / bp.sizes_m - 1.0])
            g_idx = np.arange(L.G)
            d = np.tile(1.0 / s, (L.G, 1))
            d[:, 6] *= self.model.sizes_m / bp.sizes_m
            blocks.add(offsets / s, [(L.markers + 7 * g_idx[:, None] + np.arange(7), d[:, :, None] * np.eye(7))])


def soft_l1_cost(r: np.ndarray, f_scale: float) -> float:
    """scipy's soft-L1 loss of residuals ``r``: sum of ``f^2 (2 sqrt(1 + (r/f)^2) - 2)`` / 2."""
    return float(np.sum(f_scale ** 2 * (np.sqrt(1 + (r / f_scale) ** 2) - 1)))


def levenberg_marquardt(evaluate, x0: np.ndarray, f_scale: float, max_iterations: int,
                        order: np.ndarray) -> np.ndarray:
    """Minimise the soft-L1 cost of ``evaluate(x, with_jac) -> (residuals, sparse Jacobian or
    None)`` from ``x0``: Levenberg-Marquardt steps on the reweighted normal equations (weights
    ``1 / sqrt(1 + (r/f)^2)``, the loss's), each solved by a sparse LU factorisation of the
    unknowns in ``order`` without pivoting (the matrix is positive definite; a banded block first
    and the unknowns every residual may share last keep the factors as sparse as the matrix);
    stops when a step lowers the cost by less than 1e-9 of it, or after ``max_iterations``
    evaluations of the Jacobian."""
    x = x0
    r, J = evaluate(x, True)
    cost, damping = soft_l1_cost(r, f_scale), 1e-4
    for _ in range(max_iterations):
        w = 1.0 / np.sqrt(1 + (r / f_scale) ** 2)
        JtW = J.T.multiply(w).tocsr()
        A, g = (JtW @ J).tocsr()[order][:, order], (JtW @ r)[order]
        diag = A.diagonal() + 1e-12
        while True:
            lu = splu((A + diags(damping * diag)).tocsc(), permc_spec="NATURAL", diag_pivot_thresh=0.0,
                      options={"SymmetricMode": True})
            step = np.empty_like(x)
            step[order] = lu.solve(-g)
            r_new = evaluate(x + step, False)[0]
            new_cost = soft_l1_cost(r_new, f_scale) if np.isfinite(r_new).all() else np.inf
            if new_cost < cost:
                break
            damping *= 10
            if damping > 1e8:
                return x
        x, done = x + step, cost - new_cost < 1e-9 * cost
        cost, damping = new_cost, max(damping / 10, 1e-7)
        if done:
            break
        r, J = evaluate(x, True)
    return x
