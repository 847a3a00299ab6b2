"""Smoke run of benchmarks/outputs.py (issue 10's CPU per frame of the outputs): a short recorded
stream fed into every output in their process, with a consumer on each. No timing is judged here:
the report is complete, the stream was fed at the rate asked, the child did the work, nothing was
dropped and every consumer received messages."""

import re
import subprocess
import sys
from pathlib import Path

import pytest

pytestmark = pytest.mark.slow

ROOT = Path(__file__).resolve().parents[2]


def test_quick_run_reports_cpu_per_frame_of_both_sides():
    run = subprocess.run([sys.executable, str(ROOT / "benchmarks" / "outputs.py"), "--quick", "--clients"], check=False,
                         capture_output=True, text=True, timeout=600, cwd=ROOT)
    assert run.returncode == 0, run.stderr[-3000:]
    out = run.stdout
    assert re.search(r"60 frames/s fed for 2 s per run, \d+ cores, load average [\d.]+ [\d.]+ [\d.]+", out), out
    row = re.search(r"zenoh \+ ros2 \+ vrpn \+ foxglove \+ mcap +([\d.]+) +(-?[\d.]+) +([\d.]+) +(\d+) +([\d.]+)", out)
    assert row, out
    fed_fps, _, child_ms, dropped, mcap_mb = (float(v) for v in row.groups())
    assert 50 <= fed_fps <= 70 and child_ms > 0 and dropped == 0
    assert mcap_mb > 0  # the child wrote the MCAP file
    received = re.search(r"consumers received: zenoh (\d+) messages, vrpn (\d+) messages, foxglove (\d+) messages", out)
    assert received and all(int(n) > 0 for n in received.groups()), out
