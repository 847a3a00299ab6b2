"""A serial connection to a camera node (contracts §2): Improv serial v1 and the line console
on one port, with every wait bounded.

Opening never resets the board: DTR and RTS are set low *before* the port is opened (DTR
toggles reset on the Spresense). Bytes from the node are split by :class:`cubecam.improv.Parser`
into Improv frames and text lines; lines that are not a console answer are log lines and go
to ``on_log``. A vanished port, silence past a deadline or a garbled answer raise
:class:`~cubecam.errors.SerialDeviceError`; a refusal by the node raises
:class:`~cubecam.errors.ProvisionError`.
"""

from __future__ import annotations

import logging
import re
import time
from collections import Counter, deque
from collections.abc import Callable
from dataclasses import dataclass

from cubecam import improv
from cubecam.errors import ImprovError, ProvisionError, SerialDeviceError

log = logging.getLogger(__name__)

BAUD = 115200
READ_SLICE_S = 0.05           # one read waits at most this long
WRITE_TIMEOUT_S = 2.0
STATE_RETRY_S = 1.0           # "request current state" is repeated this often while the node boots
RPC_TIMEOUT_S = 5.0           # device info, current state
SCAN_TIMEOUT_S = 20.0
CONSOLE_TIMEOUT_S = 5.0
JOIN_TIMEOUT_S = 45.0         # the node itself gives up after 30 s (Improv convention)
DETAIL_LIMIT = 3
_ERR_LINE = re.compile(r"^ERR \d+\b")
SECRET_RUN = 8  # a log line holding this many consecutive characters of a secret is hidden


def open_serial(device: str, baud: int = BAUD):
    """Open ``device`` at 115200 8N1 without toggling DTR/RTS into a reset."""
    import serial

    port = serial.Serial()
    port.port = device
    port.baudrate = baud
    port.timeout = READ_SLICE_S
    port.write_timeout = WRITE_TIMEOUT_S
    port.dtr = False
    port.rts = False
    port.exclusive = True  # another program on the same port would steal the answers
    try:
        port.open()
    except (serial.SerialException, OSError, ValueError) as exc:
        text = str(exc)
        reason = getattr(exc, "strerror", None) or text.split(": ", 1)[-1] or exc.__class__.__name__
        hint = "`cubecam list` shows attached boards"
        if "ermission denied" in text:
            hint = "your user needs access to the port (Debian/Ubuntu: the dialout group)"
        elif "exclusively lock" in text or "Resource temporarily unavailable" in text:
            reason, hint = "in use", "another program (a serial monitor?) has it open"
        raise SerialDeviceError(f"{device}: cannot open serial port ({reason}); {hint}") from None
    return port


@dataclass(frozen=True, slots=True)
class DeviceInfo:
    """Improv device info: firmware name, version, chip, device name."""

    firmware: str
    version: str
    chip: str
    name: str


@dataclass(frozen=True, slots=True)
class Network:
    ssid: str
    rssi: int
    secured: bool


class NodeLink:
    """Talk to one node over an open serial port (see :func:`open_serial`)."""

    def __init__(self, port, device: str | None = None, on_log: Callable[[str], None] | None = None):
        self.port = port
        self.device: str = device or getattr(port, "port", None) or "serial port"
        self.on_log = on_log or (lambda text: log.info("%s: %s", self.device, text))
        self.parser = improv.Parser()
        self.frames: deque[improv.Frame] = deque()
        self.lines: deque[str] = deque()
        self.bad: Counter[str] = Counter()
        self.bytes_seen = 0
        self._last_byte = time.monotonic()
        self._collect_lines = False
        self._secrets: set[str] = set()  # sent on this link: never shown again (a board may echo them)

    @classmethod
    def open(cls, device: str, on_log: Callable[[str], None] | None = None) -> NodeLink:
        return cls(open_serial(device), device, on_log)

    def close(self) -> None:
        try:
            self.port.close()
        except Exception:  # closing a vanished port may fail; nothing to do about it
            pass

    def __enter__(self) -> NodeLink:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # --- bytes ---

    def write(self, data: bytes) -> None:
        try:
            self.port.write(data)
            self.port.flush()
        except Exception as exc:  # SerialException, SerialTimeoutException, OSError
            raise SerialDeviceError(
                f"{self.device}: the port went away while writing ({_reason(exc)}); was the board unplugged?") from None

    def pump(self) -> None:
        """Read what is there (waiting at most one read slice) and sort it into frames and lines."""
        try:
            waiting = self.port.in_waiting
            data = self.port.read(max(1, min(waiting, 4096)))
        except Exception as exc:  # SerialException on a vanished port, OSError EIO on a pty
            raise SerialDeviceError(
                f"{self.device}: the port went away ({_reason(exc)}); was the board unplugged?") from None
        now = time.monotonic()
        if data:
            self.bytes_seen += len(data)
            self._last_byte = now
            events = self.parser.feed(data)
        elif now - self._last_byte > improv.PARTIAL_FRAME_TIMEOUT_S:
            events = self.parser.timeout()
        else:
            events = []
        for ev in events:
            if isinstance(ev, improv.Frame):
                self.frames.append(ev)
            elif isinstance(ev, improv.BadFrame):
                self.bad[ev.reason.split(" 0x")[0]] += 1
                # not its bytes: it may be our own Wi-Fi frame echoed back
                log.debug("%s: bad Improv frame: %s (%d bytes)", self.device, ev.reason, len(ev.raw))
            elif self._collect_lines:
                self.lines.append(ev.text)
            else:
                self.on_log(self.redact(ev.text))

    def redact(self, text: str) -> str:
        """``text`` as it may be logged or printed: hidden when it holds a run of SECRET_RUN
        characters of a secret sent on this link (a board that echoes its input, or a noisy
        line, would otherwise put the Wi-Fi password in the log)."""
        for secret in self._secrets:
            run = min(SECRET_RUN, len(secret))
            if any(secret[i:i + run] in text for i in range(len(secret) - run + 1)):
                return "(a line holding the Wi-Fi password, not shown)"
        return text

    def _heard(self) -> str:
        if not self.bytes_seen:
            return "nothing was received"
        bad = ", ".join(f"{n} x {why}" for why, n in self.bad.most_common(DETAIL_LIMIT))
        return f"{self.bytes_seen} bytes were received" + (f", bad Improv frames: {bad}" if bad else "")

    def wait_frame(self, accept: Callable[[improv.Frame], bool], deadline: float,
                   retry: Callable[[], None] | None = None,
                   retry_every_s: float = STATE_RETRY_S) -> improv.Frame | None:
        """The first frame that ``accept`` takes (others are dropped) before the monotonic
        ``deadline``; None on timeout. ``retry`` is called now and every ``retry_every_s``."""
        next_retry = time.monotonic()
        while True:
            while self.frames:
                frame = self.frames.popleft()
                if accept(frame):
                    return frame
            now = time.monotonic()
            if now >= deadline:
                return None
            if retry is not None and now >= next_retry:
                retry()
                next_retry = now + retry_every_s
            self.pump()

    # --- Improv ---

    def send_rpc(self, command: improv.Command, strings: tuple[str, ...] = ()) -> None:
        self.write(b"\n" + improv.encode_rpc(command, strings) + b"\n")

    def wait_ready(self, timeout_s: float) -> tuple[improv.State | int, list[str]]:
        """Ask for the current state once a second until the node answers (it may be booting).
        Returns the state and, when provisioned, the URLs it reported."""
        deadline = time.monotonic() + timeout_s
        frame = self.wait_frame(lambda f: f.type == improv.FrameType.CURRENT_STATE, deadline,
                                retry=lambda: self.send_rpc(improv.Command.GET_CURRENT_STATE))
        if frame is None:
            raise SerialDeviceError(
                f"{self.device}: no Improv answer in {timeout_s:g} s ({self._heard()}); "
                "is this a cubecam node with its firmware running at 115200 baud?")
        state = improv.decode_state(frame)
        urls: list[str] = []
        if state == improv.State.PROVISIONED:
            result = self.wait_frame(_result_for(improv.Command.GET_CURRENT_STATE), time.monotonic() + 1.0)
            if result is not None:
                urls = improv.decode_rpc_result(result)[1]
        return state, urls

    def wait_online(self, timeout_s: float) -> list[str]:
        """Ask for the current state once a second until the node is PROVISIONED (online) and
        reported its URL; SerialDeviceError on timeout, naming the last state seen."""
        deadline = time.monotonic() + timeout_s
        next_ask = time.monotonic()
        last = None
        is_state = lambda f: f.type == improv.FrameType.CURRENT_STATE  # noqa: E731
        while True:
            now = time.monotonic()
            if now >= deadline:
                seen = f"last state {getattr(last, 'name', last)}" if last is not None else self._heard()
                raise SerialDeviceError(f"{self.device}: the node was not online within {timeout_s:g} s ({seen})")
            if now >= next_ask:
                self.send_rpc(improv.Command.GET_CURRENT_STATE)
                next_ask = now + STATE_RETRY_S
            frame = self.wait_frame(is_state, min(deadline, next_ask))
            if frame is None:
                continue
            last = improv.decode_state(frame)
            if last != improv.State.PROVISIONED:
                continue
            result = self.wait_frame(_result_for(improv.Command.GET_CURRENT_STATE), time.monotonic() + 1.0)
            urls = _decode_result(result, self.device) if result is not None else []
            if urls:
                return urls
            raise SerialDeviceError(f"{self.device}: the node is online but reported no URL")

    def discard_input(self) -> None:
        """Forget frames and lines received so far (e.g. from before a reboot)."""
        self.pump()
        self.frames.clear()
        self.lines.clear()

    def device_info(self, timeout_s: float = RPC_TIMEOUT_S) -> DeviceInfo:
        self.send_rpc(improv.Command.GET_DEVICE_INFO)
        frame = self.wait_frame(_result_or_error(improv.Command.GET_DEVICE_INFO), time.monotonic() + timeout_s)
        if frame is None:
            raise SerialDeviceError(f"{self.device}: no answer to Improv device info in {timeout_s:g} s "
                                    f"({self._heard()})")
        if frame.type == improv.FrameType.ERROR_STATE:
            raise ProvisionError(f"{self.device}: device info refused: {_error_text(frame)}")
        strings = _decode_result(frame, self.device)
        strings += [""] * (4 - len(strings))
        return DeviceInfo(*strings[:4])

    def scan(self, timeout_s: float = SCAN_TIMEOUT_S) -> list[Network]:
        """Networks the node sees: one RPC result per network, then an empty one."""
        self.send_rpc(improv.Command.GET_WIFI_NETWORKS)
        deadline = time.monotonic() + timeout_s
        out: list[Network] = []
        while True:
            frame = self.wait_frame(_result_or_error(improv.Command.GET_WIFI_NETWORKS), deadline)
            if frame is None:
                raise SerialDeviceError(f"{self.device}: Wi-Fi scan did not finish in {timeout_s:g} s "
                                        f"({self._heard()})")
            if frame.type == improv.FrameType.ERROR_STATE:
                raise ProvisionError(f"{self.device}: scan refused: {_error_text(frame)}")
            strings = _decode_result(frame, self.device)
            if not strings:
                return out
            try:
                out.append(Network(strings[0], int(strings[1]), strings[2].upper() == "YES"))
            except (IndexError, ValueError):
                raise SerialDeviceError(f"{self.device}: malformed scan entry {strings!r}") from None

    def send_wifi(self, ssid: str, password: str, timeout_s: float = JOIN_TIMEOUT_S) -> list[str]:
        """Send Wi-Fi settings; wait until the node joined (its URLs) or failed."""
        if password:
            self._secrets.add(password)
        self.write(b"\n" + improv.encode_wifi_settings(ssid, password) + b"\n")
        deadline = time.monotonic() + timeout_s
        provisioned = False
        while True:
            frame = self.wait_frame(lambda f: f.type in (improv.FrameType.CURRENT_STATE, improv.FrameType.ERROR_STATE,
                                                         improv.FrameType.RPC_RESULT), deadline)
            if frame is None:
                raise ProvisionError(
                    f"{self.device}: the node did not report joining {ssid!r} within {timeout_s:g} s ({self._heard()})")
            if frame.type == improv.FrameType.ERROR_STATE:
                err = improv.decode_error(frame)
                if err == improv.Error.NONE:
                    continue
                hint = (": check the SSID and password, and that the network is 2.4 GHz and in range"
                        if err == improv.Error.UNABLE_TO_CONNECT else "")
                raise ProvisionError(f"{self.device}: the node could not join {ssid!r}: {_error_text(frame)}{hint}")
            if frame.type == improv.FrameType.CURRENT_STATE:
                provisioned = improv.decode_state(frame) == improv.State.PROVISIONED
                continue
            command, urls = improv.decode_rpc_result(frame)
            if command == improv.Command.WIFI_SETTINGS:
                if not provisioned:
                    log.debug("%s: Wi-Fi result before the PROVISIONED state", self.device)
                return urls

    # --- console ---

    def console(self, line: str, timeout_s: float = CONSOLE_TIMEOUT_S, secret: bool = False) -> list[str]:
        """Send one console command; the lines before ``OK``. ``ERR <code> <message>`` raises
        ProvisionError. ``secret`` keeps the command out of logs and messages."""
        shown = " ".join(line.split(" ")[:2]) + " ***" if secret else line
        if "\n" in line or "\r" in line:
            raise ProvisionError(f"console command {shown!r} must be one line")
        if secret and line.count(" ") >= 2:
            self._secrets.add(line.split(" ", 2)[2])
        self.lines.clear()
        self._collect_lines = True
        try:
            self.write(line.encode("utf-8") + b"\n")
            deadline = time.monotonic() + timeout_s
            answer: list[str] = []
            while time.monotonic() < deadline:
                self.pump()
                while self.lines:
                    text = self.lines.popleft().strip()
                    if text == "OK" or text.startswith("OK "):
                        return answer
                    if _ERR_LINE.match(text):
                        raise ProvisionError(f"{self.device}: node refused `{shown}`: {self.redact(text)}")
                    if text:
                        answer.append(text)
            raise SerialDeviceError(
                f"{self.device}: no OK/ERR answer to console command `{shown}` in {timeout_s:g} s ({self._heard()})")
        finally:
            self._collect_lines = False
            for text in self.lines:
                self.on_log(self.redact(text))
            self.lines.clear()


def _reason(exc: BaseException) -> str:
    text = getattr(exc, "strerror", None) or str(exc) or exc.__class__.__name__
    m = re.search(r"\(\d+, '([^']+)'\)", text)  # pyserial wraps OSErrors as "(5, 'Input/output error')"
    return m.group(1) if m else text


def _result_for(command: improv.Command) -> Callable[[improv.Frame], bool]:
    return lambda f: f.type == improv.FrameType.RPC_RESULT and f.data[:1] == bytes((int(command),))


def _result_or_error(command: improv.Command) -> Callable[[improv.Frame], bool]:
    is_result = _result_for(command)
    return lambda f: is_result(f) or (f.type == improv.FrameType.ERROR_STATE and f.data != b"\x00")


def _error_text(frame: improv.Frame) -> str:
    err = improv.decode_error(frame)
    if isinstance(err, improv.Error):
        return improv.ERROR_TEXT.get(err, f"error {int(err):#04x}")
    return f"error {err:#04x}"


def _decode_result(frame: improv.Frame, device: str) -> list[str]:
    try:
        return improv.decode_rpc_result(frame)[1]
    except ImprovError as exc:
        raise SerialDeviceError(f"{device}: malformed Improv answer: {exc}") from None
