"""The realistic preset as a recording: frames show the cube as built, each row at its own
instant; every true value needed for scoring is written beside the recording; the same seed
gives the same bytes; the clean preset renders exactly what it did before these effects."""

from __future__ import annotations

import filecmp
import hashlib
import tomllib
from pathlib import Path

import cv2
import numpy as np
import pytest

from cubetrack.cli.main import main
from cubetrack.core.layout import paper_cube_layout, read_layout
from cubetrack.io.camera_info import read_camera_info
from cubetrack.io.recording import Recording
from cubetrack.io.trajectory import read_tum
from cubetrack.simulate import SimulationParams, simulate
from cubetrack.simulate.params import REALISTIC
from cubetrack.simulate.render import project_points
from cubetrack.simulate.scenario import build_scene


def _corners_world(result, layout, host_time_s: float) -> np.ndarray:
    T = result.T_world_cube(host_time_s)
    return np.array([(T @ np.c_[m.corners_cube_m(), np.ones(4)].T).T[:, :3] for m in layout.markers])


def _nearest_face_error(result, cam, layout, times: np.ndarray, corners_px: np.ndarray) -> float:
    """Mean corner distance (px) to the nearest face's projection, corner j at ``times[j]``."""
    best = np.inf
    for face in range(len(layout.markers)):
        pts = np.array([_corners_world(result, layout, t)[face, j] for j, t in enumerate(times)])
        uv = project_points(cam.intrinsics, cam.T_world_cam, pts)
        best = min(best, float(np.linalg.norm(uv - corners_px, axis=1).mean()))
    return best


def test_frames_show_the_built_cube_each_row_at_its_own_instant(realistic_session):
    """Detected cube corners against three models of the frame: the built cube with each corner
    at its row's instant (the truth) fits best; the nominal layout, or one instant for the whole
    frame, fit worse."""
    result = realistic_session
    rec = Recording.open(result.path)
    params = cv2.aruco.DetectorParameters()
    params.cornerRefinementMethod = cv2.aruco.CORNER_REFINE_SUBPIX
    detector = cv2.aruco.ArucoDetector(cv2.aruco.getPredefinedDictionary(cv2.aruco.DICT_4X4_50), params)
    errors = {"truth": [], "nominal layout": [], "one instant": []}
    for cam in result.cameras:
        row_s = cam.readout_s / cam.intrinsics.height
        captures = [c for c in cam.captures if c.delivered]
        for frame, capture in zip(rec.frames(cam.name), captures, strict=True):
            image = cv2.imdecode(np.frombuffer(frame.jpeg, np.uint8), cv2.IMREAD_GRAYSCALE)
            corners, ids, _ = detector.detectMarkers(image)
            if ids is None:
                continue
            for c, i in zip(corners, ids.ravel(), strict=True):
                if i != 1:
                    continue
                c = c.reshape(4, 2).astype(float)
                # each corner's instant: the frame's stamp is the middle row's
                row_times = capture.capture_host_s + (c[:, 1] - (cam.intrinsics.height - 1) / 2) * row_s
                one_time = np.full(4, capture.capture_host_s)
                for name, layout, times in (("truth", result.true_layout, row_times),
                                            ("nominal layout", result.layout, row_times),
                                            ("one instant", result.true_layout, one_time)):
                    errors[name].append(_nearest_face_error(result, cam, layout, times, c))
    assert len(errors["truth"]) > 20
    median = {k: float(np.median(v)) for k, v in errors.items()}
    assert median["truth"] < 0.8, median  # the detector's own error on 15-25 px markers
    assert median["truth"] < 0.85 * median["nominal layout"], median
    assert median["truth"] < 0.85 * median["one instant"], median


def test_every_true_value_is_written_beside_the_recording(realistic_session):
    result, out = realistic_session, realistic_session.path
    for cam in result.cameras:
        told = read_camera_info(out / "camera_info" / f"{cam.name}.yaml")
        truth = read_camera_info(out / "true_camera_info" / f"{cam.name}.yaml")
        assert np.allclose(truth.K, cam.intrinsics.K) and np.allclose(truth.dist, cam.intrinsics.dist)
        assert np.allclose(told.K, cam.camera_info.K) and np.allclose(told.dist, cam.camera_info.dist)
        assert not np.allclose(told.K, truth.K) and told.dist[0] != truth.dist[0]
        assert told.readout_s == pytest.approx(0.03)  # the tracker is told the rolling-shutter readout
        assert truth.dist[0] == pytest.approx(-0.3)
        assert read_camera_info(result.calibration_path / "camera_info" / f"{cam.name}.yaml").K[0, 0] == told.K[0, 0]
    nominal = read_layout(out / "cube.toml")
    built = read_layout(out / "true_cube.toml")
    paper = paper_cube_layout()
    assert np.allclose(nominal.corners_m, paper.corners_m)
    assert np.allclose(built.corners_m, result.true_layout.corners_m, atol=1e-8)
    assert 0.5e-3 < np.abs(built.corners_m - paper.corners_m).max() < 6e-3
    sim = tomllib.loads((out / "simulation.toml").read_text())
    for cam in result.cameras:
        table = sim["cameras"][cam.name]
        assert table["readout_s"] == pytest.approx(0.03) and table["exposure_s"] == pytest.approx(0.005)
        assert table["row_time_s"] == pytest.approx(0.03 / 480) and table["reference_row"] == 239.5
    gt = read_tum(out / "ground_truth.tum")
    assert np.allclose(np.diff(gt.times_s), 0.001, atol=2e-6)
    k = len(gt) // 2
    assert np.allclose(gt.positions_m[k], result.T_world_cube(gt.times_s[k])[:3, 3], atol=1e-6)


def test_realistic_preset_same_seed_same_bytes(tmp_path):
    p = SimulationParams.realistic(cameras=1, duration_s=1.0, calibration_frames=2, seed=8)
    a = simulate(p, tmp_path / "a", workers=1)
    b = simulate(p, tmp_path / "b", workers=2)
    files = sorted(f.relative_to(a.path) for f in a.path.rglob("*") if f.is_file() and f.name != "recording.json")
    assert len(files) > 10
    for f in files:
        assert filecmp.cmp(a.path / f, b.path / f, shallow=False), f
    other = build_scene(SimulationParams.realistic(cameras=1, duration_s=1.0, calibration_frames=2, seed=9))
    assert not np.allclose(other.robots[0].true_layout.corners_m, a.true_layout.corners_m)
    assert not np.allclose(other.cameras[0].camera_info.K, a.camera_infos["cam1"].K)


# Digests of two small recordings rendered before the realistic effects existed (commit d9b2f63),
# every file but recording.json (creation time), simulation.toml (lists the new parameters) and
# the new truth files. The files our code writes (indices, clocks, ground truth, configs, camera_info)
# are compared byte for byte under any pins; the JPEGs' bytes depend on the OpenCV build, so they are
# compared byte for byte on that one only and, on every build, by what they decode to (the mean and
# spread of all their pixels: two libjpeg builds differ by a grey level on some pixels, a changed
# render by far more): name -> (params, JPEG count, their digest on DIGEST_VERSIONS, pixel mean, std,
# other files, their digest)
CLEAN_DIGESTS = {
    "default": (SimulationParams(cameras=2, duration_s=1.5, calibration_frames=3, seed=4),
                43, "178c824883935dfbfe9f8681663c65523080070ba34df274538a1de4074167f7", 101.109, 13.354,
                15, "399d750b1a8a31adfc72c89c65a84e9dad359e8128d8393e0a4755d51792e8bc"),
    "distorted": (SimulationParams(cameras=1, duration_s=1.0, calibration_frames=2, seed=7, robots=2,
                                   distinct_ids=True, distortion=(-0.2, 0.05, 0.001, -0.001, 0.0)),
                  22, "8c6cb2fcbbbf495627d7982b1c07bdabc230f317f4f04ca4019e0975bc23e99f", 100.074, 13.757,
                  13, "57553dd323ad9fe29861d83d317684f42b6217153a3346a0ad7b3d36e21bfe09"),
}
DIGEST_VERSIONS = ("5.0.0", "2.4")


def _digest(path: Path, files: list[Path]) -> tuple[int, str]:
    h = hashlib.sha256()
    for f in files:
        h.update(str(f.relative_to(path)).encode())
        h.update(hashlib.sha256(f.read_bytes()).digest())
    return len(files), h.hexdigest()


@pytest.mark.parametrize("name", sorted(CLEAN_DIGESTS))
def test_clean_preset_renders_exactly_what_it_did_before(tmp_path, name):
    params, count, digest, mean, std, other_count, other_digest = CLEAN_DIGESTS[name]
    simulate(params, tmp_path / name)
    path = tmp_path / name
    new = ("recording.json", "simulation.toml")
    files = sorted(f for f in path.rglob("*") if f.is_file() and f.name not in new
                   and not f.name.startswith("true_cube") and "true_camera_info" not in f.parts)
    jpegs = [f for f in files if f.suffix == ".jpg"]
    assert _digest(path, [f for f in files if f.suffix != ".jpg"]) == (other_count, other_digest)
    pixels = np.concatenate([cv2.imread(str(f), cv2.IMREAD_GRAYSCALE).ravel() for f in jpegs]).astype(float)
    assert len(files) == count and abs(pixels.mean() - mean) < 0.1 and abs(pixels.std() - std) < 0.1
    if (cv2.__version__, ".".join(np.__version__.split(".")[:2])) == DIGEST_VERSIONS:
        assert _digest(path, files) == (count, digest)


def test_every_effect_is_off_by_default_and_on_in_the_realistic_preset():
    clean, realistic = SimulationParams(), SimulationParams.realistic()
    for name, value in REALISTIC.items():
        assert getattr(realistic, name) == value != getattr(clean, name), name
    assert SimulationParams.realistic(readout_ms=0.0).readout_ms == 0.0


def test_cli_realistic_preset_with_single_effects_switched_off(capsys):
    from cubetrack.cli.main import build_parser
    from cubetrack.cli.simulate import params_from_args

    parser = build_parser()
    args = parser.parse_args(["simulate", "--out", "x", "--realistic", "--readout-ms", "0", "--people", "0"])
    p = params_from_args(args)
    assert p == SimulationParams.realistic(readout_ms=0.0, people=0)
    assert params_from_args(parser.parse_args(["simulate", "--out", "x"])) == SimulationParams()
    with pytest.raises(SystemExit):
        main(["simulate", "--help"])
    text = capsys.readouterr().out
    for option in ("--realistic", "--readout-ms MS", "--marker-shift-mm MM", "--turn-rate DEG/S", "--accel M/S2",
                   "--exposure-steps-per-s N/S", "--ground-truth-hz HZ", "--wobble DEG", "realistic: sharp"):
        assert option in text, option
