"""The sketch folder compiled as the Arduino builder compiles it, against the real Spresense
core (3.4.4, and the 3.2.0 fork that platformio.ini installs), the real GS2200-WiFi library
and the SDK 3.4.4 headers in ../shared/vendor/spresense, with the core's own flags; any
warning in our files fails (-Werror on our files, not on vendored headers)."""

from __future__ import annotations

import re
import subprocess

import pytest
from arduino_build import (
    CORE_SDK,
    CORES,
    PLATFORMIO_CORE,
    SKETCH_DIR,
    CoreBuild,
    build_sketch,
    global_functions,
    preprocess_sketch,
    require_vendor,
)


@pytest.mark.parametrize("core", [*CORES, PLATFORMIO_CORE])
def test_sketch_and_everything_under_it_compile_against_the_real_core(core, tmp_path):
    vendor = require_vendor()
    if core == PLATFORMIO_CORE and not all((vendor / d).is_dir() for d in (core, CORE_SDK[core])):
        pytest.skip(f"the PlatformIO set ({core}, {CORE_SDK[core]}) is not in {vendor}: docs/firmware.md, PlatformIO")
    result, sketch = build_sketch(core, tmp_path)
    expected = 1 + len(list((SKETCH_DIR / "src").rglob("*.cpp")))
    assert len(result.objects) == expected
    assert all(o.stat().st_size > 0 for o in result.objects)
    assert result.our_diagnostics(sketch) == []
    symbols = subprocess.run(["arm-none-eabi-nm", "-C", str(result.objects[0])], capture_output=True, text=True).stdout
    # Arduino.h declares them extern "C": the core's main() finds them by those names.
    assert re.search(r" T setup$", symbols, re.M) and re.search(r" T loop$", symbols, re.M)


def test_a_warning_in_our_code_fails_the_real_build(tmp_path):
    """The filter that gives our files -Werror sees a warning in an adapter."""
    require_vendor()
    source = tmp_path / "camera.cpp"
    text = (SKETCH_DIR / "src" / "spresense" / "camera.cpp").read_text()
    source.write_text(text.replace('#include "camera.h"', f'#include "{SKETCH_DIR}/src/spresense/camera.h"')
                      + "\nint cubecam_narrowed(long long v) { return v; }\n")
    result = subprocess.run(CoreBuild(CORES[0]).compile_command(source, tmp_path / "camera.o"),
                            capture_output=True, text=True)
    assert result.returncode == 0, result.stderr
    assert "camera.cpp" in result.stderr and "-Wconversion" in result.stderr


def test_an_api_misspelling_fails_the_real_build(tmp_path):
    require_vendor()
    source = tmp_path / "camera.cpp"
    text = (SKETCH_DIR / "src" / "spresense" / "camera.cpp").read_text()
    assert "setJPEGQuality" in text
    source.write_text(text.replace('#include "camera.h"', f'#include "{SKETCH_DIR}/src/spresense/camera.h"')
                      .replace("setJPEGQuality", "setJpegQuality"))
    result = subprocess.run(CoreBuild(CORES[0]).compile_command(source, tmp_path / "camera.o"),
                            capture_output=True, text=True)
    assert result.returncode != 0
    assert "setJpegQuality" in result.stderr


def test_sketch_preprocessing_declares_global_functions_as_the_builder_does(tmp_path):
    """A sketch may call a global function defined further down; functions in a namespace,
    class or struct get no prototype (the builder's ctags pass skips them)."""
    ino = tmp_path / "demo.ino"
    ino.write_text(
        "// a comment with braces { and a call helper(); }\n"
        "namespace {\nint twice(int v) { return 2 * v; }\n}\n"
        "struct Counter { int n; void bump() { ++n; } };\n"
        'const char* kText = "loop() {";\n'
        "void setup() { helper(twice(1)); }\n"
        "void loop() {}\n"
        "static void helper(int v) {\n  if (v) { Counter c = {0}; c.bump(); }\n}\n"
    )
    assert [proto for _, proto in global_functions(ino.read_text())] == [
        "void setup();", "void loop();", "static void helper(int v);"
    ]
    text = preprocess_sketch(ino)
    assert text.startswith("#include <Arduino.h>\n#line 1 ")
    assert text.index("static void helper(int v);") < text.index("void setup() {")
    require_vendor()
    source = tmp_path / "demo.ino.cpp"
    source.write_text(text)
    result = subprocess.run(CoreBuild(CORES[0]).compile_command(source, tmp_path / "demo.o"),
                            capture_output=True, text=True)
    assert result.returncode == 0, result.stderr
