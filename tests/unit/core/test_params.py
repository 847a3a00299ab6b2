import ast
import enum
from dataclasses import dataclass
from pathlib import Path

import pytest

from cubetrack.core.errors import ConfigError, ParamsError
from cubetrack.core.params import check, check_positive, param, params_from_table, params_to_table, params_with


class Mode(enum.Enum):
    A = "a"
    B = "b"


@dataclass(frozen=True)
class P:
    mode: Mode = param(Mode.A, "mode")
    rate_hz: float = param(1.0, "Hz")
    count: int = param(3, "n")
    flag: bool = param(False, "flag")
    ids: tuple[int, ...] = param((1, 2), "ids")


def test_table_round_trip():
    p = params_from_table(P, {"mode": "b", "rate_hz": 2, "ids": [4]}, "[x]")
    assert p == P(Mode.B, 2.0, 3, False, (4,))
    assert params_from_table(P, params_to_table(p), "[x]") == p


@pytest.mark.parametrize("table,match", [
    ({"bogus": 1}, r"\[x\]: unknown key\(s\) bogus"),
    ({"mode": "c"}, r"\[x\]\.mode: 'c' is not one of 'a', 'b'"),
    ({"count": 1.5}, "expected an integer"),
    ({"flag": 1}, "expected true or false"),
    ({"rate_hz": "fast"}, "expected a number"),
])
def test_bad_values_are_refused_with_the_key(table, match):
    with pytest.raises(ConfigError, match=match):
        params_from_table(P, table, "[x]")


@dataclass(frozen=True)
class Checked:
    rate_hz: float = param(1.0, "Hz")
    count: int = param(3, "n")

    def __post_init__(self):
        check_positive(self, "rate_hz")
        check(self.count >= 1, f"count must be at least 1, got {self.count}")


def test_a_refused_value_is_a_params_error_and_one_config_line_naming_the_source():
    with pytest.raises(ParamsError, match="rate_hz must be positive, got -1"):
        Checked(rate_hz=-1.0)
    assert issubclass(ParamsError, ConfigError) and issubclass(ParamsError, ValueError)
    with pytest.raises(ConfigError, match=r"^lab\.toml: \[x\]: count must be at least 1, got 0$") as exc:
        params_from_table(Checked, {"count": 0}, "lab.toml: [x]")
    assert type(exc.value) is ConfigError and "\n" not in str(exc.value)


def test_params_with_replaces_some_fields_checked_like_the_loader():
    p = params_from_table(P, {"count": 7, "flag": True}, "[x]")
    q = params_with(p, "--mode", mode="b")
    assert (q.mode, q.count, q.flag) == (Mode.B, 7, True)  # the other fields are kept
    with pytest.raises(ConfigError, match=r"^--mode: 'c' is not one of 'a', 'b'$"):
        params_with(p, "--mode", mode="c")
    with pytest.raises(ConfigError, match="--x: unknown key"):
        params_with(p, "--x", bogus=1)
    with pytest.raises(ConfigError, match=r"^--count: count must be at least 1"):
        params_with(Checked(), "--count", count=0)


PACKAGE = Path(__file__).resolve().parents[3] / "host" / "cubetrack"
# Not yet on the rule (their owners convert them): the outputs' parameters (issue 10) are checked
# when the output opens.
NOT_YET = {"FoxgloveParams", "VrpnParams", "ZenohJsonParams", "Ros2Params"}


def _params_classes():
    for path in sorted(PACKAGE.rglob("*.py")):
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
            if isinstance(node, ast.ClassDef) and node.name.endswith("Params") and node.name not in NOT_YET:
                yield path.relative_to(PACKAGE), node


def _composite(node: ast.ClassDef) -> bool:
    """A class whose fields are all params dataclasses (StageParams, ConfigParams): nothing to check."""
    fields = [n for n in node.body if isinstance(n, ast.AnnAssign)]
    return bool(fields) and all(ast.unparse(f.annotation).endswith("Params") for f in fields)


def test_every_params_dataclass_validates_in_post_init_with_params_error():
    """One validation rule: each params dataclass checks its values in __post_init__ (or helpers it
    calls) through the check helpers of cubetrack.core.params only, which raise ParamsError: no
    raise of its own (fuse/fusion.py, corner_filter.py, source/streams.py and simulate/params.py
    each raised by hand, SimulationParams its own SimulationError; IntrinsicsParams, DetectorParams,
    EstimatorParams and ClockSyncParams raised ParamsError by hand: none does now). A subclass of a
    params class may inherit its __post_init__."""
    found, bad = [], []
    for path, node in _params_classes():
        if _composite(node):
            continue
        found.append(node.name)
        post = next((f for f in node.body if isinstance(f, ast.FunctionDef) and f.name == "__post_init__"), None)
        if post is None and not any(ast.unparse(b).endswith("Params") for b in node.bases):
            bad.append(f"{path}: {node.name} has no __post_init__")  # (a subclass may inherit its base's)
            continue
        methods = [f for f in node.body if isinstance(f, ast.FunctionDef) and f.name.startswith("_check")]
        for function in (f for f in (post, *methods) if f is not None):
            for r in (n for n in ast.walk(function) if isinstance(n, ast.Raise)):
                bad.append(f"{path}: {node.name}.{function.name} raises {ast.unparse(r.exc) if r.exc else ''} "
                           "itself (use cubetrack.core.params.check*)")
    assert {"CalibrationParams", "BundleAdjustmentParams", "DetectorParams", "TrackParams", "SimulationParams",
            "FusionParams", "FilterParams", "SourceParams", "IntrinsicsParams", "EstimatorParams", "ClockSyncParams",
            "VrpnOutputParams", "McapOutputParams"} <= set(found)
    assert bad == []
