"""calibrate-intrinsics on real photos: OpenCV's ArUco tutorial calibration views (img_00-03,
5x7 ChArUco, 4 cm squares, 2 cm DICT_6X6_250 markers) reproduce the tutorial's own result,
tutorial_camera_charuco.yml, within 1 % in fx and fy.

Four views pin fx down only loosely (OpenCV's own standard deviation estimate is ~3.5 %), so
this is a check that the pipeline matches the reference workflow, not an accuracy claim.
"""

from pathlib import Path

import pytest

from cubetrack.calib.intrinsics import IntrinsicsParams, calibrate_intrinsics_files
from cubetrack.cli import main as cli_main
from cubetrack.io.camera_info import read_camera_info

DATA = Path(__file__).resolve().parents[2] / ".." / "shared" / "data" / "real" / "opencv-aruco-tutorial"
VIEWS = ["img_00.jpg", "choriginal.jpg", "img_02.jpg", "img_03.jpg"]  # choriginal.jpg = img_01

pytestmark = pytest.mark.skipif(not (DATA / "img_00.jpg").exists(), reason=f"real photos not found in {DATA}")


def test_reproduces_the_tutorial_focal_lengths():
    reference = read_camera_info(DATA / "tutorial_camera_charuco.yml")
    result = calibrate_intrinsics_files([DATA / v for v in VIEWS], IntrinsicsParams(), "tutorial")
    K = result.intrinsics.K
    assert K[0, 0] == pytest.approx(reference.K[0, 0], rel=0.01)
    assert K[1, 1] == pytest.approx(reference.K[1, 1], rel=0.01)
    assert result.rms_px < 0.3  # the tutorial reports 0.18 px
    assert all(v.used and v.corners == 24 for v in result.views)


def test_cli_writes_camera_info(tmp_path, monkeypatch, capsys):
    monkeypatch.setattr(cli_main, "COMMANDS", {"calibrate-intrinsics": "calibrate_intrinsics"})
    out = tmp_path / "cam.yaml"
    rc = cli_main.main(["calibrate-intrinsics", *(str(DATA / v) for v in VIEWS), "--board", "5x7",
                        "--square", "0.04", "--marker", "0.02", "--dictionary", "DICT_6X6_250",
                        "--out", str(out)])
    assert rc == 0
    written = read_camera_info(out)
    reference = read_camera_info(DATA / "tutorial_camera_charuco.yml")
    assert written.K[0, 0] == pytest.approx(reference.K[0, 0], rel=0.01)
    assert (written.width, written.height) == (640, 480) and written.camera_name == "cam"
    printed = capsys.readouterr().out
    assert "RMS reprojection error" in printed and "4 of 4 views" in printed


def test_cli_names_a_missing_image(tmp_path, monkeypatch, capsys):
    monkeypatch.setattr(cli_main, "COMMANDS", {"calibrate-intrinsics": "calibrate_intrinsics"})
    rc = cli_main.main(["calibrate-intrinsics", str(DATA / "img_00.jpg"), str(tmp_path / "gone.jpg"),
                        "--out", str(tmp_path / "cam.yaml")])
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 1 and err[-1].startswith("cubetrack calibrate-intrinsics: error:") and "gone.jpg" in err[-1]
