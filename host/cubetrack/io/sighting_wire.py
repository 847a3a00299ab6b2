"""The sighting message: what a ``cubetrack worker`` publishes per camera frame on Zenoh and
``cubetrack fuse`` reads (contracts, "Sighting messages").

One message per processed camera frame, little-endian binary, corners and never images::

    magic "CTSG" | version u8 | flags u8 | seq i64 | device, capture, arrival time f64 (seconds)
    clock: method u8 (0 none, 1 arrival, 2 round-trip), offset_s f64, drift f64, device_ref_s f64
    health: connected u8, frames u32, dropped u32, bad u32, reconnects u32
    camera: u8 length + UTF-8
    [body: u8 length + UTF-8, the one robot whose markers the message holds, when flags bit 4]
    [T_world_cam: 12 f64, rows 0-2 of the 4x4, when flags bit 0]
    dictionaries: u8 count, each u8 length + UTF-8
    detections: u16 count, each marker id i32, dictionary index u8, corners 8 f64 (TL, TR, BR, BL
    x, y in pixels), area f64 (px^2)
    [drops: u8 count, each u8 length + UTF-8 reason, u32 markers, when flags bit 3]

``flags`` bit 0: a per-frame camera pose follows (world-marker mode); bits 1-2 the detection
outcome (0 regions, 1 full frame, 2 corrupt JPEG, 3 no camera pose); bit 3: the frame's markers
that OpenCV found and the detector then dropped, counted per reason, follow (so ``cubetrack fuse``
summaries count them as ``track`` does); bit 4: the message is one body's share of the frame (a worker
publishes a frame per body it holds markers of, so that a fusion shard receives only its robots'
share; docs/scaling.md), whose name follows the camera's. Messages without bit 4 (every message before
it existed) hold the whole frame. Times are host-clock Unix
seconds after the worker's clock mapping (``capture = device + offset + drift * (device -
device_ref)``), so the fusion orders sightings exactly as one process would; the mapping itself
travels along for inspection. Floats are float64, so a decoded message is bit-identical to what
the worker computed. A newer version is refused, never guessed at.

A batch (docs/scaling.md, "Fewer, larger messages"): several sighting messages that one worker publishes
together, one Zenoh message per robot per tick, each inside exactly as it would travel alone::

    magic "CTSB" | version u8 | count u16 | count x (u32 length + a sighting message)

:func:`decode_messages` reads either a batch or a lone sighting message (what workers before batches
published); a batch of a newer version is refused with its version named.
"""

from __future__ import annotations

import math
import struct
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import NamedTuple

import numpy as np

from cubetrack.core.errors import CubetrackError
from cubetrack.core.records import CameraHealth, Detection

MAGIC = b"CTSG"
VERSION = 1
# the wire code of each value the message carries as text (cubetrack.app.tracker.FrameOutcome and
# cubetrack.source.clock.ClockFitMethod values; tests/unit/app/test_sighting_wire.py checks that every
# value has one): written out, so that neither enum's order decides a byte on the wire
OUTCOME_CODES = {"regions": 0, "full frame": 1, "corrupt": 2, "no camera pose": 3}
CLOCK_METHOD_CODES = {"none": 0, "arrival": 1, "round-trip": 2}
_OUTCOMES = {code: value for value, code in OUTCOME_CODES.items()}
_CLOCK_METHODS = {code: value for value, code in CLOCK_METHOD_CODES.items()}

_HEAD = struct.Struct("<4sBBq3dB3dB4I")
_DETECTION = struct.Struct("<iB9d")
_POSE = struct.Struct("<12d")
_U8 = struct.Struct("<B")
_U16 = struct.Struct("<H")
_U32 = struct.Struct("<I")


class SightingWireError(CubetrackError):
    """A sighting message that cannot be read (truncated, not a sighting, a newer version)."""


@dataclass(frozen=True, slots=True)
class WireClock:
    """The worker's clock mapping of the camera: host = device + offset_s + drift * (device - device_ref_s)."""

    method: str = "none"
    offset_s: float = math.nan
    drift: float = math.nan
    device_ref_s: float = math.nan


@dataclass(frozen=True, slots=True)
class WireHealth:
    """The camera's source counters at the time of the frame (since the worker started)."""

    connected: bool = True
    frames: int = 0
    dropped: int = 0
    bad: int = 0
    reconnects: int = 0


@dataclass(frozen=True, slots=True, eq=False)
class SightingMessage:
    """One camera frame's sighting as it travels between a worker and the fusion."""

    camera: str
    seq: int
    device_time_s: float
    capture_time_s: float
    arrival_time_s: float
    outcome: str
    detections: tuple[Detection, ...]
    clock: WireClock = WireClock()
    health: WireHealth = WireHealth()
    T_world_cam: np.ndarray | None = None
    dropped: Mapping[str, int] = field(default_factory=dict)  # markers found, then dropped: reason -> count
    body: str | None = None  # the one robot whose detections these are (None: the whole frame's)


def _name(text: str, what: str) -> bytes:
    raw = text.encode("utf-8")
    if len(raw) > 255:
        raise SightingWireError(f"sighting message: {what} {text[:40]!r}... is longer than 255 bytes")
    return _U8.pack(len(raw)) + raw


def encode_sighting(message: SightingMessage) -> bytes:
    """The message's bytes (see the module docstring)."""
    if message.outcome not in OUTCOME_CODES:
        raise SightingWireError(f"sighting message: unknown outcome {message.outcome!r}")
    if message.clock.method not in CLOCK_METHOD_CODES:
        raise SightingWireError(f"sighting message: unknown clock method {message.clock.method!r}")
    if len(message.detections) > 0xFFFF:
        raise SightingWireError(f"sighting message: {len(message.detections)} detections, at most 65535")
    if len(message.dropped) > 255:
        raise SightingWireError(f"sighting message: {len(message.dropped)} drop reasons, at most 255")
    flags = ((message.T_world_cam is not None) | OUTCOME_CODES[message.outcome] << 1 | bool(message.dropped) << 3
             | (message.body is not None) << 4)
    h, c = message.health, message.clock
    parts = [_HEAD.pack(MAGIC, VERSION, flags, message.seq, message.device_time_s, message.capture_time_s,
                        message.arrival_time_s, CLOCK_METHOD_CODES[c.method], c.offset_s, c.drift, c.device_ref_s,
                        h.connected, *(min(v, 0xFFFFFFFF) for v in (h.frames, h.dropped, h.bad, h.reconnects))),
             _name(message.camera, "camera name")]
    if message.body is not None:
        parts.append(_name(message.body, "body name"))
    if message.T_world_cam is not None:
        parts.append(_POSE.pack(*np.asarray(message.T_world_cam, dtype=np.float64)[:3].ravel()))
    dictionaries = sorted({d.dictionary for d in message.detections})
    if len(dictionaries) > 255:
        raise SightingWireError("sighting message: more than 255 dictionaries")
    parts.append(_U8.pack(len(dictionaries)))
    parts.extend(_name(d, "dictionary name") for d in dictionaries)
    parts.append(_U16.pack(len(message.detections)))
    for d in message.detections:
        parts.append(_DETECTION.pack(d.marker_id, dictionaries.index(d.dictionary),
                                     *np.asarray(d.corners_px, dtype=np.float64).ravel(), d.area_px2))
    if message.dropped:
        parts.append(_U8.pack(len(message.dropped)))
        for reason, count in sorted(message.dropped.items()):
            parts += [_name(reason, "drop reason"), _U32.pack(min(count, 0xFFFFFFFF))]
    return b"".join(parts)


BATCH_MAGIC = b"CTSB"
BATCH_VERSION = 1
_BATCH_HEAD = struct.Struct("<4sBH")


def _envelope(magic: bytes, version: int, parts: Sequence[bytes], what: str) -> bytes:
    """``parts`` in one envelope: magic | version u8 | count u16 | count x (u32 length + a part)."""
    if not 0 < len(parts) <= 0xFFFF:
        raise SightingWireError(f"{what}: {len(parts)} messages, 1 to 65535")
    out = [_BATCH_HEAD.pack(magic, version, len(parts))]
    for data in parts:
        out += [_U32.pack(len(data)), data]
    return b"".join(out)


def _opened(data: bytes, magic: bytes, version: int, what: str) -> list[bytes]:
    """The parts of an envelope of ``magic`` and ``version`` (:func:`_envelope`); SightingWireError (one line) for
    another version, another message or a truncated envelope."""
    if data[:4] != magic:
        raise SightingWireError(f"not a {what} (starts {data[:5]!r})")
    if len(data) > 4 and data[4] != version:
        raise SightingWireError(f"{what} version {data[4]}, this cubetrack reads version {version}")
    r = _Reader(data)
    (_, _, count) = r.take(_BATCH_HEAD, f"{what} header")
    out: list[bytes] = []
    for _ in range(count):
        (n,) = r.take(_U32, what)
        if r.at + n > len(data):
            raise SightingWireError(f"{what} truncated in its message {len(out) + 1} of {count}")
        out.append(data[r.at:r.at + n])
        r.at += n
    if r.at != len(data):
        raise SightingWireError(f"{what}: {len(data) - r.at} bytes after its end")
    return out


def encode_batch(messages: Sequence[bytes]) -> bytes:
    """Encoded sighting messages as one batch (see the module docstring)."""
    return _envelope(BATCH_MAGIC, BATCH_VERSION, messages, "sighting batch")


def decode_messages(data: bytes) -> list[SightingMessage]:
    """The sighting messages in ``data``: a batch's, or a lone message (as workers published before batches);
    :class:`SightingWireError` (one line) for anything else, a truncated batch or a newer batch version."""
    data = bytes(data)
    if data[:4] != BATCH_MAGIC:
        return [decode_sighting(data)]
    return [decode_sighting(part) for part in _opened(data, BATCH_MAGIC, BATCH_VERSION, "sighting batch")]


class _Reader:
    def __init__(self, data: bytes):
        self.data, self.at = data, 0

    def take(self, layout: struct.Struct, what: str) -> tuple:
        if self.at + layout.size > len(self.data):
            raise SightingWireError(f"sighting message truncated in its {what} ({len(self.data)} bytes)")
        values = layout.unpack_from(self.data, self.at)
        self.at += layout.size
        return values

    def name(self, what: str) -> str:
        (n,) = self.take(_U8, what)
        raw = self.data[self.at:self.at + n]
        if len(raw) < n:
            raise SightingWireError(f"sighting message truncated in its {what} ({len(self.data)} bytes)")
        self.at += n
        try:
            return raw.decode("utf-8")
        except UnicodeDecodeError:
            raise SightingWireError(f"sighting message: its {what} is not UTF-8") from None


_TIMES_AT = struct.calcsize("<4sBBq")           # device, capture and arrival time: where _HEAD packs them
_DEVICE_REF_AT = struct.calcsize("<4sBBq3dB2d")  # the clock mapping's device_ref_s
_TIMES = struct.Struct("<3d")
_F64 = struct.Struct("<d")


def restamped(data: bytes, device_time_s: float, capture_time_s: float, arrival_time_s: float,
              device_ref_s: float) -> bytes:
    """An encoded message with its times (and its clock mapping's ``device_ref_s``) replaced, the
    rest as it was: a message encoded ahead, sent when its time comes (benchmarks/fleet.py's
    stand-in for remote workers). SightingWireError when ``data`` is not a sighting message."""
    if len(data) < _HEAD.size or data[:4] != MAGIC:
        raise SightingWireError("sighting message: not a sighting (bad magic or truncated)")
    out = bytearray(data)
    _TIMES.pack_into(out, _TIMES_AT, device_time_s, capture_time_s, arrival_time_s)
    _F64.pack_into(out, _DEVICE_REF_AT, device_ref_s)
    return bytes(out)


def decode_sighting(data: bytes) -> SightingMessage:
    """The message in ``data``; :class:`SightingWireError` (one line) for anything else."""
    data = bytes(data)
    if data[:4] != MAGIC:
        raise SightingWireError(f"not a cubetrack sighting message (starts {data[:4]!r})")
    if len(data) > 4 and data[4] != VERSION:
        raise SightingWireError(f"sighting message version {data[4]}, this cubetrack reads version {VERSION}")
    r = _Reader(data)
    (_, _, flags, seq, device_s, capture_s, arrival_s, method, offset_s, drift, ref_s, connected,
     frames, dropped_frames, bad, reconnects) = r.take(_HEAD, "header")
    if flags >> 5 or method not in _CLOCK_METHODS:
        raise SightingWireError(f"sighting message: unknown flags {flags:#x} or clock method {method}")
    camera = r.name("camera name")
    body = r.name("body name") if flags & 16 else None
    T_world_cam = None
    if flags & 1:
        T_world_cam = np.vstack([np.array(r.take(_POSE, "camera pose")).reshape(3, 4), [0.0, 0.0, 0.0, 1.0]])
    (n_dict,) = r.take(_U8, "dictionaries")
    dictionaries = [r.name("dictionary name") for _ in range(n_dict)]
    (n_det,) = r.take(_U16, "detections")
    detections = []
    for _ in range(n_det):
        marker_id, index, *values = r.take(_DETECTION, "detections")
        if index >= n_dict:
            raise SightingWireError(f"sighting message: detection of marker {marker_id} names dictionary {index} "
                                    f"of {n_dict}")
        detections.append(Detection(marker_id, np.array(values[:8]).reshape(4, 2), values[8], dictionaries[index]))
    dropped = {}
    if flags & 8:
        (n_reasons,) = r.take(_U8, "drop counts")
        for _ in range(n_reasons):
            reason = r.name("drop reason")
            dropped[reason] = r.take(_U32, "drop counts")[0]
    if r.at != len(data):
        raise SightingWireError(f"sighting message: {len(data) - r.at} bytes after its end")
    return SightingMessage(camera, seq, device_s, capture_s, arrival_s, _OUTCOMES[(flags >> 1) & 3], tuple(detections),
                           WireClock(_CLOCK_METHODS[method], offset_s, drift, ref_s),
                           WireHealth(bool(connected), frames, dropped_frames, bad, reconnects), T_world_cam, dropped,
                           body)


def camera_health(message: SightingMessage, previous: CameraHealth | None, now_s: float) -> CameraHealth:
    """The outputs' health snapshot of a camera from its latest message (frames/s since the
    previous snapshot)."""
    h, c = message.health, message.clock
    fps = math.nan
    if previous is not None and now_s > previous.time_s:
        fps = (h.frames - previous.frames) / (now_s - previous.time_s)
    synced = c.method == "round-trip"
    return CameraHealth(message.camera, now_s, h.connected, fps, h.frames, h.dropped, h.bad, h.reconnects,
                        c.offset_s if synced else math.nan, c.drift * 1e6 if synced else math.nan,
                        message.arrival_time_s - message.capture_time_s)


# A fleet's fused state (docs/scaling.md, "When a shard dies"): a shard's filter state of a robot after its
# newest sighting, passed to the shard that takes the robot over. magic "CTFS" | version u8 | robot: u8 length +
# UTF-8 | time_s f64 | T_world_cube rows 0-2, 12 f64 | velocity 3 f64 | angular velocity 3 f64 | covariance 144 f64
# (12x12 over [δp, δθ, v, ω])
STATE_MAGIC = b"CTFS"
_STATE = struct.Struct("<d12d3d3d144d")


class FusedState(NamedTuple):
    """A robot's filter state as a state message carries it (``FilterFusion.last_state`` / ``seed``)."""

    robot: str
    time_s: float
    T_world_cube: np.ndarray
    velocity_m_s: np.ndarray
    angular_velocity_rad_s: np.ndarray
    covariance: np.ndarray


def encode_state(state: FusedState) -> bytes:
    """A robot's filter state as a state message."""
    values = (state.T_world_cube[:3], state.velocity_m_s, state.angular_velocity_rad_s, state.covariance)
    return (STATE_MAGIC + _U8.pack(VERSION) + _name(state.robot, "robot name")
            + _STATE.pack(state.time_s, *np.concatenate([np.ravel(v) for v in values]).tolist()))


def decode_state(data: bytes) -> FusedState:
    """The filter state in a state message; SightingWireError (one line) for anything else."""
    data = bytes(data)
    if data[:4] != STATE_MAGIC or len(data) < 5 or data[4] != VERSION:
        raise SightingWireError(f"not a cubetrack state message of version {VERSION} (starts {data[:5]!r})")
    r = _Reader(data)
    r.at = 5
    robot = r.name("robot name")
    time_s, *rest = r.take(_STATE, "state")
    v = np.array(rest, dtype=np.float64)
    T = np.eye(4)
    T[:3] = v[:12].reshape(3, 4)
    return FusedState(robot, time_s, T, v[12:15], v[15:18], v[18:].reshape(12, 12))


# A shard's fused states of a tick (docs/scaling.md, "When a shard dies"): one message per shard every
# STATE_EVERY_S holding the state message of each robot it fused since its last, in an envelope as a batch's:
# magic "CTFB" | version u8 | count u16 | count x (u32 length + a state message). Shards before session 15 put each
# robot's state alone under the robot's key: not read (refused with one line), as is a newer envelope version.
STATES_MAGIC = b"CTFB"
STATES_VERSION = 1


def encode_states(states: Sequence[FusedState]) -> bytes:
    """Robots' filter states as one states message."""
    return _envelope(STATES_MAGIC, STATES_VERSION, [encode_state(state) for state in states], "fused states message")


def states_error(data: bytes) -> str | None:
    """Why ``data`` is not a states message this cubetrack reads, judged by its head only (None: it is one)."""
    if data[:4] != STATES_MAGIC or len(data) < 5:
        return f"not a fused states message (starts {bytes(data[:5])!r})"
    return None if data[4] == STATES_VERSION else f"fused states version {data[4]}, this reads {STATES_VERSION}"


def decode_states(data: bytes) -> list[FusedState]:
    """The filter states in a states message; SightingWireError (one line) for anything else."""
    return [decode_state(part) for part in _opened(bytes(data), STATES_MAGIC, STATES_VERSION, "fused states message")]
