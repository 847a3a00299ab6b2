"""Misbehaving HTTP clients for the slot tests of the emulator and of cubecam-native."""

from __future__ import annotations

import socket
import threading


def slow_loris(address: tuple[str, int], count: int, period_s: float, stop: threading.Event) -> list[socket.socket]:
    """``count`` connections that send a request head one byte every ``period_s`` (until ``stop``)."""
    socks = [socket.create_connection(address) for _ in range(count)]

    def trickle() -> None:
        request = b"GET /status HTTP/1.1\r\nX-Slow: " + b"a" * 1000
        for i in range(len(request)):
            for s in socks:
                try:
                    s.sendall(request[i:i + 1])
                except OSError:
                    pass
            if stop.wait(period_s):
                return

    threading.Thread(target=trickle, daemon=True).start()
    return socks


def non_reading_streams(address: tuple[str, int], count: int) -> list[socket.socket]:
    """``count`` stream clients that send their request and then never read (a small receive
    buffer, so the server's sends block soon)."""
    socks = []
    for _ in range(count):
        s = socket.socket()
        s.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)
        s.connect(address)
        s.sendall(b"GET /stream HTTP/1.1\r\n\r\n")
        socks.append(s)
    return socks


def drain(sock: socket.socket, stop: threading.Event) -> None:
    """A well-behaved stream client: reads everything until stopped."""
    try:
        while not stop.is_set() and sock.recv(65536):
            pass
    except OSError:
        pass
