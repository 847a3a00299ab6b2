"""``cubetrack calibrate-intrinsics --camera URL``: the ChArUco views captured live from a camera. A
video of rendered board views with a known K (tests/unit/calib/test_intrinsics_synthetic.py),
played through OpenCV's VideoCapture as a USB camera is read, stands in for a webcam in front of
which the board is moved; the views kept, the guidance printed and the focal length recovered."""

from __future__ import annotations

import cv2
import pytest

from cubetrack.calib.intrinsics import IntrinsicsParams
from cubetrack.cli.main import main
from cubetrack.io.camera_info import read_camera_info
from tests.unit.calib.test_intrinsics_synthetic import views

FRAMES_PER_POSE = 9  # at 10 fps: each pose held 0.9 s, as a hand holds the board still


@pytest.fixture(scope="module")
def board_video(tmp_path_factory):
    path = tmp_path_factory.mktemp("intrinsics-live") / "board.avi"
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter.fourcc(*"MJPG"), 10.0, (640, 480))
    for _name, gray in views(IntrinsicsParams(), n=10):
        for _ in range(FRAMES_PER_POSE):
            writer.write(cv2.cvtColor(gray, cv2.COLOR_GRAY2BGR))
    writer.release()
    return path


def test_views_captured_live_calibrate_the_camera_with_guidance(board_video, tmp_path, capsys):
    out = tmp_path / "cam.yaml"
    assert main(["calibrate-intrinsics", "--camera", f"file:{board_video}", "--views", "6",
                 "--out", str(out)]) == 0
    err = capsys.readouterr().err
    intrinsics = read_camera_info(out)
    assert intrinsics.K[0, 0] == pytest.approx(600.0, rel=0.01) and intrinsics.K[1, 1] == pytest.approx(605.0, rel=0.01)
    assert (intrinsics.width, intrinsics.height) == (640, 480)
    kept = [line for line in err.splitlines() if ": kept (" in line]
    assert len(kept) == 6  # stopped once the views asked for were kept
    assert "move the board to:" in kept[0] and "6 views captured" in err
    assert "too soon after the last view" in err or "nothing new" in err  # a held pose is kept once


def test_photos_or_a_camera_not_both_nor_neither(board_video, tmp_path, capsys):
    assert main(["calibrate-intrinsics", "--out", str(tmp_path / "c.yaml")]) == 1
    assert main(["calibrate-intrinsics", str(board_video), "--camera", "usb:0", "--out", str(tmp_path / "c.yaml")]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 2 and all("either photos of the board or --camera URL" in line for line in err)


def test_a_camera_that_cannot_be_opened_is_one_line(tmp_path, capsys):
    assert main(["calibrate-intrinsics", "--camera", "usb:97", "--out", str(tmp_path / "c.yaml")]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "cannot open usb:97" in err[0]
    assert not (tmp_path / "c.yaml").exists()
