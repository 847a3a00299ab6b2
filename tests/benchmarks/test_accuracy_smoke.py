"""Smoke run of benchmarks/accuracy.py (issues 5 and 15's goal benchmark): one short seed of every
configuration in the clean preset and of two in the realistic one. The targets are the benchmark's
business; here: the report is complete, and on every scene our tracker's errors are finite and
below the paper's mean fusion's."""

import json
import math

import pytest

from tests.helpers.benchmarks import load_benchmark

pytestmark = pytest.mark.slow


def test_quick_run_reports_every_configuration_and_beats_the_paper_mean(tmp_path, capsys):
    bench = load_benchmark("accuracy")
    assert bench.main(["--quick", "--duration", "6", "--jobs", "2", "--out", str(tmp_path)]) == 0
    text = capsys.readouterr().out

    # every configuration and preset has its rows (ours, the paper's mean, our mean) and a target line
    lines = text.splitlines()
    expected = {(bench.CLEAN, ci) for ci in range(len(bench.CONFIGS))} | {(bench.REALISTIC, ci)
                                                                           for ci in bench.QUICK_REALISTIC}
    for name, *_ in bench.CONFIGS:
        table_row = [line for line in lines if line.startswith(name) and bench.LABELS[bench.OURS] in line]
        assert len(table_row) == 1 and bench.CLEAN in table_row[0], name
    for preset, ci in expected:
        label = f"{preset} {bench.CONFIGS[ci][0]}"
        # a target line for ours and for ours smoothed (the same replay's poses smoothed offline)
        assert sum(line.strip().startswith(label) and "pos ≤" in line for line in lines) == 2, label
    realistic_rows = [line for line in lines if bench.REALISTIC in line and bench.LABELS[bench.OURS] in line]
    assert len(realistic_rows) == len(bench.QUICK_REALISTIC)
    for method in (bench.PAPER, bench.OUR_MEAN):
        assert sum(bench.LABELS[method] in line for line in lines) == len(expected)
    speed = [line for line in lines if line.startswith("speed (one core")]
    assert len(speed) == 1 and "naive loop" in speed[0] and "ratio ours/naive" in speed[0]
    assert lines[-1].startswith("SUMMARY: ")

    doc = json.loads((tmp_path / bench.REPORT_FILE).read_text(encoding="utf-8"))
    assert {(scene["preset"], scene["config"]) for scene in doc["scenes"]} == expected
    assert len(doc["scenes"]) == len(expected)
    for scene in doc["scenes"]:
        ours, paper = scene["methods"][bench.OURS], scene["methods"][bench.PAPER]
        assert math.isfinite(ours["pos_cm"]) and math.isfinite(ours["rot_deg"]), scene["config"]
        assert ours["scored"] > 0.8 * ours["poses"] > 0, scene["config"]
        # ours is better than the paper's mean on the same recording (by how much: the benchmark's job)
        assert ours["pos_cm"] < paper["pos_cm"], scene["config"]
        assert scene["methods"][bench.SMOOTHED]["scored"] >= ours["scored"], scene["config"]
        assert ours["rot_deg"] < paper["rot_deg"], scene["config"]
    s = doc["speed"]
    assert s["frames"] > 0 and s["naive_fps"] > 0 and s["ours_fps"] > 0
    assert s["ours_robot_poses"] > 0 and s["naive_marker_poses"] > 0
