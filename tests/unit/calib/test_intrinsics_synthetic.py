"""Intrinsic calibration on rendered ChArUco views with known K (ground truth by construction),
and its refusals: too few usable views, mixed image sizes, bad board text."""

import cv2
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from cubetrack.calib.intrinsics import IntrinsicsParams, calibrate_intrinsics, make_board
from cubetrack.cli.calibrate_intrinsics import parse_board
from cubetrack.core.errors import CalibrationError, ConfigError, ImageError
from cubetrack.core.geometry import make_T
from cubetrack.detect.detector import CornerRefinement, read_gray

K_TRUE = np.array([[600.0, 0, 322.0], [0, 605.0, 236.0], [0, 0, 1]])


def render_board(params, T_cam_board, ss=3):
    """The board (its top-left outer corner at the board frame's origin, x right, y down in the
    image of the board, as OpenCV's board object points) seen by K_TRUE, anti-aliased."""
    board = make_board(params)
    px_per_m = 4000
    w_m, h_m = params.squares_x * params.square_m, params.squares_y * params.square_m
    tex = board.generateImage((int(w_m * px_per_m), int(h_m * px_per_m)), marginSize=0, borderBits=1)
    tex = cv2.copyMakeBorder(tex, 200, 200, 200, 200, cv2.BORDER_CONSTANT, value=255)
    s = 1.0 / px_per_m
    A = np.array([[s, 0, -(200 - 0.5) * s], [0, s, -(200 - 0.5) * s], [0, 0, 1]])  # texture px -> board m
    Hb = K_TRUE @ np.column_stack([T_cam_board[:3, 0], T_cam_board[:3, 1], T_cam_board[:3, 3]])
    S = np.array([[ss, 0, (ss - 1) / 2], [0, ss, (ss - 1) / 2], [0, 0, 1]])
    hi = cv2.warpPerspective(tex, S @ Hb @ A, (640 * ss, 480 * ss), flags=cv2.INTER_LINEAR, borderValue=120)
    img = cv2.resize(hi.astype(np.float32), (640, 480), interpolation=cv2.INTER_AREA)
    img = cv2.GaussianBlur(img, (0, 0), 0.6)
    return np.clip(np.round(img), 0, 255).astype(np.uint8)


def views(params, n=8):
    rng = np.random.default_rng(3)
    out = []
    centre = np.array([params.squares_x * params.square_m / 2, params.squares_y * params.square_m / 2, 0])
    for i in range(n):
        R = Rotation.from_euler("xyz", [rng.uniform(-35, 35), rng.uniform(-35, 35), rng.uniform(-20, 20)],
                                degrees=True).as_matrix()
        t = np.array([rng.uniform(-0.05, 0.05), rng.uniform(-0.04, 0.04), rng.uniform(0.38, 0.5)]) - R @ centre
        out.append((f"view{i}", render_board(params, make_T(R, t))))
    return out


@pytest.fixture(scope="module")
def board_views():
    return views(IntrinsicsParams())


def test_recovers_the_true_focal_length(board_views):
    result = calibrate_intrinsics(board_views, IntrinsicsParams(), "synthetic")
    K = result.intrinsics.K
    assert K[0, 0] == pytest.approx(600.0, rel=0.002) and K[1, 1] == pytest.approx(605.0, rel=0.002)
    assert K[0, 2] == pytest.approx(322.0, abs=2.0) and K[1, 2] == pytest.approx(236.0, abs=2.0)
    assert result.rms_px < 0.1
    assert all(v.used and v.corners >= 6 and v.rms_px < 0.2 for v in result.views)
    assert (result.intrinsics.width, result.intrinsics.height) == (640, 480)
    assert result.intrinsics.camera_name == "synthetic"


def test_refuses_too_few_usable_views(board_views):
    blank = np.full((480, 640), 200, np.uint8)
    images = board_views[:2] + [("blank.jpg", blank)]
    with pytest.raises(CalibrationError, match=r"only 2 of 3 images.*need 3.*blank.jpg: 0"):
        calibrate_intrinsics(images, IntrinsicsParams())


def test_unusable_views_are_reported_not_fatal(board_views):
    blank = np.full((480, 640), 200, np.uint8)
    result = calibrate_intrinsics(board_views[:4] + [("blank.jpg", blank)], IntrinsicsParams())
    assert [v.used for v in result.views] == [True] * 4 + [False]
    assert "0 corners" in result.views[-1].reason


def test_refuses_mixed_image_sizes(board_views):
    with pytest.raises(ImageError, match="small.png: image is 320x240"):
        calibrate_intrinsics(board_views[:3] + [("small.png", np.zeros((240, 320), np.uint8))])


def test_read_gray_names_bad_files(tmp_path):
    with pytest.raises(ImageError, match="missing.jpg: image file not found"):
        read_gray(tmp_path / "missing.jpg")
    (tmp_path / "bad.jpg").write_bytes(b"\xff\xd8garbage\xff\xd9")
    with pytest.raises(ImageError, match="bad.jpg"):
        read_gray(tmp_path / "bad.jpg")


def test_parse_board():
    assert parse_board("5x7") == (5, 7) and parse_board("12X9") == (12, 9)
    for bad in ("5", "5x", "x7", "5*7", "five by seven"):
        with pytest.raises(ConfigError, match="COLSxROWS"):
            parse_board(bad)


def test_params_are_checked():
    with pytest.raises(ValueError, match="smaller than the square"):
        IntrinsicsParams(square_m=0.02, marker_m=0.03)
    with pytest.raises(ValueError, match="'edge' is not available"):
        IntrinsicsParams(marker_refinement=CornerRefinement.EDGE)
