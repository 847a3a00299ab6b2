"""Per-camera corrections estimated over a session: each camera's time offset and extrinsic error.

A real rig's cameras are constantly off in two ways that per-frame noise does not describe
(docs/tracking.md "Cameras that disagree"): a calibration leaves each camera a few millimetres and
0.1-0.3° from where its extrinsics put it, the same error in every frame of the session; and a
camera without a clock is stamped from its frames' arrival, late by a transfer time of its own
(tens of ms, the same frame after frame). Both make the camera see the body consistently off the
pose the other cameras agree on. So each camera ``c`` gets a correction ``θ_c = (δt, δφ, τ)``:
its centre moved by ``δt`` (world frame, metres), its orientation turned by ``δφ`` about its
centre (world frame, radians: ``R_world_cam' = Exp(δφ) R_world_cam``) and its frames taken
``τ`` seconds after their stamps.

Estimated from the innovations: every accepted camera frame's corners, reprojected at the
filter's prediction (the pose the sightings before it, mostly other cameras', agree on), give
residuals ``r ≈ J (θ_c - θ_true) + n`` with ``J = H [M | H_v]``: ``H`` the corners' Jacobian by
the body pose, ``M`` how a camera error moves the body as that camera sees it (``δp = -δt +
[p - c]× δφ``, ``δθ = -δφ``, as in :func:`cubetrack.fuse.filter_kernels.calibration_discount`),
``H_v = [v; ω]`` how a time offset does; the noise ``n`` is the corners' own (Huber-weighted)
plus the prediction's uncertainty projected, ``S = W⁻¹ + H P Hᵀ``. Each frame adds its
information ``Jᵀ S⁻¹ J`` and ``Jᵀ S⁻¹ (J θ_c - r)`` to the camera's sums, which fade with
``correction_memory_s``; the correction is the regularised solution ``(Λ₀ + Σ Λ)⁻¹ Σ b``, with
a zero-mean prior ``Λ₀`` of ``correction_*_sigma`` (a camera stays uncorrected unless its frames
insist) and clipped to ``CLIP_SIGMAS`` of it. Only the relative errors are seen: what every
camera shares cannot be told from the body's own motion or the world frame, so it is taken out
(:class:`CameraCorrections`, ``common``): for the time offsets their median (most cameras' stamps
are right, a camera without a clock is the exception: the others keep zero), for the extrinsic
errors their mean (every camera is off by its calibration's error, the world frame is their
average). Without that, all cameras' corrections drift together, following the prediction's lag.

Which parts are estimated is a setting (``[filter] correction_*``, all off by default): the time
offsets find cameras stamped tens of ms late or early and cost nothing on cameras that agree
(tests/unit/fuse/test_camera_corrections.py); the extrinsic part follows the prediction's lag as
much as the cameras' errors and costs accuracy on cameras that agree (docs/tracking.md).

Everything here is a value: :class:`CameraCorrections` is frozen, each step makes a new one, so
the fusion's replays of late sightings stay exact. What a watcher of moved cameras reads is
:class:`CameraCorrection` (:meth:`cubetrack.fuse.fusion.FilterFusion.camera_corrections`): the
correction, its covariance, how many frames made it and the running innovation statistics.
"""

from __future__ import annotations

import dataclasses
import math
import statistics
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from types import MappingProxyType

import numpy as np

from cubetrack.core.geometry import R_from_rotvec, invert_T, make_T
from cubetrack.estimate.reprojection import CornerSet, reprojection_jacobian_px
from cubetrack.fuse.filter_kernels import moved_pose, packed_sets, reprojection, taken_at
from cubetrack.fuse.multi_view_fit import solve_joint

CLIP_SIGMAS = 4.0  # a correction is bounded to this many prior standard deviations per axis
SIZE = 7  # [δt (3, m), δφ (3, rad), τ (1, s)]
_STATS_MEMORY = 20  # the innovation statistics average over about this many frames


@dataclass(frozen=True, slots=True)
class CorrectionPriors:
    """The zero-mean prior of each camera's correction (1 sigma per axis) and the sums' memory;
    a sigma of 0 keeps that part at zero. Built from :class:`cubetrack.fuse.corner_filter.FilterParams`."""

    position_sigma_m: float
    rotation_sigma_rad: float
    time_sigma_s: float
    memory_s: float

    @property
    def enabled(self) -> bool:
        return self.memory_s > 0 and max(self.position_sigma_m, self.rotation_sigma_rad, self.time_sigma_s) > 0

    @property
    def sigmas(self) -> np.ndarray:
        return np.repeat([self.position_sigma_m, self.rotation_sigma_rad, self.time_sigma_s], [3, 3, 1])


@dataclass(frozen=True, slots=True, eq=False)
class CameraCorrection:
    """One camera's correction and what it rests on (read-only arrays).

    ``offset`` (7,): ``[δt (m), δφ (rad), τ (s)]`` as applied (module doc); ``covariance`` (7x7)
    its uncertainty (the prior where no frame informs it); ``information`` / ``vector``: the faded
    sums of the frames (without the prior; sums over robots add); ``frames``: how many frames
    informed it; ``time_s``: the capture time of the newest; ``rms_px``: the running RMS of the
    frames' residuals at the prediction, corrected; ``chi2``: the running mean of
    ``rᵀ S⁻¹ r / len(r)`` (about 1 while the camera agrees with the others as its correction says;
    growing when it has moved)."""

    camera: str
    offset: np.ndarray
    covariance: np.ndarray
    information: np.ndarray
    vector: np.ndarray
    frames: int = 0
    time_s: float = float("-inf")
    rms_px: float = float("nan")
    chi2: float = float("nan")

    @property
    def position_m(self) -> np.ndarray:
        """How far the camera's centre is moved (world frame), metres."""
        return self.offset[0:3]

    @property
    def rotation_rad(self) -> np.ndarray:
        """The rotation vector (world frame, about the camera's centre) applied to its orientation."""
        return self.offset[3:6]

    @property
    def time_offset_s(self) -> float:
        """Seconds from a frame's stamp to when it was taken, as estimated."""
        return float(self.offset[6])


def corrected_T_world_cam(T_world_cam: np.ndarray, offset: np.ndarray) -> np.ndarray:
    """A camera's pose with the correction ``offset`` (7,) applied (module doc)."""
    if not offset[:6].any():
        return T_world_cam
    return make_T(R_from_rotvec(offset[3:6]) @ T_world_cam[:3, :3], T_world_cam[:3, 3] + offset[0:3])


TERM_PRIOR_SAMPLES = 5  # the calibration term as set counts as this many samples of a camera's disagreement ...
TERM_MEMORY_SAMPLES = 20  # ... and the running estimate averages over about this many
TERM_SCALE_BOUNDS = (0.25, 4.0)  # a camera's term is kept within these factors of the term as set
TERM_SPAN_S = 0.05  # the other cameras' sightings at most this far in time from a sample make its reference
TERM_FIT_ITERATIONS = 30  # Gauss-Newton steps at most of a reference fit (it starts at the filter's pose)
TERM_REFERENCE_RMS_PX = 3.0  # a reference fit whose own corners are further off than this (RMS) is not used


@dataclass(frozen=True, slots=True)
class CameraTerm:
    """How much one camera disagrees with the others, against the filter's calibration term:
    ``log_ratio2`` the running mean of log((its corners' distance from the pose the other cameras
    make, px)² over (the term's own spread there, px)²), each sample within the squared
    ``TERM_SCALE_BOUNDS`` (a log mean: one wild sample, e.g. at a track start, moves it little),
    starting at 0 (the term as set) and moving towards the samples; ``samples`` how many made it;
    ``time_s`` the capture time of the newest sample or attempt."""

    samples: int
    log_ratio2: float
    time_s: float

    @property
    def scale(self) -> float:
        """The factor on the camera's calibration term (its sigmas), within ``TERM_SCALE_BOUNDS``."""
        low, high = TERM_SCALE_BOUNDS
        return min(max(math.exp(self.log_ratio2 / 2.0), low), high)  # (np.clip costs more than a sample's update)


@dataclass(frozen=True, slots=True)
class CameraCorrections:
    """Every camera's :class:`CameraCorrection` so far (camera name -> correction; none yet: zero)
    and ``common`` (7,): what all cameras share (the mean of the extrinsic parts, the median of the
    time offsets: module doc), the rig's, not a camera's, so a camera's frames get its offset less
    the common one (:meth:`applied`); ``terms``: each camera's :class:`CameraTerm` (how its
    calibration term is sized, :func:`term_observed`)."""

    by_camera: Mapping[str, CameraCorrection] = field(default_factory=lambda: MappingProxyType({}))
    common: np.ndarray = field(default_factory=lambda: np.zeros(SIZE))
    terms: Mapping[str, CameraTerm] = field(default_factory=lambda: MappingProxyType({}))

    def term_scale(self, camera: str) -> float:
        """The factor on the filter's calibration term for ``camera``'s frames (1: none measured yet)."""
        term = self.terms.get(camera)
        return 1.0 if term is None else term.scale

    def get(self, camera: str) -> CameraCorrection | None:
        return self.by_camera.get(camera)

    def applied(self, camera: str) -> np.ndarray | None:
        """The offset (7,) applied to ``camera``'s frames (None: none yet)."""
        correction = self.by_camera.get(camera)
        return None if correction is None else correction.offset - self.common


def _read_only(a: np.ndarray) -> np.ndarray:
    a.setflags(write=False)
    return a


def solved(camera: str, information: np.ndarray, vector: np.ndarray, priors: CorrectionPriors, frames: int,
           time_s: float, rms_px: float, chi2: float) -> CameraCorrection:
    """The correction of ``camera`` from its (faded) sums and the prior, clipped (module doc)."""
    sigmas = priors.sigmas
    on = sigmas > 0
    offset, covariance = np.zeros(SIZE), np.diag(sigmas**2)
    if on.any():
        block = np.ix_(on, on)
        total = information[block] + np.diag(1.0 / sigmas[on] ** 2)
        try:
            cov_on = np.linalg.inv(total)
        except np.linalg.LinAlgError:
            cov_on = np.diag(sigmas[on] ** 2)
        offset[on] = np.clip(cov_on @ vector[on], -CLIP_SIGMAS * sigmas[on], CLIP_SIGMAS * sigmas[on])
        covariance[block] = cov_on
    return CameraCorrection(camera, _read_only(offset), _read_only(covariance), _read_only(information),
                            _read_only(vector), frames, time_s, rms_px, chi2)


def camera_jacobian(H: np.ndarray, T_world_cube: np.ndarray, T_cam_world: np.ndarray, velocity_m_s: np.ndarray,
                     angular_velocity_rad_s: np.ndarray) -> np.ndarray:
    """``J = H [M | H_v]`` (2N, 7): the residuals' change with a camera's correction (module doc)."""
    d = T_world_cube[:3, 3] + T_cam_world[:3, :3].T @ T_cam_world[:3, 3]  # p - c
    M = np.zeros((6, SIZE))
    M[0:3, 0:3] = -np.eye(3)
    M[0:3, 3:6] = np.array([[0.0, -d[2], d[1]], [d[2], 0.0, -d[0]], [-d[1], d[0], 0.0]])
    M[3:6, 3:6] = -np.eye(3)
    M[0:3, 6], M[3:6, 6] = velocity_m_s, angular_velocity_rad_s
    return H @ M


def observed(corrections: CameraCorrections, priors: CorrectionPriors, sets: Sequence[CornerSet],
             T_world_cube: np.ndarray, velocity_m_s: np.ndarray, angular_velocity_rad_s: np.ndarray, time_s: float,
             covariance: np.ndarray, corner_noise_px: float, huber_px: float) -> CameraCorrections:
    """``corrections`` after one accepted camera frame: ``sets`` (one camera's, seen with its
    correction applied: its extrinsics and time offset) against the filter's prediction at ``time_s`` (pose,
    velocities and their 12x12 covariance ``[δp, δθ, δv, δω]``: a set taken at another time sees
    the pose moved there, as uncertain as the velocities are)."""
    if not priors.enabled or not sets:
        return corrections
    camera = sets[0].camera
    r, H = reprojection_jacobian_px(T_world_cube, sets, time_s, velocity_m_s, angular_velocity_rad_s)
    a = np.abs(r)
    w = np.where(a <= huber_px, 1.0, huber_px / np.maximum(a, 1e-12)) / corner_noise_px**2  # W (diagonal)
    try:  # S⁻¹ = W - W H (P⁻¹ + Hᵀ W H)⁻¹ Hᵀ W  (Woodbury)
        WH = w[:, None] * H
        inner = np.linalg.inv(np.linalg.inv(covariance) + H.T @ WH)
    except np.linalg.LinAlgError:
        return corrections
    J = camera_jacobian(H[:, :6], T_world_cube, sets[0].T_cam_world, velocity_m_s, angular_velocity_rad_s)

    def s_inv(x: np.ndarray) -> np.ndarray:
        return w[:, None] * x - WH @ (inner @ (WH.T @ x))

    SJ = s_inv(J)
    Sr = s_inv(r[:, None])[:, 0]
    old = corrections.get(camera)
    theta = corrections.applied(camera)
    theta = np.zeros(SIZE) if theta is None else theta
    fade = 0.0 if old is None else math.exp(-max(time_s - old.time_s, 0.0) / priors.memory_s)
    information = J.T @ SJ + (0.0 if old is None else fade * old.information)
    vector = SJ.T @ (J @ theta) - J.T @ Sr + (0.0 if old is None else fade * old.vector)
    rms, chi2 = float(np.sqrt(np.mean(r**2))), float(r @ Sr / len(r))
    if old is not None and old.frames:
        k = 1.0 / min(old.frames + 1, _STATS_MEMORY)
        rms = math.sqrt((1 - k) * old.rms_px**2 + k * rms**2)
        chi2 = (1 - k) * old.chi2 + k * chi2
    new = solved(camera, information, vector, priors, frames=(0 if old is None else old.frames) + 1,
                 time_s=time_s if old is None else max(time_s, old.time_s), rms_px=rms, chi2=chi2)
    by_camera = {**corrections.by_camera, camera: new}
    common = np.zeros(SIZE)
    if len(by_camera) > 1:
        offsets = np.array([c.offset for c in by_camera.values()])
        common[:6], common[6] = offsets[:, :6].mean(axis=0), np.median(offsets[:, 6])
    return CameraCorrections(MappingProxyType(by_camera), _read_only(common), corrections.terms)


def combined(all_corrections: Sequence[CameraCorrections], priors: CorrectionPriors) -> dict[str, CameraCorrection]:
    """Each camera's correction from the sums of several robots' (their information adds)."""
    cameras = sorted({c for corrections in all_corrections for c in corrections.by_camera})
    out = {}
    for camera in cameras:
        parts = [c.by_camera[camera] for c in all_corrections if camera in c.by_camera]
        if len(parts) == 1:
            out[camera] = parts[0]
            continue
        frames = sum(p.frames for p in parts)
        out[camera] = solved(camera, np.sum([p.information for p in parts], axis=0),
                             np.sum([p.vector for p in parts], axis=0), priors,
                             frames=frames, time_s=max(p.time_s for p in parts),
                             rms_px=math.sqrt(sum(p.frames * p.rms_px**2 for p in parts) / frames),
                             chi2=sum(p.frames * p.chi2 for p in parts) / frames)
    return out


def term_spread_px2(H: np.ndarray, T_world_cube: np.ndarray, T_cam_world: np.ndarray, sigma_t_m: float,
                    sigma_phi_rad: float, sigma_s: float) -> float:
    """The calibration term's spread in one camera's corners, px² per coordinate (the mean of the
    diagonal of ``H Σ Hᵀ``, i.e. ``trace(Σ HᵀH) / rows``): ``H`` (2N, 6) the corners' Jacobian by the
    body pose ``T_world_cube`` seen from ``T_cam_world``, ``Σ`` the body's apparent motion from a camera
    error of ``sigma_t_m`` per axis, ``sigma_phi_rad`` per axis and scale ``sigma_s``, as
    :func:`cubetrack.fuse.filter_kernels.calibration_discount` models it."""
    z = T_cam_world[2, :3]  # the optical axis in the world frame
    d = T_world_cube[:3, 3] + T_cam_world[:3, :3].T @ T_cam_world[:3, 3]  # p - c
    M = camera_jacobian(np.eye(6), T_world_cube, T_cam_world, np.zeros(3), np.zeros(3))[:, :6]
    u = np.concatenate([z * float(z @ d), np.zeros(3)])
    sigma = M @ np.diag(np.repeat([sigma_t_m**2, sigma_phi_rad**2], 3)) @ M.T + sigma_s**2 * np.outer(u, u)
    return float(np.sum(sigma * (H.T @ H))) / len(H)


def term_due(corrections: CameraCorrections, cameras: Sequence[str], time_s: float, every_s: float) -> str | None:
    """Of ``cameras``, the one whose term sample is most overdue at ``time_s`` (none for
    ``every_s`` seconds or never), or None."""
    def last(camera: str) -> float:
        term = corrections.terms.get(camera)
        return float("-inf") if term is None else term.time_s

    due = sorted((last(c), c) for c in cameras if time_s - last(c) >= every_s)
    return due[0][1] if due else None


def seen_at(sets: Sequence[CornerSet], T_world_cube: np.ndarray, velocity_m_s: np.ndarray,
            angular_velocity_rad_s: np.ndarray, time_s: float) -> list[CornerSet]:
    """``sets`` as if taken at ``time_s``: each camera moved by the body's motion (at the given
    velocities, from ``T_world_cube`` at ``time_s``) between the two times, backwards, so a
    fit of the still body at ``time_s`` explains them."""
    out = []
    for s in sets:
        G = moved_pose(T_world_cube, velocity_m_s, angular_velocity_rad_s, s.time_s - time_s) @ invert_T(T_world_cube)
        out.append(dataclasses.replace(s, T_cam_world=s.T_cam_world @ G, time_s=time_s))
    return out


def term_observed(corrections: CameraCorrections, own: Sequence[CornerSet], others: Sequence[CornerSet],
                  T_world_cube: np.ndarray, velocity_m_s: np.ndarray, angular_velocity_rad_s: np.ndarray,
                  sigmas: tuple[float, float, float], corner_noise_px: float) -> CameraCorrections:
    """``corrections`` with one sample of a camera's disagreement: ``own`` (its corners, one
    frame) against the body's pose that ``others`` (at least two other cameras' corners, a few
    milliseconds away) make by themselves at ``own``'s time (a leave-one-out fit, started at the
    filter's pose ``T_world_cube`` predicted to that time; the others' frames moved to that time
    at the filter's velocities, :func:`seen_at`: a few frames milliseconds apart cannot tell
    velocity from the cameras' disagreement). The sample is the camera's corner spread there
    (robust: the median squared distance of a corner, as a Gaussian's per-coordinate variance),
    less the corners' own noise, over the calibration term's spread (``sigmas``: position m,
    orientation rad, scale; as set); its log (a geometric mean: one wild sample, e.g. at a track
    start, moves it little) moves the camera's :class:`CameraTerm` (prior: the term as set, ``TERM_PRIOR_SAMPLES``
    samples' worth). Where the reference cannot be made, or the spread is within the corners' own
    noise (the statistic sees nothing of the cameras' error there: on the simulator's renders every
    sample was, and pulled the term to its lower bound where the renders need it as set,
    docs/tracking.md "Why the renders want the full term"), only the attempt's time is kept (the
    camera waits for its next turn, as after a sample)."""
    if not own:
        return corrections
    t, camera = own[0].time_s, own[0].camera
    old = corrections.terms.get(camera) or CameraTerm(0, 0.0, float("-inf"))
    if len({s.camera for s in others}) < 2:
        return term_tried(corrections, camera, t)
    reference = solve_joint(seen_at(others, T_world_cube, velocity_m_s, angular_velocity_rad_s, t), T_world_cube, t,
                            corner_noise_px, iterations=TERM_FIT_ITERATIONS)
    if reference is None or reference.rms_px > TERM_REFERENCE_RMS_PX:
        return term_tried(corrections, camera, t)
    moving = not taken_at(own, t)  # a rolling shutter's faces and rows: at their own instants
    r, H = reprojection(reference.T_world_cube, *packed_sets(own), t, velocity_m_s, angular_velocity_rad_s, moving,
                        True)
    spread_px2 = statistics.median((r[0::2] ** 2 + r[1::2] ** 2).tolist()) / (2.0 * math.log(2.0))
    term_px2 = term_spread_px2(H[:, :6], reference.T_world_cube, own[0].T_cam_world, *sigmas)
    if not (math.isfinite(spread_px2) and term_px2 > 0.0) or spread_px2 <= corner_noise_px**2:
        return term_tried(corrections, camera, t)  # within the corners' own noise: it cannot see the term
    low, high = TERM_SCALE_BOUNDS
    sample = math.log(min(max(max(spread_px2 - corner_noise_px**2, 0.0) / term_px2, low**2), high**2))
    k = 1.0 / min(old.samples + 1 + TERM_PRIOR_SAMPLES, TERM_MEMORY_SAMPLES)
    return _with_term(corrections, camera,
                      CameraTerm(old.samples + 1, (1.0 - k) * old.log_ratio2 + k * sample, max(t, old.time_s)))


def term_tried(corrections: CameraCorrections, camera: str, time_s: float) -> CameraCorrections:
    """``corrections`` with ``camera``'s turn at ``time_s`` taken and no sample (no reference, or
    none of its corners matched): it waits for its next turn, as after a sample."""
    old = corrections.terms.get(camera) or CameraTerm(0, 0.0, float("-inf"))
    return _with_term(corrections, camera, CameraTerm(old.samples, old.log_ratio2, max(time_s, old.time_s)))


def _with_term(corrections: CameraCorrections, camera: str, term: CameraTerm) -> CameraCorrections:
    return CameraCorrections(corrections.by_camera, corrections.common,
                             MappingProxyType({**corrections.terms, camera: term}))
