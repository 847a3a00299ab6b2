"""benchmarks/done_when.py's verdicts (issue 26's "Done when"): a figure is met by its target,
by "within 15 % of the floor" only where the floor is above the target and the preset allows it
(the realistic one; the clean preset's targets hold as written), otherwise not; a detection ratio
is met only at 1.000. No scene is rendered here (the script's run is a benchmark)."""

import importlib
import math
from pathlib import Path

import pytest

BENCHMARKS = Path(__file__).resolve().parents[2] / "benchmarks"


@pytest.fixture
def bench(monkeypatch):
    monkeypatch.syspath_prepend(str(BENCHMARKS))
    return importlib.import_module("done_when")


def test_a_figure_within_15_percent_of_a_floor_above_the_target_is_met_by_the_floor(bench):
    assert bench.verdict(0.9, 1.0, 1.5, True) == bench.MET_TARGET
    assert bench.verdict(1.70, 1.0, 1.5, True) == bench.MET_FLOOR        # 1.13x the floor
    assert bench.verdict(1.76, 1.0, 1.5, True) == bench.NOT_MET          # 1.17x the floor
    assert bench.verdict(1.1, 1.0, 0.9, True) == bench.NOT_MET           # the floor is below the target
    assert bench.verdict(0.40, 0.35, 1.27, False) == bench.NOT_MET       # clean: no floor clause
    assert bench.verdict(math.nan, 1.0, 1.5, True) == bench.NOT_MET      # the workflow produced nothing


def test_detection_ratio_is_met_only_at_one_to_three_decimals(bench):
    assert bench.dr_verdict(1.0) == bench.dr_verdict(0.9996) == bench.MET_TARGET
    assert bench.dr_verdict(0.999) == bench.dr_verdict(math.nan) == bench.NOT_MET


def test_a_cell_states_its_ratios_to_the_floor_and_the_presets_rule(bench):
    scene = bench.parse_scene("realistic:1:939:held-out")
    row = bench.cell(scene, {"pos_cm": 0.7, "rot_deg": 1.4, "dr": 1.0}, {"pos_cm": 1.4, "rot_deg": 1.4})
    assert row["pos_over_floor"] == pytest.approx(0.5) and row["rot_over_floor"] == pytest.approx(1.0)
    assert row["verdict"] == {"position": bench.MET_FLOOR, "rotation": bench.MET_FLOOR, "dr": bench.MET_TARGET}
    clean = bench.cell(bench.parse_scene("clean:1:939:held-out"), {"pos_cm": 0.15, "rot_deg": 0.37, "dr": 1.0},
                       {"pos_cm": 1.0, "rot_deg": 1.3})
    assert clean["verdict"]["position"] == bench.MET_TARGET and clean["verdict"]["rotation"] == bench.NOT_MET


@pytest.mark.parametrize("text", ["realistic:1:939", "rig:1:939:held-out", "clean:1:939:tuned"])
def test_a_malformed_scene_is_refused(bench, text):
    with pytest.raises(ValueError, match="PRESET:CONFIG:SEED:ROLE"):
        bench.parse_scene(text)
