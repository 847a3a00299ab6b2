"""Fixtures for the firmware tests: test JPEGs and a running cubecam-native."""

from __future__ import annotations

from pathlib import Path

import pytest
from firmware_tools import require_tools

from tests.helpers.native import NativeNode, build_native


@pytest.fixture(scope="session")
def native_binary() -> Path:
    require_tools("make", "g++")
    return build_native()


@pytest.fixture(scope="session")
def jpeg_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """Six distinct 640x480 JPEG frames, each a grey level plus noise (30-60 kB, like a real scene)."""
    import cv2
    import numpy as np

    folder = tmp_path_factory.mktemp("frames")
    rng = np.random.default_rng(7)
    for i in range(6):
        img = np.full((480, 640, 3), 40 * i + 20, np.uint8)
        img[::2, ::2] = rng.integers(0, 255, (240, 320, 3), dtype=np.uint8)
        cv2.putText(img, f"frame {i}", (40, 240), cv2.FONT_HERSHEY_SIMPLEX, 3, (255, 255, 255), 6)
        ok, data = cv2.imencode(".jpg", img, [cv2.IMWRITE_JPEG_QUALITY, 70])
        assert ok
        (folder / f"frame{i:02d}.jpg").write_bytes(data.tobytes())
    return folder


@pytest.fixture
def node(native_binary: Path, jpeg_dir: Path):
    """A provisioned node streaming at 30 fps on an ephemeral port, serial on a pty."""
    with NativeNode(jpeg_dir, fps=30) as n:
        yield n
