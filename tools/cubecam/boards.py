"""Spresense boards attached over USB: the main board's CP2102N bridge, USB 10C4:EA60."""

from __future__ import annotations

import logging
from dataclasses import dataclass

from cubecam.errors import CubecamError

log = logging.getLogger(__name__)

USB_VID = 0x10C4
USB_PID = 0xEA60
NAME_QUERY_TIMEOUT_S = 2.0


@dataclass(frozen=True, slots=True)
class Board:
    """An attached board: its serial device, the USB serial number and description, and the
    node's name when it was asked for and answered (None otherwise)."""

    device: str
    serial_number: str
    description: str
    name: str | None = None


def attached_boards() -> list[Board]:
    """Serial ports with the Spresense USB id, sorted by device."""
    from serial.tools import list_ports

    out = []
    for p in list_ports.comports():
        if p.vid == USB_VID and p.pid == USB_PID:
            out.append(Board(p.device, p.serial_number or "", p.description or ""))
    return sorted(out, key=lambda b: b.device)


def query_name(device: str, timeout_s: float = NAME_QUERY_TIMEOUT_S) -> str | None:
    """The node's name from Improv device info, None when it does not answer in time."""
    from cubecam.link import NodeLink

    try:
        with NodeLink.open(device, on_log=lambda text: None) as node:
            node.wait_ready(timeout_s)
            return node.device_info(timeout_s).name or None
    except CubecamError as exc:
        log.info("%s: no name: %s", device, exc)
        return None
