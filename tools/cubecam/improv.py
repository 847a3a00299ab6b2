"""Improv Wi-Fi serial, version 1: a portable codec (no I/O).

Frame: ``b"IMPROV"``, version ``0x01``, type, length (1 byte), data, checksum = sum of all
preceding bytes mod 256. A frame starts a line: the node ends every log line with ``\\n``, and
writers send ``\\n`` after each frame (as the JS SDK and ESPHome do). One encoder per frame
type; :class:`Parser` splits a byte stream into frames and the text lines around them.
Values of the enums are the wire bytes.
"""

from __future__ import annotations

import enum
from dataclasses import dataclass

from cubecam.errors import ImprovError

MAGIC = b"IMPROV"
VERSION = 1
HEADER_LEN = len(MAGIC) + 3  # magic, version, type, length
MAX_DATA = 255
PARTIAL_FRAME_TIMEOUT_S = 0.1  # a partial frame is dropped after this long without a byte
MAX_LINE = 4096                 # longer text lines are cut (and emitted) here


class FrameType(enum.IntEnum):
    CURRENT_STATE = 0x01
    ERROR_STATE = 0x02
    RPC = 0x03
    RPC_RESULT = 0x04


class State(enum.IntEnum):
    STOPPED = 0x00
    AWAITING_AUTHORIZATION = 0x01
    READY = 0x02  # "authorized"
    PROVISIONING = 0x03
    PROVISIONED = 0x04


class Error(enum.IntEnum):
    NONE = 0x00
    INVALID_RPC = 0x01
    UNKNOWN_RPC = 0x02
    UNABLE_TO_CONNECT = 0x03
    NOT_AUTHORIZED = 0x04
    BAD_HOSTNAME = 0x05
    UNKNOWN = 0xFF


class Command(enum.IntEnum):
    WIFI_SETTINGS = 0x01
    GET_CURRENT_STATE = 0x02
    GET_DEVICE_INFO = 0x03
    GET_WIFI_NETWORKS = 0x04
    HOSTNAME = 0x05
    DEVICE_NAME = 0x06


ERROR_TEXT = {
    Error.NONE: "no error",
    Error.INVALID_RPC: "invalid RPC packet or bad checksum",
    Error.UNKNOWN_RPC: "unknown RPC command",
    Error.UNABLE_TO_CONNECT: "unable to connect to the network",
    Error.NOT_AUTHORIZED: "not authorized",
    Error.BAD_HOSTNAME: "bad hostname",
    Error.UNKNOWN: "unknown error",
}


def checksum(data: bytes) -> int:
    return sum(data) & 0xFF


def encode_frame(frame_type: int, data: bytes) -> bytes:
    """One whole frame (without the trailing newline)."""
    if len(data) > MAX_DATA:
        raise ImprovError(f"Improv frame data is {len(data)} bytes; at most {MAX_DATA} fit")
    body = MAGIC + bytes((VERSION, int(frame_type), len(data))) + data
    return body + bytes((checksum(body),))


def _strings(values: list[str] | tuple[str, ...]) -> bytes:
    out = b""
    for v in values:
        raw = v.encode("utf-8")
        if len(raw) > 255:
            raise ImprovError(f"Improv string of {len(raw)} bytes is too long (at most 255)")
        out += bytes((len(raw),)) + raw
    return out


def encode_current_state(state: State) -> bytes:
    return encode_frame(FrameType.CURRENT_STATE, bytes((int(state),)))


def encode_error_state(error: Error) -> bytes:
    return encode_frame(FrameType.ERROR_STATE, bytes((int(error),)))


def encode_rpc(command: Command, strings: list[str] | tuple[str, ...] = ()) -> bytes:
    """An RPC command frame; data = command, payload length, payload (length-prefixed strings)."""
    payload = _strings(strings)
    if len(payload) > 253:
        raise ImprovError(f"Improv RPC payload of {len(payload)} bytes is too long (at most 253)")
    return encode_frame(FrameType.RPC, bytes((int(command), len(payload))) + payload)


def encode_wifi_settings(ssid: str, password: str) -> bytes:
    return encode_rpc(Command.WIFI_SETTINGS, (ssid, password))


def encode_rpc_result(command: Command, strings: list[str] | tuple[str, ...] = ()) -> bytes:
    """An RPC result frame; data = command, total length, length-prefixed strings."""
    payload = _strings(strings)
    if len(payload) > 253:
        raise ImprovError(f"Improv RPC result of {len(payload)} bytes is too long (at most 253)")
    return encode_frame(FrameType.RPC_RESULT, bytes((int(command), len(payload))) + payload)


@dataclass(frozen=True, slots=True)
class Frame:
    """A decoded frame: its type and data (checksum verified)."""

    type: int
    data: bytes


@dataclass(frozen=True, slots=True)
class Line:
    """A text line between frames (log output, console answers), without its line ending."""

    text: str


@dataclass(frozen=True, slots=True)
class BadFrame:
    """Bytes that started like a frame but were not one (wrong version, bad checksum)."""

    reason: str
    raw: bytes


Event = Frame | Line | BadFrame


def _split_strings(payload: bytes, what: str) -> list[str]:
    out = []
    i = 0
    while i < len(payload):
        n = payload[i]
        if i + 1 + n > len(payload):
            raise ImprovError(f"{what}: a string runs past the end of the data")
        out.append(payload[i + 1:i + 1 + n].decode("utf-8", "replace"))
        i += 1 + n
    return out


def decode_state(frame: Frame) -> State | int:
    if frame.type != FrameType.CURRENT_STATE or len(frame.data) != 1:
        raise ImprovError(f"not a current-state frame: type {frame.type}, {len(frame.data)} data bytes")
    try:
        return State(frame.data[0])
    except ValueError:
        return frame.data[0]


def decode_error(frame: Frame) -> Error | int:
    if frame.type != FrameType.ERROR_STATE or len(frame.data) != 1:
        raise ImprovError(f"not an error-state frame: type {frame.type}, {len(frame.data)} data bytes")
    try:
        return Error(frame.data[0])
    except ValueError:
        return frame.data[0]


def decode_rpc(frame: Frame) -> tuple[int, list[str]]:
    """(command, strings) of an RPC frame."""
    return _decode_command_frame(frame, FrameType.RPC, "RPC")


def decode_rpc_result(frame: Frame) -> tuple[int, list[str]]:
    """(command, strings) of an RPC result frame."""
    return _decode_command_frame(frame, FrameType.RPC_RESULT, "RPC result")


def _decode_command_frame(frame: Frame, frame_type: FrameType, what: str) -> tuple[int, list[str]]:
    if frame.type != frame_type:
        raise ImprovError(f"not an {what} frame: type {frame.type}")
    if len(frame.data) < 2:
        raise ImprovError(f"{what} frame too short ({len(frame.data)} bytes)")
    command, length = frame.data[0], frame.data[1]
    if length != len(frame.data) - 2:
        raise ImprovError(f"{what} length byte says {length}, data has {len(frame.data) - 2}")
    return command, _split_strings(frame.data[2:], what)


class Parser:
    """Incremental splitter of a serial byte stream into :class:`Frame`, :class:`Line` and
    :class:`BadFrame` events. A frame is recognised where ``IMPROV`` starts (normally at the
    start of a line); ``\\r`` before ``\\n`` and the empty line after a frame are dropped.
    Call :meth:`timeout` when no byte came for :data:`PARTIAL_FRAME_TIMEOUT_S`: a partial frame
    is then dropped, as the device side does."""

    def __init__(self) -> None:
        self._line = bytearray()
        self._frame = bytearray()  # the frame being read (empty: reading a line)
        self._after_frame = False

    def feed(self, data: bytes) -> list[Event]:
        events: list[Event] = []
        for b in data:
            if self._frame:
                self._frame_byte(b, events)
            else:
                self._line_byte(b, events)
        return events

    def timeout(self) -> list[Event]:
        """Drop a partial frame (reported as a BadFrame); a partial text line is kept."""
        if not self._frame:
            return []
        raw = bytes(self._frame)
        self._frame.clear()
        return [BadFrame("partial frame: no byte for 100 ms", raw)]

    def _line_byte(self, b: int, events: list[Event]) -> None:
        if b == 0x0A:
            text = bytes(self._line).rstrip(b"\r")
            self._line.clear()
            if text or not self._after_frame:
                events.append(Line(text.decode("utf-8", "replace")))
            self._after_frame = False
            return
        self._line.append(b)
        if self._line.endswith(MAGIC):
            before = bytes(self._line[:-len(MAGIC)]).rstrip(b"\r")
            self._line.clear()
            if before:
                events.append(Line(before.decode("utf-8", "replace")))
            self._frame[:] = MAGIC
            return
        if len(self._line) >= MAX_LINE:
            events.append(Line(bytes(self._line).decode("utf-8", "replace")))
            self._line.clear()
        self._after_frame = False

    def _frame_byte(self, b: int, events: list[Event]) -> None:
        self._frame.append(b)
        n = len(self._frame)
        if n == len(MAGIC) + 1 and b != VERSION:
            self._bad(f"unsupported Improv version {b}", events)
            return
        if n < HEADER_LEN or n < HEADER_LEN + self._frame[HEADER_LEN - 1] + 1:
            return
        raw = bytes(self._frame)
        if checksum(raw[:-1]) != raw[-1]:
            self._bad(f"bad checksum {raw[-1]:#04x}, expected {checksum(raw[:-1]):#04x}", events)
            return
        self._frame.clear()
        self._after_frame = True
        events.append(Frame(raw[len(MAGIC) + 1], raw[HEADER_LEN:-1]))

    def _bad(self, reason: str, events: list[Event]) -> None:
        events.append(BadFrame(reason, bytes(self._frame)))
        self._frame.clear()
        self._after_frame = True  # the rest of the junk runs to the end of its line
