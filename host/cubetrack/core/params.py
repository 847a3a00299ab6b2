"""One loader and one writer for every stage's parameter dataclass.

Each stage defines a frozen dataclass whose fields carry their default and, in the field's
``metadata["doc"]``, their unit and meaning. A TOML table maps 1:1 onto the fields; unknown
keys and wrongly typed values are refused with a message naming the table and the key.

One validation rule: a params dataclass checks its values in ``__post_init__`` and refuses a
bad one with :class:`cubetrack.core.errors.ParamsError` (:func:`check` raises it); the loader
turns that into a one-line :class:`cubetrack.core.errors.ConfigError` naming where the value
came from (``<file>: [section]``, or a command-line option for :func:`params_with`).
"""

from __future__ import annotations

import dataclasses
import enum
import math
import tomllib
import types
import typing
from pathlib import Path
from typing import Any, TypeVar

from cubetrack.core.errors import ConfigError, CubetrackError, ParamsError

if typing.TYPE_CHECKING:
    from _typeshed import DataclassInstance

P = TypeVar("P", bound="DataclassInstance")  # a params dataclass


def param(default: Any, doc: str) -> Any:
    """A dataclass field with its default and its documentation (unit, range, meaning)."""
    return dataclasses.field(default=default, metadata={"doc": doc})


def check(condition: bool, message: str) -> None:
    """Refuse a parameter value: raise :class:`ParamsError` with ``message`` unless ``condition``.
    For ``__post_init__`` of params dataclasses."""
    if not condition:
        raise ParamsError(message)


def check_positive(params: Any, *names: str, unit: str = "") -> None:
    """Refuse any of the fields ``names`` of ``params`` that is not a positive number (with a
    ``unit``, e.g. "seconds": also finite, and the message names the unit)."""
    for name in names:
        value = getattr(params, name)
        if unit:
            check(_finite(value) and value > 0, f"{name} must be a positive number of {unit}, got {value!r}")
        else:
            check(value > 0, f"{name} must be positive, got {value}")


def check_non_negative(params: Any, *names: str, unit: str = "") -> None:
    """Refuse any of the fields ``names`` of ``params`` that is negative (with a ``unit``, e.g.
    "seconds": also one that is not finite, and the message names the unit)."""
    for name in names:
        value = getattr(params, name)
        if unit:
            check(_finite(value) and value >= 0, f"{name} must be a non-negative number of {unit}, got {value}")
        else:
            check(value >= 0, f"{name} must not be negative, got {value}")


def check_between(params: Any, low: float, high: float, *names: str) -> None:
    """Refuse any of the fields ``names`` of ``params`` outside [``low``, ``high``]."""
    for name in names:
        value = getattr(params, name)
        check(low <= value <= high, f"{name} must be between {low:g} and {high:g}, got {value}")


def check_finite(params: Any) -> None:
    """Refuse a float field that is not finite, or a tuple field holding anything but finite numbers."""
    for f in dataclasses.fields(params):
        value = getattr(params, f.name)
        if isinstance(value, float):
            check(math.isfinite(value), f"{f.name} must be a finite number, got {value}")
        elif isinstance(value, tuple):
            check(all(_finite(x) for x in value), f"{f.name} must be a list of finite numbers, got {value}")


def check_at_least(params: Any, minimum: int, *names: str) -> None:
    """Refuse any of the fields ``names`` of ``params`` below ``minimum``."""
    for name in names:
        value = getattr(params, name)
        check(value >= minimum, f"{name} must be at least {minimum}, got {value}")


def _finite(value: Any) -> bool:
    return isinstance(value, (int, float)) and math.isfinite(value)


def _coerce(value: Any, annotation: Any, where: str) -> Any:
    origin = typing.get_origin(annotation)
    if origin in (typing.Union, types.UnionType):
        options = typing.get_args(annotation)
        if value is None and type(None) in options:
            return None
        for option in options:
            if option is type(None):
                continue
            try:
                return _coerce(value, option, where)
            except ConfigError:
                continue
        raise ConfigError(f"{where}: {value!r} is not one of {annotation}")
    if origin is tuple:
        if not isinstance(value, (list, tuple)):
            raise ConfigError(f"{where}: expected a list, got {value!r}")
        args = typing.get_args(annotation)
        item = args[0] if args else Any
        return tuple(_coerce(v, item, where) for v in value)
    if isinstance(annotation, type) and issubclass(annotation, enum.Enum):
        try:
            return annotation(value)
        except ValueError:
            choices = ", ".join(repr(m.value) for m in annotation)
            raise ConfigError(f"{where}: {value!r} is not one of {choices}") from None
    if annotation is bool:
        if not isinstance(value, bool):
            raise ConfigError(f"{where}: expected true or false, got {value!r}")
        return value
    if annotation is int:
        if isinstance(value, bool) or not isinstance(value, int):
            raise ConfigError(f"{where}: expected an integer, got {value!r}")
        return value
    if annotation is float:
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise ConfigError(f"{where}: expected a number, got {value!r}")
        return float(value)
    if annotation is str:
        if not isinstance(value, str):
            raise ConfigError(f"{where}: expected a string, got {value!r}")
        return value
    return value


def read_toml(path: str | Path, what: str) -> dict[str, Any]:
    """Read a TOML file; ConfigError naming ``path`` and ``what`` it should be (e.g. "cube
    layout") when it is missing, unreadable or not TOML."""
    path = Path(path)
    try:
        return tomllib.loads(path.read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise ConfigError(f"{path}: {what} file not found") from None
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as exc:
        raise ConfigError(f"{path}: not valid TOML: {exc}") from None
    except RecursionError:
        raise ConfigError(f"{path}: not valid TOML: nested too deeply") from None
    except OSError as exc:
        raise ConfigError(f"{path}: cannot read the {what}: {exc.strerror or exc}") from None


def params_from_table(cls: type[P], table: dict[str, Any] | None, where: str) -> P:
    """Build the params dataclass ``cls`` from a TOML table; ``where`` names it in errors."""
    table = dict(table or {})
    hints = typing.get_type_hints(cls)
    names = {f.name for f in dataclasses.fields(cls)}
    unknown = sorted(set(table) - names)
    if unknown:
        raise ConfigError(
            f"{where}: unknown key(s) {', '.join(unknown)}; valid keys: {', '.join(sorted(names))}"
        )
    values = {k: _coerce(v, hints[k], f"{where}.{k}") for k, v in table.items()}
    return _build(lambda: cls(**values), where)


def params_with(params: P, where: str, **values: Any) -> P:
    """``params`` with some fields replaced, each value checked as the loader checks a table's
    (``where`` names the source in errors, e.g. ``"--fusion"``); the other fields are kept."""
    hints = typing.get_type_hints(type(params))
    names = {f.name for f in dataclasses.fields(params)}
    unknown = sorted(set(values) - names)
    if unknown:
        raise ConfigError(f"{where}: unknown key(s) {', '.join(unknown)}; valid keys: {', '.join(sorted(names))}")
    coerced = {k: _coerce(v, hints[k], where) for k, v in values.items()}
    return _build(lambda: dataclasses.replace(params, **coerced), where)


def _build(make: typing.Callable[[], P], where: str) -> P:
    """Run ``make`` (a params constructor); its refusal becomes one line naming ``where``."""
    try:
        return make()
    except (CubetrackError, TypeError, ValueError) as exc:
        raise ConfigError(f"{where}: {exc}") from None


def params_to_table(params: Any) -> dict[str, Any]:
    """The TOML table of a params dataclass (enums by value, tuples as lists)."""
    out: dict[str, Any] = {}
    for f in dataclasses.fields(params):
        value = getattr(params, f.name)
        if isinstance(value, enum.Enum):
            value = value.value
        elif isinstance(value, tuple):
            value = [v.value if isinstance(v, enum.Enum) else v for v in value]
        if value is not None:
            out[f.name] = value
    return out


def params_to_commented_toml(section: str, params: Any) -> str:
    """A TOML table of ``params`` with each field's documentation as a comment above it."""
    import tomli_w  # only this helper writes TOML

    lines = [f"[{section}]"]
    table = params_to_table(params)
    for f in dataclasses.fields(params):
        doc = f.metadata.get("doc", "")
        if doc:
            lines.append(f"# {doc}")
        if f.name in table:
            lines.append(tomli_w.dumps({f.name: table[f.name]}).strip())
        else:
            lines.append(f"# {f.name} = (unset)")
    return "\n".join(lines) + "\n"
