"""Helpers of the firmware tests: builds through firmware/Makefile, tool checks."""

from __future__ import annotations

import shutil
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[2]
if str(REPO) not in sys.path:  # tests.helpers, also when pytest is not run as "python -m pytest"
    sys.path.insert(0, str(REPO))

from tests.helpers.native import FIRMWARE_DIR, make_firmware  # noqa: E402

BUILD_DIR = FIRMWARE_DIR / "build"


def require_tools(*tools: str) -> None:
    """Skip when a tool is not installed (CI installs them all: see tests/install.sh)."""
    missing = [t for t in tools if shutil.which(t) is None]
    if missing:
        pytest.skip(f"not installed: {', '.join(missing)} (Debian packages, see firmware/README.md)")


_made: dict[str, subprocess.CompletedProcess[str]] = {}


def make(target: str) -> subprocess.CompletedProcess[str]:
    """Run `make -C firmware <target>` once per session; fail the test with its output on error."""
    if target not in _made:
        result = make_firmware(target)
        if result.returncode != 0:
            pytest.fail(f"make {target} failed:\n{result.stdout[-6000:]}\n{result.stderr[-6000:]}")
        _made[target] = result
    return _made[target]
