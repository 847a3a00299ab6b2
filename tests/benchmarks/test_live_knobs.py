"""benchmarks/live.py's knobs for issue 31's live-premium measurements: the ``[live]`` section that
--worker-kind and --workers write into the live tracker's config (read back as the tracker reads it),
and --wake-cost's report (the same frames back to back and woken per frame)."""

import re
import subprocess
import sys
import tomllib
from pathlib import Path

import pytest

from cubetrack.core.frame_pool import LiveParams, WorkerKind
from cubetrack.core.params import params_from_table
from tests.helpers.benchmarks import load_benchmark

ROOT = Path(__file__).resolve().parents[2]


def _live_params(section: str) -> LiveParams:
    return params_from_table(LiveParams, tomllib.loads(section).get("live"), "[live]")


def test_worker_kind_and_count_reach_the_trackers_live_section():
    live = load_benchmark("live")
    both = live.live_section(live.parse_args(["--worker-kind", "camera-process", "--workers", "1"]))
    assert _live_params(both) == LiveParams(workers=1, worker_kind=WorkerKind.CAMERA_PROCESS)
    assert _live_params(live.live_section(live.parse_args(["--workers", "3"]))) == LiveParams(workers=3)
    assert live.live_section(live.parse_args([])) == ""   # the config's own [live]
    with pytest.raises(SystemExit):
        live.parse_args(["--workers", "0"])


def test_wake_cost_runs_alone_with_a_positive_gap():
    live = load_benchmark("live")
    for bad in (["--wake-cost", "0"], ["--wake-cost", "1", "--speed-only"], ["--wake-cost", "1", "--worker-split"],
                ["--wake-cost", "1", "--frames-per-wake", "0"]):
        with pytest.raises(SystemExit):
            live.parse_args(bad)


@pytest.mark.slow
def test_wake_cost_prints_each_steps_cpu_both_ways_and_their_ratios(tmp_path):
    command = [sys.executable, str(ROOT / "benchmarks" / "live.py"), "--quick", "--wake-cost", "1",  # 60 frames
               "--speed-rounds", "2", "--out", str(tmp_path)]
    run = subprocess.run(command, check=False, capture_output=True, text=True, timeout=900, cwd=ROOT)
    assert run.returncode == 0, run.stderr[-3000:]
    lines = run.stdout.splitlines()
    assert lines[0].startswith("waking per frame: the first 60 frames") and "nproc" in lines[0]
    back, woken, ratio = ([float(v) for v in re.findall(r"\d+\.\d+", line.split(":", 1)[1])] for line in lines[1:4])
    assert lines[2].startswith("  a 1 ms sleep before each")
    for row in (back, woken):
        assert len(row) == 4 and all(v > 0 for v in row)
        assert row[3] == pytest.approx(sum(row[:3]), abs=0.002)   # all = planning + work + fusion (printed rounded)
    assert ratio == pytest.approx([w / b for w, b in zip(woken, back, strict=True)], rel=0.05, abs=0.01)
