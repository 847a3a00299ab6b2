"""Watching every camera against the others while tracking (issue 27): a bumped camera is
noticed, set aside and, once re-calibrated (:mod:`cubetrack.calib.recalibrate`), let back in.

For each camera, a few of its sightings a second (``samples_per_s``) are checked against the
cube pose the OTHER cameras give at the same instant: a joint fit of their matched corners within
``reference_span_s`` of the sighting, with the cube's velocities
(:func:`cubetrack.fuse.multi_view_fit.solve_joint`), needing ``reference_cameras`` other cameras
that the watcher trusts. The sighting's corners and those reference world points form a
:class:`WatchSample`. Every ``check_every_s`` each camera's samples of the last ``window_s``
are fitted as a camera resection (:func:`refit_camera`: the pose that best explains what this
camera saw of points the others located) and compared with the camera's **settled pose**: the
same fit over its samples of the ``baseline_s`` before the window (refitted every
``baseline_every_s``, once four times ``min_points`` corners over ``settle_span_s`` are there). The settled pose holds
what the calibration left between this camera and the others, so that is never taken for a
move; a camera is therefore only judged once it has one (``settle_span_s`` of samples after the start or after
rejoining). The camera is **moved** when

- the window's pose moves the camera's corners by more than ``moved_px`` (RMS over the window's
  points) against the settled pose,
- and it is more than ``moved_m`` or ``moved_deg`` away from it (the fit keeps the pose near the
  settled one by a prior of ``WINDOW_PRIOR_M`` and ``WINDOW_PRIOR_DEG``: a window of points
  bunched in one spot leaves a translation and a rotation that mimic each other free),
- and it explains the window ``moved_ratio`` (4) times better than the settled pose (median corner
  residual: a rigid move of the camera explains what it sees; references that disagree among
  themselves, as where real calibrations are off by several pixels, do not),
- and each half of the window is explained better by the window's pose than by the settled one,
  by more than half ``moved_px`` (median corner residual: a consistent offset, not a few bad
  references).

A small bump (its corners moved by a few px, within ``moved_sigmas`` of a noisy camera's own window
shifts) is judged again by a longer window: the last ``long_window_s`` of its samples, by the same
tests, against ``long_sigmas`` times the shift of its own windows as long and ``long_ratio``. A still
camera's longer windows shift less (the robot is seen in more places); a bump's shift lasts.

Until it is declared, a bumped camera would pull the fused pose towards its own for the seconds
its window takes; so each checked sighting is also judged on its own (:meth:`CameraWatch._judge`):
a camera whose last ``suspect_samples`` samples each miss the other cameras' cube pose by more
than ``suspect_px`` (median corner residual at its settled pose), and which misses most now (the
fused prediction, else the other cameras' cube pose: :meth:`CameraWatch._misses_most`), is
**suspect**: out of the fusion and, with four cameras or more and while it is the only one, no one's
reference (:meth:`CameraWatch.referee`), still checked, until as many samples in a row agree again or it is
declared moved (at least ``reference_cameras`` others stay in use).
And since a check waits for the other cameras' sightings around it, the very first sightings
after a bump come before any check: :meth:`CameraWatch.off_prediction` holds a sighting out of
the fusion when it misses the fused prediction by more than ``gate_prediction_px`` and
``gate_prediction_ratio`` times more than the other cameras' latest sightings do (their median).

A moved camera spoils the references it takes part in, so its partners' windows shift too (with
three cameras, about as much as its own). With four cameras or more a suspect camera whose window
says moved is declared; otherwise, of several cameras whose window says moved, the one whose pose
fitted to its window's newer half makes the others' references agree with them again
(:meth:`CameraWatch._others_miss_px`; with three cameras, of two within ``NEAR_TIE``, the one whose own
checks' references still agree among themselves as before: :meth:`CameraWatch._references_rise_px`);
of one, it is declared if it is the one that disagreed most
with the others inside the reference fits it took part in over the window (the median corner
residual of its sets there), else none is declared yet. Then every camera's window restarts. A moved camera is set aside
(:meth:`CameraWatch.excluded`: its sightings leave the fusion, and it serves nobody as a
reference) and its samples are gathered for its re-calibration until :meth:`CameraWatch.rejoin`.

A slow drift (a clamp slipping millimetres a minute) never makes a window say moved; it is followed
instead, each step a ``followed`` event, no alarm (:meth:`CameraWatch._follow`, every ``baseline_every_s``).
Each camera's
settled pose over its first whole ``baseline_s`` is its **anchor**. A camera's own settled pose is
fitted against the OTHER cameras' references, so when one camera drifts its settled pose moves with
it; but every other camera's moves too, as the drifting camera sits in their references (the
gauge), about as much. So a camera whose settled pose has moved more than ``follow_m`` from its
anchor is followed only when that move, put into the others' references (:func:`with_camera_at`),
takes their settled poses back to their anchors: the shift its move makes in its own corners must
be ``follow_ratio`` times the largest shift left in any other's. The move is fitted as a shift of
the camera's position alone, its orientation kept: a robot's sightings, bunched at one distance from
the camera, hardly tell a sideways shift from a turn, and the spans' wander took one for the other
(docs/calibration.md). Its pose in use then moves by that shift (the fusion takes its sightings
there), its anchor becomes its settled pose, and the others keep their samples with their references
fitted again.

Pure: sightings in, events out; no clock, no thread (the re-calibration fit is the caller's to
run in the background).
"""

from __future__ import annotations

import dataclasses
import datetime
import enum
import math
from collections import Counter, deque
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from cubetrack.core.geometry import (
    invert_T,
    position_quat_from_T,
    rotation_angle,
    so3_left_jacobian,
    transform_points,
)
from cubetrack.core.layout import CubeLayout
from cubetrack.core.params import check, check_at_least, check_positive, param
from cubetrack.core.records import CubeSighting
from cubetrack.estimate.match import match_faces
from cubetrack.estimate.params import EstimatorParams
from cubetrack.estimate.pose import estimate_cube
from cubetrack.estimate.reprojection import CornerSet, moved_pose, perturbed, reprojection_residuals_px
from cubetrack.fuse.fusion import sighting_corner_sets
from cubetrack.fuse.multi_view_fit import robust_gauss_newton, robust_least_squares, solve_joint


@dataclass(frozen=True, slots=True)
class WatchParams:
    """The ``[camera_watch]`` section of the tracker config (docs/calibration.md, "Watching the cameras")."""

    enabled: bool = param(False, "watch every camera against the others while tracking; set a moved one aside and "
                                 "re-calibrate it from the robots' sightings")
    samples_per_s: float = param(8.0, "sightings per camera and second checked against the other cameras (the "
                                      "rest are not: each check is a multi-camera fit)")
    checks_per_s: float = param(40.0, "sightings checked per second over all cameras at most: with more cameras than "
                                      "checks_per_s / samples_per_s each camera is checked less often, in turn, so "
                                      "16 cameras cost what 5 do")
    reference_span_s: float = param(0.15, "the other cameras' sightings within this many seconds of a checked "
                                          "one form its reference cube pose, seconds")
    reference_cameras: int = param(2, "other cameras that must see the cube for a reference (one alone is weak in "
                                      "depth: the watcher then says so and waits)")
    reference_cameras_max: int = param(4, "other cameras in a reference at most (those with a sighting nearest in "
                                          "time): with many cameras a check stays a small fit")
    reference_rms_px: float = param(3.0, "a reference fit with a larger RMS corner residual is not used, pixels")
    window_s: float = param(2.0, "sliding window of a camera's checked sightings, seconds")
    check_every_s: float = param(0.5, "how often each camera's window is fitted, seconds")
    min_points: int = param(40, "corners a window needs before it can declare a camera moved")
    baseline_s: float = param(30.0, "a camera's settled pose (what a window is compared with) is fitted to its "
                                    "checked sightings of this many seconds before the window, seconds")
    baseline_every_s: float = param(5.0, "how often the settled pose is fitted again, seconds")
    settle_span_s: float = param(8.0, "a settled pose is fitted only to samples spanning this long at least (a "
                                      "camera is judged from then on): fitted to the robot's first seconds in one "
                                      "spot, it took up the other cameras' error there and wandered 30-60 mm / 1 deg "
                                      "along the turn / sideways-shift ambiguity, and a window where the robot was "
                                      "seen elsewhere said moved (docs/calibration.md, Session 26), seconds")
    moved_px: float = param(5.0, "moved: the refitted pose moves the camera's corners by more than this (RMS), "
                                 "pixels")
    moved_sigmas: float = param(4.0, "moved, a small bump: ... or by more than this many times the camera's own "
                                     "window shift while unmoved (the RMS of its windows' shifts over the baseline_s "
                                     "before the window; at least moved_min_px): a bump that moves the corners by "
                                     "3-5 px is far out of a quiet camera's 0.5-1 px (docs/calibration.md, Session "
                                     "28); 0: moved_px alone")
    moved_min_px: float = param(2.0, "moved, a small bump: ... never by less than this, pixels")
    long_window_s: float = param(6.0, "moved, a small bump that lasts: a second, longer window of the camera's "
                                      "checked sightings, judged as the window is against its own noise (the RMS "
                                      "shift of windows as long: a still camera's 6 s windows shift 25 % less than "
                                      "its 2 s ones, a bump's as much); the bump of issue 27's seed 443 (1.5-3.5 px) "
                                      "was never declared without it (docs/calibration.md, Session 31); seconds, "
                                      "0: none")
    long_sigmas: float = param(3.5, "moved, by the long window: its shift over this many times its own noise (as "
                                    "moved_sigmas)")
    long_min_px: float = param(2.0, "moved, by the long window: its corner shift threshold never under this, pixels")
    long_ratio: float = param(3.0, "moved, by the long window: its pose explains it this many times better than the "
                                   "settled pose (as moved_ratio; with three cameras the bumped camera's 3-4.2, its "
                                   "partners' under 2.9: a rigid move explains only the camera that moved)")
    moved_ratio: float = param(4.0, "moved: ... and the window's pose explains the window this many times better "
                                    "(median corner residual) than the settled pose")
    moved_m: float = param(0.01, "moved: ... and the camera is more than this far from its pose, metres")
    moved_deg: float = param(0.5, "moved: ... or turned by more than this, degrees")
    rejoin_points: int = param(400, "corners gathered since a camera moved before its re-calibration is tried")
    rejoin_rounds: int = param(20, "rounds of the re-calibration's joint fit (the camera's pose, then the cube's "
                                   "poses with this camera's corners in them, alternately) at most")
    rejoin_sigma_m: float = param(0.002, "a re-calibrated pose rejoins when its position is known to this "
                                         "(standard deviation), metres")
    rejoin_sigma_deg: float = param(0.05, "... and its orientation to this (standard deviation), degrees")
    rejoin_spread_m: float = param(0.005, "... and its sightings themselves pin its position to this: the standard "
                                          "deviation of its fits leaving out each of 8 blocks of them (in time) in "
                                          "turn (a block jackknife), metres (session 26: replaces rejoin_agree_m, "
                                          "its older and newer halves within 4 mm)")
    rejoin_spread_deg: float = param(0.15, "... and its orientation to this, degrees (replaces rejoin_agree_deg, 0.1)")
    corner_noise_px: float = param(0.5, "corner noise the fits assume (scales their uncertainty), pixels")
    gate_px: float = param(12.0, "a sighting's detections are matched to faces within this of where its own "
                                 "camera's cube pose projects them, pixels")
    suspect_px: float = param(4.0, "suspect: a camera's last suspect_samples checked sightings each miss the other "
                                   "cameras' cube pose by more than this (median corner residual at its settled "
                                   "pose), pixels; a suspect camera leaves the fusion until it agrees again")
    suspect_samples: int = param(2, "checked sightings in a row that make a camera suspect, or clear it")
    gate_prediction_px: float = param(3.0, "a watched camera's sighting is held out of the fusion when it misses the "
                                           "fused prediction by more than this (median corner residual at its "
                                           "settled pose) and gate_prediction_ratio times more than the other "
                                           "cameras' latest sightings (their median: one other camera's miss "
                                           "let a bumped camera's first sightings in, docs/calibration.md, "
                                           "Session 28), pixels; 0: never")
    gate_prediction_ratio: float = param(4.0, "... see gate_prediction_px")
    gate_hold_ratio: float = param(0.0, "a camera's sighting held off the prediction holds its later ones too while "
                                        "each misses the prediction by more than gate_prediction_px, this many "
                                        "times the camera's own misses before the hold (their median over window_s) "
                                        "and more than the other cameras' latest (their median), for window_s at "
                                        "most, until one does not: a bumped camera's second and "
                                        "third sightings, fused before, dragged the track and made a still camera "
                                        "miss most; 2 cut the burnt seeds' largest errors after a bump but not the "
                                        "held-out one's, and cost unbumped sessions 2-3 poses of 900 "
                                        "(docs/calibration.md, Session 30); 0: never (the default)")
    follow_m: float = param(0.0, "drift: a camera whose settled pose has moved more than this since its anchor "
                                 "(its settled pose over its first whole baseline_s, or at its last follow) is "
                                 "followed when moving it by that much makes the other cameras' settled poses "
                                 "agree with their anchors again (follow_ratio), metres; 0: never (the default: "
                                 "0.002 followed a 2 mm/min drift to within 3.2-6.4 mm on the development scenes, "
                                 "5.6 mm on a held-out one, not the 5 mm aimed at; docs/calibration.md)")
    follow_px: float = param(0.3, "drift: ... and when that move shifts its corners by more than this (RMS): with no "
                                  "drift a camera's settled position wanders 0.11-0.55 px from its anchor in ten "
                                  "minutes (references joined over unsynchronised sightings of a robot turning; "
                                  "follow_ratio keeps it unfollowed), pixels")
    follow_ratio: float = param(2.0, "drift: ... when the camera's own move shifts its corners this many times more "
                                     "(RMS px) than the largest shift left in any other camera's settled pose once "
                                     "it is moved")

    def __post_init__(self) -> None:
        check_at_least(self, 0, "gate_prediction_px", "follow_m", "settle_span_s", "moved_sigmas", "gate_hold_ratio",
                       "long_window_s")
        check_positive(self, "baseline_s", "baseline_every_s", "samples_per_s", "checks_per_s", "reference_span_s",
                       "reference_rms_px", "window_s", "check_every_s", "moved_px", "moved_min_px",
                       "long_sigmas", "long_min_px", "long_ratio", "moved_ratio", "moved_m", "moved_deg",
                       "rejoin_sigma_m", "rejoin_sigma_deg", "rejoin_spread_m",
                       "rejoin_spread_deg", "corner_noise_px", "gate_px", "suspect_px", "gate_prediction_ratio",
                       "follow_px", "follow_ratio")
        check_at_least(self, 1, "reference_cameras", "suspect_samples")
        check(self.reference_cameras_max >= self.reference_cameras, f"reference_cameras_max "
              f"({self.reference_cameras_max}) must be at least reference_cameras ({self.reference_cameras})")
        check_at_least(self, 0, "rejoin_rounds")
        check_at_least(self, 6, "min_points", "rejoin_points")
        check(self.check_every_s <= self.window_s,
              f"check_every_s ({self.check_every_s}) must not exceed window_s ({self.window_s})")
        check(self.long_window_s == 0 or self.window_s < self.long_window_s < self.baseline_s,
              f"long_window_s ({self.long_window_s}) must be 0 or between window_s ({self.window_s}) and "
              f"baseline_s ({self.baseline_s})")
        check(self.window_s < self.baseline_s, f"window_s ({self.window_s}) must be shorter than baseline_s "
              f"({self.baseline_s})")
        check(self.settle_span_s < self.baseline_s, f"settle_span_s ({self.settle_span_s}) must be shorter than "
              f"baseline_s ({self.baseline_s})")


@enum.unique
class CameraState(enum.Enum):
    WATCHED = "watched"  # in the fusion, checked against the others
    SUSPECT = "suspect"  # disagrees with the others right now: out of the fusion, still checked and judged
    RECALIBRATING = "re-calibrating"  # moved: set aside, its sightings gathered for a new pose


@enum.unique
class EventKind(enum.Enum):
    MOVED = "moved"
    REJOINED = "rejoined"
    FOLLOWED = "followed"  # a drift's step: the pose in use moved, no alarm


@dataclass(frozen=True, slots=True, eq=False)
class WatchEvent:
    """Something the watcher decided: ``camera`` ``kind`` at host time ``time_s``; ``offset_m``
    and ``offset_deg`` how far its pose moved (moved: the window's refit against the pose it
    had; rejoined: the new pose against the one before the move; followed: the drift's step of
    the pose in use); ``T_world_cam`` the refitted or new pose; ``sightings`` how many sightings
    the new pose comes from (rejoined)."""

    kind: EventKind
    camera: str
    time_s: float
    offset_m: float
    offset_deg: float
    T_world_cam: np.ndarray
    sightings: int = 0

    @property
    def message(self) -> str:
        """One line for the status line and logs."""
        if self.kind is EventKind.MOVED:
            return f"{self.camera} moved {100 * self.offset_m:.1f} cm / {self.offset_deg:.1f} deg; set aside"
        if self.kind is EventKind.FOLLOWED:
            return f"{self.camera} drifting: followed {1000 * self.offset_m:.1f} mm"
        return (f"{self.camera} re-calibrated from {self.sightings} sightings ({100 * self.offset_m:.1f} cm / "
                f"{self.offset_deg:.1f} deg from its old pose); rejoined")


@dataclass(frozen=True, slots=True, eq=False)
class DriftStep:
    """A drift followed (its event: ``followed``, no alarm): at host time ``time_s`` the pose in
    use of ``camera`` moved by ``offset_m`` / ``offset_deg`` to ``T_world_cam``, its settled pose's
    move since its anchor; ``shift_px`` that move's shift of its corners (RMS), ``others_px`` /
    ``others_after_px`` the largest shift of another camera's settled pose from its anchor before
    and after the camera was moved in their references."""

    camera: str
    time_s: float
    offset_m: float
    offset_deg: float
    shift_px: float
    others_px: float
    others_after_px: float
    T_world_cam: np.ndarray


def clock_text(time_s: float) -> str:
    """A host time (Unix seconds) as the UTC wall-clock time of the status line, HH:MM:SS."""
    return datetime.datetime.fromtimestamp(time_s, datetime.UTC).strftime("%H:%M:%S")


def event_record(event: WatchEvent) -> dict[str, Any]:
    """One event as a JSON object (a line of ``camera_watch.jsonl`` and an entry of run.json)."""
    position, q = position_quat_from_T(event.T_world_cam)
    return {"event": event.kind.value, "camera": event.camera, "time": round(event.time_s, 6),
            "utc": clock_text(event.time_s), "offset_m": round(event.offset_m, 5),
            "offset_deg": round(event.offset_deg, 4), "sightings": event.sightings,
            "position": [round(float(v), 6) for v in position], "quaternion_xyzw": [round(float(v), 9) for v in q]}


@dataclass(frozen=True, slots=True, eq=False)
class WatchSample:
    """One checked sighting: the cube's corners where the other cameras put them
    (``points_world_m`` (N, 3)), where this camera saw them (``normalized`` (N, 2), undistorted
    normalised image coordinates; ``focal_px`` (N,) its focal length). For the re-calibration's
    joint fit (:func:`cubetrack.calib.recalibrate.recalibrate`): the sighting's own corner sets
    (``own_sets``), the other cameras' (``reference_sets``) and the cube pose they gave
    (``T_world_cube``, None when not kept); ``reference_rms_px`` the RMS corner residual of that
    fit (how well the other cameras agree among themselves)."""

    camera: str
    time_s: float
    points_world_m: np.ndarray
    normalized: np.ndarray
    focal_px: np.ndarray
    own_sets: tuple[CornerSet, ...] = ()
    reference_sets: tuple[CornerSet, ...] = ()
    T_world_cube: np.ndarray | None = None
    reference_rms_px: float = 0.0


VELOCITY_SIGMA = (1.0, 4.0)  # the reference fits' prior spread of the cube's velocities: m/s, rad/s
# the watcher's fits' Gauss-Newton steps at most (they stop on convergence): on a bumped 4-camera scene within
# 0.012 mm / 0.01 deg of the trust-region solver's solutions, 5.2x (reference fits) and 1.8x (camera refits)
# cheaper (docs/history/camera-watch.md, "The reference fit by Gauss-Newton")
FIT_ITERATIONS = 30
# the watcher matches a sighting's faces where the fused prediction projects them, within this (ids distinct): a
# bumped camera's corners land several pixels off (1 deg ~ 10 px here), the prediction's own error is a few px
PREDICTION_GATE_PX = 40.0
# a check's reference fit takes this many sightings of each other camera, those nearest the checked one in time (more
# average the corners' noise; each costs the fit and the matching)
REFERENCE_SIGHTINGS = 2
# three cameras, several windows saying moved: the best newer-pose miss within this ratio of the second best is a near
# tie, which the references' rise decides (CameraWatch._culprit; docs/calibration.md, "Session 29")
NEAR_TIE = 0.8
WINDOW_PRIOR_M = 0.05  # a window's fit: prior spread of the camera's position about its settled pose, metres
WINDOW_PRIOR_DEG = 3.0  # ... and of its orientation, degrees
# a drift's follow: the settled pose's position fitted again (its orientation kept) with a prior of this spread about
# its anchor, metres: a robot's sightings pin a camera's distance weakly, and a span's settled pose wanders
# millimetres from one span to the next while its corners move by a tenth of a pixel (none instead: the same steps
# to 0.2 mm on the development scenes, docs/calibration.md)
FOLLOW_PRIOR_M = 0.002


def stacked(samples: Sequence[WatchSample]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The samples' points, normalised image points and focal lengths, one array each."""
    return (np.concatenate([s.points_world_m for s in samples]), np.concatenate([s.normalized for s in samples]),
            np.concatenate([s.focal_px for s in samples]))


@dataclass(frozen=True, slots=True, eq=False)
class CameraFit:
    """A camera pose fitted to world points: ``T_world_cam``; ``sigma_m`` and ``sigma_deg`` the
    largest standard deviation of its position (m) and orientation (deg, about any world axis)
    at the given corner noise; ``rms_px`` the RMS corner residual after the fit; ``points`` how
    many corners were used."""

    T_world_cam: np.ndarray
    sigma_m: float
    sigma_deg: float
    rms_px: float
    points: int

    def offset_from(self, T_world_cam: np.ndarray) -> tuple[float, float]:
        """How far this pose is from ``T_world_cam``: the distance between the optical centres
        (m) and the angle between the orientations (deg)."""
        return (float(np.linalg.norm(self.T_world_cam[:3, 3] - T_world_cam[:3, 3])),
                rotation_angle(T_world_cam[:3, :3], self.T_world_cam[:3, :3], unit="deg"))


def set_medians(values: np.ndarray, lengths: Sequence[int]) -> list[float]:
    """The median of each consecutive run of ``values`` (runs of ``lengths``, none empty), in
    one sort: each run's middle one or two values once sorted within the runs."""
    n = np.asarray(lengths)
    start = np.concatenate([[0], np.cumsum(n)[:-1]])
    ordered = values[np.lexsort((values, np.repeat(np.arange(len(n)), n)))]
    return ((ordered[start + (n - 1) // 2] + ordered[start + n // 2]) / 2.0).tolist()


def residuals_px(T_world_cam: np.ndarray, points_world_m: np.ndarray, normalized: np.ndarray,
                 focal_px: np.ndarray) -> np.ndarray:
    """(N, 2) reprojection residuals (px) of world points seen at ``normalized`` (undistorted
    normalised image coordinates, each point's camera focal length ``focal_px``) by a camera at
    ``T_world_cam``. A point at or behind the camera gets a 1000 px residual."""
    R, p = T_world_cam[:3, :3], T_world_cam[:3, 3]
    in_cam = (points_world_m - p) @ R
    z = in_cam[:, 2]
    ok = z > 1e-6
    out = np.full((len(z), 2), 1000.0)
    out[ok] = (in_cam[ok, :2] / z[ok, None] - normalized[ok]) * focal_px[ok, None]
    return out


def resection_jacobian_px(T_world_cam: np.ndarray, points_world_m: np.ndarray, focal_px: np.ndarray) -> np.ndarray:
    """(2N, 6) derivative of :func:`residuals_px` (rows u0, v0, u1, ...) by a world-frame
    increment ``[δp (m), δθ (rad)]`` of the camera pose (as :func:`cubetrack.estimate.reprojection.perturbed`)."""
    R, p = T_world_cam[:3, :3], T_world_cam[:3, 3]
    v = points_world_m - p
    in_cam = v @ R
    z = np.where(in_cam[:, 2] > 1e-6, in_cam[:, 2], np.inf)
    # d(x, y, z)_cam: by δp -R^T, by δθ R^T [v]x
    d_p = np.broadcast_to(-R.T, (len(v), 3, 3))
    skew = np.zeros((len(v), 3, 3))
    skew[:, 0, 1], skew[:, 0, 2], skew[:, 1, 2] = -v[:, 2], v[:, 1], -v[:, 0]
    skew[:, 1, 0], skew[:, 2, 0], skew[:, 2, 1] = v[:, 2], -v[:, 1], v[:, 0]
    d_theta = R.T[None] @ skew
    d_cam = np.concatenate([d_p, d_theta], axis=2)  # (N, 3, 6)
    proj = np.zeros((len(v), 2, 3))
    proj[:, 0, 0] = proj[:, 1, 1] = focal_px / z
    proj[:, 0, 2] = -focal_px * in_cam[:, 0] / z**2
    proj[:, 1, 2] = -focal_px * in_cam[:, 1] / z**2
    return (proj @ d_cam).reshape(-1, 6)


def refit_camera(points_world_m: np.ndarray, normalized: np.ndarray, focal_px: np.ndarray,
                 T_world_cam_init: np.ndarray, corner_noise_px: float = 0.5,
                 f_scale_px: float = 2.0, prior_sigma: tuple[float, float] | None = None,
                 position_only: bool = False) -> CameraFit | None:
    """The camera pose that best explains ``normalized`` (N, 2) as images of ``points_world_m``
    (N, 3), started from ``T_world_cam_init``; None with fewer than six points or when the fit
    fails. ``corner_noise_px`` scales the covariance; ``f_scale_px`` is the robust loss's knee;
    ``prior_sigma`` (m, rad): a Gaussian prior keeping the pose near ``T_world_cam_init`` (a
    window of points bunched in one spot leaves a translation and a rotation that mimic each
    other free); ``position_only``: the orientation kept as ``T_world_cam_init``'s, the position
    alone fitted (``sigma_deg`` 0; the prior's rotation part unused)."""
    X = np.asarray(points_world_m, float).reshape(-1, 3)
    uv = np.asarray(normalized, float).reshape(-1, 2)
    f = np.broadcast_to(np.asarray(focal_px, float), (len(X),))
    if len(X) < 6:
        return None
    T0 = np.asarray(T_world_cam_init, float)
    n = 3 if position_only else 6
    prior = np.zeros(0) if prior_sigma is None else np.repeat(1.0 / np.asarray(prior_sigma, float), 3)[:n]

    def pose(x: np.ndarray) -> np.ndarray:
        return perturbed(T0, np.concatenate([x, np.zeros(6 - n)]))

    def fun(x: np.ndarray) -> np.ndarray:
        return np.concatenate([residuals_px(pose(x), X, uv, f).ravel() / corner_noise_px, x * prior
                               if len(prior) else prior])

    def jac(x: np.ndarray) -> np.ndarray:
        J = resection_jacobian_px(pose(x), X, f)
        if n == 6:
            J[:, 3:6] = J[:, 3:6] @ so3_left_jacobian(x[3:6])  # x holds a finite rotation increment
        J = J[:, :n] / corner_noise_px
        return np.vstack([J, np.diag(prior)]) if len(prior) else J

    solved = robust_gauss_newton(fun, jac, n, f_scale_px / corner_noise_px, FIT_ITERATIONS) or robust_least_squares(
        fun, jac, np.array([0.01, 0.01, 0.01, 0.002, 0.002, 0.002])[:n], f_scale_px / corner_noise_px, 60)
    if solved is None:
        return None
    x, covariance, _ = solved
    T = pose(x)
    r = residuals_px(T, X, uv, f)
    sigma_m = math.sqrt(max(float(np.linalg.eigvalsh(covariance[:3, :3]).max()), 0.0))
    sigma_rad = math.sqrt(max(float(np.linalg.eigvalsh(covariance[3:, 3:]).max()), 0.0)) if n == 6 else 0.0
    return CameraFit(T, sigma_m, math.degrees(sigma_rad), float(np.sqrt(np.mean(r**2))), len(X))


def shift_px(fit: CameraFit, T_world_cam: np.ndarray, samples: Sequence[WatchSample]) -> float:
    """How far (RMS, px) the refitted pose moves the samples' corners in the image against ``T_world_cam``."""
    X, uv, f = stacked(samples)
    moved = residuals_px(T_world_cam, X, uv, f) - residuals_px(fit.T_world_cam, X, uv, f)
    return float(np.sqrt(np.mean(np.sum(moved**2, axis=1))))


@dataclass(frozen=True, slots=True, eq=False)
class Verdict:
    """A window's fit against the pose in use: the fit, its corner shift (px, RMS) and offset
    (m, deg), and whether the camera moved by the thresholds (both halves agreeing)."""

    fit: CameraFit
    shift_px: float
    offset_m: float
    offset_deg: float
    moved: bool


def median_residuals_px(fit: CameraFit, T_world_cam: np.ndarray, samples: Sequence[WatchSample]
                        ) -> tuple[float, float]:
    """The samples' median corner residual (px) against ``T_world_cam`` and against the refitted pose."""
    X, uv, f = stacked(samples)
    before = np.linalg.norm(residuals_px(T_world_cam, X, uv, f), axis=1)
    after = np.linalg.norm(residuals_px(fit.T_world_cam, X, uv, f), axis=1)
    return float(np.median(before)), float(np.median(after))


def improvement_px(fit: CameraFit, T_world_cam: np.ndarray, samples: Sequence[WatchSample]) -> float:
    """How much better the refitted pose explains the samples than ``T_world_cam``: the median
    corner residual (px) against the one minus that against the other."""
    before, after = median_residuals_px(fit, T_world_cam, samples)
    return before - after


def window_verdict(samples: Sequence[WatchSample], T_world_cam: np.ndarray, params: WatchParams,
                   moved_px: float | None = None, moved_ratio: float | None = None) -> Verdict | None:
    """Fit a camera's window of samples against its settled pose ``T_world_cam`` and judge it
    (see the module doc) by the corner shift ``moved_px`` (None: ``params.moved_px``; a small bump's:
    :meth:`CameraWatch._moved_px`) and the ratio ``moved_ratio`` (None: ``params.moved_ratio``); None when
    the window holds under ``min_points`` corners or the fit fails."""
    moved_px = params.moved_px if moved_px is None else moved_px
    moved_ratio = params.moved_ratio if moved_ratio is None else moved_ratio
    if sum(len(s.points_world_m) for s in samples) < params.min_points:
        return None
    fit = refit_camera(*stacked(samples), T_world_cam, params.corner_noise_px,
                       prior_sigma=(WINDOW_PRIOR_M, math.radians(WINDOW_PRIOR_DEG)))
    if fit is None:
        return None
    shift = shift_px(fit, T_world_cam, samples)
    off_m, off_deg = fit.offset_from(T_world_cam)
    before, after = median_residuals_px(fit, T_world_cam, samples)
    moved = (shift > moved_px and (off_m > params.moved_m or off_deg > params.moved_deg)
             and before >= moved_ratio * after)
    if moved:  # consistent: each half on its own is explained much better by the new pose
        middle = len(samples) // 2
        moved = middle >= 2 and all(improvement_px(fit, T_world_cam, part) > moved_px / 2
                                    for part in (samples[:middle], samples[middle:]))
    return Verdict(fit, shift, off_m, off_deg, moved)


def holds(sample: WatchSample, camera: str) -> bool:
    """Whether ``camera``'s sightings are in the sample's reference."""
    return any(s.camera == camera for s in sample.reference_sets)


def with_camera_at(sample: WatchSample, camera: str, T_cam_world: np.ndarray | None, corner_noise_px: float
                   ) -> WatchSample | None:
    """The sample as if ``camera`` stood at ``T_cam_world`` (None: as if it had not been seen):
    its sightings in the reference taken there (or left out) and the reference fitted again, the
    sample's corners placed in the world by that fit (the sample itself when its reference does not
    hold ``camera``); None when it kept no cube pose or corner sets, or the fit fails."""
    if not holds(sample, camera):
        return sample
    if sample.T_world_cube is None or not sample.own_sets:
        return None
    sets = tuple(s for s in sample.reference_sets if s.camera != camera) if T_cam_world is None else tuple(
        dataclasses.replace(s, T_cam_world=T_cam_world) if s.camera == camera else s for s in sample.reference_sets)
    refit = solve_joint(sets, sample.T_world_cube, sample.time_s, corner_noise_px, velocity_sigma=VELOCITY_SIGMA,
                        iterations=FIT_ITERATIONS)
    if refit is None:
        return None
    points = np.concatenate([transform_points(moved_pose(refit.T_world_cube, refit.velocity_m_s,
                                                         refit.angular_velocity_rad_s, s.time_s - sample.time_s),
                                              s.points_cube_m) for s in sample.own_sets])
    return dataclasses.replace(sample, points_world_m=points, reference_sets=sets, T_world_cube=refit.T_world_cube,
                               reference_rms_px=refit.rms_px)


def without_camera(sample: WatchSample, camera: str, reference_cameras: int) -> WatchSample | None:
    """The sample with ``camera``'s sightings taken out of its reference (a camera declared moved
    since: they may be from after its move, and the older and newer parts of a re-calibration
    would otherwise hold different cameras' calibrations), or None when fewer than
    ``reference_cameras`` other cameras are left in it. Its corners' world points stay the old
    reference's until the re-calibration's joint fit places them again
    (:func:`cubetrack.calib.recalibrate.joint_fit`, from its first round)."""
    if not holds(sample, camera):
        return sample
    sets = tuple(s for s in sample.reference_sets if s.camera != camera)
    return dataclasses.replace(sample, reference_sets=sets) if len({s.camera for s in sets}) >= reference_cameras \
        else None


class CameraWatch:
    """Every camera watched against the others (see the module doc). Visible state: ``state``
    (camera -> :class:`CameraState`), ``T_world_cam`` (camera -> the pose the tracker uses: the
    calibrated one, or the re-calibrated one after :meth:`rejoin`), ``settled`` (camera -> its
    settled pose), ``samples`` (camera -> its checked sightings: the window and the settled pose's
    span while watched, everything since the move while re-calibrating), ``moved_pose`` (camera ->
    its settled pose when it moved), ``events`` (every decision so far) and ``stats`` (counts of
    checked sightings and why others were not)."""

    def __init__(self, layouts: dict[str, CubeLayout], T_world_cams: dict[str, np.ndarray],
                 params: WatchParams = WatchParams(), estimator_params: EstimatorParams | None = None):
        self.layouts = layouts
        self.params = params
        self.estimator_params = estimator_params or EstimatorParams()
        self.T_world_cam = {c: np.asarray(T, float).copy() for c, T in T_world_cams.items()}
        self.state = {c: CameraState.WATCHED for c in T_world_cams}
        self.samples: dict[str, deque[WatchSample]] = {c: deque() for c in T_world_cams}
        self.moved_pose: dict[str, np.ndarray] = {}
        self.settled: dict[str, np.ndarray] = {}
        self._next_baseline_s = -math.inf
        self._disagreement: dict[str, deque[tuple[float, float]]] = {c: deque() for c in T_world_cams}
        # camera -> its checks' (time, RMS corner residual of the reference fit, px; refused ones too): how well the
        # OTHER cameras agree among themselves where this one checks (_references_rise_px)
        self._reference_rms: dict[str, deque[tuple[float, float]]] = {c: deque() for c in T_world_cams}
        # (camera, window length) -> its windows' (time, shift px) against its settled pose: its own noise while
        # unmoved (_moved_px)
        self._shifts: dict[tuple[str, float], deque[tuple[float, float]]] = {}
        # camera -> its latest samples' (time, median corner miss at its settled pose, px)
        self._misses: dict[str, deque[tuple[float, float]]] = {c: deque(maxlen=params.suspect_samples)
                                                               for c in T_world_cams}
        self._off_prediction: dict[str, dict[str, tuple[float, float]]] = {r: {} for r in layouts}
        # (robot, camera) -> its misses of the prediction not held, (time, px), and its hold: (since, its level then)
        self._own_misses: dict[tuple[str, str], deque[tuple[float, float]]] = {}
        self._holding: dict[tuple[str, str], tuple[float, float]] = {}
        self.events: list[WatchEvent] = []
        self.follows: list[DriftStep] = []
        # camera -> its settled pose over its first whole baseline_s, or at its last follow: what a drift is
        # measured from
        self.anchor: dict[str, np.ndarray] = {}
        self.stats: Counter[str] = Counter()
        self._recent: dict[str, deque[CubeSighting]] = {r: deque() for r in layouts}
        self._sets: dict[tuple[str, str, int, bool], tuple[np.ndarray | None, list[CornerSet]]] = {}
        self._predicted: dict[tuple[str, str, int], np.ndarray] = {}  # a recent sighting's fused prediction
        self._pending: deque[CubeSighting] = deque()
        self._next_sample_s: dict[str, float] = {}
        self._newest_s = -math.inf
        self._next_check_s = -math.inf

    def excluded(self, camera: str) -> bool:
        """Whether the camera's sightings must stay out of the fusion: it is suspect, or it moved
        and has not rejoined (who serves as a reference: :meth:`referee`)."""
        return self.state.get(camera, CameraState.WATCHED) is not CameraState.WATCHED

    def referee(self, camera: str) -> bool:
        """Whether the camera's sightings may serve in the others' references: not while it
        re-calibrates; not while suspect either, where every check keeps ``reference_cameras``
        others without it (four cameras or more) and no other camera is suspect. With three, a
        suspect camera set aside would leave the other two unchecked, and its own window judged
        against references holding the camera that really moved (issue 27's seed 58: cam3 bumped,
        the suspect cam2 declared)."""
        state = self.state.get(camera, CameraState.WATCHED)
        return state is CameraState.WATCHED or (state is CameraState.SUSPECT and not self._suspects_aside())

    def _suspects_aside(self) -> bool:
        """Whether a suspect camera is no one's reference (see :meth:`referee`): with four cameras or more,
        while it is the only one. Several suspect at once say that the references disagree where the robot
        is, not that each camera moved; set aside together they left references of two cameras that
        disagreed more, every other camera then missed them, and three still cameras were declared moved
        (5 cameras, seed 67: docs/calibration.md, "Session 28")."""
        suspects = sum(s is CameraState.SUSPECT for s in self.state.values())
        return len(self.state) - 2 >= self.params.reference_cameras and suspects <= 1

    def off_prediction(self, sighting: CubeSighting, T_world_cube: np.ndarray) -> bool:
        """Whether a watched camera's sighting must be held out of the fusion: it misses the
        fused prediction ``T_world_cube`` (at its capture time) by more than ``gate_prediction_px``
        (median corner residual at the camera's settled pose), and ``gate_prediction_ratio`` times
        more than the latest sightings of the other cameras in use (within ``window_s``; at least
        ``reference_cameras`` of them) miss it, by their median: one other camera missing too (its
        own sighting off, or the prediction off from its view) does not let a bumped camera in. The
        first sightings after a bump come before any check can judge them (a check waits for the
        other cameras' sightings around it); this keeps them out. With ``gate_hold_ratio`` (off by
        default) a held camera's later sightings stay held while each misses the prediction by more
        than ``gate_prediction_px``, that many times its own misses before the hold and more than the
        others' latest (their median), for ``window_s`` at most."""
        p = self.params
        settled = self.settled.get(sighting.camera)
        if p.gate_prediction_px <= 0 or settled is None or sighting.robot not in self.layouts:
            return False
        sets = self._corner_sets(sighting)[1]
        if not sets:
            return False
        points_world_m = transform_points(T_world_cube, np.concatenate([s.points_cube_m for s in sets]))
        residual = residuals_px(settled, points_world_m, np.concatenate([s.normalized for s in sets]),
                                np.repeat([s.focal_px for s in sets], [len(s.normalized) for s in sets]))
        miss = float(np.median(np.linalg.norm(residual, axis=1)))
        t = sighting.capture_time_s
        latest = self._off_prediction[sighting.robot]
        latest[sighting.camera] = (t, miss)
        others = [m for c, (s, m) in latest.items() if c != sighting.camera and not self.excluded(c)
                  and s >= t - p.window_s]
        if p.gate_hold_ratio > 0 and self._held_on((sighting.robot, sighting.camera), t, miss, others):
            return True
        held = (miss > p.gate_prediction_px and len(others) >= p.reference_cameras
                and miss > p.gate_prediction_ratio * float(np.median(others)))
        self.stats["held off the prediction"] += held
        if p.gate_hold_ratio > 0:
            self._note_miss((sighting.robot, sighting.camera), t, miss, held)
        return held

    def _held_on(self, key: tuple[str, str], t: float, miss: float, others: list[float]) -> bool:
        """``gate_hold_ratio``: whether the (robot, camera) sighting stays held, its camera's earlier one
        having been held within ``window_s`` and this one missing the prediction as :meth:`off_prediction`
        says."""
        p = self.params
        hold = self._holding.pop(key, None)
        if hold is None or t - hold[0] > p.window_s or miss <= max(
                p.gate_prediction_px, p.gate_hold_ratio * hold[1], float(np.median(others)) if others else 0.0):
            return False
        self._holding[key] = hold
        self.stats["held on"] += 1
        return True

    def _note_miss(self, key: tuple[str, str], t: float, miss: float, held: bool) -> None:
        """``gate_hold_ratio``: keep a sighting's miss among its (robot, camera)'s own over ``window_s``
        when it was let in, or start a hold at the level of those when it was held."""
        own = self._own_misses.setdefault(key, deque())
        while own and own[0][0] < t - self.params.window_s:
            own.popleft()
        if not held:
            own.append((t, miss))
        elif own:
            self._holding[key] = (t, float(np.median([m for _, m in own])))

    def points(self, camera: str) -> int:
        """Corners the camera's samples hold (a re-calibrating camera's progress towards ``rejoin_points``)."""
        return sum(len(s.points_world_m) for s in self.samples.get(camera, ()))

    def ready(self) -> list[str]:
        """The re-calibrating cameras with ``rejoin_points`` corners gathered: their
        re-calibration can be tried (:func:`cubetrack.calib.recalibrate.recalibrate`)."""
        return [c for c, s in self.state.items()
                if s is CameraState.RECALIBRATING and self.points(c) >= self.params.rejoin_points]

    def add(self, sighting: CubeSighting, T_world_cube: np.ndarray | None = None) -> list[WatchEvent]:
        """Take one sighting (any camera, any robot, in about capture order) and the fused
        prediction of its cube's pose at its capture time (None: no track), which its faces are
        matched by; returns the events it led to (a camera declared moved, a drift followed)."""
        if sighting.robot not in self.layouts or sighting.camera not in self.state:
            return []
        t, p = sighting.capture_time_s, self.params
        self._newest_s = max(self._newest_s, t)
        recent = self._recent[sighting.robot]
        recent.append(sighting)
        if T_world_cube is not None:
            self._predicted[(sighting.camera, sighting.robot, sighting.seq)] = T_world_cube
        keep_s = 2.0 * p.reference_span_s + 1.0
        while recent and recent[0].capture_time_s < self._newest_s - keep_s:
            old = recent.popleft()
            for by_prediction in (True, False):
                self._sets.pop((old.camera, old.robot, old.seq, by_prediction), None)
            self._predicted.pop((old.camera, old.robot, old.seq), None)
        if t >= self._next_sample_s.get(sighting.camera, -math.inf):  # checks_per_s shared by the cameras in turn
            self._pending.append(sighting)
            self._next_sample_s[sighting.camera] = t + self._sample_interval_s()
        while self._pending and self._pending[0].capture_time_s + self.params.reference_span_s <= self._newest_s:
            checked = self._pending.popleft()
            sample = self._sample(checked)
            if sample is not None:
                self.samples[sample.camera].append(sample)
                self._judge(sample, checked.robot)
        if self._newest_s < self._next_check_s:
            return []
        self._next_check_s = self._newest_s + self.params.check_every_s
        return self._check(self._newest_s)

    def rejoin(self, camera: str, T_world_cam: np.ndarray, time_s: float, sightings: int) -> WatchEvent:
        """Let a re-calibrated camera back in at its new pose ``T_world_cam`` (host time ``time_s``;
        ``sightings`` it was found from); its window restarts."""
        before = self.moved_pose.pop(camera, self.T_world_cam[camera])
        self.T_world_cam[camera] = np.asarray(T_world_cam, float).copy()
        self.state[camera] = CameraState.WATCHED
        self.samples[camera].clear()
        for span_s in (self.params.window_s, self.params.long_window_s):
            self._shifts.pop((camera, span_s), None)
        for trail in self._reference_rms.values():  # the references change: with this camera from now on
            trail.clear()
        self.settled.pop(camera, None)
        self.anchor.clear()
        fit = CameraFit(self.T_world_cam[camera], 0.0, 0.0, 0.0, 0)
        offset_m, offset_deg = fit.offset_from(before)
        event = WatchEvent(EventKind.REJOINED, camera, time_s, offset_m, offset_deg, self.T_world_cam[camera].copy(),
                           sightings)
        self.events.append(event)
        return event

    def _check(self, now_s: float) -> list[WatchEvent]:
        """Fit every watched camera's window; declare the one :meth:`_culprit` names, if any."""
        p = self.params
        verdicts: dict[str, Verdict] = {}
        baseline = now_s >= self._next_baseline_s
        if baseline:
            self._next_baseline_s = now_s + p.baseline_every_s
        for camera, samples in self.samples.items():
            if self.state[camera] is CameraState.RECALIBRATING:
                continue
            while samples and samples[0].time_s < now_s - p.window_s - p.baseline_s:
                samples.popleft()
            if baseline:
                self._settle(camera, [s for s in samples if s.time_s < now_s - p.window_s])
            if camera not in self.settled:
                continue
            verdict = self._verdict(camera, samples, p.window_s, now_s)
            if p.long_window_s > 0:  # a small bump: an offset that lasts, against the longer window's own noise
                longer = self._verdict(camera, samples, p.long_window_s, now_s)
                if longer is not None and longer.moved and (verdict is None or not verdict.moved):
                    self.stats["moved by the long window"] += 1
                    verdict = longer
            if verdict is not None:
                verdicts[camera] = verdict
        worst = self._culprit(verdicts, now_s)
        if worst is None:
            followed = self._follow(now_s) if baseline and not any(v.moved for v in verdicts.values()) else None
            return [] if followed is None else [followed]
        return [self._declare(*worst, now_s)]

    def _verdict(self, camera: str, samples: Sequence[WatchSample], span_s: float, now_s: float) -> Verdict | None:
        """The camera's samples of the last ``span_s`` judged against its settled pose by
        :func:`window_verdict` at :meth:`_moved_px`'s threshold for windows that long; the window's
        shift joins that history."""
        window = [s for s in samples if s.time_s >= now_s - span_s]
        ratio = self.params.moved_ratio if span_s == self.params.window_s else self.params.long_ratio
        verdict = window_verdict(window, self.settled[camera], self.params, self._moved_px(camera, span_s, now_s),
                                 ratio)
        if verdict is not None:
            self._shifts[camera, span_s].append((now_s, verdict.shift_px))
        return verdict

    def _moved_px(self, camera: str, span_s: float, now_s: float) -> float:
        """The corner shift (px) that says ``camera`` moved now by its window of ``span_s``
        (``window_s``, or ``long_window_s``): ``moved_px``, or less, down to ``moved_min_px``
        (``long_min_px`` for the long window), ``moved_sigmas`` times the RMS shift of its windows
        as long that ended in the ``baseline_s`` before this window began (its own noise while
        unmoved, once it has a quarter of that span's checks; a bump's windows are in it only once
        they are older than a window)."""
        p, shifts = self.params, self._shifts.setdefault((camera, span_s), deque())
        while shifts and shifts[0][0] < now_s - span_s - p.baseline_s:
            shifts.popleft()
        past = [shift for t, shift in shifts if t <= now_s - span_s]
        if p.moved_sigmas <= 0 or len(past) < p.baseline_s / p.check_every_s / 4:
            return p.moved_px
        noise_px = math.sqrt(sum(shift**2 for shift in past) / len(past))
        sigmas, floor_px = (p.moved_sigmas, p.moved_min_px) if span_s == p.window_s else (p.long_sigmas, p.long_min_px)
        return min(p.moved_px, max(floor_px, sigmas * noise_px))

    def _follow(self, now_s: float) -> WatchEvent | None:
        """Follow a drift (see the module doc). With every camera watched, each one's settled pose
        over a whole ``baseline_s`` is fitted again near its anchor, its position alone (a prior of
        ``FOLLOW_PRIOR_M``); each camera that has moved more than ``follow_m`` is tried: moved so
        in the others' references, how far (RMS px of their corners) do their settled poses stay
        from their anchors? The one that leaves the least is followed if its own move shifts its
        corners by more than ``follow_px`` and ``follow_ratio`` times more: its pose in use moves by
        that much, its anchor becomes that pose, and the others keep their samples with their
        references fitted again. Returns the ``followed`` event, or None."""
        p = self.params
        if p.follow_m <= 0 or any(s is not CameraState.WATCHED for s in self.state.values()):
            return None
        start_s = now_s - p.window_s - p.baseline_s + p.baseline_every_s
        spans = {c: [s for s in self.samples[c] if s.time_s < now_s - p.window_s] for c in self.settled}
        spans = {c: span for c, span in spans.items() if span and span[0].time_s <= start_s}
        for camera in spans:
            self.anchor.setdefault(camera, self.settled[camera])
        if len(spans) < p.reference_cameras + 1:
            return None
        prior = (FOLLOW_PRIOR_M, math.inf)  # the orientation is not fitted
        near = {c: refit_camera(*stacked(span), self.anchor[c], p.corner_noise_px, prior_sigma=prior,
                                position_only=True) for c, span in spans.items()}
        best: tuple[float, str, CameraFit, dict[str, CameraFit], dict[str, list[WatchSample]]] | None = None
        for camera, fit in near.items():
            if fit is None or np.linalg.norm(fit.T_world_cam[:3, 3] - self.anchor[camera][:3, 3]) <= p.follow_m:
                continue
            T_cam_world = invert_T(self.T_world_cam[camera] @ invert_T(self.anchor[camera]) @ fit.T_world_cam)
            again = {c: [m for m in (with_camera_at(s, camera, T_cam_world, p.corner_noise_px)
                                     for s in self.samples[c]) if m is not None] for c in spans if c != camera}
            refits = {c: refit_camera(*stacked(kept), self.settled[c], p.corner_noise_px)
                      for c, kept in ((c, [s for s in again[c] if s.time_s < now_s - p.window_s]) for c in again)
                      if kept}
            if len(refits) < len(again) or any(f is None for f in refits.values()):
                continue
            others = {c: f for c, f in refits.items() if f is not None}
            left = max(shift_px(f, self.anchor[c], spans[c]) for c, f in others.items())
            if best is None or left < best[0]:
                best = left, camera, fit, others, again
        if best is None:
            return None
        left, camera, fit, others, again = best
        shift = shift_px(fit, self.anchor[camera], spans[camera])
        if shift <= p.follow_px or shift < p.follow_ratio * left:
            return None
        T_new = self.T_world_cam[camera] @ invert_T(self.anchor[camera]) @ fit.T_world_cam
        off_m, off_deg = CameraFit(T_new, 0.0, 0.0, 0.0, 0).offset_from(self.T_world_cam[camera])
        before = max(shift_px(CameraFit(self.settled[c], 0.0, 0.0, 0.0, 0), self.anchor[c], spans[c]) for c in others)
        self.follows.append(DriftStep(camera, now_s, off_m, off_deg, shift, before, left, T_new.copy()))
        self.stats["drift followed"] += 1
        self.T_world_cam[camera] = T_new
        self.anchor[camera] = fit.T_world_cam
        for other, refit in others.items():
            self.settled[other] = refit.T_world_cam
            self.samples[other] = deque(again[other])
        event = WatchEvent(EventKind.FOLLOWED, camera, now_s, off_m, off_deg, T_new.copy())
        self.events.append(event)
        return event

    def _declare(self, camera: str, verdict: Verdict, now_s: float) -> WatchEvent:
        """Declare ``camera`` moved (its ``verdict``, at ``now_s``): set it aside with its window's
        newer half as its first samples; every watched camera's window restarts; a re-calibrating
        camera keeps what it gathered with this one taken out of its references
        (:func:`without_camera`): a second camera moved before the first rejoined."""
        p = self.params
        window = [s for s in self.samples[camera] if s.time_s >= now_s - p.window_s]
        for other, samples in self.samples.items():
            self._misses[other].clear()
            self._reference_rms[other].clear()  # the references change: without this camera from now on
            if self.state[other] is CameraState.RECALIBRATING:  # keeps what it gathered, without this one
                kept = [k for k in (without_camera(s, camera, p.reference_cameras) for s in samples) if k is not None]
                samples.clear()
                samples.extend(kept)
                continue
            samples.clear()
            if self.state[other] is CameraState.SUSPECT:
                self.state[other] = CameraState.WATCHED
        self.anchor.clear()  # the others' settled poses were fitted against references that held it
        self.samples[camera].extend(window[len(window) // 2:])  # the newer half: after the move
        self.state[camera] = CameraState.RECALIBRATING
        self.moved_pose[camera] = self.settled.pop(camera)
        event = WatchEvent(EventKind.MOVED, camera, now_s, verdict.offset_m, verdict.offset_deg,
                           verdict.fit.T_world_cam.copy())
        self.events.append(event)
        return event

    def _culprit(self, verdicts: dict[str, Verdict], now_s: float) -> tuple[str, Verdict] | None:
        """The camera to declare moved, if any: of the cameras whose window says moved, the one
        that disagreed most with the others in the references it took part in over the window
        (a moved camera shifts its partners' windows too, through their references). With four
        cameras or more, the camera whose leaving out of the references makes the others agree
        best (:meth:`_others_miss_px`), if its window says moved and the others then agree within
        ``suspect_px``: a camera whose small bump went unseen spoils its partners' references, and
        a partner's window said moved (issue 27's seed 151: cam4 and cam1 declared for cam5). With
        three cameras, of several whose window says moved, the one whose pose fitted to its
        window's newer half makes the others agree again (:meth:`_others_miss_px`); where the
        best two are within ``NEAR_TIE`` of each other, the one of them whose checks' references
        (the two others) still agree as before (:meth:`_references_rise_px`; issue 27's seed 263)."""
        for trail in self._disagreement.values():
            while trail and trail[0][0] < now_s - self.params.window_s:
                trail.popleft()
        moved = [c for c, v in verdicts.items() if v.moved]
        if not moved:
            return None
        suspects = [c for c in moved if self.state[c] is CameraState.SUSPECT and self._suspects_aside()]
        if suspects:  # named when it became suspect; no one's reference since
            top = max(suspects, key=lambda c: verdicts[c].shift_px)
            return top, verdicts[top]
        if self._suspects_aside():  # each left out in turn: the one without which the others agree
            miss = {c: self._others_miss_px(c, None, now_s) for c in verdicts}
            top = min(miss, key=lambda c: miss[c])
            return (top, verdicts[top]) if top in moved and miss[top] <= self.params.suspect_px else None
        if len(moved) > 1:  # each in turn put where its window's newer half says: the one that makes the others agree
            miss = {c: self._others_miss_px(c, self._newer_pose(c, verdicts[c], now_s), now_s) for c in moved}
            top, second = sorted(moved, key=lambda c: miss[c])[:2]
            if miss[top] > NEAR_TIE * miss[second] and len(self.state) - 1 <= self.params.reference_cameras:
                rise = {c: self._references_rise_px(c, now_s) for c in (top, second)}
                if not any(math.isnan(r) for r in rise.values()):  # the one whose references still agree
                    self.stats["near tie"] += 1
                    top = min((top, second), key=lambda c: rise[c])
            return top, verdicts[top]
        score = {c: float(np.median([d for _, d in self._disagreement[c]])) if self._disagreement[c] else 0.0
                 for c in verdicts}
        top = max(score, key=lambda c: score[c])
        return (top, verdicts[top]) if top in moved else None

    def _references_rise_px(self, camera: str, now_s: float) -> float:
        """How much worse the other cameras agree among themselves where ``camera`` is checked: the
        median RMS corner residual of its checks' reference fits over the window's newer half, less
        that over its checks before the window (px; NaN without both). A moved camera spoils the
        references it takes part in, never its own: with three cameras the references of its checks
        are the two others, which still agree, while each partner's hold the moved camera."""
        p, trail = self.params, self._reference_rms[camera]
        newer = [rms for t, rms in trail if t >= now_s - p.window_s / 2]
        before = [rms for t, rms in trail if t < now_s - p.window_s]
        return float(np.median(newer) - np.median(before)) if newer and before else math.nan

    def _newer_pose(self, camera: str, verdict: Verdict, now_s: float) -> np.ndarray:
        """The camera's pose fitted to its samples of the window's newer half (the window's own
        fit straddles the move), or the window's when that fit fails."""
        newer = [s for s in self.samples[camera] if s.time_s >= now_s - self.params.window_s / 2]
        fit = refit_camera(*stacked(newer), verdict.fit.T_world_cam, self.params.corner_noise_px,
                           prior_sigma=(WINDOW_PRIOR_M, math.radians(WINDOW_PRIOR_DEG))) if newer else None
        return verdict.fit.T_world_cam if fit is None else fit.T_world_cam

    def _others_miss_px(self, camera: str, T_world_cam: np.ndarray | None, now_s: float) -> float:
        """If ``camera`` were at ``T_world_cam`` (None: left out, where ``reference_cameras`` others
        are left): the median corner miss (px, at their settled
        poses) of the other watched cameras' samples of the window's newer half (after the move,
        as the one declared keeps) whose reference it took part in, the
        references fitted again with it there (or without it). With three cameras a moved one spoils both others'
        references, and their windows can say moved as loudly as its own; put at its window's pose,
        only the camera that really moved makes the others' references agree with them again."""
        T_cam_world, p, misses = None if T_world_cam is None else invert_T(T_world_cam), self.params, []
        for other, samples in self.samples.items():
            settled = self.settled.get(other)
            if other == camera or settled is None or self.state[other] is CameraState.RECALIBRATING:
                continue
            for sample in samples:
                if sample.time_s < now_s - p.window_s / 2 or not holds(sample, camera) or (
                        T_cam_world is None and len({s.camera for s in sample.reference_sets}) <= p.reference_cameras):
                    continue
                moved = with_camera_at(sample, camera, T_cam_world, p.corner_noise_px)
                if moved is not None:
                    residual = residuals_px(settled, moved.points_world_m, moved.normalized, moved.focal_px)
                    misses.append(float(np.median(np.linalg.norm(residual, axis=1))))
        return float(np.median(misses)) if misses else math.inf

    def _judge(self, sample: WatchSample, robot: str) -> None:
        """Make the sample's camera suspect, or clear it: its last ``suspect_samples`` samples all
        miss the other cameras' cube pose by more than ``suspect_px`` at its settled pose, and it is
        the camera that misses most now (:meth:`_misses_most`); cleared once as many in a row are
        within ``suspect_px``. At least ``reference_cameras`` others must stay in use."""
        camera, p = sample.camera, self.params
        settled = self.settled.get(camera)
        if settled is None or self.state[camera] is CameraState.RECALIBRATING:
            return
        misses = self._misses[camera]
        residual = residuals_px(settled, sample.points_world_m, sample.normalized, sample.focal_px)
        misses.append((sample.time_s, float(np.median(np.linalg.norm(residual, axis=1)))))
        if len(misses) < p.suspect_samples:
            return
        if self.state[camera] is CameraState.SUSPECT:
            self.stats["checked while suspect"] += 1
            if max(m for _, m in misses) <= p.suspect_px:
                self.state[camera] = CameraState.WATCHED
            return
        in_use = [c for c, s in self.state.items() if s is CameraState.WATCHED]
        if min(m for _, m in misses) <= p.suspect_px or len(in_use) - 1 < p.reference_cameras:
            return
        if self._misses_most(camera, robot, in_use, sample.time_s):
            self.state[camera] = CameraState.SUSPECT
            self.stats["suspect"] += 1

    def _misses_most(self, camera: str, robot: str, in_use: Sequence[str], time_s: float) -> bool:
        """Whether ``camera`` misses most of the cameras in use right now (each one's latest miss
        within ``suspect_samples`` sampling intervals and ``reference_span_s`` of ``time_s``): by
        its miss of the fused prediction (:meth:`off_prediction`'s), else, without a recent one, by
        its checks' miss of the other cameras' cube pose. A moved camera spoils its partners'
        references, so with three cameras a partner's check can miss more than its own (issue
        27's seed 31: cam1 15.5 px, the bumped cam2 14.0 px); the fused prediction, made by the
        cameras before the move, is missed by the moved camera alone (cam2 15.5 px, cam1 2.7 px)."""
        since_s = time_s - self.params.suspect_samples * self._sample_interval_s() - self.params.reference_span_s
        latest = self._off_prediction.get(robot, {})
        if latest.get(camera, (-math.inf, 0.0))[0] < since_s:
            latest = {c: m[-1] for c, m in self._misses.items() if m}  # holds this camera's sample just judged
        others = [m for c, (t, m) in latest.items() if c != camera and c in in_use and t >= since_s]
        return latest[camera][1] >= max(others, default=0.0)

    def _sample_interval_s(self) -> float:
        """How often each camera's sightings are checked at most, seconds (``samples_per_s``, or
        less often in turn when ``checks_per_s`` is shared by many cameras)."""
        return max(1.0 / self.params.samples_per_s, len(self.state) / self.params.checks_per_s)

    def _settle(self, camera: str, samples: Sequence[WatchSample]) -> None:
        """Fit the camera's settled pose to its samples before the window, given enough of them
        (``4 min_points`` corners over ``settle_span_s`` at least)."""
        if samples and sum(len(s.points_world_m) for s in samples) >= 4 * self.params.min_points and (
                samples[-1].time_s - samples[0].time_s >= self.params.settle_span_s):
            start = self.settled.get(camera, self.T_world_cam[camera])
            fit = refit_camera(*stacked(samples), start, self.params.corner_noise_px)
            if fit is not None:
                self.settled[camera] = fit.T_world_cam

    def _corner_sets(self, sighting: CubeSighting, by_prediction: bool = True
                     ) -> tuple[np.ndarray | None, list[CornerSet]]:
        """A cube pose for the sighting and its corners matched to faces by it (once per
        sighting): with ``by_prediction``, the fused prediction given to :meth:`add` where it
        matches a face (a compiled projection; within ``PREDICTION_GATE_PX``, or ``gate_px`` where
        an id is on several faces); else the sighting's own estimate (a per-marker pose search,
        ~10x dearer, but the faces a moved camera really saw: a checked sighting's own corners)."""
        key = (sighting.camera, sighting.robot, sighting.seq, by_prediction)
        found = self._sets.get(key)
        layout = self.layouts[sighting.robot]
        predicted = self._predicted.get(key[:3]) if by_prediction else None
        if found is None and predicted is not None:
            gate_px = self.params.gate_px if layout.has_repeated_ids else PREDICTION_GATE_PX
            matches = match_faces(sighting.detections, layout, sighting.intrinsics, sighting.T_world_cam, predicted,
                                  gate_px=gate_px)
            if matches:
                found = predicted, sighting_corner_sets(matches, sighting.intrinsics, sighting.T_world_cam,
                                                        sighting.camera, sighting.capture_time_s)
                self._sets[key] = found
        if found is None:
            estimate = sighting.estimate or estimate_cube(
                sighting.detections, layout, sighting.intrinsics, sighting.T_world_cam, camera=sighting.camera,
                robot=sighting.robot, seq=sighting.seq, capture_time_s=sighting.capture_time_s,
                arrival_time_s=sighting.arrival_time_s, params=self.estimator_params)
            if estimate is None:
                found = None, []
            else:
                matches = match_faces(sighting.detections, layout, sighting.intrinsics, sighting.T_world_cam,
                                      estimate.T_world_cube, gate_px=self.params.gate_px)
                found = estimate.T_world_cube, sighting_corner_sets(matches, sighting.intrinsics, sighting.T_world_cam,
                                                                    sighting.camera, sighting.capture_time_s)
            self._sets[key] = found
        return found

    def _reference_sets(self, sighting: CubeSighting) -> list[CornerSet]:
        """The corner sets of the other cameras' reference for a checked sighting: of the
        ``reference_cameras_max`` other cameras in use with a sighting nearest in time within
        ``reference_span_s``, the ``REFERENCE_SIGHTINGS`` sightings of each nearest in time."""
        t, span = sighting.capture_time_s, self.params.reference_span_s
        near = sorted(((abs(o.capture_time_s - t), o) for o in self._recent[sighting.robot]
                       if o.camera != sighting.camera and abs(o.capture_time_s - t) <= span), key=lambda item: item[0])
        taken: Counter[str] = Counter()
        chosen: list[CubeSighting] = []
        # a re-calibrating camera's samples are its new pose's data (calib.recalibrate): every sighting in the span
        per_camera = math.inf if self.state[sighting.camera] is CameraState.RECALIBRATING else REFERENCE_SIGHTINGS
        for _, o in near:
            if taken[o.camera] < per_camera and self.referee(o.camera) and (
                    o.camera in taken or len(taken) < self.params.reference_cameras_max):
                taken[o.camera] += 1
                chosen.append(o)
        return [s for o in chosen for s in self._corner_sets(o)[1]]

    def _sample(self, sighting: CubeSighting) -> WatchSample | None:
        """The sighting against the other watched cameras' cube pose at its time, or None (counted)."""
        T_own, mine = self._corner_sets(sighting, by_prediction=False)
        if T_own is None or not mine:
            self.stats["no cube matched"] += 1
            return None
        others = self._reference_sets(sighting)
        if len({s.camera for s in others}) < self.params.reference_cameras:
            self.stats["too few other cameras"] += 1
            return None
        # started from the sighting's cube pose (the fused prediction, or its camera's own estimate)
        t = sighting.capture_time_s
        reference = solve_joint(others, T_own, t, self.params.corner_noise_px, velocity_sigma=VELOCITY_SIGMA,
                                iterations=FIT_ITERATIONS)
        if reference is not None:  # kept over the window and baseline_s (a re-calibrating camera's too)
            trail = self._reference_rms[sighting.camera]
            trail.append((t, reference.rms_px))
            while trail[0][0] < t - self.params.window_s - self.params.baseline_s:
                trail.popleft()
        if reference is None or reference.rms_px > self.params.reference_rms_px:
            self.stats["reference fit refused"] += 1
            return None
        self.stats["checked"] += 1
        r = np.linalg.norm(reprojection_residuals_px(reference.T_world_cube, others, t, reference.velocity_m_s,
                                                     reference.angular_velocity_rad_s).reshape(-1, 2), axis=1)
        for s, disagreement in zip(others, set_medians(r, [len(s.points_cube_m) for s in others]), strict=True):
            self._disagreement[s.camera].append((t, disagreement))
        points = [transform_points(moved_pose(reference.T_world_cube, reference.velocity_m_s,
                                              reference.angular_velocity_rad_s, s.time_s - t), s.points_cube_m)
                  for s in mine]
        normalized = np.concatenate([s.normalized for s in mine])
        focal = np.concatenate([np.full(len(s.normalized), s.focal_px) for s in mine])
        return WatchSample(sighting.camera, t, np.concatenate(points), normalized, focal, tuple(mine), tuple(others),
                           reference.T_world_cube, reference.rms_px)

