"""Emulated webcams for tests: a camera's recorded frames as a video file that OpenCV's VideoCapture
reads as it reads a USB camera (``file:<video>?at=<unix time>``, docs/live.md)."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import cv2
import numpy as np


def paced_video(times_s: Sequence[float], paths: Sequence[Path], fps: float, out: Path) -> Path:
    """The frames at ``paths`` (captured at ``times_s``) as an MJPEG AVI at a constant ``fps``,
    each video frame the newest captured by its time (a gap repeats the frame before), so frame k
    of the video shows the scene at ``times_s[0] + k / fps``."""
    first = cv2.imread(str(paths[0]))
    writer = cv2.VideoWriter(str(out), cv2.VideoWriter.fourcc(*"MJPG"), fps, (first.shape[1], first.shape[0]))
    for k in range(int((times_s[-1] - times_s[0]) * fps) + 1):
        i = int(np.searchsorted(times_s, times_s[0] + k / fps + 0.25 / fps)) - 1
        writer.write(cv2.imread(str(paths[max(i, 0)])))
    writer.release()
    return out
