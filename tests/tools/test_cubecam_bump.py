"""The emulator's tripod knock (cubecam.bump): a turned camera's frames are the old ones resampled
so that every direction moves where the turned lens would put it; served over a real socket from
the moment of the bump on, the frames before it untouched."""

from __future__ import annotations

import math
import time
import urllib.error
import urllib.request

import cv2
import numpy as np
import pytest

from cubecam.bump import Bump, RotationWarp, parse_bump
from cubecam.emulator import Emulator
from cubecam.errors import EmulatorError
from cubecam.testdata import CameraSpec, write_recording
from cubetrack.core.cameras import CameraIntrinsics
from cubetrack.io.camera_info import write_camera_info

W, H, F = 320, 240, 260.0


def lens(dist: tuple[float, ...] = (0.0,) * 5) -> CameraIntrinsics:
    K = np.array([[F, 0, 159.5], [0, F, 119.5], [0, 0, 1]])
    return CameraIntrinsics(W, H, K, np.array(dist, float))


def spot_jpeg(u: float, v: float) -> bytes:
    """A grey frame with a dark Gaussian spot centred at (u, v)."""
    x, y = np.meshgrid(np.arange(W), np.arange(H))
    image = 230 - 200 * np.exp(-((x - u) ** 2 + (y - v) ** 2) / (2 * 3.0**2))
    return cv2.imencode(".jpg", image.astype(np.uint8), [cv2.IMWRITE_JPEG_QUALITY, 98])[1].tobytes()


def spot(jpeg: bytes) -> np.ndarray:
    image = 255.0 - cv2.imdecode(np.frombuffer(jpeg, np.uint8), cv2.IMREAD_GRAYSCALE).astype(float) - 150.0
    image[image < 0] = 0.0  # the background (25) and the grey strip the old frame never saw (127)
    y, x = np.nonzero(image)
    w = image[y, x]
    return np.array([np.sum(w * x), np.sum(w * y)]) / np.sum(w)


def test_a_pan_moves_the_centre_sideways_by_f_tan_angle():
    warp = RotationWarp(lens(), Bump("cam", 3.0).R_old_new)
    moved = spot(warp(spot_jpeg(159.5, 119.5)))
    # the turned camera (about its y axis, x towards z) sees the old optical axis f tan(3 deg) to the left
    assert moved == pytest.approx([159.5 - F * math.tan(math.radians(3.0)), 119.5], abs=0.15)


def test_with_distortion_a_tilted_camera_sees_each_point_where_its_lens_puts_the_turned_ray():
    info = lens((-0.25, 0.08, 0.001, -0.001, 0.0))
    bump = Bump("cam", 2.0, (1.0, 0.0, 0.0))
    warp = RotationWarp(info, bump.R_old_new)
    for u, v in [(60.0, 50.0), (250.0, 190.0), (159.5, 119.5)]:
        ray = cv2.undistortPoints(np.array([[[u, v]]]), info.K, info.dist).reshape(2)
        turned = bump.R_old_new.T @ np.array([*ray, 1.0])  # the same direction in the turned camera
        expected = cv2.projectPoints(turned[None], np.zeros(3), np.zeros(3), info.K, info.dist)[0].reshape(2)
        assert spot(warp(spot_jpeg(u, v))) == pytest.approx(expected, abs=0.2)
        assert np.linalg.norm(expected - [u, v]) > 5.0  # a 2 deg tilt moves it visibly


def test_bump_text_and_bad_bumps():
    assert parse_bump("cam2:8:1.5") == Bump("cam2", 1.5, (0.0, 1.0, 0.0), 8.0)
    assert parse_bump("cam2:0:-2:1,0,0") == Bump("cam2", -2.0, (1.0, 0.0, 0.0), 0.0)
    for text in ("cam2", "cam2:8", "cam2:x:1", ":1:1", "cam2:1:1:1,0"):
        with pytest.raises(EmulatorError, match="expected CAM:AT_S:DEG"):
            parse_bump(text)
    with pytest.raises(EmulatorError, match="turn of 0"):
        Bump("cam2", 0.0)
    with pytest.raises(EmulatorError, match="non-zero vector"):
        Bump("cam2", 1.0, (0.0, 0.0, 0.0))


def capture(url: str) -> tuple[int, bytes]:
    """The newest frame's number and JPEG (waits for the first one: 503 until then)."""
    while True:
        try:
            with urllib.request.urlopen(url + "capture", timeout=5) as r:
                return int(r.headers["X-Frame"]), r.read()
        except urllib.error.HTTPError as exc:
            assert exc.code == 503, exc
            time.sleep(0.02)


def test_the_emulator_serves_the_turned_frames_from_the_bump_on(tmp_path):
    rec = write_recording(tmp_path / "rec", [CameraSpec("cam1"), CameraSpec("cam2")], frames=30, fps=10.0,
                          width=W, height=H)
    with pytest.raises(EmulatorError, match="no camera_info/cam2.yaml"):
        Emulator(rec, bumps=(Bump("cam2", 1.0, at_s=0.5),))
    (rec / "camera_info").mkdir()
    for cam in ("cam1", "cam2"):
        write_camera_info(lens(), rec / "camera_info" / f"{cam}.yaml")
    with pytest.raises(EmulatorError, match="no camera 'cam9'"):
        Emulator(rec, bumps=(Bump("cam9", 1.0, at_s=0.5),))
    originals = {p.read_bytes() for p in (rec / "cam2").glob("*.jpg")}
    with Emulator(rec, loop=True) as emu:
        _, before = capture(emu.base_urls["cam2"])
        emu.bump(Bump("cam2", 4.0))
        when = emu.bumped[0][0]
        seq, _ = capture(emu.base_urls["cam2"])
        while (found := capture(emu.base_urls["cam2"]))[0] <= seq:  # a frame released after the bump
            time.sleep(0.02)
        _, after = found
        _, other = capture(emu.base_urls["cam1"])
    assert before in originals and after not in originals
    assert other in {p.read_bytes() for p in (rec / "cam1").glob("*.jpg")}  # the other camera untouched
    image = cv2.imdecode(np.frombuffer(after, np.uint8), cv2.IMREAD_COLOR)
    assert image.shape == (H, W, 3)
    # a 4 deg pan leaves a grey strip f (tan 4 deg) = 18 px wide at the edge the old frame never saw
    assert np.all(np.abs(image[:, W - 15:].astype(int) - 128) <= 3) and not np.all(image[:, :W - 25] == 128)
    assert emu.bumped == [(when, Bump("cam2", 4.0))]
