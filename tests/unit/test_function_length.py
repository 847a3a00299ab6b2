"""No function in host/ or tools/ is longer than 80 lines (from its ``def`` to its last line, docstring
included; a nested function counts on its own and inside its parent), except the few listed below,
each with the reason it is still long. An entry that is no longer needed fails too: the list shrinks.
"""

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
MAX_LINES = 80

# "path:qualified name" -> why it is still longer than MAX_LINES
ALLOWED = {
}


def function_lengths(path: Path) -> dict[str, int]:
    """Each function's (and method's) qualified name in ``path`` -> its length in lines."""
    lengths: dict[str, int] = {}

    def visit(node: ast.AST, prefix: str) -> None:
        for child in ast.iter_child_nodes(node):
            if isinstance(child, ast.FunctionDef | ast.AsyncFunctionDef):
                name = prefix + child.name
                lengths[name] = (child.end_lineno or child.lineno) - child.lineno + 1
                visit(child, name + ".")
            elif isinstance(child, ast.ClassDef):
                visit(child, prefix + child.name + ".")
            else:
                visit(child, prefix)

    visit(ast.parse(path.read_text(encoding="utf-8")), "")
    return lengths


def long_functions() -> dict[str, int]:
    """``path:name`` -> length of every function in host/ and tools/ longer than MAX_LINES."""
    found = {}
    for path in sorted((ROOT / "host").rglob("*.py")) + sorted((ROOT / "tools").rglob("*.py")):
        for name, lines in function_lengths(path).items():
            if lines > MAX_LINES:
                found[f"{path.relative_to(ROOT)}:{name}"] = lines
    return found


def test_no_function_is_longer_than_80_lines():
    found = long_functions()
    too_long = {name: lines for name, lines in found.items() if name not in ALLOWED}
    assert not too_long, f"functions longer than {MAX_LINES} lines (split them): {too_long}"
    stale = sorted(set(ALLOWED) - set(found))
    assert not stale, f"no longer longer than {MAX_LINES} lines, remove from ALLOWED: {stale}"


def test_lengths_count_def_to_last_line(tmp_path):
    """The measure itself: a method and a nested function are named by their owners and measured
    from ``def`` to their last line."""
    body = "\n".join(f"        x{i} = {i}" for i in range(MAX_LINES))
    source = (f"class A:\n    def long(self):\n        def inner():\n            pass\n{body}\n\n"
              "def short():\n    pass\n")
    path = tmp_path / "m.py"
    path.write_text(source)
    assert function_lengths(path) == {"A.long": MAX_LINES + 3, "A.long.inner": 2, "short": 2}
