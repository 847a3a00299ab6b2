"""Trajectory evaluation against a ground truth (the paper's §III metrics).

Reads trajectories only; never touches the tracking pipeline.

- Position RMSE: each estimated pose against the ground truth at the estimate's own time,
  interpolated between the two ground-truth samples around it (linearly; rotation by slerp), with
  no alignment (the world frame comes from calibration). The paper's eq. 7 takes the ground-truth
  sample nearest in time instead; that score is reported beside it (``*_nearest``): at a 100 Hz
  ground truth it is up to 5 ms off the pose's instant, which is not the tracker's error.
  Estimates farther than ``max_time_diff_s`` from any ground-truth sample are scored by neither.
- Rotation RMSE: RMS of the angle between estimated and ground-truth orientation at the same
  instants, in degrees.
- Detection ratio (paper eq. 8): detected time / total time with a message timeout (0.5 s). The
  total is the ground truth's time span; every gap between consecutive estimates longer than
  the timeout (and the lead-in before the first / lead-out after the last estimate, when longer
  than the timeout) counts as undetected.
- Output rate: estimates per second of ground-truth span.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

from cubetrack.core.errors import EvaluationError
from cubetrack.core.params import check_positive, param
from cubetrack.io.trajectory import Trajectory


@dataclass(frozen=True, slots=True)
class EvaluationParams:
    """How an estimate is scored against ground truth."""

    detection_timeout_s: float = param(0.5, "seconds without an estimate after which the robot counts as "
                                            "lost (paper: 0.5 s)")
    max_time_diff_s: float = param(0.02, "seconds; estimates farther than this from any ground-truth "
                                         "sample are not scored")

    def __post_init__(self) -> None:
        check_positive(self, "detection_timeout_s", "max_time_diff_s")


@dataclass(frozen=True, slots=True)
class EvaluationResult:
    """Scores of one estimated trajectory (lengths in metres, angles in degrees, rates in Hz)."""

    position_rmse_m: float
    rotation_rmse_deg: float
    detection_ratio: float
    output_rate_hz: float
    poses_scored: int
    poses_total: int
    duration_s: float
    position_errors_m: np.ndarray
    rotation_errors_deg: np.ndarray
    position_rmse_nearest_m: float
    rotation_rmse_nearest_deg: float

    def as_dict(self) -> dict:
        return {
            "position_rmse_m": self.position_rmse_m,
            "rotation_rmse_deg": self.rotation_rmse_deg,
            "position_rmse_nearest_m": self.position_rmse_nearest_m,
            "rotation_rmse_nearest_deg": self.rotation_rmse_nearest_deg,
            "detection_ratio": self.detection_ratio,
            "output_rate_hz": self.output_rate_hz,
            "poses_scored": self.poses_scored,
            "poses_total": self.poses_total,
            "duration_s": self.duration_s,
            "position_median_m": float(np.median(self.position_errors_m)) if self.poses_scored else float("nan"),
            "position_max_m": float(np.max(self.position_errors_m)) if self.poses_scored else float("nan"),
        }


def nearest_indices(times_ref_s: np.ndarray, times_s: np.ndarray) -> np.ndarray:
    """Index into sorted ``times_ref_s`` of the sample nearest to each of ``times_s``."""
    idx = np.clip(np.searchsorted(times_ref_s, times_s), 1, len(times_ref_s) - 1)
    left, right = times_ref_s[idx - 1], times_ref_s[idx]
    return np.where(np.abs(times_s - left) <= np.abs(right - times_s), idx - 1, idx)


def truth_at(ground_truth: Trajectory, times_s: np.ndarray) -> tuple[np.ndarray, Rotation]:
    """The ground truth at each of ``times_s``: positions (N, 3) interpolated linearly and
    orientations by slerp between the two samples around each time (the end samples outside)."""
    ref = ground_truth.times_s
    t = np.clip(np.asarray(times_s, dtype=float), ref[0], ref[-1])
    hi = np.clip(np.searchsorted(ref, t, side="right"), 1, len(ref) - 1)
    lo = hi - 1
    span = ref[hi] - ref[lo]
    a = np.where(span > 0, (t - ref[lo]) / np.where(span > 0, span, 1.0), 0.0)
    positions = (1.0 - a)[:, None] * ground_truth.positions_m[lo] + a[:, None] * ground_truth.positions_m[hi]
    r_lo = Rotation.from_quat(ground_truth.quats_xyzw[lo])
    step = (r_lo.inv() * Rotation.from_quat(ground_truth.quats_xyzw[hi])).as_rotvec()
    return positions, r_lo * Rotation.from_rotvec(a[:, None] * step)


def position_rmse_m(positions_m: np.ndarray, reference_m: np.ndarray) -> float:
    """Paper eq. 7: sqrt(mean(|p_i - p̂_i|²)) over paired (N, 3) positions."""
    d = np.asarray(positions_m) - np.asarray(reference_m)
    return float(np.sqrt(np.mean(np.sum(d * d, axis=1))))


def _rms(values: np.ndarray) -> float:
    return float(np.sqrt(np.mean(values**2))) if values.size else float("nan")


def detection_ratio(times_s: np.ndarray, start_s: float, end_s: float, timeout_s: float) -> float:
    """Paper eq. 8 over [start_s, end_s]: 1 - (sum of estimate gaps longer than the timeout) / span."""
    span = end_s - start_s
    if span <= 0:
        raise EvaluationError(f"evaluation span must be positive, got {span:.3f} s")
    t = np.sort(np.asarray(times_s, dtype=float))
    t = t[(t >= start_s) & (t <= end_s)]
    if t.size == 0:
        return 0.0
    gaps = np.diff(np.concatenate([[start_s], t, [end_s]]))
    lost = float(np.sum(gaps[gaps > timeout_s]))
    return max(0.0, 1.0 - lost / span)


def evaluate(estimate: Trajectory, ground_truth: Trajectory,
             params: EvaluationParams = EvaluationParams()) -> EvaluationResult:
    """Score ``estimate`` against ``ground_truth`` (both on the same host clock)."""
    if len(ground_truth) < 2:
        raise EvaluationError("ground truth needs at least two poses")
    start, end = float(ground_truth.times_s[0]), float(ground_truth.times_s[-1])
    inside = (estimate.times_s >= start - params.max_time_diff_s) & (estimate.times_s <= end + params.max_time_diff_s)
    if not np.any(inside):
        raise EvaluationError(
            f"estimate ({estimate.times_s[0]:.3f}..{estimate.times_s[-1]:.3f} s) and ground truth "
            f"({start:.3f}..{end:.3f} s) do not overlap in time: are both on the host clock?"
        )
    idx = nearest_indices(ground_truth.times_s, estimate.times_s)
    close = np.abs(ground_truth.times_s[idx] - estimate.times_s) <= params.max_time_diff_s
    gi = idx[close]
    p_est, r_est = estimate.positions_m[close], Rotation.from_quat(estimate.quats_xyzw[close])
    p_truth, r_truth = truth_at(ground_truth, estimate.times_s[close])
    p_err = np.linalg.norm(p_est - p_truth, axis=1)
    r_err = np.degrees((r_truth.inv() * r_est).magnitude())
    r_err_nearest = np.degrees((Rotation.from_quat(ground_truth.quats_xyzw[gi]).inv() * r_est).magnitude())
    scored = bool(p_err.size)
    span = end - start
    return EvaluationResult(
        position_rmse_m=position_rmse_m(p_est, p_truth) if scored else float("nan"),
        rotation_rmse_deg=_rms(r_err),
        detection_ratio=detection_ratio(estimate.times_s, start, end, params.detection_timeout_s),
        output_rate_hz=float(np.sum(inside)) / span,
        poses_scored=int(p_err.size),
        poses_total=len(estimate),
        duration_s=span,
        position_errors_m=p_err,
        rotation_errors_deg=r_err,
        position_rmse_nearest_m=position_rmse_m(p_est, ground_truth.positions_m[gi]) if scored else float("nan"),
        rotation_rmse_nearest_deg=_rms(r_err_nearest),
    )
