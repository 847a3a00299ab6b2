"""Every dotted name the code's comments and the docs point at exists.

A reference is ``cubetrack.x.y`` or ``cubecam.x.y`` anywhere in the Python sources of host/ and tools/
or in README.md and docs/*.md, or a name quoted in backticks that starts with one of cubetrack's
folders (``app.tracker.Tracker``: relative to the package). Each must import and resolve attribute by
attribute (a dataclass field or an annotated attribute counts). File names (``cubetrack.toml``) and
the format tags in NOT_NAMES are not references.

In the Python sources a Sphinx role with a short target (:func:`name`, :meth:`Class.method`,
:attr:`sock`) is a reference too, relative to its module: a name of the module (attribute by
attribute after it), or a member of a class the module defines (an attribute, an annotation, or a
``self.<name> =`` assignment in the module).
"""

import ast
import dataclasses
import importlib
import inspect
import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
PACKAGES = ("cubetrack", "cubecam")
FOLDERS = sorted(p.name for p in (ROOT / "host" / "cubetrack").iterdir() if (p / "__init__.py").exists())
NAME = r"[A-Za-z_][A-Za-z0-9_]*"
ABSOLUTE = re.compile(rf"(?<![\w./-])(?:{'|'.join(PACKAGES)})(?:\.{NAME})+")
RELATIVE = re.compile(rf"`+((?:{'|'.join(FOLDERS)})(?:\.{NAME})+)(?:\(\))?`+")
ROLE = re.compile(rf":(?:func|class|meth|attr|data|mod|exc|obj|const):`~?\.?({NAME}(?:\.{NAME})*)`")
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
    return [*sources, ROOT / "README.md", *sorted((ROOT / "docs").rglob("*.md"))]


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


def module_name(path: Path) -> str:
    """The dotted module name of a source file under host/ or tools/."""
    parts = path.relative_to(ROOT).with_suffix("").parts[1:]
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def short_references(text: str) -> set[str]:
    """The targets of the Sphinx roles in ``text`` that are not fully qualified."""
    return {m.group(1) for m in ROLE.finditer(text) if not m.group(1).startswith(tuple(p + "." for p in PACKAGES))}


def resolves_in_module(module: object, source: str, target: str) -> bool:
    """Whether the short ``target`` names something of ``module`` (whose text is ``source``)."""
    first, *rest = target.split(".")
    if hasattr(module, first):
        owner = getattr(module, first)
        for part in rest:
            if not has_member(owner, part):
                return False
            owner = getattr(owner, part, None)
        return True
    if rest:
        return False
    assigned = {node.attr for node in ast.walk(ast.parse(source))
                if isinstance(node, ast.Attribute) and isinstance(node.ctx, ast.Store)
                and isinstance(node.value, ast.Name) and node.value.id == "self"}
    classes = [c for c in vars(module).values() if inspect.isclass(c) and c.__module__ == module.__name__]
    return first in assigned or any(has_member(c, first) for c in classes)


def test_references_resolve():
    broken = sorted(f"{path.relative_to(ROOT)}: {name}" for path in texts()
                    for name in references(path.read_text(encoding="utf-8")) if not resolves(name))
    assert not broken, "references to names that do not exist:\n" + "\n".join(broken)


def test_short_references_in_docstrings_resolve():
    broken = []
    for path in texts():
        if path.suffix != ".py" or path.name == "__main__.py":  # __main__ runs its command
            continue
        source = path.read_text(encoding="utf-8")
        module = importlib.import_module(module_name(path))
        broken += [f"{path.relative_to(ROOT)}: {target}" for target in sorted(short_references(source))
                   if not resolves_in_module(module, source, target)]
    assert not broken, "short references to names their module does not have:\n" + "\n".join(broken)


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


def test_a_broken_short_reference_is_found():
    """The short check itself, on cubetrack.io.files: its own function, a missing one, an attribute
    its class sets on self, a method of a missing class; qualified names are left to the other test."""
    import cubetrack.io.files as module

    source = Path(module.__file__).read_text(encoding="utf-8")
    text = (":func:`atomic_write`, :func:`~.no_such_function`, :meth:`NoSuchClass.run`, "
            ":func:`cubetrack.io.files.atomic_write`")
    targets = short_references(text)
    assert targets == {"atomic_write", "no_such_function", "NoSuchClass.run"}
    assert {t for t in targets if not resolves_in_module(module, source, t)} == {"no_such_function",
                                                                                  "NoSuchClass.run"}
