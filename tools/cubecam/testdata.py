"""Synthetic camera material for tests and examples: real JPEGs (OpenCV-encoded) of a plain
colour with the frame number written on it, as image folders or recording folders
(contracts §3) with chosen timing, clock drift, drops and corrupt files.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

FRAME_BGR = (40, 200, 60)  # the frames' background colour (B, G, R): a green no UI uses


def synthetic_jpeg(index: int, width: int = 320, height: int = 240, quality: int = 85,
                   bgr: tuple[int, int, int] = FRAME_BGR) -> bytes:
    """A JPEG of a plain colour with ``index`` written large in the middle."""
    import cv2
    import numpy as np

    img = np.empty((height, width, 3), np.uint8)
    img[:] = bgr
    text = str(index)
    scale = height / 80.0
    (tw, th), _ = cv2.getTextSize(text, cv2.FONT_HERSHEY_SIMPLEX, scale, 3)
    cv2.putText(img, text, ((width - tw) // 2, (height + th) // 2), cv2.FONT_HERSHEY_SIMPLEX, scale,
                (255, 255, 255), 3, cv2.LINE_AA)
    ok, buf = cv2.imencode(".jpg", img, [cv2.IMWRITE_JPEG_QUALITY, quality])
    if not ok:
        raise RuntimeError("OpenCV could not encode a JPEG")
    return buf.tobytes()


def write_images(folder: str | Path, count: int, width: int = 320, height: int = 240) -> Path:
    """``count`` JPEGs named ``frame_0000.jpg`` ... in ``folder`` (created)."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    for i in range(count):
        (folder / f"frame_{i:04d}.jpg").write_bytes(synthetic_jpeg(i, width, height))
    return folder


@dataclass(frozen=True, slots=True)
class CameraSpec:
    """One synthetic camera: its device clock at the first frame (``boot_offset_s``), its rate
    against the host clock (``rate`` host s per device s: 1 + drift), frames dropped (by index),
    and how many frame files to corrupt (the last ones but one) or delete."""

    name: str
    boot_offset_s: float = 100.0
    rate: float = 1.0
    drop: tuple[int, ...] = ()
    corrupt_files: int = 0
    missing_files: int = 0
    clock_csv: bool = False


def write_recording(path: str | Path, cameras: list[CameraSpec], frames: int = 20, fps: float = 10.0,
                    host_start_s: float = 1_700_000_000.0, latency_s: float = 0.03,
                    width: int = 320, height: int = 240) -> Path:
    """A recording folder where frame i of each camera is captured at host time
    ``host_start_s + i / fps`` and arrives ``latency_s`` later; device time =
    ``boot_offset_s + (host - host_start_s) / rate``. Returns the path."""
    from cubetrack.core.cameras import ClockSample
    from cubetrack.io.recording import CameraEntry, RecordingWriter

    path = Path(path)
    with RecordingWriter(path, [CameraEntry(c.name, f"synthetic://{c.name}") for c in cameras]) as w:
        for cam in cameras:
            names = []
            for i in range(frames):
                host = host_start_s + i / fps
                device = cam.boot_offset_s + (host - host_start_s) / cam.rate
                if i in cam.drop:
                    continue
                names.append(w.add_frame(cam.name, i + 1, device, host + latency_s,
                                         synthetic_jpeg(i, width, height)))
            if cam.clock_csv:
                for k in range(int(frames / fps) + 2):
                    send = host_start_s + k - 0.002
                    recv = host_start_s + k + 0.002
                    w.add_clock_sample(cam.name, ClockSample(send, cam.boot_offset_s + k / cam.rate, recv))
            for name in names[-1 - cam.corrupt_files:-1] if cam.corrupt_files else []:
                (path / cam.name / name).write_bytes(b"\xff\xd8\xff\xe0 truncated garbage")
            missing = names[-1 - cam.corrupt_files - cam.missing_files:-1 - cam.corrupt_files]
            for name in missing if cam.missing_files else []:
                (path / cam.name / name).unlink()
    return path
