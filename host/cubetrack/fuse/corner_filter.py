"""A constant-velocity SE(3) filter whose measurements are cube corners in camera images.

State (world frame): ``position_m``, the orientation ``R_world_cube`` of the cube frame,
``velocity_m_s`` and ``angular_velocity_rad_s`` (rad/s). The covariance ``P`` (12x12) is over the
error state ``[δp, δθ, δv, δω]`` with ``R = exp(δθ) R̂`` (world-frame rotation error): the pose
block first, the order of :func:`cubetrack.fuse.multi_view_fit.solve_joint`.

Prediction: white-noise acceleration and angular acceleration (``accel_noise``, ``angular_accel_noise``,
spectral densities; along the world's z axis ``vertical_accel_noise``: a floor robot's height hardly
changes). About the world's z axis the angular acceleration noise has two levels: the turning one
(``yaw_accel_noise``) from a sharp turn (yaw rate above ``sharp_turn_rad_s``) until ``turn_hold_s``
after the last, the steady one (``steady_yaw_accel_noise``) otherwise, so a robot that turns sharply
is followed through its turns and one that does not gets a smoother heading. Either is raised to
``manoeuvre_yaw_accel_noise`` while the sightings say the robot manoeuvres: the yaw's corrections,
each over the spread the motion model expects of it, lean one way over the last ~0.15 s (a z-test
against their long mean square, ``manoeuvre_z2``): the yaw lags a turn's onset, noise flips sign.
The levels are part of the state (a function of the sightings in capture order). Update: an
iterated EKF (Gauss-Newton on the prior plus the reprojection error of every matched corner of one
camera frame), with Huber weights per coordinate, so one camera's weak monocular depth is
constrained by the prediction instead of being trusted. A frame whose residual after the update is
above ``gate_rms_px`` is rejected (outlier gating), and the state is left unchanged.
"""

from __future__ import annotations

import dataclasses
import functools
import math
from collections.abc import Sequence
from dataclasses import dataclass

import cv2
import numpy as np

from cubetrack.core.geometry import make_T
from cubetrack.core.params import check_at_least, check_non_negative, check_positive, param
from cubetrack.estimate.reprojection import CornerSet, perturbed
from cubetrack.fuse.filter_kernels import OK, moved_pose, packed_sets, predicted_covariance, solve_update, taken_at

_POSE, _VELOCITY, _ANGULAR_VELOCITY = slice(0, 6), slice(6, 9), slice(9, 12)  # error-state blocks
_RATES = np.zeros((12, 12))  # d(state)/dt under constant velocity: δp' = δv, δθ' = δω
_RATES[0:6, 6:12] = np.eye(6)
_IDENTITY = np.eye(12)


@dataclass(frozen=True, slots=True)
class FilterParams:
    """The motion model and measurement model of :class:`PoseFilter`."""

    accel_noise: float = param(0.5, "white-noise acceleration spectral density, m/s^2/sqrt(Hz)")
    vertical_accel_noise: float = param(
        0.05, "the same along the world's z axis for a body with motion = \"floor\" (a robot on a floor hardly "
        "moves up or down; a free body gets accel_noise), m/s^2/sqrt(Hz): the less, the more the track's height "
        "pins one camera's depth along its ray (docs/tracking.md \"A floor robot's height\")")
    angular_accel_noise: float = param(0.5, "white-noise angular acceleration spectral density about the "
                                       "world's x and y axes (tilting), rad/s^2/sqrt(Hz)")
    yaw_accel_noise: float = param(5.0, "white-noise angular acceleration spectral density about the world's z axis "
                                   "while the robot turns sharply (robots turn sharply, they tilt little), "
                                   "rad/s^2/sqrt(Hz)")
    steady_yaw_accel_noise: float = param(3.0, "the same once it has not turned sharply for turn_hold_s, "
                                               "rad/s^2/sqrt(Hz)")
    sharp_turn_rad_s: float = param(2.0, "a yaw rate above this is a sharp turn, rad/s")
    turn_hold_s: float = param(3.0, "the turning noise holds this long after the last sharp turn, seconds")
    manoeuvre_yaw_accel_noise: float = param(
        8.0, "the yaw's angular acceleration noise while the sightings say the robot manoeuvres (manoeuvre_z2), at "
        "least: rad/s^2/sqrt(Hz) (docs/tracking.md \"Session 28\")")
    manoeuvre_z2: float = param(
        6.0, "the sightings say the robot manoeuvres when the yaw's corrections, each over its expected spread, lean "
        "one way: their short fading mean squared above this many times its variance (the long mean square times the "
        "short mean's sum of squared weights; 6: a z-test at 2.45 sigma); the yaw lags a turn's onset that way, "
        "while noise flips sign; 0: never")
    manoeuvre_short_s: float = param(0.15, "the time constant of that short signed mean, seconds")
    manoeuvre_long_s: float = param(3.0, "the time constant of the long mean square it is tested against, seconds")
    manoeuvre_min_samples: float = param(
        3.0, "the short mean must pool at least this many corrections (1 / its sum of squared weights): slower "
        "sightings (a camera frame every 0.15 s or more) say nothing of a trend")
    manoeuvre_hold_s: float = param(0.5, "the manoeuvre's noise holds this long after the last such update, seconds")
    corner_noise_px: float = param(0.5, "corner measurement noise (1 sigma), pixels, of a corner whose marker's border "
                                   "modules are 2.5 px wide or wider; narrower ones get more, each its own (issue 26, "
                                   "docs/tracking.md \"Each corner's own noise\")")
    corner_noise_by_width: bool = param(
        True, "weigh each corner by the edge fit's error law (its border modules' width, issue 26); the corners of "
        "another [detector] corner_refinement do not follow it, and a config with one turns this off unless it says "
        "otherwise (the template fit's: rotation 0.32 against 0.22 deg with it, tests/e2e/test_track_template.py)")
    camera_position_sigma_m: float = param(
        0.002, "how far a calibrated camera may be from where its extrinsics put it (1 sigma per axis), metres: "
        "every corner of one camera frame shares this error, so cameras that disagree by it are not read as "
        "motion (docs/tracking.md \"Cameras that disagree\"; 0: cameras taken as exact)")
    camera_rotation_sigma_deg: float = param(
        0.1, "the same for the camera's orientation (1 sigma per axis), degrees (real calibrations leave 0.1-0.3)")
    camera_scale_sigma: float = param(
        0.005, "the same for the camera's scale: its focal length's error (or its corners' bias outwards), a fraction "
        "(1 sigma), which moves the body along the camera's optical axis by that fraction of its depth, so a "
        "camera's depth is trusted less than its view across (docs/tracking.md \"Cameras that disagree\"; 0: none; "
        "0.005 since issue 25's third round)")
    wobble_sigma_deg: float = param(
        0.0, "a robot's wobble on an uneven floor: each camera frame sees the body rolled and pitched about the floor "
        "point below it by this much (1 sigma per axis, independent from frame to frame: a vibration faster than the "
        "motion model follows), degrees; 0: none (docs/tracking.md \"What the term absorbs on the renders\": 0.5 "
        "gains 3-6 % position on the realistic renders and costs the clean ones 0.001 cm; not the default)")
    free_body_term_scale: float = param(
        0.5, "the calibration term (the three camera sigmas above) is multiplied by this for a body whose cube "
        "layout file says motion = \"free\" (hand-held, not driving on a floor), which also gets no wobble: on renders "
        "the term as set stands in for a floor robot's wobble, which a free body has not (docs/tracking.md \"A motion "
        "switch per body\"); bodies with motion = \"floor\" (the default) get the term as set")
    camera_term_samples_per_s: float = param(
        0.0, "the calibration term above sized per camera (docs/tracking.md \"Each camera's term from the others\"): "
        "this many of a camera's frames a second (e.g. 4) are compared with the pose the other cameras make without "
        "it, and its term follows how far off it is (within 1/4-4x of the term as set); 0: every camera gets the term "
        "as set (not the default: it costs the simulator's presets position accuracy, docs/tracking.md)")
    correction_time_sigma_s: float = param(
        0.0, "per-camera corrections estimated over the session (docs/tracking.md \"Per-camera corrections\"): the "
        "prior (1 sigma) of a camera's time offset (its frames taken that much before or after their stamps), seconds; "
        "0.05 for cameras without a clock (stamped from arrival, each late by its own transfer time); bounded to 4 "
        "sigma; 0: not estimated")
    correction_position_sigma_m: float = param(
        0.0, "the same for a camera's position error (1 sigma per axis), metres (0: not estimated; measured to "
        "cost accuracy on cameras that agree, docs/tracking.md)")
    correction_rotation_sigma_deg: float = param(0.0, "the same for a camera's orientation error (1 sigma per axis), "
                                                 "degrees (0: not estimated)")
    correction_memory_s: float = param(60.0, "what a camera's frames said about its correction fades over this many "
                                       "seconds (a camera that moves is followed; 0: no corrections)")
    huber_px: float = param(1.5, "corner residuals beyond this are down-weighted (Huber), pixels")
    gate_rms_px: float = param(2.0, "a camera frame whose RMS residual after the update exceeds this is "
                                    "rejected, pixels")
    face_gate_px: float = param(1.2, "a face whose corners stay farther off than this (RMS) after the update is "
                                     "left out, pixels")
    iterations: int = param(2, "Gauss-Newton iterations of each update (the prediction starts close: more change "
                               "nothing measurable)")
    init_velocity_sigma: float = param(0.5, "velocity uncertainty (1 sigma) at track start, m/s")
    init_angular_velocity_sigma: float = param(3.0, "angular velocity uncertainty (1 sigma) at track start, rad/s "
                                               "(robots turn at up to 3.5 rad/s: a tighter prior pulls a "
                                               "start in a turn towards no turn)")
    smooth_lag_s: float = param(0.0, "fixed-lag smoothing: each pose leaves once sightings this many "
                                "seconds newer have been applied, smoothed over them (more accurate, this much later; "
                                "at most [fusion] history_s; docs/tracking.md); 0: at once, from the "
                                "sightings up to its time")
    smooth_margin_s: float = param(0.2, "fixed-lag smoothing: a pose still held this long after its smooth_lag_s (on "
                                   "the host clock: its robot left every camera's view, a camera stalled) leaves "
                                   "anyway, smoothed over the sightings there are, seconds")

    def __post_init__(self) -> None:
        check_positive(self, "accel_noise", "vertical_accel_noise", "angular_accel_noise", "yaw_accel_noise",
                       "steady_yaw_accel_noise", "sharp_turn_rad_s", "turn_hold_s", "manoeuvre_yaw_accel_noise",
                       "manoeuvre_short_s", "manoeuvre_long_s", "corner_noise_px", "huber_px", "gate_rms_px",
                       "face_gate_px",
                       "init_velocity_sigma", "init_angular_velocity_sigma")
        check_non_negative(self, "manoeuvre_z2", "manoeuvre_min_samples")
        check_non_negative(self, "manoeuvre_hold_s", unit="seconds")
        check_non_negative(self, "camera_position_sigma_m", unit="metres")
        check_non_negative(self, "camera_scale_sigma", "camera_term_samples_per_s", "free_body_term_scale")
        check_non_negative(self, "camera_rotation_sigma_deg", "correction_rotation_sigma_deg", "wobble_sigma_deg",
                           unit="degrees")
        check_non_negative(self, "correction_position_sigma_m", unit="metres")
        check_non_negative(self, "correction_time_sigma_s", "correction_memory_s", unit="seconds")
        check_at_least(self, 1, "iterations")
        check_non_negative(self, "smooth_lag_s", "smooth_margin_s", unit="seconds")

    def for_free_body(self) -> FilterParams:
        """These settings for a body with ``motion = "free"``: the calibration term times
        ``free_body_term_scale``, no wobble (a free body has no floor to wobble about), its vertical
        acceleration as its horizontal one."""
        k = self.free_body_term_scale
        return dataclasses.replace(self, vertical_accel_noise=self.accel_noise,
                                   camera_position_sigma_m=k * self.camera_position_sigma_m,
                                   camera_rotation_sigma_deg=k * self.camera_rotation_sigma_deg,
                                   camera_scale_sigma=k * self.camera_scale_sigma, wobble_sigma_deg=0.0)


@dataclass(frozen=True, slots=True)
class UpdateResult:
    """Outcome of one measurement update: accepted or gated out, with the RMS residual (px)."""

    accepted: bool
    rms_px: float
    points: int


def transition(dt_s: float) -> np.ndarray:
    """The error state's transition over ``dt_s`` seconds of constant velocity (``δp += dt δv``,
    ``δθ += dt δω``): what :meth:`PoseFilter.predict` applies to the covariance."""
    return _IDENTITY + dt_s * _RATES


Noise = tuple[np.ndarray, np.ndarray, np.ndarray]


def _motion_noise(params: FilterParams, turning: bool, manoeuvre: bool) -> Noise:
    """``(A, B, C)`` with the process noise over a step of ``dt`` = ``A |dt|³/3 + B dt²/2 + C |dt|``
    (white acceleration and angular acceleration, per axis; the yaw's while turning sharply or not)."""
    yaw = params.yaw_accel_noise if turning else params.steady_yaw_accel_noise
    if manoeuvre:
        yaw = max(yaw, params.manoeuvre_yaw_accel_noise)
    q = np.repeat([params.accel_noise**2, params.vertical_accel_noise**2, params.angular_accel_noise**2, yaw**2],
                  [2, 1, 2, 1])  # p (x, y; z), θ (x, y; z)
    A, B, C = np.zeros((12, 12)), np.zeros((12, 12)), np.zeros((12, 12))
    A[0:6, 0:6] = np.diag(q)
    B[0:6, 6:12] = B[6:12, 0:6] = np.diag(q)
    C[6:12, 6:12] = np.diag(q)
    for m in (A, B, C):
        m.setflags(write=False)
    return A, B, C


@functools.lru_cache(maxsize=8)
def _motion_noises(params: FilterParams) -> tuple[Noise, Noise, Noise, Noise]:
    """:func:`_motion_noise` for each (turning, manoeuvre), at ``2 * turning + manoeuvre``: a filter
    takes them once (a prediction then hashes no params)."""
    return tuple(_motion_noise(params, turning, manoeuvre)  # type: ignore[return-value]
                 for turning in (False, True) for manoeuvre in (False, True))


class PoseFilter:
    """One robot's filter: ``predict`` / ``update`` in time order. Every step replaces the state's
    arrays rather than writing into them, so a :meth:`copy` is an independent snapshot. The pose
    is kept as one read-only 4x4 ``T_world_cube`` (``position_m`` and ``R_world_cube`` are views
    of it): the steps that need it as a matrix do not rebuild it."""

    def __init__(self, params: FilterParams, time_s: float, T_world_cube: np.ndarray, covariance: np.ndarray,
                 velocity_m_s: np.ndarray | None = None, angular_velocity_rad_s: np.ndarray | None = None):
        """Start at ``time_s`` from a pose with its covariance: 6x6 over ``[δp, δθ]`` (velocities
        then start at zero with the params' spreads) or 12x12 over ``[δp, δθ, v, ω]``."""
        self.params = params
        self._noises = _motion_noises(params)
        self.time_s = time_s
        self._set_pose(make_T(T_world_cube[:3, :3], T_world_cube[:3, 3]))
        self.velocity_m_s = np.zeros(3) if velocity_m_s is None else np.asarray(velocity_m_s, dtype=float).copy()
        self.angular_velocity_rad_s = (np.zeros(3) if angular_velocity_rad_s is None
                                       else np.asarray(angular_velocity_rad_s, dtype=float).copy())
        self.turning_until_s = float("-inf")  # the turning noise until then (see predict)
        # the yaw's corrections over their spreads: short signed mean, its sum of squared weights (0: none yet),
        # long mean square, the last one's time; the manoeuvre's noise until then (see _note_yaw_correction)
        self.yaw_short, self.yaw_weight2, self.yaw_long, self.yaw_time_s = 0.0, 0.0, 0.0, time_s
        self.manoeuvre_until_s = float("-inf")
        self._note_turn()
        P = np.zeros((12, 12))
        if covariance.shape == (12, 12):
            P[:] = covariance
        else:
            P[_POSE, _POSE] = covariance
            P[_VELOCITY, _VELOCITY] = np.eye(3) * params.init_velocity_sigma**2
            P[_ANGULAR_VELOCITY, _ANGULAR_VELOCITY] = np.eye(3) * params.init_angular_velocity_sigma**2
        self.P = (P + P.T) / 2.0

    def _note_turn(self) -> None:
        """Hold the turning noise for ``turn_hold_s`` from now if the robot turns sharply."""
        if abs(self.angular_velocity_rad_s[2]) > self.params.sharp_turn_rad_s:
            self.turning_until_s = self.time_s + self.params.turn_hold_s

    def _note_yaw_correction(self, correction_rad: float, spread_rad2: float) -> None:
        """Hold the manoeuvre's yaw noise for ``manoeuvre_hold_s`` from now if the update's yaw correction
        ``correction_rad`` (over ``spread_rad2``, its variance were the motion model right: the prior's yaw
        variance less the posterior's) and the ones before it lean one way (``manoeuvre_z2``): fading means
        over time, so corrections a few ms apart (cameras in step) count as one."""
        prm = self.params
        if prm.manoeuvre_z2 <= 0.0 or spread_rad2 <= 0.0:
            return
        z = correction_rad / math.sqrt(spread_rad2)
        if self.yaw_weight2 == 0.0:  # the first: both means start at it
            keep_short = keep_long = 0.0
        else:
            dt = self.time_s - self.yaw_time_s
            keep_short, keep_long = math.exp(-dt / prm.manoeuvre_short_s), math.exp(-dt / prm.manoeuvre_long_s)
        self.yaw_short = keep_short * self.yaw_short + (1.0 - keep_short) * z
        self.yaw_weight2 = keep_short * keep_short * self.yaw_weight2 + (1.0 - keep_short) ** 2
        self.yaw_long = keep_long * self.yaw_long + (1.0 - keep_long) * z * z
        self.yaw_time_s = self.time_s
        if (self.yaw_short * self.yaw_short > prm.manoeuvre_z2 * self.yaw_weight2 * self.yaw_long
                and self.yaw_weight2 * prm.manoeuvre_min_samples <= 1.0):
            self.manoeuvre_until_s = self.time_s + prm.manoeuvre_hold_s

    def _set_pose(self, T_world_cube: np.ndarray) -> None:
        """Take ``T_world_cube`` (a new array nothing else holds) as the pose."""
        T_world_cube.setflags(write=False)
        self._T_world_cube = T_world_cube

    @property
    def T_world_cube(self) -> np.ndarray:
        """The pose (read-only 4x4)."""
        return self._T_world_cube

    @property
    def position_m(self) -> np.ndarray:
        """The cube's origin in the world frame (read-only view of the pose), metres."""
        return self._T_world_cube[:3, 3]

    @property
    def R_world_cube(self) -> np.ndarray:
        """The cube frame's orientation in the world frame (read-only view of the pose)."""
        return self._T_world_cube[:3, :3]

    @property
    def pose_covariance(self) -> np.ndarray:
        """(6, 6) covariance of the world-frame pose increment ``[δp (m), δθ (rad)]``."""
        return self.P[_POSE, _POSE].copy()

    def copy(self) -> PoseFilter:
        """An independent snapshot (cheap: the arrays are shared until a step replaces them)."""
        snapshot = object.__new__(type(self))
        snapshot.__dict__.update(self.__dict__)  # what copy.copy does, without its generic dispatch
        return snapshot

    def predicted(self, time_s: float) -> np.ndarray:
        """The pose extrapolated to ``time_s`` at constant velocity (no state change)."""
        return moved_pose(self.T_world_cube, self.velocity_m_s, self.angular_velocity_rad_s,
                          float(time_s - self.time_s))

    def predict(self, time_s: float) -> None:
        """Move the state to ``time_s`` (constant velocity) and grow the covariance."""
        dt = time_s - self.time_s
        if dt == 0.0:
            return
        self._set_pose(self.predicted(time_s))
        A, B, C = self._noises[2 * (self.time_s <= self.turning_until_s) + (self.time_s <= self.manoeuvre_until_s)]
        self.P = predicted_covariance(self.P, dt, A, B, C)  # F P Fᵀ + the process noise, F = transition(dt)
        self.time_s = time_s

    def error_from(self, other: PoseFilter) -> np.ndarray:
        """The error state ``[δp, δθ, δv, δω]`` (12,) that moves ``other``'s state to this one's
        (``R = exp(δθ) R_other``, the rest differences)."""
        return np.concatenate([self.position_m - other.position_m,
                               cv2.Rodrigues(self.R_world_cube @ other.R_world_cube.T)[0].ravel(),
                               self.velocity_m_s - other.velocity_m_s,
                               self.angular_velocity_rad_s - other.angular_velocity_rad_s])

    def moved(self, delta: np.ndarray, covariance: np.ndarray) -> PoseFilter:
        """A snapshot of this filter with its state moved by the error state ``delta`` (12,) and
        ``covariance`` (12x12) as its covariance (a smoother's correction)."""
        moved = self.copy()
        moved._set_pose(perturbed(self.T_world_cube, delta[_POSE]))
        moved.velocity_m_s = self.velocity_m_s + delta[_VELOCITY]
        moved.angular_velocity_rad_s = self.angular_velocity_rad_s + delta[_ANGULAR_VELOCITY]
        moved.P = (covariance + covariance.T) / 2.0
        return moved

    def _solve(self, sets: Sequence[CornerSet], term_scale: float
               ) -> tuple[np.ndarray, np.ndarray | None, np.ndarray, np.ndarray]:
        """Gauss-Newton on prior + Huber-weighted corner residuals (the cameras' calibration term
        times ``term_scale``, and the body's wobble): (δ (12,), the covariance after
        it (None if its information is singular), the pose moved by δ (4x4 ``T_world_cube``),
        residuals px there, less what the cameras' calibration error explains
        (:func:`cubetrack.fuse.filter_kernels.calibration_discount`)). Compiled:
        :func:`cubetrack.fuse.filter_kernels.solve_update`.

        Corners taken at the filter's time see only the pose block of the state: their information
        adds to that block and their gradient to its rows. A set taken at another instant (a
        rolling shutter's row time) sees the pose moved there at the filter's velocities, so it
        informs the velocities too (the full 12-column Jacobian); so does a set whose corners were
        taken at their own rows' instants (``row_offsets_s``)."""
        prm = self.params
        moving = not taken_at(sets, self.time_s)
        k = term_scale
        status, delta, _info, T, r, P, P_ok = solve_update(
            self.T_world_cube, self.P, self.time_s, self.velocity_m_s, self.angular_velocity_rad_s, *packed_sets(sets),
            moving, prm.iterations, prm.huber_px,
            inverse_variances(sets, prm.corner_noise_px, prm.corner_noise_by_width),
            k * prm.camera_position_sigma_m, k * math.radians(prm.camera_rotation_sigma_deg),
            k * prm.camera_scale_sigma, math.radians(prm.wobble_sigma_deg))
        if status != OK:
            raise np.linalg.LinAlgError("singular matrix")
        return delta, (P if P_ok else None), T, r

    def update(self, sets: Sequence[CornerSet], term_scale: float = 1.0) -> UpdateResult:
        """Iterated EKF update with the corners of ``sets``, each taken at its ``time_s`` (the
        filter's time, or near it: a rolling-shutter row time); ``term_scale``: the factor on the
        calibration term for their camera (:meth:`cubetrack.fuse.camera_corrections.CameraCorrections.term_scale`).

        A face whose corners stay more than ``face_gate_px`` (RMS) off after the update is
        dropped and the update redone; the whole sighting is rejected if its RMS residual is
        above ``gate_rms_px`` or no face is left.
        """
        sets = [s for s in sets if s is not None and len(s.faces)]
        while sets:
            delta, P, T, r = self._solve(sets, term_scale)
            if len(sets) == 1 and len(sets[0].faces) == 1:   # one face: none to leave out
                break
            face_rms = np.sqrt((r * r).reshape(-1, 8).sum(axis=1) / 8.0)  # RMS of 4 corners x (x, y) per face
            worst = int(face_rms.argmax())
            if face_rms[worst] <= self.params.face_gate_px:
                break
            sets = _without_face(sets, worst)
        if not sets:
            return UpdateResult(False, float("inf"), 0)
        rms = math.sqrt(float(r @ r) / r.size)
        if not math.isfinite(rms) or rms > self.params.gate_rms_px:
            return UpdateResult(False, rms, r.size // 2)
        if P is None:
            raise np.linalg.LinAlgError("singular matrix")
        self._note_yaw_correction(float(delta[5]), float(self.P[5, 5] - P[5, 5]))
        self.P = P
        self._set_pose(T)
        self.velocity_m_s = self.velocity_m_s + delta[_VELOCITY]
        self.angular_velocity_rad_s = self.angular_velocity_rad_s + delta[_ANGULAR_VELOCITY]
        self._note_turn()
        return UpdateResult(True, rms, r.size // 2)


def inverse_variances(sets: Sequence[CornerSet], corner_noise_px: float, by_width: bool = True) -> np.ndarray:
    """(N,) each corner's inverse variance (1/px^2) in the stacking order of ``sets``: the nominal
    ``corner_noise_px`` times the corner's own factor (:attr:`CornerSet.noise_scale`; 1 without one,
    and for every corner when not ``by_width``)."""
    scales = [s.noise_scale if by_width and s.noise_scale is not None else np.ones(len(s.points_cube_m))
              for s in sets]
    sigma_px = corner_noise_px * (scales[0] if len(scales) == 1 else np.concatenate(scales))
    return 1.0 / (sigma_px * sigma_px)


def _without_face(sets: Sequence[CornerSet], index: int) -> list[CornerSet]:
    """The corner sets with their ``index``-th face overall (in stacking order) removed."""
    out = []
    for s in sets:
        n = len(s.faces)
        if 0 <= index < n:
            keep = np.ones(4 * n, dtype=bool)
            keep[4 * index: 4 * index + 4] = False
            if n > 1:
                out.append(dataclasses.replace(s, points_cube_m=s.points_cube_m[keep], normalized=s.normalized[keep],
                                               noise_scale=None if s.noise_scale is None else s.noise_scale[keep],
                                               row_offsets_s=None if s.row_offsets_s is None
                                               else s.row_offsets_s[keep],
                                               faces=s.faces[:index] + s.faces[index + 1:]))
        else:
            out.append(s)
        index -= n
    return out
