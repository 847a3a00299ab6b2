"""benchmarks/accuracy.py --template on one short clean scene (--configs): the template-corner row
beside ours, in the table and the JSON report, from the same recording, closer to the truth in
rotation (the clean preset's perfect cube needs no body calibration)."""

import json
import math

import pytest

from tests.helpers.benchmarks import load_benchmark

pytestmark = pytest.mark.slow


def test_template_row_from_the_same_recording(tmp_path, capsys):
    bench = load_benchmark("accuracy")
    assert bench.main(["--quick", "--duration", "3", "--presets", "clean", "--configs", "1", "--template",
                       "--no-speed", "--out", str(tmp_path)]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert sum(bench.LABELS[bench.TEMPLATE] in line and not line.startswith("targets") for line in lines) == 1
    assert sum(line.strip().startswith(f"{bench.CLEAN} {bench.CONFIGS[1][0]}") and "pos ≤" in line
               for line in lines) == 3  # targets for ours, ours smoothed and ours + template
    doc = json.loads((tmp_path / bench.REPORT_FILE).read_text(encoding="utf-8"))
    assert [(s["preset"], s["config"]) for s in doc["scenes"]] == [(bench.CLEAN, 1)]  # --configs 1 only
    methods = doc["scenes"][0]["methods"]
    ours, template = methods[bench.OURS], methods[bench.TEMPLATE]
    assert math.isfinite(template["rot_deg"]) and template["scored"] >= 0.95 * ours["scored"] > 0
    assert template["rot_deg"] < ours["rot_deg"]
    assert (tmp_path / bench.scene_dir(tmp_path, 1, 101).name / "track" / bench.TEMPLATE / "run.json").exists()
