"""The host package's imports go one way only (docs/developing.md): checked on the source."""

import ast
from pathlib import Path

import pytest

PACKAGE = Path(__file__).resolve().parents[2] / "host" / "cubetrack"

BASE = {"errors", "geometry", "params", "progress", "records", "layout"}
IO = {"io"}
PIPELINE = ["timesync", "source", "detect", "estimate", "calibrate", "joint", "filter", "refine", "fuse", "sink", "pipeline"]


def rank(module: str) -> int:
    """Higher rank may import lower rank, never the reverse."""
    top = module.split(".")[0]
    if top in BASE:
        return 0
    if top in IO:
        return 1
    if top in PIPELINE:
        return 2 + PIPELINE.index(top)
    if top == "intrinsics":
        return 2 + PIPELINE.index("detect") + 1
    if top in ("simulate", "evaluate", "plot"):
        return 2  # beside the pipeline: base + io only (checked separately)
    if top == "live":
        return 2 + len(PIPELINE)  # feeds live sources to the pipeline
    if top == "demo":
        return 90  # an orchestration of whole commands, used by the CLI only
    if top == "cli":
        return 100
    return 50


def imports_of(path: Path) -> set[str]:
    tree = ast.parse(path.read_text(encoding="utf-8"))
    found = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.ImportFrom) and node.module and node.module.startswith("cubetrack."):
            found.add(node.module.removeprefix("cubetrack."))
        elif isinstance(node, ast.Import):
            for alias in node.names:
                if alias.name.startswith("cubetrack."):
                    found.add(alias.name.removeprefix("cubetrack."))
    return found


def modules():
    for path in sorted(PACKAGE.rglob("*.py")):
        rel = path.relative_to(PACKAGE).with_suffix("")
        name = ".".join(p for p in rel.parts if p != "__init__") or "__init__"
        yield name, path


@pytest.mark.parametrize("name,path", list(modules()), ids=lambda v: str(v) if isinstance(v, str) else "")
def test_imports_go_downstream_only(name, path):
    if name == "__init__":
        return
    mine = rank(name)
    for imported in imports_of(path):
        if imported.split(".")[0] == name.split(".")[0]:
            continue  # inside one package (e.g. io.config -> io.recording)
        assert rank(imported) <= mine, f"{name} (rank {mine}) imports {imported} (rank {rank(imported)})"
        assert not imported.startswith("cli"), f"{name} imports the CLI"


@pytest.mark.parametrize("side", ["simulate", "evaluate"])
def test_side_modules_use_only_base_and_io(side):
    paths = [p for n, p in modules() if n.split(".")[0] == side]
    assert paths, f"no module {side}"
    for path in paths:
        for imported in imports_of(path):
            top = imported.split(".")[0]
            assert top in BASE | IO | {side}, f"{path.name} imports {imported}"
