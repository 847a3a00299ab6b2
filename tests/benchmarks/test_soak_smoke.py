"""Short run of benchmarks/soak.py (issue 12's fault soak): 8 emulated cameras with faults for
20 s, the tracker live in its own process. Never a timing here (the targets are the benchmark's
business): the report is complete, every fault kind was injected, and the counts add up -- what
the emulator injected against what the tracker counted, frames recorded against frames counted,
every fault recovered, still recovering at the end, or not recovered."""

import json
import subprocess
import sys
from pathlib import Path

import pytest

pytestmark = pytest.mark.slow

ROOT = Path(__file__).resolve().parents[2]


def test_quick_soak_prints_a_complete_report_whose_counts_add_up(tmp_path):
    command = [sys.executable, str(ROOT / "benchmarks" / "soak.py"), "--quick", "--out", str(tmp_path)]
    run = subprocess.run(command, check=False, capture_output=True, text=True, timeout=600, cwd=ROOT)
    assert run.returncode == 0, run.stderr[-3000:]
    lines = run.stdout.splitlines()
    assert lines[0].startswith("soak: 8 cameras x 10 fps for 20 s")
    assert "nproc" in lines[0] and "load average" in lines[0]
    for start in ("  command: ", "faults injected: ", "poses: ", "tracker process: RSS ", "SUMMARY: "):
        assert sum(line.startswith(start) for line in lines) == 1, start
    assert lines[-1].startswith("SUMMARY: ")

    r = json.loads((tmp_path / "soak_report.json").read_text(encoding="utf-8"))
    cameras = r["cameras"]
    assert len(cameras) == 7 and r["silent"]["name"] == "cam8"
    kinds = {kind for c in cameras.values() for kind in c["injected"]}
    assert kinds == {"disconnect", "stall", "corrupt"}
    for name, c in cameras.items():
        injected = sum(c["injected"].values())
        assert c["recovered"] + c["in_progress"] + c["not_recovered"] == injected, name
        assert len(c["recovery_s"]) == c["recovered"] and all(t >= 0 for t in c["recovery_s"]), name
        assert c["frames_recorded"] == c["frames"] > 0, name  # the session recording holds every frame counted
        # every cut or endless stall is one reconnect of the tracker (bar one still pending at the end)
        assert c["reconnect_faults"] - c["in_progress"] <= c["reconnects"] <= c["reconnect_faults"], name
        corrupt = c["injected"].get("corrupt", 0)
        assert corrupt - c["in_progress"] <= sum(c["bad_parts"].values()) <= corrupt, name
    assert cameras["cam1"]["injected"] == {} and cameras["cam1"]["reconnects"] == 0
    assert r["injected_total"] == sum(sum(c["injected"].values()) for c in cameras.values())
    assert r["injected_total"] == r["recovered_total"] + r["in_progress_total"] + r["not_recovered_total"]
    assert r["worst_recovery_s"] == max(t for c in cameras.values() for t in c["recovery_s"])
    # the camera that never answers: connections accepted, no frame, the tracker keeps retrying
    assert r["silent"]["connections_accepted"] >= 1 and r["silent"]["frames"] == 0 and r["silent"]["reconnects"] >= 1
    assert 0 < r["poses"] and 0 <= r["pose_slots_lost"] <= r["pose_slots"]
    assert r["exit_status"] == 0 and not r["traceback"]
    assert r["rss_mb_start"] > 0 and r["threads_start"] > 0 and r["samples_at_s"][0] < r["samples_at_s"][1] <= 20
    assert (r["failures"] == []) == ("all targets met" in lines[-1])
