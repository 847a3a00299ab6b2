"""decode_gray(rows=...): only the top of a sequential JPEG is decoded, with the full decode's
pixels; anything else is decoded in full; broken data still fails with ImageError."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from cubetrack.core.errors import ImageError
from cubetrack.detect.detector import decode_gray


def _scene(height: int = 240, width: int = 320, colour: bool = False) -> np.ndarray:
    rng = np.random.default_rng(3)
    yy, xx = np.mgrid[0:height, 0:width]
    base = (128 + 60 * np.sin(xx / 9.0) * np.cos(yy / 13.0) + rng.normal(0, 12, (height, width))).clip(0, 255)
    if not colour:
        return base.astype(np.uint8)
    return np.dstack([base, np.roll(base, 7, axis=1), 255 - base]).astype(np.uint8)


def _jpeg(image: np.ndarray, *params: int) -> bytes:
    ok, buf = cv2.imencode(".jpg", image, [cv2.IMWRITE_JPEG_QUALITY, 85, *params])
    assert ok
    return buf.tobytes()


@pytest.mark.parametrize("kind, mcu_rows", [
    ("gray", 8), ("colour 4:2:0", 16), ("colour 4:4:4", 8), ("gray, restart markers", 8)])
def test_the_top_rows_are_the_full_decodes(kind, mcu_rows):
    params = {"colour 4:2:0": [cv2.IMWRITE_JPEG_SAMPLING_FACTOR, cv2.IMWRITE_JPEG_SAMPLING_FACTOR_420],
              "colour 4:4:4": [cv2.IMWRITE_JPEG_SAMPLING_FACTOR, cv2.IMWRITE_JPEG_SAMPLING_FACTOR_444],
              "gray, restart markers": [cv2.IMWRITE_JPEG_RST_INTERVAL, 3]}.get(kind, [])
    data = _jpeg(_scene(colour=kind.startswith("colour")), *params)
    full = decode_gray(data)
    assert full.shape == (240, 320)
    for rows in (1, 8, 9, 100, 240 - mcu_rows):
        top = decode_gray(data, rows=rows)
        expected_rows = -(-rows // mcu_rows) * mcu_rows
        assert top.shape == (expected_rows, 320), (rows, top.shape)
        np.testing.assert_array_equal(top, full[:expected_rows])
    for rows in (240 - mcu_rows + 1, 240, 10_000):   # into the last MCU row or beyond: the whole image
        np.testing.assert_array_equal(decode_gray(data, rows=rows), full)


def test_a_progressive_jpeg_is_decoded_in_full():
    data = _jpeg(_scene(), cv2.IMWRITE_JPEG_PROGRESSIVE, 1)
    np.testing.assert_array_equal(decode_gray(data, rows=40), decode_gray(data))


def test_broken_data_fails_as_without_rows():
    data = _jpeg(_scene())
    with pytest.raises(ImageError, match="cam1 frame 3: truncated JPEG"):
        decode_gray(data[: len(data) // 2], "cam1 frame 3", rows=40)
    with pytest.raises(ImageError, match="empty image data"):
        decode_gray(b"", rows=40)
    header_only = data[:200] + b"\xff\xd9"
    with pytest.raises(ImageError):
        decode_gray(header_only, rows=40)
    with pytest.raises(ImageError, match="not a decodable"):
        decode_gray(b"\xff\xd8 not a jpeg at all" + b"\xff\xd9", rows=40)


def test_mangled_jpegs_decode_or_fail_with_an_image_error():
    """Bytes of a frame overwritten at random (header and data): the top-rows decode gives the
    full decode's top rows or falls back to it, and every failure is an ImageError."""
    data = _jpeg(_scene(colour=True), cv2.IMWRITE_JPEG_SAMPLING_FACTOR, cv2.IMWRITE_JPEG_SAMPLING_FACTOR_420)
    rng = np.random.default_rng(11)
    outcomes = set()
    for _ in range(150):
        mangled = bytearray(data)
        for at in rng.integers(2, min(len(data) - 2, 700 if rng.random() < 0.7 else len(data) - 2), size=3):
            mangled[at] = int(rng.integers(0, 256))
        mangled = bytes(mangled)
        try:
            top = decode_gray(mangled, rows=60)
        except ImageError:
            outcomes.add("error")
            continue
        full = decode_gray(mangled)
        np.testing.assert_array_equal(top, full[: len(top)])
        outcomes.add("decoded")
    assert outcomes == {"decoded", "error"}


def test_a_region_search_finding_nothing_searches_the_whole_decoded_frame():
    """The frame worker decodes a region frame only down to the regions' lowest edge; when the
    regions find nothing, the full-frame search gets the whole frame (here: a marker below them)."""
    from pathlib import Path

    from cubetrack.app.tracker import FrameProcessor, StageParams
    from cubetrack.core.cameras import CameraIntrinsics, WorldConfig
    from cubetrack.core.layout import paper_cube_layout
    from cubetrack.core.records import Frame, FrameJob, FrameOutcome
    from cubetrack.io.config import RobotConfig

    gray = np.full((480, 640), 200, np.uint8)
    dictionary = cv2.aruco.getPredefinedDictionary(cv2.aruco.DICT_4X4_50)
    gray[380:440, 300:360] = cv2.aruco.generateImageMarker(dictionary, 1, 60)
    jpeg = _jpeg(cv2.GaussianBlur(gray, (0, 0), 0.8))
    intrinsics = CameraIntrinsics(K=np.array([[500.0, 0, 320], [0, 500.0, 240], [0, 0, 1]]), dist=np.zeros(5),
                                  width=640, height=480)
    robot = RobotConfig("red", paper_cube_layout(cube_size_m=0.11, marker_id=1), Path("red.toml"))
    worker = FrameProcessor({"cam1": intrinsics}, WorldConfig("DICT_4X4_50", 0, 0.25), (robot,),
                         {"cam1": np.eye(4)}, StageParams())
    frame = Frame("cam1", 1, 0.0, 0.0, jpeg)
    below = worker.work(FrameJob(frame, 0.0, ((260, 340, 400, 476),), frozenset()))
    above = worker.work(FrameJob(frame, 0.0, ((100, 40, 200, 120),), frozenset()))
    assert below.outcome is FrameOutcome.REGIONS and above.outcome is FrameOutcome.FULL_FRAME
    for result in (below, above):
        (sighting,) = result.sightings
        assert [d.marker_id for d in sighting.detections] == [1]
    np.testing.assert_allclose(above.sightings[0].detections[0].corners_px,
                               below.sightings[0].detections[0].corners_px, atol=1e-6)


@pytest.mark.parametrize("colour", [False, True])
def test_the_decode_gives_opencvs_grayscale_pixels(colour):
    """simplejpeg's libjpeg-turbo gives the pixels cv2.imdecode(IMREAD_GRAYSCALE) gave before it,
    byte for byte: no result downstream changes with the decoder."""
    data = _jpeg(_scene(colour=colour), cv2.IMWRITE_JPEG_SAMPLING_FACTOR, cv2.IMWRITE_JPEG_SAMPLING_FACTOR_420)
    expected = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_GRAYSCALE)
    gray = decode_gray(data)
    assert gray.dtype == np.uint8 and gray.flags.c_contiguous
    np.testing.assert_array_equal(gray, expected)
    top = decode_gray(data, rows=50)
    assert top.shape == (64 if colour else 56, 320)   # MCU rows of 16 (4:2:0) or 8 (gray)
    np.testing.assert_array_equal(top, expected[:len(top)])


def test_other_formats_still_decode():
    image = _scene()
    ok, png = cv2.imencode(".png", image)
    assert ok
    np.testing.assert_array_equal(decode_gray(png.tobytes(), rows=10), image)
