"""The sketch folder built as the Arduino builder builds it, against the real Spresense
core in ../shared/vendor/spresense (see its README): the .ino preprocessed (Arduino.h
first, prototypes of the sketch's global functions), then the sketch and everything
under its src/ compiled to object files with the command line of the core's own
platform.txt recipe (board "spresense", MainCore, 1.5 MB, debug off).

Nothing is linked: the SDK's prebuilt libraries are not in the vendored tree.
"""

from __future__ import annotations

import re
import shlex
import shutil
import subprocess
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[2]
SKETCH_DIR = REPO / "firmware" / "cubecam"
VENDOR = REPO.parent / "shared" / "vendor" / "spresense"
CORES = ("core-3.4.4", "core-3.2.0")
SDK = "sdk-3.4.4-headers"
# The set platformio.ini pins: the core at tag 2.6.0 and the SDK package 2.6.0 (its
# release/ headers). Not in the vendored tree; docs/firmware.md, "PlatformIO", says how to
# lay it out beside it. Each core is built against its own SDK headers.
PLATFORMIO_CORE = "core-2.6.0"
CORE_SDK = {"core-3.4.4": SDK, "core-3.2.0": SDK, PLATFORMIO_CORE: "sdk-2.6.0-headers"}
# The board menu choices a cubecam node needs (boards.txt): MainCore with 1.5 MB for the
# camera buffers, debug off.
MENU = {"Core": "Main", "Memory": "1536", "Debug": "Disabled"}
# Libraries the sketch uses, by the folder the Arduino builder puts on the include path.
CORE_LIBRARIES = ("Camera", "EEPROM/src", "Watchdog", "LowPower/src", "SPI", "File/src")
GS2200_LIBRARY = "gs2200-wifi/src"
# Arduino IDE 1.8.16, as in the vendored README; arduino-cli passes 10607.
IDE_VERSION = "10816"
# Our own warnings on top of the core's "all" level; only diagnostics in our files count.
OUR_WARNINGS = ("-Wshadow", "-Wconversion")
DIAGNOSTIC = re.compile(r"^(?P<path>[^:\n]+):\d+:\d+: (?P<kind>warning|error): .*$", re.M)


def require_vendor() -> Path:
    """The vendored Spresense tree, or a skip that says where it was looked for."""
    if not (VENDOR / "README.md").is_file():
        pytest.skip(f"the real Spresense sources are not at {VENDOR} (../shared/vendor/spresense); "
                    "see firmware/README.md")
    return VENDOR


def read_properties(path: Path) -> dict[str, str]:
    """key=value lines of an Arduino platform.txt / boards.txt."""
    props = {}
    for line in path.read_text(encoding="utf-8", errors="replace").splitlines():
        line = line.strip()
        if line and not line.startswith("#") and "=" in line:
            key, value = line.split("=", 1)
            props[key.strip()] = value.strip()
    return props


def expand(text: str, props: dict[str, str]) -> str:
    """Substitutes {name} until nothing known is left (unknown names stay as they are)."""
    for _ in range(20):
        new = re.sub(r"\{([\w.-]+)\}", lambda m: props.get(m.group(1), m.group(0)), text)
        if new == text:
            return new
        text = new
    raise ValueError(f"recursive property in {text!r}")


@dataclass(frozen=True)
class CoreBuild:
    """Compile commands of one vendored core (core-3.4.4 or core-3.2.0)."""

    core: str

    @property
    def core_dir(self) -> Path:
        return VENDOR / self.core

    def properties(self) -> dict[str, str]:
        platform = read_properties(self.core_dir / "platform.txt")
        boards = read_properties(self.core_dir / "boards.txt")
        props = dict(platform)
        for key, value in boards.items():
            if key.startswith("spresense.") and ".menu." not in key:
                props[key.removeprefix("spresense.")] = value
        for menu, choice in MENU.items():
            prefix = f"spresense.menu.{menu}.{choice}."
            props.update({k.removeprefix(prefix): v for k, v in boards.items() if k.startswith(prefix)})
        props.update({
            "runtime.platform.path": str(self.core_dir),
            "runtime.ide.version": IDE_VERSION,
            "build.arch": "SPRESENSE",  # the platform folder's architecture, as the builder names it
            "build.kernel": str(VENDOR / CORE_SDK[self.core]),
            "compiler.path": "",  # Debian's arm-none-eabi-g++ on PATH (the board package ships GCC 9)
            "compiler.warning_flags": platform["compiler.warning_flags.all"],
            "type_prefix": "",
        })
        return props

    def include_flags(self) -> list[str]:
        dirs = [self.core_dir / "cores" / "spresense", self.core_dir / "variants" / "spresense"]
        dirs += [self.core_dir / "libraries" / lib for lib in CORE_LIBRARIES]
        dirs.append(VENDOR / GS2200_LIBRARY)
        return [f"-I{d}" for d in dirs]

    def compile_command(self, source: Path, obj: Path) -> list[str]:
        props = self.properties()
        props.update({"includes": " ".join(shlex.quote(f) for f in self.include_flags()),
                      "source_file": str(source), "object_file": str(obj)})
        return shlex.split(expand(props["recipe.cpp.o.pattern"], props)) + list(OUR_WARNINGS)


def _signature_start(code: str, brace: int) -> int:
    """Where the declaration that ends at `brace` starts: after the previous ; } { or directive."""
    start = max(code.rfind(c, 0, brace) for c in ";{}")
    directive = code.rfind("\n#", 0, brace)
    if directive > start:
        start = code.find("\n", directive + 1)
    return start + 1


def _blank_comments_and_strings(text: str) -> str:
    """The text with comments, string and character literals replaced by spaces (newlines kept)."""
    pattern = re.compile(r'//[^\n]*|/\*.*?\*/|"(?:\\.|[^"\\\n])*"|\'(?:\\.|[^\'\\\n])*\'', re.S)
    return pattern.sub(lambda m: re.sub(r"[^\n]", " ", m.group(0)), text)


def global_functions(text: str) -> list[tuple[int, str]]:
    """(line, prototype) of every function defined at global scope, as the builder's ctags
    pass keeps them: functions inside a namespace, class or struct get no prototype."""
    code = _blank_comments_and_strings(text)
    found = []
    scopes: list[str] = []
    for m in re.finditer(r"[{}]", code):
        if m.group(0) == "}":
            if scopes:
                scopes.pop()
            continue
        head_start = _signature_start(code, m.start())
        head = code[head_start:m.start()]
        words = head.split()
        if re.search(r"\bnamespace\b", head):
            scopes.append("namespace")
        elif re.search(r"\b(class|struct|union|enum)\b", head) and "(" not in head:
            scopes.append("type")
        elif (not scopes and re.search(r"\)\s*(const\s*)?$", head) and words
              and words[0] not in ("if", "for", "while", "switch")):
            first_char = head_start + len(head) - len(head.lstrip())
            found.append((code.count("\n", 0, first_char) + 1, " ".join(words) + ";"))
            scopes.append("function")
        else:
            scopes.append("block")
    return found


def preprocess_sketch(ino: Path) -> str:
    """The .ino as the Arduino builder hands it to the compiler (sketch.ino.cpp)."""
    text = ino.read_text()
    functions = global_functions(text)
    quoted = str(ino).replace("\\", "\\\\")
    out = ["#include <Arduino.h>", f'#line 1 "{quoted}"']
    lines = text.splitlines()
    insert_at = functions[0][0] if functions else len(lines) + 1
    out += lines[: insert_at - 1]
    out += [proto for _, proto in functions]
    out.append(f'#line {insert_at} "{quoted}"')
    out += lines[insert_at - 1:]
    return "\n".join(out) + "\n"


@dataclass(frozen=True)
class BuildResult:
    objects: list[Path]
    diagnostics: dict[Path, str]  # compiler output of each source that said anything

    def our_diagnostics(self, sketch_copy: Path) -> list[str]:
        """Warnings and errors located in the sketch (its copy) rather than in vendored code."""
        found = []
        for output in self.diagnostics.values():
            for m in DIAGNOSTIC.finditer(output):
                path = Path(m.group("path"))
                if sketch_copy in path.parents or SKETCH_DIR in path.parents or path.suffix == ".ino":
                    found.append(m.group(0))
        return found


def build_sketch(core: str, workdir: Path, jobs: int = 2) -> tuple[BuildResult, Path]:
    """Copies the sketch folder to workdir (as the builder does), preprocesses the .ino and
    compiles it and every .cpp under src/ to objects. Fails the test on a compiler error."""
    if shutil.which("arm-none-eabi-g++") is None:
        pytest.skip("not installed: arm-none-eabi-g++ (Debian gcc-arm-none-eabi)")
    build = CoreBuild(core)
    sketch = workdir / "sketch"
    shutil.copytree(SKETCH_DIR, sketch)
    ino_cpp = sketch / "cubecam.ino.cpp"
    ino_cpp.write_text(preprocess_sketch(SKETCH_DIR / "cubecam.ino"))
    sources = [ino_cpp, *sorted((sketch / "src").rglob("*.cpp"))]
    objects = [workdir / "obj" / (str(s.relative_to(sketch)).replace("/", "_") + ".o") for s in sources]
    objects[0].parent.mkdir(parents=True, exist_ok=True)

    def run(pair: tuple[Path, Path]) -> tuple[Path, subprocess.CompletedProcess[str]]:
        source, obj = pair
        return source, subprocess.run(build.compile_command(source, obj), capture_output=True, text=True)

    with ThreadPoolExecutor(max_workers=jobs) as pool:
        results = list(pool.map(run, zip(sources, objects, strict=True)))
    failed = [f"{s}:\n{r.stderr[-4000:]}" for s, r in results if r.returncode != 0]
    if failed:
        pytest.fail(f"{core}: compile errors\n" + "\n".join(failed))
    diagnostics = {s: r.stderr for s, r in results if r.stderr.strip()}
    return BuildResult(objects, diagnostics), sketch
