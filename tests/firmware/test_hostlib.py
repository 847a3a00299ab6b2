"""The Spresense adapters and the core over the real library code on the host
(`make -C firmware hostlib`): the real Camera.cpp image buffers and threads and the real
GS2200-WiFi sources built for the host under ASan/UBSan, over fakes of the layer beneath
them (firmware/hostlib/). Each doctest case of firmware/test/hostlib runs in its own
process, so a sanitizer abort in one names that case."""

from __future__ import annotations

import re
import subprocess

import pytest
from arduino_build import VENDOR, require_vendor
from firmware_tools import BUILD_DIR, FIRMWARE_DIR, JOBS, require_tools

CASES = sorted(
    name
    for path in (FIRMWARE_DIR / "test" / "hostlib").glob("test_*.cpp")
    for name in re.findall(r'^TEST_CASE\("([^"]+)"\)', path.read_text(), re.M)
)
_built: list[bool] = []


def hostlib_binary():
    require_vendor()
    require_tools("make", "g++")
    if not _built:
        result = subprocess.run(["make", "-C", str(FIRMWARE_DIR), "-j", JOBS, "hostlib", f"VENDOR={VENDOR}"],
                                capture_output=True, text=True)
        if result.returncode != 0:
            pytest.fail(f"make hostlib failed:\n{result.stdout[-4000:]}\n{result.stderr[-6000:]}")
        _built.append(True)
    return BUILD_DIR / "hostlib-unit"


def test_every_case_is_known_to_the_binary():
    listed = subprocess.run([str(hostlib_binary()), "--list-test-cases"], capture_output=True, text=True).stdout
    assert len(CASES) >= 8
    for name in CASES:
        assert "," not in name, "doctest filters split at commas"
        assert name in listed


@pytest.mark.parametrize("case", CASES)
def test_node_life_over_the_real_libraries(case):
    binary = hostlib_binary()
    result = subprocess.run([str(binary), f"--test-case={case}"], capture_output=True, text=True, timeout=300)
    output = result.stdout[-6000:] + result.stderr[-6000:]
    assert result.returncode == 0, output
    assert re.search(r"test cases:\s*1 \|\s*1 passed", result.stdout), output
    assert "runtime error" not in result.stderr, output  # UBSan
