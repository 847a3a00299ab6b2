"""Provisioning a camera node over USB serial (contracts §2).

The flow, every step bounded:

1. wait for the node: Improv "request current state" once a second until it answers
   (opening the port does not reset it, but it may still be booting);
2. Improv device info (firmware, version, chip, name);
3. station mode: Improv "send Wi-Fi settings", then wait for PROVISIONED and the node's URL,
   or its error (the node keeps the credentials once it joined);
   access-point mode: ``set mode ap``, ``set ssid``, ``set password`` on the console (Improv
   only joins networks as a station);
4. console settings: ``set name``, ``set jpeg_quality``, ``set fps``, ``set ip``, then ``save``
   — each answered ``OK`` or ``ERR <code> <message>``; they come after the Wi-Fi step because
   the node stores its running settings when it joins;
5. the node applies saved settings at boot, so when any were changed (or with ``reboot``):
   ``reboot``, then wait until it is back online and take its URL.

The password travels inside the Improv frame (or the console line in access-point mode) and
is never logged or printed.
"""

from __future__ import annotations

import ipaddress
import logging
import re
import time
from dataclasses import dataclass, field
from pathlib import Path

from cubecam import improv
from cubecam.errors import ProvisionError
from cubecam.link import JOIN_TIMEOUT_S, NodeLink

log = logging.getLogger(__name__)

BOOT_TIMEOUT_S = 15.0
REBOOT_SETTLE_S = 0.5  # the node reboots 100 ms after its OK; answers before that are stale
MODES = ("station", "ap")
_NAME = re.compile(r"^[A-Za-z0-9_-]{1,32}$")


@dataclass(frozen=True, slots=True)
class ProvisionRequest:
    """What to set. None leaves a setting as the node has it. ``ip`` is ``dhcp`` or
    ``a.b.c.d/prefix,gateway``; ``fps`` frames per second (the node accepts 30, 15, 7.5)."""

    ssid: str
    password: str = field(repr=False)
    name: str | None = None
    jpeg_quality: int | None = None
    fps: float | None = None
    mode: str | None = None
    ip: str | None = None
    boot_timeout_s: float = BOOT_TIMEOUT_S
    join_timeout_s: float = JOIN_TIMEOUT_S
    reboot: bool = False

    def check(self) -> ProvisionRequest:
        ssid_bytes = len(self.ssid.encode("utf-8"))
        if not 1 <= ssid_bytes <= 32:
            raise ProvisionError(f"SSID must be 1 to 32 bytes, got {ssid_bytes}")
        if "," in self.ssid or not all(" " <= c <= "~" for c in self.ssid):
            raise ProvisionError(f"SSID {self.ssid!r}: the node takes printable ASCII without commas "
                                 "(its scan list and AT commands separate fields with them)")
        pw = len(self.password.encode("utf-8"))
        if pw and not 8 <= pw <= 63:
            raise ProvisionError(f"a WPA2 password has 8 to 63 bytes (characters, unless beyond ASCII), got {pw} "
                                 "(empty = open network)")
        if any(ord(c) < 0x20 or ord(c) == 0x7F for c in self.password):
            raise ProvisionError("the password must be one line without control characters (tab, ...): "
                                 "the node takes any other character, commas, quotes and spaces included")
        if self.name is not None and not _NAME.match(self.name):
            raise ProvisionError(f"name {self.name!r}: use 1-32 letters, digits, '_' or '-'")
        if self.jpeg_quality is not None and not 1 <= self.jpeg_quality <= 100:
            raise ProvisionError(f"JPEG quality must be 1..100, got {self.jpeg_quality}")
        if self.fps is not None and not 0 < self.fps <= 30:
            raise ProvisionError(f"fps must be in (0, 30], got {self.fps}")
        if self.mode is not None and self.mode not in MODES:
            raise ProvisionError(f"mode must be station or ap, got {self.mode!r}")
        if self.ip is not None:
            check_ip(self.ip)
        return self


def check_ip(text: str) -> str:
    """``dhcp`` or ``a.b.c.d/prefix,gateway`` with the gateway inside the network."""
    if text == "dhcp":
        return text
    m = re.fullmatch(r"(\d+\.\d+\.\d+\.\d+)/(\d{1,2}),(\d+\.\d+\.\d+\.\d+)", text)
    try:
        if not m:
            raise ValueError
        iface = ipaddress.IPv4Interface(f"{m.group(1)}/{m.group(2)}")
        gateway = ipaddress.IPv4Address(m.group(3))
    except ValueError:
        raise ProvisionError(
            f"--ip {text!r}: use dhcp or a.b.c.d/prefix,gateway (e.g. 192.168.1.21/24,192.168.1.1)") from None
    if gateway not in iface.network:
        raise ProvisionError(f"--ip {text!r}: gateway {gateway} is outside {iface.network}")
    return text


def _fps_text(fps: float) -> str:
    return f"{fps:g}"


@dataclass(frozen=True, slots=True)
class ProvisionResult:
    name: str
    url: str            # the node's page, e.g. http://192.168.1.21/
    stream_url: str     # what a tracker config's [[cameras]] url takes
    firmware: str
    version: str


def stream_url(url: str) -> str:
    base = url if url.endswith("/") else url + "/"
    return base + "stream"


def _console_settings(req: ProvisionRequest) -> list[str]:
    out = []
    if req.name is not None:
        out.append(f"set name {req.name}")
    if req.jpeg_quality is not None:
        out.append(f"set jpeg_quality {req.jpeg_quality}")
    if req.fps is not None:
        out.append(f"set fps {_fps_text(req.fps)}")
    if req.ip is not None:
        out.append(f"set ip {req.ip}")
    return out


def provision(node: NodeLink, req: ProvisionRequest, say=lambda text: None) -> ProvisionResult:
    """Run the provisioning flow (module docstring) on an open link; ``say`` gets progress lines."""
    req.check()
    state, _ = node.wait_ready(req.boot_timeout_s)
    say(f"node answered, state {_state_name(state)}")
    info = node.device_info()
    say(f"firmware {info.firmware} {info.version} on {info.chip}, name {info.name or '(unset)'}")
    settings = _console_settings(req)
    reboot = req.reboot or bool(settings)
    urls: list[str] = []
    if req.mode == "ap":
        # Improv joins networks as a station; an access point is set up through the console.
        node.console("set mode ap")
        node.console(f"set ssid {req.ssid}")
        node.console(f"set password {req.password}", secret=True)
        say(f"access point {req.ssid!r} set")
        reboot = True
    else:
        say(f"sending Wi-Fi settings for {req.ssid!r}")
        urls = node.send_wifi(req.ssid, req.password, req.join_timeout_s)
        say(f"joined {req.ssid!r}" + (f": {urls[0]}" if urls else ""))
        if req.mode == "station":
            settings.insert(0, "set mode station")
    for command in settings:
        node.console(command)
        say(command)
    if settings or req.mode == "ap":
        node.console("save")
        say("settings saved")
    if reboot:
        node.console("reboot")
        say("rebooting to apply the settings")
        time.sleep(REBOOT_SETTLE_S)
        node.discard_input()
        urls = node.wait_online(req.boot_timeout_s + req.join_timeout_s)
    elif not urls:
        urls = node.wait_online(5.0)
    url = urls[0]
    name = req.name or info.name or ""
    return ProvisionResult(name, url, stream_url(url), info.firmware, info.version)


def _state_name(state) -> str:
    return state.name if isinstance(state, improv.State) else f"{int(state):#04x}"


def read_password(password_file: str | None, stdin, prompt) -> str:
    """The password from a file (first line), else stdin when it is not a terminal, else a prompt."""
    if password_file is not None:
        try:
            text = Path(password_file).read_text(encoding="utf-8")
        except OSError as exc:
            raise ProvisionError(f"{password_file}: cannot read the password file ({exc.strerror or exc})") from None
        return text.splitlines()[0] if text else ""
    if stdin is not None and not stdin.isatty():
        return stdin.readline().rstrip("\r\n")
    return prompt("Wi-Fi password: ")
