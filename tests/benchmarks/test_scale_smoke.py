"""Smoke run of benchmarks/scale.py (issue 13's benchmark): a short simulated recording through the
workers' per-frame work, the fusion in process and 2 publisher processes over loopback Zenoh. No
timing is judged here: the report is complete and its counts are consistent."""

import re
import subprocess
import sys
from pathlib import Path

import pytest

pytestmark = pytest.mark.slow

ROOT = Path(__file__).resolve().parents[2]


def number(pattern: str, text: str) -> float:
    m = re.search(pattern, text)
    assert m, f"{pattern!r} not in:\n{text}"
    return float(m.group(1))


def test_quick_run_prints_a_complete_consistent_report():
    run = subprocess.run([sys.executable, str(ROOT / "benchmarks" / "scale.py"), "--quick"], check=False,
                         capture_output=True, text=True, timeout=600, cwd=ROOT)
    assert run.returncode == 0, run.stderr[-3000:]
    out = run.stdout
    assert number(r"cores: (\d+);", out) >= 1
    messages = number(r"; (\d+) sighting messages from", out)
    mean_bytes = number(r"bytes per message: mean (\d+)", out)
    jpeg_bytes = number(r"a JPEG of the same frames is ~(\d+)", out)
    assert messages > 0 and 88 <= mean_bytes < jpeg_bytes / 20  # corners, not images (contracts §7)
    assert number(r"worker: per-frame work ([\d.]+) ms CPU", out) > 0
    decode_us = number(r"fusion in process: decode ([\d.]+) us", out)
    fuse_us = number(r"decode \+ rebuild \+ fuse ([\d.]+) us CPU", out)
    assert 0 < decode_us < fuse_us
    assert number(r"\((\d+) poses\)", out) > 0
    # 2 publishers x 2 cameras x 10 fps for 3 s: what was received was offered, and was decoded
    offered = number(r"offered (\d+)/s", out)
    received = number(r"received (\d+)/s", out)
    assert offered == 40 and 0 < received <= offered
    assert number(r"subscriber CPU ([\d.]+) us per message", out) > 0
    assert re.search(r"200 cameras x 10 fps: 2000 messages/s, [\d.]+ MB/s of sightings; one fusion process needs "
                     r"[\d.]+ cores \(ceiling \d+ messages/s = \d+ cameras at 10 fps\)", out), out
