"""Real footage end to end: ../shared/data/real/caliscope-4cam (4 unsynchronised, calibrated 1280x720
webcams at ~6 fps, a hand-held ChArUco board printed inverted) converted by ``cubetrack import``,
tracked with the default settings (the config the import writes), and scored against the board's
own ChArUco corners triangulated from the calibrated cameras (benchmarks/real_footage.py); the
paper's mean fusion of the same frames is scored the same way.

The conversion and the three replays run once per session (a few tens of seconds on 2 cores)."""

from __future__ import annotations

import tomllib
from pathlib import Path

import numpy as np
import pytest

from tests.helpers.benchmarks import load_benchmark

ROOT = Path(__file__).resolve().parents[2]
DATA = ROOT / ".." / "shared" / "data" / "real" / "caliscope-4cam"
pytestmark = pytest.mark.skipif(not DATA.is_dir(), reason=f"{DATA} not present (the real footage is in ../shared)")


@pytest.fixture(scope="session")
def imported(tmp_path_factory):
    from cubetrack.app.import_rig import import_caliscope

    work = tmp_path_factory.mktemp("caliscope")
    return import_caliscope(DATA, work), work


@pytest.fixture(scope="session")
def reference():
    return load_benchmark("real_footage").charuco_reference(DATA)


@pytest.fixture(scope="session")
def sightings():
    return []  # what the default run's filter fusion got (filled by ``scores``)


@pytest.fixture(scope="session")
def scores(imported, reference, sightings):
    bench = load_benchmark("real_footage")
    _result, work = imported
    return {name: bench.score(bench.track(work, name, sections, got), reference)
            for name, sections, got in (("default", {}, sightings), ("mean", {"fusion": {"method": "mean"}}, None))}


def test_the_import_writes_what_track_reads(imported):
    from cubetrack.app.config import load_config
    from cubetrack.io.config import read_extrinsics
    from cubetrack.io.recording import Recording

    result, _work = imported
    assert result.frames == {f"cam{i}": 111 for i in range(4)}
    config, params = load_config(result.config)
    # the board is printed inverted: white-on-black markers only, one search per frame (not the image and its negative)
    assert params.detector.detect_inverted_marker and not params.detector.detect_normal_marker
    assert not params.estimator.use_upright_prior
    assert sorted(config.robots[0].layout.ids) == list(range(10))
    assert config.robots[0].layout.motion == "free"  # a hand-held board: the body's motion switch (issue 25)
    recording = Recording.open(result.recording)
    assert all(len(recording.clock_samples(c)) == 111 for c in recording.camera_names)
    # x_cam = R x_world + t: the camera centre is -R^T t
    with (DATA / "calibration" / "camera_array.toml").open("rb") as f:
        cam0 = tomllib.load(f)["cameras"]["0"]
    R, t = np.array(cam0["rotation"]), np.array(cam0["translation"])
    np.testing.assert_allclose(read_extrinsics(result.extrinsics)["cam0"].T_world_cam[:3, 3], -R.T @ t, atol=1e-9)


def test_the_reference_is_a_rigid_board_to_about_a_millimetre(reference):
    rms_mm = np.array([i.rms_m for i in reference.values() if i.T_world_body is not None]) * 1000.0
    assert len(reference) >= 45 and len(rms_mm) >= 40 and np.median(rms_mm) < 1.5, (len(reference), len(rms_mm))
    # an instant is one where two cameras see the board's own ids: cam3's stray id 998 at sync 67
    # (cam1 alone sees the board there) does not make one
    assert 67 not in reference


def test_the_reference_keeps_only_cameras_that_agree(reference):
    """A camera frame whose corners are more than 3 px (RMS) from the other cameras' reference is left
    out of it; what is kept moves the board by about half a millimetre when any one camera is left out."""
    bench = load_benchmark("real_footage")
    posed = [i for i in reference.values() if i.T_world_body is not None]
    assert sum(len(i.dropped) for i in posed) >= 5
    for inst in posed:
        assert all(inst.reprojection_px[c] > bench.MAX_VIEW_RMS_PX for c in inst.dropped), inst
        if len(inst.used) >= 3:
            assert all(inst.reprojection_px[c] <= bench.MAX_VIEW_RMS_PX for c in inst.used), inst
        assert inst.t0_s <= inst.t_s <= inst.t1_s
    loo_mm = np.array([v for i in posed for v in i.loo_mm.values()])
    assert len(loo_mm) >= 60 and np.median(loo_mm) < 1.0, np.median(loo_mm)
    lines = bench.reference_report(reference)
    assert len(lines) == 7 and all(f"cam{c}:" in "".join(lines) for c in range(4)), lines


def test_each_cameras_stamp_offset_is_found_against_the_others(reference):
    """Without any tracker: each camera's best stamp offset against the board the other cameras see
    is within the searched span and fits at least as well as its stamps as they are; the stamps of
    this footage are off by tens of ms (measured -20, -20, +25, +15 ms), not the 85 ms the tracker's
    poses suggested for cam1."""
    offsets = load_benchmark("real_footage").camera_time_offsets(reference)
    assert sorted(offsets) == [0, 1, 2, 3]
    for best_s, at_best_px, at_zero_px in offsets.values():
        assert -0.1 <= best_s <= 0.1 and at_best_px <= at_zero_px, offsets
    assert abs(offsets[1][0]) < 0.05, offsets


def test_the_default_tracker_follows_the_board_better_than_the_mean_fusion(scores):
    """Issue 25's targets, with the default settings and the import's board as a free body (`motion = "free"`,
    the documented switch for the body's motion): measured against the reference of the cameras that agree,
    poses at 48 of the 48 instants, filter median 1.66, p95 4.83, max 6.87 mm, rotation median 0.53 deg (the
    board as a floor body, the defaults before the switch: 2.39 / 4.56 / 7.77 mm, 0.51 deg); mean fusion 3.46 /
    9.57 / 13.68 mm (docs/tracking.md "A motion switch per body")."""
    ours, mean = scores["default"], scores["mean"]
    assert ours.fraction >= 0.98, ours.line("default")
    assert np.median(ours.position_mm) <= 2.0, ours.line("default")
    # each error knows its reference's cameras (2-4 agreeing ones; every count occurs on this footage)
    assert len(ours.reference_cameras) == len(ours.position_mm) and set(ours.reference_cameras) == {2, 3, 4}
    assert ours.by_reference("default").count(" instants, median ") == 3, ours.by_reference("default")
    assert ours.position_mm.max() <= 20.0 and np.median(ours.rotation_deg) <= 0.6, ours.line("default")
    assert np.percentile(ours.position_mm, 95) <= 6.0, ours.line("default")
    assert np.median(ours.position_mm) < np.median(mean.position_mm), (ours.line("default"), mean.line("mean"))
    assert np.percentile(ours.position_mm, 95) < np.percentile(mean.position_mm, 95), (ours.line("default"),
                                                                                       mean.line("mean"))


def test_the_scorings_floor_is_a_triangulation_and_the_calibration_term_departs_from_it(imported, reference,
                                                                                         scores, sightings):
    """One fit per instant of the tracker's own corners (benchmarks/real_footage.py's ``instant_fits``):
    every camera taken as exact (a triangulation, as the reference is) is within about a millimetre of the
    reference (measured 0.92 mm median; 0.39 mm where all four cameras agree); weighed by the calibration term
    as set (the filter's measurement model at one instant) it is 2.99 mm away; the default filter (2.44 mm) lies
    between: its motion model wins back part of what the term costs against this reference, not all of it
    (docs/tracking.md "The scoring's floor")."""
    from cubetrack.app.config import load_config

    bench = load_benchmark("real_footage")
    result, _work = imported
    config, params = load_config(result.config)
    fits = bench.instant_fits(reference, sightings, config.robots[0].layout, params.filter,
                              params.fusion.max_view_angle_deg)
    exact, kept, term = (np.median(fits[name].position_mm) for name in bench.INSTANT_FITS)
    ours = np.median(scores["default"].position_mm)
    assert all(fits[name].fraction == 1.0 for name in bench.INSTANT_FITS), [f.line(n) for n, f in fits.items()]
    assert kept <= exact <= 1.5 and 2.0 < term, [f.line(n) for n, f in fits.items()]
    assert exact < ours < term, (ours, [f.line(n) for n, f in fits.items()])
