"""CDR encoding of the few ROS 2 messages cubetrack publishes, without a ROS install.

The bytes are what a ROS 2 publisher puts on the wire (and in a ROS 2 bag): OMG CDR, little
endian, after the 4-byte encapsulation header ``00 01 00 00`` (CDR_LE); every primitive is
aligned to its size counted from the end of that header; a string is a uint32 length that
counts its terminating NUL, the bytes, the NUL; a sequence is a uint32 count, then the
elements. Messages (field order as in their ``.msg`` files):

- ``geometry_msgs/msg/PoseStamped``: Header, Pose
- ``nav_msgs/msg/Odometry``: Header, string child_frame_id, PoseWithCovariance, TwistWithCovariance
- ``tf2_msgs/msg/TFMessage``: TransformStamped[] (Header, string child_frame_id, Transform)

with Header = (int32 sec, uint32 nanosec, string frame_id), Pose = (Point, Quaternion xyzw),
covariances = float64[36] row-major.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass
from functools import lru_cache

import numpy as np

ENCAPSULATION_CDR_LE = b"\x00\x01\x00\x00"


@dataclass(frozen=True, slots=True)
class RosType:
    """A ROS 2 message type: its name (``pkg/msg/Name``), its DDS name and its REP-2016 hash."""

    name: str
    rihs01: str

    @property
    def dds_name(self) -> str:
        """``pkg::msg::dds_::Name_``, the type name rmw implementations use on the wire."""
        package, kind, short = self.name.split("/")
        return f"{package}::{kind}::dds_::{short}_"


# RIHS01 hashes as the ROS 2 type-description generator computes them (identical in Humble's
# message definitions, Iron, Jazzy, Kilted and Rolling for these types; Humble's rmw does not
# publish them, see ros2.py).
POSE_STAMPED = RosType("geometry_msgs/msg/PoseStamped",
                       "RIHS01_10f3786d7d40fd2b54367835614bff85d4ad3b5dab62bf8bca0cc232d73b4cd8")
ODOMETRY = RosType("nav_msgs/msg/Odometry",
                   "RIHS01_3cc97dc7fb7502f8714462c526d369e35b603cfc34d946e3f2eda2766dfec6e0")
TF_MESSAGE = RosType("tf2_msgs/msg/TFMessage",
                     "RIHS01_e369d0f05a23ae52508854b66f6aa0437f3449d652e8cbf22d5abe85d020f087")


@dataclass(frozen=True, slots=True)
class Transform:
    """One ``geometry_msgs/msg/TransformStamped``: ``child`` in ``parent`` at ``time_s``."""

    time_s: float
    parent: str
    child: str
    position_m: np.ndarray
    quaternion_xyzw: np.ndarray


class _Writer:
    """Appends aligned little-endian CDR primitives after the encapsulation header."""

    def __init__(self) -> None:
        self.body = bytearray()

    def align(self, size: int) -> None:
        self.body += b"\x00" * (-len(self.body) % size)

    def uint32(self, value: int) -> None:
        self.align(4)
        self.body += struct.pack("<I", value)

    def float64s(self, values) -> None:
        self.align(8)
        self.body += _float64s(len(values)).pack(*values)

    def string(self, text: str) -> None:
        self.align(4)
        self.body += _string(text)

    def header(self, time_s: float, frame_id: str) -> None:
        sec, nanosec = stamp(time_s)
        self.align(4)
        self.body += struct.pack("<iI", sec, nanosec)
        self.string(frame_id)

    def bytes(self) -> bytes:
        return ENCAPSULATION_CDR_LE + bytes(self.body)


@lru_cache(maxsize=64)
def _float64s(count: int) -> struct.Struct:
    return struct.Struct(f"<{count}d")


@lru_cache(maxsize=256)
def _string(text: str) -> bytes:
    """A CDR string (uint32 length with the NUL, the UTF-8 bytes, NUL), once per frame id."""
    data = text.encode("utf-8") + b"\x00"
    return struct.pack("<I", len(data)) + data


def stamp(time_s: float) -> tuple[int, int]:
    """``builtin_interfaces/Time`` (int32 sec, uint32 nanosec) of a Unix time in seconds."""
    nanoseconds = round(time_s * 1e9)
    sec, nanosec = divmod(nanoseconds, 1_000_000_000)
    return int(sec), int(nanosec)


def _pose(writer: _Writer, position_m: np.ndarray, quaternion_xyzw: np.ndarray) -> None:
    writer.float64s([*np.asarray(position_m, float).reshape(3).tolist(),
                     *np.asarray(quaternion_xyzw, float).reshape(4).tolist()])


def pose_stamped(time_s: float, frame_id: str, position_m: np.ndarray, quaternion_xyzw: np.ndarray) -> bytes:
    """``geometry_msgs/msg/PoseStamped``."""
    w = _Writer()
    w.header(time_s, frame_id)
    _pose(w, position_m, quaternion_xyzw)
    return w.bytes()


def odometry(time_s: float, frame_id: str, child_frame_id: str, position_m: np.ndarray,
             quaternion_xyzw: np.ndarray, pose_covariance: np.ndarray | None,
             linear_m_s: np.ndarray | None, angular_rad_s: np.ndarray | None) -> bytes:
    """``nav_msgs/msg/Odometry``. The pose is in ``frame_id``; the twist (``linear_m_s``,
    ``angular_rad_s``) must already be in ``child_frame_id``, as the message defines it.
    Missing values are zeros (covariance zeros = unknown)."""
    w = _Writer()
    w.header(time_s, frame_id)
    w.string(child_frame_id)
    _pose(w, position_m, quaternion_xyzw)
    w.float64s(_ZEROS_36 if pose_covariance is None else np.asarray(pose_covariance, float).reshape(36).tolist())
    w.float64s(_ZEROS_3 if linear_m_s is None else np.asarray(linear_m_s, float).tolist())
    w.float64s(_ZEROS_3 if angular_rad_s is None else np.asarray(angular_rad_s, float).tolist())
    w.float64s(_ZEROS_36)
    return w.bytes()


_ZEROS_3, _ZEROS_36 = (0.0,) * 3, (0.0,) * 36


def tf_message(transforms: list[Transform] | tuple[Transform, ...]) -> bytes:
    """``tf2_msgs/msg/TFMessage``."""
    w = _Writer()
    w.uint32(len(transforms))
    for t in transforms:
        w.header(t.time_s, t.parent)
        w.string(t.child)
        _pose(w, t.position_m, t.quaternion_xyzw)
    return w.bytes()

