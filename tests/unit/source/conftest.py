"""Real local HTTP servers for the live source: the camera emulator (the firmware's HTTP API and
its fault injection) serving synthetic JPEGs on 127.0.0.1, and helpers to read from it."""

from __future__ import annotations

import time

import pytest

from cubecam.testdata import write_images

FPS = 8.0


@pytest.fixture(scope="session")
def images(tmp_path_factory):
    return write_images(tmp_path_factory.mktemp("source-images"), 16, 160, 120)


def collect(live, seconds: float, until=None):
    """Take events from a LiveCameras for ``seconds`` (or until ``until(frames, clocks)``)."""
    frames, clocks = [], []
    deadline = time.monotonic() + seconds
    while time.monotonic() < deadline:
        event = live.get(0.05)
        if event is None:
            continue
        (frames if hasattr(event, "jpeg") else clocks).append(event)
        if until is not None and until(frames, clocks):
            break
    return frames, clocks
