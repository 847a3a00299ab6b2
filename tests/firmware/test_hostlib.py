"""The Spresense adapters and the core over the real library code on the host
(`make -C firmware hostlib`): the real Camera.cpp image buffers and threads and the real
GS2200-WiFi sources built for the host under ASan/UBSan, over fakes of the layer beneath
them (firmware/hostlib/). Each doctest case of firmware/test/hostlib runs in its own
process, so a sanitizer abort in one names that case."""

from __future__ import annotations

import io
import os
import re
import subprocess
from pathlib import Path

import numpy as np
import pytest
from arduino_build import VENDOR, require_vendor
from firmware_tools import BUILD_DIR, FIRMWARE_DIR, make_firmware, require_tools
from PIL import Image

CASES = sorted(
    name
    for path in (FIRMWARE_DIR / "test" / "hostlib").glob("test_*.cpp")
    for name in re.findall(r'^TEST_CASE\("([^"]+)"\)', path.read_text(), re.M)
)
# Run by test_the_60_s_run_delivers_parts_that_decode, with real JPEG frames.
DONE_CASE = "done: 60 s of three clients with a favicon and a stalled and a reset client"
_built: list[bool] = []


def hostlib_binary():
    require_vendor()
    require_tools("make", "g++")
    if not _built:
        result = make_firmware("hostlib", f"VENDOR={VENDOR}")
        if result.returncode != 0:
            pytest.fail(f"make hostlib failed:\n{result.stdout[-4000:]}\n{result.stderr[-6000:]}")
        _built.append(True)
    return BUILD_DIR / "hostlib-unit"


def test_every_case_is_known_to_the_binary():
    listed = subprocess.run([str(hostlib_binary()), "--list-test-cases"], capture_output=True, text=True).stdout
    assert len(CASES) >= 8
    for name in CASES:
        assert "," not in name, "doctest filters split at commas"
        assert name in listed


def run_case(case: str, env: dict[str, str] | None = None) -> None:
    result = subprocess.run([str(hostlib_binary()), f"--test-case={case}"], capture_output=True, text=True,
                            timeout=300, env={**os.environ, **(env or {})})
    output = result.stdout[-6000:] + result.stderr[-6000:]
    assert result.returncode == 0, output
    assert re.search(r"test cases:\s*1 \|\s*1 passed", result.stdout), output
    assert "runtime error" not in result.stderr, output  # UBSan


@pytest.mark.parametrize("case", [c for c in CASES if c != DONE_CASE])
def test_node_life_over_the_real_libraries(case):
    run_case(case)


def scene_jpegs(folder: Path, count: int = 6) -> list[bytes]:
    """VGA JPEGs of 24-44 kB: smooth gradients, hard-edged blocks and a textured band, so
    the encoder works as on a room with markers; quality 70-85 as a node sends them."""
    rng = np.random.default_rng(24)
    files = []
    for k in range(count):
        y, x = np.mgrid[0:480, 0:640]
        img = np.stack([(x * 255 // 639), (y * 255 // 479), ((x + y + 40 * k) % 256)], axis=-1).astype(np.float64)
        for _ in range(12):
            x0, y0 = int(rng.integers(0, 600)), int(rng.integers(0, 440))
            img[y0:y0 + int(rng.integers(20, 120)), x0:x0 + int(rng.integers(20, 120))] = rng.integers(0, 256, 3)
        img[200:260] += rng.normal(0, 18 + 4 * k, (60, 640, 3))
        buf = io.BytesIO()
        Image.fromarray(np.clip(img, 0, 255).astype(np.uint8)).save(buf, "JPEG", quality=70 + 3 * k)
        (folder / f"frame{k}.jpg").write_bytes(buf.getvalue())
        files.append(buf.getvalue())
    return files


def mjpeg_parts(stream: bytes) -> list[bytes]:
    """The bodies of a multipart stream, each its Content-Length long; a last part cut off
    by the end of the run is left out."""
    parts = []
    for m in re.finditer(rb"Content-Length: (\d+)\r\n", stream):
        body = stream.find(b"\r\n\r\n", m.end() - 2) + 4
        end = body + int(m.group(1))
        if end <= len(stream):
            parts.append(stream[body:end])
    return parts


def test_the_60_s_run_delivers_parts_that_decode(tmp_path):
    """The issue's "done when" run, the sensor delivering real JPEGs: every part each
    streaming client kept is one of them, whole, and decodes to a 640x480 image."""
    frames_dir, out_dir = tmp_path / "frames", tmp_path / "streams"
    frames_dir.mkdir()
    out_dir.mkdir()
    frames = scene_jpegs(frames_dir)
    assert all(20_000 <= len(f) <= 50_000 for f in frames), [len(f) for f in frames]
    run_case(DONE_CASE, {"CUBECAM_JPEG_DIR": str(frames_dir), "CUBECAM_STREAM_OUT": str(out_dir)})
    streams = sorted(out_dir.glob("client-*.mjpeg"))
    assert len(streams) == 3
    for path in streams:
        parts = mjpeg_parts(path.read_bytes())
        assert len(parts) >= 80, path.name  # 20 s or more at about 5 fps
        for part in parts:
            assert part in frames, path.name
            with Image.open(io.BytesIO(part)) as img:
                img.load()
                assert img.size == (640, 480)
