"""The same doctest unit tests on the host (ASan + UBSan) and on a Cortex-M4F under QEMU,
the M4 size report and the sketch folder's layout. The sketch is compiled against the real
Spresense core in test_real_core_build.py."""

from __future__ import annotations

import json
import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
from firmware_tools import BUILD_DIR, FIRMWARE_DIR, make, require_tools

SKETCH_DIR = FIRMWARE_DIR / "cubecam"
CORE_DIR = SKETCH_DIR / "src" / "core"

QEMU = [
    "qemu-system-arm", "-M", "mps2-an386", "-nographic", "-monitor", "none", "-serial", "none",
    "-semihosting-config", "enable=on,target=native", "-kernel",
]
SUMMARY = re.compile(r"test cases:\s*(\d+) \|\s*(\d+) passed \|\s*(\d+) failed")


def doctest_counts(output: str) -> tuple[int, int, int]:
    m = SUMMARY.search(output)
    assert m, output[-3000:]
    return int(m.group(1)), int(m.group(2)), int(m.group(3))


def count_test_cases(pattern: str) -> int:
    return sum(p.read_text().count("\nTEST_CASE(") for p in FIRMWARE_DIR.glob(pattern))


def run_qemu(elf: Path) -> subprocess.CompletedProcess[str]:
    return subprocess.run(["timeout", "120", *QEMU, str(elf)], capture_output=True, text=True)


def test_unit_tests_pass_on_host_with_sanitizers():
    require_tools("g++", "make")
    if not Path("/usr/include/doctest/doctest.h").exists():
        pytest.skip("doctest-dev is not installed")
    make("unit-host")
    result = subprocess.run([str(BUILD_DIR / "unit-host")], capture_output=True, text=True, timeout=120)
    total, passed, failed = doctest_counts(result.stdout)
    assert result.returncode == 0, result.stdout[-4000:] + result.stderr[-4000:]
    assert failed == 0 and passed == total
    assert total == count_test_cases("test/test_*.cpp") + count_test_cases("test/host/test_*.cpp")
    assert "runtime error" not in result.stderr  # UBSan


def test_unit_tests_pass_on_cortex_m4_under_qemu():
    require_tools("arm-none-eabi-g++", "qemu-system-arm", "arm-none-eabi-readelf")
    make("unit-m4")
    elf = BUILD_DIR / "unit-m4.elf"
    attrs = subprocess.run(["arm-none-eabi-readelf", "-A", str(elf)], capture_output=True, text=True).stdout
    assert "Tag_CPU_arch: v7E-M" in attrs
    assert "Tag_FP_arch: VFPv4-D16" in attrs
    assert "Tag_ABI_VFP_args: VFP registers" in attrs  # hard float, as the Spresense toolchain
    result = run_qemu(elf)
    total, passed, failed = doctest_counts(result.stdout)
    assert result.returncode == 0, result.stdout[-4000:]
    assert failed == 0 and passed == total
    assert total == count_test_cases("test/test_*.cpp")  # every shared case ran on the M4


def test_qemu_run_reports_failures_as_a_nonzero_exit():
    require_tools("arm-none-eabi-g++", "qemu-system-arm")
    make("m4-failcheck")
    result = run_qemu(BUILD_DIR / "m4-failcheck.elf")
    assert result.returncode == 1, result.stdout
    assert doctest_counts(result.stdout) == (2, 1, 1)


def test_m4_size_report_within_budget():
    require_tools("arm-none-eabi-g++", "arm-none-eabi-size", "arm-none-eabi-nm")
    make("size")
    report = (BUILD_DIR / "size-m4.txt").read_text()
    print(report)
    totals = re.search(r"^\s*(\d+)\s+(\d+)\s+(\d+)\s+\d+\s+\w+\s+\(TOTALS\)", report, re.M)
    assert totals, report
    text, data, bss = map(int, totals.groups())
    assert 5_000 < text < 64_000  # the core stays small next to the 1.5 MB flash
    assert data == 0 and bss == 0  # no hidden globals in the core
    ram = {name: int(size) for size, name in re.findall(r"\d+ (\d+) B cubecam_ram_(\w+)", report)}
    assert ram["node"] < 16_000
    assert ram["per_client"] < 2_000


def test_sketch_is_hardware_glue_only():
    sketch = (SKETCH_DIR / "cubecam.ino").read_text()
    assert len(sketch.splitlines()) <= 150
    includes = re.findall(r'#include [<"]([^>"]+)[>"]', sketch)
    assert includes[0] == "Arduino.h" and "src/core/node.h" in includes
    assert all(i.startswith("src/spresense/") for i in includes[2:])
    for word in ("HTTP", "IMPROV", "Content-Type", "GET "):
        assert word not in sketch


def test_sketch_folder_holds_only_what_the_board_builds():
    """The Arduino builder compiles the sketch's src/ tree recursively: host-only code stays outside."""
    files = sorted(str(p.relative_to(SKETCH_DIR)) for p in SKETCH_DIR.rglob("*") if p.is_file())
    assert "cubecam.ino" in files
    assert not [f for f in files if f.endswith(".ino") and f != "cubecam.ino"]  # one sketch, merged as written
    stray = [f for f in files if f != "cubecam.ino" and not re.fullmatch(r"src/(core|spresense)/\w+\.(h|cpp)", f)]
    assert stray == []
    host_only = ("posix", "test", "fuzz", "bench", "m4", "hostlib")
    assert all((FIRMWARE_DIR / d).is_dir() and not (SKETCH_DIR / "src" / d).exists() for d in host_only)


def test_sketch_sources_include_each_other_by_relative_path():
    """Arduino puts no sketch folder on the include path: quotes resolve next to the including file."""
    for path in sorted(SKETCH_DIR.rglob("*")):
        if path.suffix not in (".h", ".cpp", ".ino"):
            continue
        for name in re.findall(r'#include "([^"]+)"', path.read_text()):
            assert (path.parent / name).is_file(), f"{path}: {name}"


def test_core_is_portable():
    for path in sorted(CORE_DIR.glob("*")):
        includes = re.findall(r'#include [<"]([^>"]+)[>"]', path.read_text())
        local = [i for i in includes if (CORE_DIR / i).is_file()]
        assert all(i in local or i in ("stddef.h", "stdint.h", "string.h") for i in includes), path


def test_core_allocates_nothing_and_throws_nothing_on_the_m4():
    require_tools("arm-none-eabi-g++", "arm-none-eabi-nm")
    make("size")
    objects = sorted(str(p) for p in (BUILD_DIR / "m4" / CORE_DIR.relative_to(FIRMWARE_DIR)).glob("*.o"))
    undefined = subprocess.run(["arm-none-eabi-nm", "-u", *objects], capture_output=True, text=True).stdout
    symbols = {s for s in re.findall(r"\bU (\S+)", undefined) if not re.match(r"_ZN7cubecam|_ZNK7cubecam", s)}
    # Only string functions and 64-bit division: no operator new/delete, malloc, printf,
    # __cxa_* (exceptions, guards) or anything else from the C/C++ runtime.
    allowed = {"memcpy", "memset", "memchr", "memcmp", "strlen", "strcmp", "strchr", "strstr"}
    allowed |= {"__aeabi_ldivmod", "__aeabi_uldivmod"}
    assert symbols <= allowed, symbols - allowed


def test_platformio_ini_is_valid():
    pio = shutil.which("pio") or str(Path(sys.executable).parent / "pio")
    if not Path(pio).exists():
        pytest.skip("platformio is not installed (pip install platformio==6.2.0)")
    env = dict(os.environ, PLATFORMIO_SETTING_ENABLE_TELEMETRY="No")
    result = subprocess.run([pio, "project", "config", "--json-output"], cwd=FIRMWARE_DIR.parent,
                            capture_output=True, text=True, timeout=120, env=env)
    assert result.returncode == 0, result.stderr
    sections = {name: dict(options) for name, options in json.loads(result.stdout)}
    opts = sections["env:spresense"]
    assert opts["platform"].partition("#")[0] == "https://github.com/maxgerhardt/platform-sonyspresense.git"  # pinned
    assert opts["board"] == "spresense"
    assert opts["framework"] == ["arduino"]
    assert int(opts["monitor_speed"]) == 115200
    assert int(opts["board_upload.maximum_ram_size"]) >= 1_000_000
    assert any("GS2200-WiFi" in dep for dep in opts["lib_deps"])
    # PlatformIO builds the sketch folder the Arduino IDE opens, all of it, as the Arduino builder does.
    assert Path(sections["platformio"]["src_dir"]) == SKETCH_DIR
    assert opts["build_src_filter"] == ["+<*>"]
