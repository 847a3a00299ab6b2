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


def test_the_markers_frame_truth_puts_the_calibrated_markers_where_the_built_ones_are(bench):
    """A body calibrated exactly (the built markers in the nominal layout's best-fit frame, as
    calibrate-body writes it) posed by the moved truth places every marker where the cube as built
    has it under the truth's pose; a cube built as designed leaves the truth as it was."""
    import numpy as np
    from scipy.spatial.transform import Rotation

    from cubetrack.calib.body import best_fit_transform, moved_layout
    from cubetrack.core.geometry import make_T
    from cubetrack.core.layout import paper_cube_layout
    from cubetrack.io.trajectory import Trajectory
    from cubetrack.simulate import SimulationParams
    from cubetrack.simulate.imperfections import built_layout

    nominal = paper_cube_layout()
    built = built_layout(nominal, SimulationParams.realistic(), np.random.default_rng(505))
    calibrated = moved_layout(built, best_fit_transform(built.corners_m.reshape(-1, 3),
                                                        nominal.corners_m.reshape(-1, 3)))
    turns = Rotation.from_rotvec([[0.0, 0.0, 0.3], [0.05, -0.04, 2.0], [0.1, 0.0, -1.0]])
    truth = Trajectory(np.array([0.0, 0.1, 0.2]), np.array([[0.1, 0.2, 0.3], [0.4, -0.1, 0.3], [-0.2, 0.0, 0.31]]),
                       turns.as_quat())
    moved = bench.markers_frame_truth(truth, nominal, built)
    offset = Rotation.from_quat(moved.quats_xyzw[0]) * Rotation.from_quat(truth.quats_xyzw[0]).inv()
    assert np.degrees(offset.magnitude()) > 0.1  # the build errors turn the frame
    for k in range(3):
        T_world_design = make_T(turns[k].as_matrix(), truth.positions_m[k])
        T_world_markers = make_T(Rotation.from_quat(moved.quats_xyzw[k]).as_matrix(), moved.positions_m[k])
        for b, c in zip(built.markers, calibrated.markers, strict=True):
            np.testing.assert_allclose(T_world_markers @ c.T_cube_marker, T_world_design @ b.T_cube_marker, atol=1e-9)
    same = bench.markers_frame_truth(truth, nominal, nominal)
    np.testing.assert_allclose(same.positions_m, truth.positions_m, atol=1e-12)
    np.testing.assert_allclose(np.abs(np.sum(same.quats_xyzw * truth.quats_xyzw, axis=1)), 1.0, atol=1e-12)
