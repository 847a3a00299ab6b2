"""Every dotted name the code's comments and the docs point at exists.

A reference is ``cubetrack.x.y`` or ``cubecam.x.y`` anywhere in the Python sources of host/ and tools/
or in README.md and docs/*.md, or a name quoted in backticks that starts with one of cubetrack's
folders (``app.tracker.Tracker``: relative to the package). Each must import and resolve attribute by
attribute (a dataclass field or an annotated attribute counts). File names (``cubetrack.toml``) and
the format tags in NOT_NAMES are not references.
"""

import dataclasses
import importlib
import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
PACKAGES = ("cubetrack", "cubecam")
FOLDERS = sorted(p.name for p in (ROOT / "host" / "cubetrack").iterdir() if (p / "__init__.py").exists())
NAME = r"[A-Za-z_][A-Za-z0-9_]*"
ABSOLUTE = re.compile(rf"(?<![\w./-])(?:{'|'.join(PACKAGES)})(?:\.{NAME})+")
RELATIVE = re.compile(rf"`+((?:{'|'.join(FOLDERS)})(?:\.{NAME})+)(?:\(\))?`+")
FILE_SUFFIXES = {"py", "ino", "toml", "json", "jsonl", "md", "txt", "yaml", "yml", "log", "csv", "tum", "svg", "pdf"}
# dotted strings that name something other than a Python object
NOT_NAMES = {
    "cubetrack.recording": "the format tag of recording.json (io/recording.py FORMAT)",
    "cubetrack.run": "the format tag of a run record (io/run.py FORMAT)",
    "cubetrack.CameraHealth": "the title of the Foxglove JSON schema of camera health (sink/foxglove.py)",
}


def texts() -> list[Path]:
    """The files whose references are checked."""
    sources = sorted((ROOT / "host").rglob("*.py")) + sorted((ROOT / "tools").rglob("*.py"))
    return [*sources, ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]


def references(text: str) -> set[str]:
    """The dotted names in ``text``, each fully qualified (``cubetrack.`` before a relative one)."""
    found = {m.group(0).rstrip(".") for m in ABSOLUTE.finditer(text)}
    found |= {f"cubetrack.{m.group(1)}" for m in RELATIVE.finditer(text)}
    return {name for name in found if name.rsplit(".", 1)[-1] not in FILE_SUFFIXES and name not in NOT_NAMES}


def has_member(owner: object, name: str) -> bool:
    """Whether ``owner`` (a module or a class) has ``name``: an attribute, a dataclass field or an
    annotated attribute of it or of a base class."""
    if hasattr(owner, name):
        return True
    if dataclasses.is_dataclass(owner) and name in {f.name for f in dataclasses.fields(owner)}:
        return True
    classes = getattr(owner, "__mro__", (owner,))
    return any(name in getattr(c, "__annotations__", {}) for c in classes)


def resolves(dotted: str) -> bool:
    """Whether ``dotted`` names a module, or a module's attribute (attribute by attribute)."""
    parts = dotted.split(".")
    for split in range(len(parts), 0, -1):
        try:
            owner: object = importlib.import_module(".".join(parts[:split]))
        except ModuleNotFoundError:
            continue
        for part in parts[split:]:
            if not has_member(owner, part):
                return False
            owner = getattr(owner, part, None)
        return True
    return False


def test_references_resolve():
    broken = sorted(f"{path.relative_to(ROOT)}: {name}" for path in texts()
                    for name in references(path.read_text(encoding="utf-8")) if not resolves(name))
    assert not broken, "references to names that do not exist:\n" + "\n".join(broken)


def test_a_broken_reference_is_found():
    """The check itself: an absolute and a relative reference to a missing name fail, existing ones
    pass, file names are skipped."""
    text = ("see :func:`cubetrack.app.tracker.no_such_function` and ``detect.nowhere``, "
            "``cubetrack.core.errors.CubetrackError``, `cubecam.cli.main`, cubetrack.toml")
    names = references(text)
    assert names == {"cubetrack.app.tracker.no_such_function", "cubetrack.detect.nowhere",
                     "cubetrack.core.errors.CubetrackError", "cubecam.cli.main"}
    assert {n for n in names if not resolves(n)} == {"cubetrack.app.tracker.no_such_function",
                                                     "cubetrack.detect.nowhere"}
