"""Helpers of the cubecam tool tests: running the command, checking its error output."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]
CUBECAM = [sys.executable, "-m", "cubecam.cli"]


def run_cubecam(*args: str, input: str | None = None, timeout: float = 30.0, env: dict | None = None):
    """Run the cubecam command in a subprocess (as a user would), bounded in time."""
    return subprocess.run([*CUBECAM, *args], input=input, capture_output=True, text=True, timeout=timeout,
                          env={**os.environ, **(env or {})}, cwd=REPO)


def assert_one_line_error(returncode: int, stderr: str, *fragments: str) -> None:
    """Exit status 1, no traceback, exactly one error line on stderr, naming the fragments."""
    assert returncode == 1, (returncode, stderr)
    assert "Traceback" not in stderr, stderr
    lines = [line for line in stderr.splitlines() if ": error: " in line]
    assert len(lines) == 1, stderr
    for fragment in fragments:
        assert fragment in lines[0], (fragment, lines[0])
