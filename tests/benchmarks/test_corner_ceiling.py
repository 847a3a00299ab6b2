"""Smoke run of benchmarks/corner_ceiling.py (issue 15: what better corners would buy) on a tiny
realistic scene: the report has its residual table and a row per corner set and layout, the
oracle corners agree with the detected ones to a fraction of a pixel (the oracle is the picture's
truth), and exact oracle corners track the cube as built much better than noisy ones."""

import importlib
import json
import math
from pathlib import Path

import numpy as np
import pytest

pytestmark = pytest.mark.slow

BENCHMARKS = Path(__file__).resolve().parents[2] / "benchmarks"


def test_oracle_corners_are_the_pictures_truth_and_exact_ones_track_better(tmp_path, capsys, monkeypatch):
    monkeypatch.syspath_prepend(str(BENCHMARKS))
    bench = importlib.import_module("corner_ceiling")
    report_path = tmp_path / "report.json"
    assert bench.main(["--out", str(tmp_path), "--duration", "3", "--configs", "1", "--sigmas", "0", "0.3",
                       "--no-template", "--no-tune", "--calibration-frames", "40", "--json", str(report_path)]) == 0
    text = capsys.readouterr().out
    report = json.loads(report_path.read_text())

    assert "| corners | sigma px | layout |" in text
    rows = {(r["corners"], r["sigma_px"], r["layout"]): r for r in report["rows"]}
    layouts = (bench.NOMINAL, bench.TRUE)
    assert set(rows) == {(c, s, lay) for c, s in (("detected (edge fit)", 0.0), ("oracle", 0.0), ("oracle", 0.3))
                         for lay in layouts}
    for r in rows.values():
        assert all(math.isfinite(v) for v in r["default"]["mean"].values()), r

    # nearly every detection has its true marker, and the edge fit is within a fraction of a pixel
    # of it wherever the face is seen within 60° of its normal
    assert report["oracle_matched"][0] >= 0.95 * report["detections"][0] > 0
    head_on = [v for name, v in report["residuals"]["edge"].items() if float(name.split("-")[1]) <= 60 and v["corners"]]
    assert head_on and all(v["rms_px"] < 0.3 for v in head_on), head_on
    assert all(math.isfinite(v["radial_sd_px"]) and abs(v["radial_mean_px"]) < 0.3 for v in head_on), head_on

    exact = rows[("oracle", 0.0, bench.TRUE)]["default"]["mean"]["rot_deg"]
    noisy = rows[("oracle", 0.3, bench.TRUE)]["default"]["mean"]["rot_deg"]
    assert exact < 0.85 * noisy, (exact, noisy)


def test_the_floor_with_exact_corners_on_a_clean_scene_is_zero(tmp_path, capsys, monkeypatch):
    """--floor (issue 26): a per-instant fit with the true camera and body to the oracle's corners
    recovers the true pose on a clean scene (global shutter: nothing else differs), and the
    detector's corners leave a finite, larger error. --decompose in the same run: a row per
    ladder step, and the filter given everything true tracks better than as tracked."""
    monkeypatch.syspath_prepend(str(BENCHMARKS))
    bench = importlib.import_module("corner_ceiling")
    report_path = tmp_path / "report.json"
    assert bench.main(["--out", str(tmp_path), "--preset", "clean", "--duration", "2", "--configs", "1", "--sigmas",
                       "0", "--no-template", "--no-tune", "--calibration-frames", "40", "--floor", "--decompose",
                       "--json", str(report_path)]) == 0
    out = capsys.readouterr().out
    assert "floor: per-instant fit" in out and "decomposition: the tracker's filter" in out
    report = json.loads(report_path.read_text())
    (floor,) = report["floor"].values()
    assert floor["oracle"]["all"]["sightings"] == floor["edge"]["all"]["sightings"] > 0
    assert floor["oracle"]["all"]["pos_cm"] < 1e-3 and floor["oracle"]["all"]["rot_deg"] < 1e-3, floor["oracle"]
    assert 0.01 < floor["edge"]["all"]["pos_cm"] < 5.0 and 0.01 < floor["edge"]["all"]["rot_deg"] < 5.0, floor["edge"]
    (rows,) = report["decomposition"]["as tracked"].values()
    assert list(rows) == [" + ".join(true) or "nothing" for true in bench.LADDER]
    assert all(math.isfinite(r[k]["rot_deg"]) and r[k]["dr"] > 0.9
               for r in rows.values() for k in ("causal", "smoothed")), rows
    everything = rows["body + cameras + stamps + corners"]["causal"]
    assert everything["rot_deg"] < rows["nothing"]["causal"]["rot_deg"], rows


def test_error_parts_tell_a_marker_grown_outward_from_one_shifted(monkeypatch):
    """The bias / noise split (issue 26): corners pushed out from the quad's centre are a radial
    error and an outward offset of every side; the same corners shifted sideways are neither on
    average (the radial parts cancel over the four corners)."""
    monkeypatch.syspath_prepend(str(BENCHMARKS))
    bench = importlib.import_module("corner_ceiling")
    square = np.array([[10.0, 10.0], [30.0, 10.0], [30.0, 30.0], [10.0, 30.0]])   # clockwise, y down
    grown = square + 0.1 * (square - square.mean(axis=0)) / np.linalg.norm(square - square.mean(axis=0), axis=1,
                                                                             keepdims=True)
    radial, tangential, offset = bench.error_parts(grown, square)
    np.testing.assert_allclose(radial, 0.1, atol=1e-12)
    np.testing.assert_allclose(tangential, 0.0, atol=1e-12)
    np.testing.assert_allclose(offset, 0.1 / math.sqrt(2.0), atol=1e-12)
    radial, _, offset = bench.error_parts(square + [0.2, 0.0], square)
    assert abs(radial.mean()) < 1e-12 and abs(offset.mean()) < 1e-12
    np.testing.assert_allclose(np.sort(offset), [-0.2, 0.0, 0.0, 0.2], atol=1e-12)
