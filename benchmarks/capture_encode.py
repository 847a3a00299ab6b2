"""What a USB-camera frame costs on its way into the pipeline (cubetrack.source.capture): the
grayscale JPEG encode the capture reader does per frame, against the colour encode it does not do
and against the baseline of this run, reading the same frame through OpenCV's VideoCapture (the
decode every capture pays); also what the later decode in detection costs per JPEG.

Frames: the caliscope-4cam webcam footage (../shared/data/real), at its 1280x720 and resized to
640x480. Printed: milliseconds per frame (median of rounds) and each as a ratio to the read, with
the core count and load average (the machine is shared).

Usage: python benchmarks/capture_encode.py [--video FILE] [--frames N] [--rounds R]
"""

from __future__ import annotations

import argparse
import itertools
import os
import statistics
import sys
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import simplejpeg

DATA = Path(__file__).resolve().parents[1] / ".." / "shared" / "data" / "real" / "caliscope-4cam"
VIDEO = DATA / "video" / "cam_0.mp4"


def per_frame_ms(work: Callable[[], object], n: int, rounds: int) -> float:
    """Median over ``rounds`` of the mean time of ``n`` calls, ms."""
    times = []
    for _ in range(rounds):
        start = time.perf_counter()
        for _ in range(n):
            work()
        times.append((time.perf_counter() - start) / n * 1000.0)
    return statistics.median(times)


def cycling(work: Callable[[Any], object], items: Sequence[Any]) -> Callable[[], object]:
    """``work`` applied to ``items`` in turn, one per call."""
    it = itertools.cycle(items)
    return lambda: work(next(it))


def gray_encode(image: np.ndarray) -> bytes:
    """What the capture reader does with a frame (cubetrack.source.capture)."""
    return simplejpeg.encode_jpeg(np.ascontiguousarray(cv2.cvtColor(image, cv2.COLOR_BGR2GRAY))[:, :, None], 90, "GRAY")


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--video", type=Path, default=VIDEO, help="a video file (default: caliscope cam_0)")
    parser.add_argument("--frames", type=int, default=20, help="frames per round")
    parser.add_argument("--rounds", type=int, default=5, help="rounds (the median is printed)")
    args = parser.parse_args(argv)
    capture = cv2.VideoCapture(str(args.video), cv2.CAP_FFMPEG)
    frames = []
    while len(frames) < args.frames:
        ok, image = capture.read()
        if not ok:
            break
        frames.append(image)
    capture.release()
    if not frames:
        print(f"{args.video}: no frames", file=sys.stderr)
        return 1

    def read_all() -> None:
        cap = cv2.VideoCapture(str(args.video), cv2.CAP_FFMPEG)
        for _ in frames:
            cap.read()
        cap.release()

    read_ms = per_frame_ms(read_all, 1, args.rounds) / len(frames)
    print(f"cores {os.cpu_count()}, load average {os.getloadavg()[0]:.1f}; {len(frames)} frames of {args.video.name}; "
          f"baseline: VideoCapture read {read_ms:.2f} ms/frame at {frames[0].shape[1]}x{frames[0].shape[0]}")
    for size in ((frames[0].shape[1], frames[0].shape[0]), (640, 480)):
        images = [cv2.resize(f, size) for f in frames]
        jpegs = [gray_encode(i) for i in images]
        rows = {
            "gray: cvtColor + encode q90 (what the reader does)": cycling(gray_encode, images),
            "colour: encode q90": cycling(lambda i: simplejpeg.encode_jpeg(i, 90, "BGR"), images),
            "decode of the gray JPEG (detection)": cycling(lambda j: simplejpeg.decode_jpeg(j, "GRAY"), jpegs),
        }
        for name, work in rows.items():
            ms = per_frame_ms(work, len(images), args.rounds)
            print(f"{size[0]}x{size[1]} {name:<52} {ms:6.2f} ms/frame  {ms / read_ms:5.2f} x read")
        print(f"{size[0]}x{size[1]} gray JPEG {statistics.median(len(j) for j in jpegs) / 1024:.0f} KiB")
    return 0


if __name__ == "__main__":
    sys.exit(main())
