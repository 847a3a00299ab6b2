"""Smoke run of benchmarks/live.py (issue 9's benchmark): 2 emulated cameras for a few seconds,
the tracker live over HTTP in its own process. The targets are the benchmark's business (never
a timing here): the report is complete and consistent (its counts add up, its verdicts follow
from its figures), and the live run tracked the robot."""

import itertools
import json
import math
import re
import subprocess
import sys
from pathlib import Path

import pytest

from tests.helpers.benchmarks import load_benchmark

pytestmark = pytest.mark.slow

ROOT = Path(__file__).resolve().parents[2]


def test_quick_run_prints_and_saves_a_complete_report(tmp_path):
    command = [sys.executable, str(ROOT / "benchmarks" / "live.py"), "--quick", "--outputs", "--out", str(tmp_path)]
    run = subprocess.run(command, check=False, capture_output=True, text=True, timeout=900, cwd=ROOT)
    assert run.returncode == 0, run.stderr[-3000:]
    lines = run.stdout.splitlines()
    for start in ("live benchmark: 2 cameras x 10 fps", "  command: ", "  after the first ", "  frames/s: offered",
                  "  CPU: ", "  CPU per frame: naive loop ", "  the machine's speed in this run ",
                  "  arrival -> pose ms: p50", "  over time (", "  RSS: ", "  accuracy vs ground truth: live",
                  "  same ", "  per frame, one thread: ", "  outputs: files only ", "SUMMARY: "):
        assert sum(line.startswith(start) for line in lines) == 1, start
    assert "nproc" in lines[0] and "naive loop" in next(line for line in lines if line.startswith("  same "))

    doc = json.loads((tmp_path / "live_report.json").read_text(encoding="utf-8"))
    live, acc, speed = doc["live"], doc["accuracy"], doc["speed"]
    assert doc["nproc"] >= 1 and "--live" in live["command"]
    # the counts add up: every frame offered was processed or dropped (and counted)
    assert live["offered_frames"] > 0 and live["processed_frames"] > 0
    assert live["offered_frames"] == live["processed_frames"] + live["dropped_behind"] + live["dropped_before_clock"]
    assert math.isclose(live["dropped_fraction"], (live["dropped_behind"] + live["dropped_before_clock"])
                        / live["offered_frames"])
    for kind in ("arrival_ms", "capture_ms"):
        p = live[kind]
        assert 0 <= p["p50"] <= p["p95"] <= p["p99"], kind
    assert live["poses"] > 0 and live["cpu_ms_per_frame"] > 0 and live["cpu_ms_per_frame_warm"] > 0
    assert live["rss_end_mb"] > 0 and live["processed_fps_warm"] > 0  # frames were processed after the warm-up
    assert live["rss_start_mb"] > 0 and live["rss_mid_mb"] > 0
    rss = live["rss_over_time"]   # from the start on, the tracker and its worker processes
    assert rss and [t for t, _mb, _n in rss] == sorted(t for t, _mb, _n in rss)
    assert all(mb > 0 and n >= 1 for _t, mb, n in rss)
    assert 0 < live["first_pose_s"] < live["wall_s"]  # start-up: the first pose came during the session
    # the machine's speed in the run: the emulator's CPU per frame served, the tracker's start-up before its session
    assert live["emulator_ms_per_frame"] > 0
    # (the start-up is read off the first status line, which a busy loop prints late: an upper bound that can
    # exceed the first pose's moment, as a clean-clone CI run at load ~4 saw; it is within the run)
    assert 0 < live["startup_s"] < live["wall_s"] if live["over_time"] else math.isnan(live["startup_s"])
    rss_line = next(line for line in lines if line.startswith("  RSS: "))
    assert live["kernels_warm_s"] > 0 and "before it, the kernels " in rss_line  # warmed before the timed run
    # interval by interval (between status lines): in order, within the run, no more poses than the run's
    ends = [(i["from_s"], i["to_s"]) for i in live["over_time"]]
    assert all(0 <= a < b for a, b in ends) and all(b == c for (_, b), (c, _) in itertools.pairwise(ends))
    assert sum(i["poses"] for i in live["over_time"]) <= live["poses"]
    assert all(i["dropped"] >= 0 for i in live["over_time"])
    assert math.isnan(live["offered_fps_warm"]) or live["offered_fps_warm"] > 0  # no status line after 1.5 s of 5
    for run in ("live", "offline"):
        assert 0 < acc[run]["pos_cm"] < 2.0 and 0 < acc[run]["rot_deg"] < 2.0, run
        assert acc[run]["detection_ratio"] > 0.5, run
    assert math.isclose(acc["pos_ratio"], acc["live"]["pos_cm"] / acc["offline"]["pos_cm"])
    assert speed["frames"] > 0 and speed["naive_fps"] > 0 and speed["ours_fps"] > 0 and speed["inline_fps"] > 0
    for part in ("work_ms", "fuse_ms"):
        assert 0 < speed[part]["p50"] <= speed[part]["p95"], part
    assert math.isclose(speed["ratio"], speed["ours_fps"] / speed["naive_fps"])
    # CPU per frame beside the throughput: ours as replayed and the live run's, against the naive loop's
    assert speed["naive_cpu_ms"] > 0 and speed["corner_refinement"] == "edge"
    assert math.isclose(speed["live_cpu_ratio"], live["cpu_ms_per_frame"] / speed["naive_cpu_ms"])
    assert math.isclose(speed["cpu_ratio"], (speed["ours_cpu_ms"]["main"] + speed["ours_cpu_ms"]["workers"])
                        / speed["naive_cpu_ms"], rel_tol=0.2)   # the median of rounds of each
    # the targets' verdicts follow from the report's own figures (which ones a loaded machine misses is
    # the benchmark's business): each target is listed as missed exactly when its figure misses it
    bench = load_benchmark("live")
    a = live["arrival_ms"]
    missed = {"dropped": live["dropped_fraction"] > bench.TARGET_DROPPED,
              "p95 arrival->pose": not a["p95"] <= bench.TARGET_P95_MS,
              "p99 arrival->pose": not a["p99"] <= bench.TARGET_P99_MS,
              "throughput ours/naive": not speed["ratio"] >= bench.TARGET_SPEED,
              "live CPU per frame / naive": not speed["live_cpu_ratio"] <= bench.TARGET_CPU,
              "live accuracy": not max(acc["pos_ratio"], acc["rot_ratio"]) <= 1.0 + bench.TARGET_ACCURACY}
    for name, miss in missed.items():
        assert any(f.startswith(name) for f in doc["failures"]) == miss, (name, doc["failures"])
    assert lines[-1] == "SUMMARY: all targets met" if not doc["failures"] else \
        lines[-1].startswith(f"SUMMARY: {len(doc['failures'])} target(s) missed: ")
    # --outputs: a second session with every output on, compared with the first (pose files only)
    out = doc["outputs"]
    assert out["files_only"]["processed_fps"] == live["processed_fps"]
    for flag in ("--zenoh", "--ros2", "--vrpn 127.0.0.1:", "--foxglove 127.0.0.1:", "--mcap "):
        assert flag in out["flags"], flag
    assert out["all_outputs"]["poses"] > 0 and out["mcap_mb"] > 0
    assert math.isclose(out["processed_ratio"], out["all_outputs"]["processed_fps"] / live["processed_fps"])
    assert math.isclose(out["cpu_ratio"], out["all_outputs"]["cpu_ms_per_frame"] / live["cpu_ms_per_frame"])
    # the live poses and the offline replay are kept in --out
    assert (tmp_path / "live" / "robot.jsonl").exists() and (tmp_path / "offline" / "robot.tum").exists()


def test_template_speed_only_run_uses_template_corners_and_its_target(tmp_path):
    """--template: ours runs with [detector] corner_refinement = "template" (the config it loaded
    says so) and is held to the template throughput target (2.5), not the default one (4)."""
    command = [sys.executable, str(ROOT / "benchmarks" / "live.py"), "--quick", "--speed-only", "--template",
               "--out", str(tmp_path)]
    run = subprocess.run(command, check=False, capture_output=True, text=True, timeout=900, cwd=ROOT)
    assert run.returncode == 0, run.stderr[-3000:]
    speed = json.loads((tmp_path / "speed_report.json").read_text(encoding="utf-8"))["speed"]
    assert speed["corner_refinement"] == "template"
    assert 'corner_refinement = "template"' in (tmp_path / "template_config.toml").read_text(encoding="utf-8")
    lines = run.stdout.splitlines()
    assert "template corners" in lines[0]
    assert any(line.startswith("  CPU per frame: naive loop ") for line in lines)
    assert lines[-1] == "SUMMARY: throughput target met" if speed["ratio"] >= 2.5 else "< 2.5" in lines[-1]


def test_worker_split_reports_where_a_camera_worker_process_spends_its_cpu(tmp_path):
    """--worker-split: one camera worker process's loop in the benchmark's process, fed by the emulator:
    frames processed (no more than its cameras delivered) and the CPU per processed frame of each part."""
    command = [sys.executable, str(ROOT / "benchmarks" / "live.py"), "--quick", "--worker-split",
               "--out", str(tmp_path)]
    run = subprocess.run(command, check=False, capture_output=True, text=True, timeout=900, cwd=ROOT)
    assert run.returncode == 0, run.stderr[-3000:]
    line = run.stdout.splitlines()[-1]
    found = re.search(r"over 1 cameras .*: (\d+) frames processed of (\d+) received; thread CPU per processed frame: "
                      r"work .* ([0-9.]+) ms, planning ([0-9.]+) ms, sending the result ([0-9.]+) ms, the rest .* "
                      r"([0-9.]+) ms; the tracker's process standing in .* ([0-9.]+) ms$", line)
    assert found, line
    processed, received = int(found.group(1)), int(found.group(2))
    assert 0 < processed <= received
    assert all(float(found.group(k)) > 0.0 for k in range(3, 8)), line
