"""The host package's folders import one way only (docs/architecture.md): checked on the source.

Each folder of ``host/cubetrack`` may import the folders listed for it here and nothing else;
``cubetrack`` never imports ``cubecam`` (the device tools import the tracker, not the reverse).
"""

import ast
from pathlib import Path

import pytest

PACKAGE = Path(__file__).resolve().parents[2] / "host" / "cubetrack"

# folder -> the folders it may import (besides itself). The pipeline runs
# source -> detect -> estimate -> fuse -> sink; a stage imports only earlier stages. The stages
# that compute (source, detect, estimate, fuse) and calibration do not import io: they take
# typed values (core) and never read a file; the workflow layer (app) reads the files for them.
ALLOWED = {
    "core": set(),
    "io": {"core"},
    "source": {"core"},
    "detect": {"core"},
    "estimate": {"core", "detect"},
    "fuse": {"core", "detect", "estimate"},
    "sink": {"core", "io"},
    "calib": {"core", "source", "detect", "estimate", "fuse"},
    "evaluate": {"core", "io"},
    "simulate": {"core", "io"},
    "app": {"core", "io", "source", "detect", "estimate", "fuse", "sink", "calib", "evaluate", "simulate"},
    "cli": {"core", "io", "source", "detect", "estimate", "fuse", "sink", "calib", "evaluate", "simulate", "app"},
}


def imports_of(path: Path) -> set[str]:
    """Every module a file imports (absolute names), at any depth of the file."""
    tree = ast.parse(path.read_text(encoding="utf-8"))
    found = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.ImportFrom) and node.module:
            if node.level:
                raise AssertionError(f"{path}: relative import of {node.module!r}; import cubetrack.<folder> instead")
            found.add(node.module)
        elif isinstance(node, ast.Import):
            found.update(alias.name for alias in node.names)
    return found


def folder_of(path: Path) -> str:
    rel = path.relative_to(PACKAGE)
    return rel.parts[0] if len(rel.parts) > 1 else ""


SOURCES = sorted(PACKAGE.rglob("*.py"))


def test_every_module_sits_in_a_known_folder():
    loose = [p.name for p in SOURCES if folder_of(p) == "" and p.name != "__init__.py"]
    assert loose == [], f"modules outside the stage folders: {loose}"
    unknown = {folder_of(p) for p in SOURCES} - set(ALLOWED) - {""}
    assert unknown == set(), f"folders without an import rule in this test: {unknown}"


def violations(mine: str, names: set[str]) -> list[str]:
    """What a module of folder ``mine`` may not import among ``names``."""
    bad = []
    for name in sorted(names):
        parts = name.split(".")
        if parts[0] == "cubecam":
            bad.append(f"{name} (cubetrack never imports cubecam)")
        elif parts[0] == "cubetrack" and len(parts) > 1 and mine and parts[1] != mine \
                and parts[1] not in ALLOWED[mine]:
            bad.append(f"{name} ({mine}/ may import only {sorted(ALLOWED[mine])})")
    return bad


@pytest.mark.parametrize("path", SOURCES, ids=lambda p: str(p.relative_to(PACKAGE)))
def test_imports_follow_the_folder_map(path):
    assert violations(folder_of(path), imports_of(path)) == []


def test_the_map_itself_has_no_cycle():
    seen: dict[str, int] = {}

    def depth(folder: str, trail: tuple[str, ...] = ()) -> int:
        assert folder not in trail, f"import cycle in the map: {' -> '.join(trail + (folder,))}"
        if folder not in seen:
            seen[folder] = 1 + max((depth(d, trail + (folder,)) for d in ALLOWED[folder]), default=0)
        return seen[folder]

    for folder in ALLOWED:
        depth(folder)


def test_the_rule_catches_violations():
    """The check is not vacuous: a later stage, the CLI and cubecam are each refused."""
    assert violations("detect", {"cubetrack.core.errors", "cubetrack.detect.detector"}) == []
    assert len(violations("detect", {"cubetrack.fuse.fusion"})) == 1
    assert len(violations("fuse", {"cubetrack.sink.base"})) == 1
    assert len(violations("app", {"cubetrack.cli.command"})) == 1
    assert len(violations("app", {"cubecam.emulator"})) == 1
    assert len(violations("calib", {"cubetrack.io.recording"})) == 1  # calibration reads no file
    assert violations("", {"cubetrack.core.errors"}) == []
