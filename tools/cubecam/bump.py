"""A camera knocked on its tripod, in the emulator (issue 27): from a given moment on, a camera's
frames are those it would have taken turned by a small rotation about its own optical centre.

A turn about the optical centre is the one camera move an image alone can show exactly: every
pixel's ray turns by the same rotation, whatever the depth of what it sees, so the new frame is
the old one resampled (:class:`RotationWarp`: each pixel of the new frame undistorted to its ray,
the ray turned back into the old camera, projected with the lens's distortion, the old frame
sampled there; the strip the old frame never saw is mid grey). A bumped tripod head pans or
tilts about a point a few centimetres behind the sensor, so a real knock also shifts the camera
by about that lever times the angle (1 mm per degree for a 6 cm head); that shift needs the
scene's depth and is not emulated here: the simulator's ``--bump-camera`` renders both.

``CAM:AT_S:DEG`` (``--bump cam2:8:1.5``) turns ``cam2`` by 1.5 degrees about its image's vertical
axis (a pan) 8 seconds after the emulator started; ``CAM:AT_S:DEG:X,Y,Z`` names the axis in the
camera's frame (x right, y down, z forward: ``1,0,0`` tilts it). :meth:`cubecam.emulator.Emulator.bump`
turns a camera at once (tests wait for a condition, then bump).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from cubecam.errors import EmulatorError
from cubetrack.core.cameras import CameraIntrinsics
from cubetrack.core.geometry import R_from_rotvec
from cubetrack.io.camera_info import read_camera_info

GREY = 128  # what the new frame shows where the old one saw nothing
PAN_AXIS = (0.0, 1.0, 0.0)
MAX_BUMP_DEG = 20.0


@dataclass(frozen=True, slots=True)
class Bump:
    """Turn ``camera`` by ``rotation_deg`` about ``axis`` (its own frame: x right, y down, z
    forward) ``at_s`` seconds after the emulator started (None: when asked)."""

    camera: str
    rotation_deg: float
    axis: tuple[float, float, float] = PAN_AXIS
    at_s: float | None = None

    def __post_init__(self) -> None:
        if not 0.0 < abs(self.rotation_deg) <= MAX_BUMP_DEG:
            raise EmulatorError(f"bump: a turn of 0 < |deg| <= {MAX_BUMP_DEG:g} degrees, got {self.rotation_deg:g}")
        if not math.isfinite(sum(self.axis)) or math.hypot(*self.axis) == 0.0:
            raise EmulatorError(f"bump: the axis must be a non-zero vector, got {self.axis}")
        if self.at_s is not None and not self.at_s >= 0.0:
            raise EmulatorError(f"bump: the time must be >= 0 seconds, got {self.at_s:g}")

    @property
    def R_old_new(self) -> np.ndarray:
        """The bumped camera's orientation in the camera's old frame (3x3)."""
        axis = np.asarray(self.axis, float) / math.hypot(*self.axis)
        return R_from_rotvec(axis * math.radians(self.rotation_deg))

    def describe(self) -> str:
        x, y, z = self.axis
        return f"{self.camera} turned {self.rotation_deg:g} deg about its ({x:g}, {y:g}, {z:g}) axis"


def parse_bump(text: str) -> Bump:
    """``CAM:AT_S:DEG`` or ``CAM:AT_S:DEG:X,Y,Z`` (see the module doc)."""
    parts = text.split(":")
    try:
        if len(parts) not in (3, 4) or not parts[0]:
            raise ValueError
        axis = PAN_AXIS
        if len(parts) == 4:
            x, y, z = (float(v) for v in parts[3].split(","))
            axis = (x, y, z)
        return Bump(parts[0], float(parts[2]), axis, float(parts[1]))
    except ValueError:
        raise EmulatorError(f"--bump {text!r}: expected CAM:AT_S:DEG or CAM:AT_S:DEG:X,Y,Z, e.g. cam2:8:1.5") from None


class RotationWarp:
    """Resamples a camera's frames as the camera turned by ``R_old_new`` would have taken them
    (see the module doc); the pixel maps are computed once."""

    def __init__(self, intrinsics: CameraIntrinsics, R_old_new: np.ndarray, jpeg_quality: int = 90):
        w, h = intrinsics.width, intrinsics.height
        u, v = np.meshgrid(np.arange(w, dtype=np.float64), np.arange(h, dtype=np.float64))
        pixels = np.stack([u.ravel(), v.ravel()], axis=1).reshape(-1, 1, 2)
        rays = cv2.undistortPoints(pixels, intrinsics.K, intrinsics.dist).reshape(-1, 2)
        rays_old = np.column_stack([rays, np.ones(len(rays))]) @ np.asarray(R_old_new, float).T
        behind = rays_old[:, 2] <= 1e-6
        rays_old[behind, 2] = 1.0
        seen, _ = cv2.projectPoints(rays_old, np.zeros(3), np.zeros(3), intrinsics.K, intrinsics.dist)
        seen = seen.reshape(-1, 2)
        seen[behind] = -1.0
        self.map_x = seen[:, 0].reshape(h, w).astype(np.float32)
        self.map_y = seen[:, 1].reshape(h, w).astype(np.float32)
        self.size = (w, h)
        self.jpeg_quality = jpeg_quality

    def __call__(self, jpeg: bytes) -> bytes:
        """The frame as the turned camera sees it (the input unchanged if it is not a JPEG of the camera's size)."""
        image = cv2.imdecode(np.frombuffer(jpeg, np.uint8), cv2.IMREAD_UNCHANGED)
        if image is None or (image.shape[1], image.shape[0]) != self.size:
            return jpeg
        turned = cv2.remap(image, self.map_x, self.map_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT,
                           borderValue=(GREY, GREY, GREY))
        ok, out = cv2.imencode(".jpg", turned, [cv2.IMWRITE_JPEG_QUALITY, self.jpeg_quality])
        return out.tobytes() if ok else jpeg


def camera_intrinsics(recording: Path, camera: str) -> CameraIntrinsics:
    """The lens a bumped camera's frames are resampled with: the recording's true intrinsics
    (a simulated one's ``true_camera_info``) when it has them, else its ``camera_info``."""
    for folder in ("true_camera_info", "camera_info"):
        path = recording / folder / f"{camera}.yaml"
        if path.is_file():
            return read_camera_info(path)
    raise EmulatorError(f"bump: {recording} has no camera_info/{camera}.yaml to turn {camera}'s frames with")
