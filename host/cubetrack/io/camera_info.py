"""Camera intrinsics files: ROS ``camera_info`` YAML (read and write) and OpenCV FileStorage YAML
(read), as :class:`cubetrack.core.cameras.CameraIntrinsics`.

Pixel convention: OpenCV's, (0, 0) is the centre of the top-left pixel; ``K`` is the 3x3
camera matrix in pixels; ``dist`` the plumb_bob (k1, k2, p1, p2, k3) coefficients. One key of
ours beside ROS's: ``rolling_shutter_readout_s`` (optional, default 0: a global shutter), the
sensor's readout time from the top row to the bottom row, which the tracker's measurement model
uses (each corner is seen at its row's time).
"""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import yaml

from cubetrack.core.cameras import CameraIntrinsics
from cubetrack.core.errors import CameraInfoError
from cubetrack.io.files import atomic_write

_MAX_NUMBERS = 64  # more than any camera matrix or distortion model holds


def _small(value: object) -> bool:
    """Whether a (nested) list has at most _MAX_NUMBERS items in all: YAML aliases let a
    file of a few hundred bytes hold billions of numbers."""
    todo, seen = [value], 0
    while todo:
        item = todo.pop()
        seen += 1
        if seen > _MAX_NUMBERS:
            return False
        if isinstance(item, list):
            todo.extend(item[:_MAX_NUMBERS + 1])
    return True


def _matrix(value: object, n: int, path: Path, key: str) -> np.ndarray:
    data = value.get("data") if isinstance(value, dict) else value
    if not _small(data):
        raise CameraInfoError(f"{path}: {key} must hold {n or 'a list of'} numbers")
    try:
        arr = np.asarray(data, dtype=float).reshape(-1)
    except (TypeError, ValueError):
        raise CameraInfoError(f"{path}: {key} must hold {n or 'a list of'} numbers") from None
    if n and arr.size != n:
        raise CameraInfoError(f"{path}: {key} must hold {n} numbers, has {arr.size}")
    return arr


def _opencv_matrix(loader: yaml.SafeLoader, node: yaml.MappingNode) -> dict:
    return loader.construct_mapping(node, deep=True)


class _Loader(yaml.SafeLoader):
    """Safe YAML that also reads OpenCV FileStorage files: an ``!!opencv-matrix`` node becomes a
    mapping (rows, cols, dt, data). OpenCV's own reader is not used for them: a malformed matrix
    node (e.g. without ``cols``) corrupts its heap and aborts the whole process (OpenCV 5.0.0,
    found by fuzzing)."""

    yaml_constructors = {**yaml.SafeLoader.yaml_constructors, "tag:yaml.org,2002:opencv-matrix": _opencv_matrix}


READOUT_KEY = "rolling_shutter_readout_s"  # an addition of ours: top row to bottom row, seconds
_OPENCV_DIRECTIVE = re.compile(r"\A\s*%YAML:1\.\d+[^\n]*\n")  # OpenCV's spelling, which PyYAML refuses


def read_camera_info(path: str | Path) -> CameraIntrinsics:
    """Read intrinsics from a ROS camera_info YAML or an OpenCV FileStorage YAML file."""
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise CameraInfoError(f"{path}: camera_info file not found") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise CameraInfoError(f"{path}: cannot read camera_info: {exc}") from None
    opencv = text.lstrip().startswith("%YAML:") or "!!opencv-matrix" in text
    try:
        doc = yaml.load(_OPENCV_DIRECTIVE.sub("", text, count=1), Loader=_Loader)
    except yaml.YAMLError as exc:
        reason = str(exc).splitlines()[0]
        raise CameraInfoError(f"{path}: not valid YAML: {reason}") from None
    except RecursionError:
        raise CameraInfoError(f"{path}: not valid YAML: nested too deeply") from None
    if not isinstance(doc, dict) or "camera_matrix" not in doc:
        raise CameraInfoError(
            f"{path}: not a ROS camera_info file (needs image_width, image_height, camera_matrix, "
            "distortion_coefficients)"
        )
    K = _matrix(doc["camera_matrix"], 9, path, "camera_matrix").reshape(3, 3)
    dist = _matrix(doc.get("distortion_coefficients", {"data": [0.0] * 5}), 0, path,
                   "distortion_coefficients")
    model = doc.get("distortion_model", "plumb_bob")
    if model not in ("plumb_bob", "rational_polynomial"):
        raise CameraInfoError(f"{path}: distortion_model {model!r} is not supported (plumb_bob)")
    try:
        if opencv and "image_width" not in doc and "image_height" not in doc:
            # older OpenCV files omit the size: infer it from the principal point
            width, height = int(round(2 * K[0, 2] + 1)), int(round(2 * K[1, 2] + 1))
        else:
            width, height = int(doc["image_width"]), int(doc["image_height"])
    except (KeyError, TypeError, ValueError, OverflowError):
        raise CameraInfoError(f"{path}: needs integer image_width and image_height") from None
    readout = doc.get(READOUT_KEY, 0.0)
    if isinstance(readout, bool) or not isinstance(readout, (int, float)) or not 0.0 <= readout < 1.0:
        raise CameraInfoError(f"{path}: {READOUT_KEY} must be a number of seconds in [0, 1), got {readout!r}")
    return CameraIntrinsics(width, height, K, dist, str(doc.get("camera_name", path.stem)), float(readout))


def camera_info_to_dict(intr: CameraIntrinsics) -> dict:
    """The ROS camera_info YAML document (the layout ROS ``camera_calibration`` writes)."""
    K = intr.K
    P = np.zeros((3, 4))
    P[:3, :3] = K

    def block(rows: int, cols: int, data: np.ndarray) -> dict:
        return {"rows": rows, "cols": cols, "data": [float(v) for v in np.ravel(data)]}

    doc = {
        "image_width": int(intr.width),
        "image_height": int(intr.height),
        "camera_name": intr.camera_name or "camera",
        "camera_matrix": block(3, 3, K),
        "distortion_model": "plumb_bob",
        "distortion_coefficients": block(1, len(intr.dist), intr.dist),
        "rectification_matrix": block(3, 3, np.eye(3)),
        "projection_matrix": block(3, 4, P),
    }
    if intr.readout_s > 0:  # not ROS's: a global-shutter camera's file stays plain camera_info
        doc[READOUT_KEY] = float(intr.readout_s)
    return doc


def write_camera_info(intr: CameraIntrinsics, path: str | Path) -> None:
    """Write ROS camera_info YAML (atomically)."""
    atomic_write(path, yaml.safe_dump(camera_info_to_dict(intr), sort_keys=False))
