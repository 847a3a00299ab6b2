"""Contracts §1: third-party clients read a node's stream as they read ESP32 cameras:
OpenCV (FFmpeg backend), the ffmpeg command line, and a browser rendering ``/``."""

from __future__ import annotations

import shutil
import subprocess

import cv2
import numpy as np
import pytest

from cubecam.testdata import FRAME_BGR

CHROMIUM = shutil.which("chromium") or shutil.which("chromium-browser")
FFMPEG = shutil.which("ffmpeg")


def frame_colour_fraction(img: np.ndarray, bgr=FRAME_BGR, tol: int = 40) -> float:
    """Fraction of the image's pixels within ``tol`` of the test frames' background colour."""
    diff = np.abs(img[:, :, :3].astype(int) - np.array(bgr, int)).max(axis=2)
    return float((diff <= tol).mean())


def test_opencv_videocapture_reads_the_stream(node):
    cap = cv2.VideoCapture(node.base_url + "stream", cv2.CAP_FFMPEG,
                           [cv2.CAP_PROP_OPEN_TIMEOUT_MSEC, 5000, cv2.CAP_PROP_READ_TIMEOUT_MSEC, 5000])
    try:
        assert cap.isOpened(), "OpenCV could not open the stream"
        for _ in range(5):
            ok, img = cap.read()
            assert ok, "OpenCV could not read a frame"
            assert img.shape[:2] == (node.height, node.width)
            assert frame_colour_fraction(img) > 0.5
    finally:
        cap.release()


@pytest.mark.skipif(FFMPEG is None, reason="ffmpeg is not installed (Debian package ffmpeg)")
def test_ffmpeg_reads_the_stream(node, tmp_path):
    out = tmp_path / "f%02d.png"
    done = subprocess.run([FFMPEG, "-hide_banner", "-nostdin", "-loglevel", "error", "-rw_timeout", "5000000",
                           "-i", node.base_url + "stream", "-frames:v", "4", "-y", str(out)],
                          capture_output=True, text=True, timeout=30)
    assert done.returncode == 0, done.stderr
    frames = sorted(tmp_path.glob("f*.png"))
    assert len(frames) == 4
    for f in frames:
        img = cv2.imread(str(f))
        assert img.shape[:2] == (node.height, node.width)
        assert frame_colour_fraction(img) > 0.5


@pytest.mark.skipif(CHROMIUM is None, reason="Chromium is not installed (Debian package chromium)")
def test_chromium_shows_a_frame_on_the_index_page(node, tmp_path):
    shot = tmp_path / "page.png"
    done = subprocess.run([CHROMIUM, "--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
                           "--disable-background-networking", "--disable-component-update", "--disable-sync",
                           "--disable-dev-shm-usage", f"--user-data-dir={tmp_path / 'profile'}",
                           f"--screenshot={shot}", "--window-size=800,600", node.base_url],
                          capture_output=True, text=True, timeout=60)
    assert done.returncode == 0 and shot.exists(), done.stderr[-2000:]
    img = cv2.imread(str(shot))
    assert img is not None and img.std() > 5, "the screenshot is blank"
    # the frame (plain green, 320x240) is on the page: at least 80% of its area in that colour
    green_px = frame_colour_fraction(img) * img.shape[0] * img.shape[1]
    assert green_px > 0.8 * node.width * node.height, green_px
