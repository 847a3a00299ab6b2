"""Smoke run of benchmarks/refine_bias.py (issue 26: the refined cameras' error and scale, ours
against a baseline commit's code) on a tiny clean scene, with HEAD as the baseline: the report
has a row per calibration, the baseline ran from its own extracted tree, and the shape of each
row (every camera, a scale near 1) is right. How good the cameras are is the benchmark's business."""

import json

import pytest

from tests.helpers.benchmarks import load_benchmark

pytestmark = pytest.mark.slow


def test_quick_run_reports_world_marker_baseline_and_ours(tmp_path, capsys):
    bench = load_benchmark("refine_bias")
    report = tmp_path / "report.json"
    assert bench.main(["--presets", "clean", "--seeds", "7", "--configs", "1", "--duration", "2",
                       "--calibration-frames", "12", "--baseline", "HEAD", "--out", str(tmp_path),
                       "--json", str(report)]) == 0
    text = capsys.readouterr().out
    for label in (bench.WORLD, bench.BASE, bench.OURS):
        assert sum(line.startswith(f"| {label} | cam1 ") for line in text.splitlines()) == 1, label
    assert "summary (worst over the scenes" in text and "baseline HEAD" in text

    (scene,) = json.loads(report.read_text(encoding="utf-8"))["scenes"]
    assert set(scene["rows"]) == {bench.WORLD, bench.BASE, bench.OURS}
    for label, row in scene["rows"].items():
        assert set(row["cameras"]) == {"cam1", "cam2", "cam3"}, label
        assert 0.99 < row["scale"] < 1.01, label
        assert row["max_mm"] >= row["mean_mm"] > 0, label
    # HEAD's tree and ours are the same code on the same recording
    assert scene["rows"][bench.BASE]["cameras"] == scene["rows"][bench.OURS]["cameras"]


def test_a_baseline_that_is_no_commit_is_a_one_line_error(tmp_path, capsys):
    bench = load_benchmark("refine_bias")
    with pytest.raises(SystemExit) as exc:
        bench.main(["--baseline", "no-such-commit", "--out", str(tmp_path)])
    assert exc.value.code == 2
    assert "--baseline no-such-commit: git archive failed" in capsys.readouterr().err
