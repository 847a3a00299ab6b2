"""Trajectory files (contracts §5): TUM (``timestamp tx ty tz qx qy qz qw``) and JSONL.

Timestamps are Unix seconds on the host clock (estimated capture time), positions metres,
quaternions scalar-last (x, y, z, w).
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from cubetrack.core.errors import TrajectoryError
from cubetrack.core.records import TrackedPose
from cubetrack.io.files import LineFile, cannot_write, os_errors_as


@dataclass(frozen=True, slots=True, eq=False)
class Trajectory:
    """Timestamped poses: ``times_s`` (N,), ``positions_m`` (N, 3), ``quats_xyzw`` (N, 4)."""

    times_s: np.ndarray
    positions_m: np.ndarray
    quats_xyzw: np.ndarray

    def __post_init__(self) -> None:
        n = len(self.times_s)
        if self.positions_m.shape != (n, 3) or self.quats_xyzw.shape != (n, 4):
            raise TrajectoryError(
                f"trajectory arrays disagree: {n} times, positions {self.positions_m.shape}, "
                f"quaternions {self.quats_xyzw.shape}"
            )

    def __len__(self) -> int:
        return len(self.times_s)


def read_tum(path: str | Path) -> Trajectory:
    """Read a TUM trajectory; ``#`` comments and blank lines are ignored."""
    path = Path(path)
    rows = []
    try:
        lines = path.read_text(encoding="utf-8").splitlines()
    except FileNotFoundError:
        raise TrajectoryError(f"{path}: trajectory file not found") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise TrajectoryError(f"{path}: cannot read: {exc}") from None
    for line_no, line in enumerate(lines, start=1):
        line = line.strip()
        if not line or line.startswith("#"):
            continue
        parts = line.replace(",", " ").split()
        try:
            values = [float(p) for p in parts]
        except ValueError:
            values = []
        if len(values) != 8 or not np.all(np.isfinite(values)):
            raise TrajectoryError(
                f"{path}:{line_no}: expected 8 numbers 'timestamp tx ty tz qx qy qz qw', got {line!r}"
            )
        rows.append(values)
    if not rows:
        raise TrajectoryError(f"{path}: no poses in trajectory")
    a = np.array(rows)
    order = np.argsort(a[:, 0], kind="stable")
    a = a[order]
    return Trajectory(a[:, 0], a[:, 1:4], a[:, 4:8])


def format_tum_line(time_s: float, position_m: np.ndarray, q_xyzw: np.ndarray) -> str:
    """One TUM line (microsecond timestamps, sub-millimetre positions)."""
    # plain floats (the same digits): numpy's scalars format several times slower (runs once per output pose)
    (x, y, z), (qx, qy, qz, qw) = np.asarray(position_m, dtype=float).tolist(), np.asarray(q_xyzw, dtype=float).tolist()
    return f"{time_s:.6f} {x:.6f} {y:.6f} {z:.6f} {qx:.9f} {qy:.9f} {qz:.9f} {qw:.9f}\n"


def write_tum(trajectory: Trajectory, path: str | Path) -> None:
    """Write a whole trajectory as TUM."""
    with Path(path).open("w", encoding="utf-8") as f:
        for t, p, q in zip(trajectory.times_s, trajectory.positions_m, trajectory.quats_xyzw, strict=True):
            f.write(format_tum_line(t, p, q))


def pose_to_json(pose: TrackedPose) -> dict:
    """The JSONL object of one fused pose (contracts §5)."""
    out = {
        "time": round(float(pose.time_s), 6),
        "robot": pose.robot,
        "position": [round(v, 6) for v in np.asarray(pose.position_m, dtype=float).tolist()],
        "quaternion_xyzw": [round(v, 9) for v in np.asarray(pose.quaternion_xyzw, dtype=float).tolist()],
        "cameras": list(pose.cameras),
        "markers": list(pose.markers),
        "latency": round(float(pose.latency_s), 6),
    }
    if pose.arrival_latency_s is not None:
        out["arrival_latency"] = round(float(pose.arrival_latency_s), 6)
    if pose.predicted:
        out["predicted"] = True
    if pose.smoothed:
        out["smoothed"] = True
    if pose.smooth_lag_s is not None:
        out["smooth_lag_s"] = pose.smooth_lag_s
    return out


class PoseWriter:
    """Streams fused poses of one robot to ``<dir>/<robot>.tum`` and ``<dir>/<robot>.jsonl``,
    one whole line per pose and file as it comes (:class:`cubetrack.io.files.LineFile`): a killed
    process loses at most the pose it was writing (its TUM line may be there without its JSONL
    line), and a full disk is a :class:`TrajectoryError` naming the file, the files still
    holding whole lines."""

    def __init__(self, out_dir: str | Path, robot: str):
        out_dir = Path(out_dir)
        self.tum_path = out_dir / f"{robot}.tum"
        self.jsonl_path = out_dir / f"{robot}.jsonl"
        self._files: list[LineFile] = []
        try:
            with os_errors_as(TrajectoryError, out_dir):
                out_dir.mkdir(parents=True, exist_ok=True)
                for path in (self.tum_path, self.jsonl_path):
                    self._files.append(LineFile(path))
        except BaseException:
            self.close()
            raise
        self.count = 0

    def write(self, pose: TrackedPose) -> None:
        tum, jsonl = self._files
        writing = tum   # one try for both files (as os_errors_as, without a context per line: this runs per pose)
        try:
            tum.write_line(format_tum_line(pose.time_s, pose.position_m, pose.quaternion_xyzw).rstrip("\n"))
            writing = jsonl
            jsonl.write_line(json.dumps(pose_to_json(pose)))
        except OSError as exc:
            raise TrajectoryError(cannot_write(writing.path, exc)) from None
        self.count += 1

    def close(self) -> None:
        for f in self._files:
            f.close()

    def __enter__(self) -> PoseWriter:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
