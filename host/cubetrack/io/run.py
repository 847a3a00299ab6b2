"""The run record (contracts §5): ``run.json`` beside what a command wrote, saying how it was made.

Every output of ``cubetrack track``, ``calibrate``, ``record``, ``simulate`` and ``demo`` gets one:
the software versions, the resolved parameters (every section, defaults filled in, as the
stages used them) and the inputs (absolute paths; files with their SHA-256), so a result can be
reproduced or compared. Written atomically. Layout::

    {"format": "cubetrack.run", "version": 1, "command": "track", "created": "<ISO 8601 UTC>",
     "versions": {"cubetrack": "0.1.0", "python": "3.11.9", "numpy": "...", "opencv": "..."},
     "parameters": {"detector": {...}, "fusion": {...}, ...},
     "inputs": {"config": {"path": "/abs/config.toml", "sha256": "..."},
                "recording": {"path": "/abs/rec"}, ...}}
"""

from __future__ import annotations

import hashlib
import json
import platform
import sys
from collections.abc import Mapping
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

from cubetrack.core.errors import ConfigError
from cubetrack.core.params import params_to_table
from cubetrack.io.files import atomic_write

FORMAT = "cubetrack.run"
VERSION = 1
RUN_FILE = "run.json"


def run_record_beside(file: str | Path) -> Path:
    """Where the run record of an output *file* goes: ``extrinsics.toml`` -> ``extrinsics.run.json``
    (an output folder's is ``<folder>/run.json``)."""
    return Path(file).with_suffix(".run.json")


def _versions() -> dict[str, str]:
    from cubetrack import __version__

    versions = {"cubetrack": __version__, "python": platform.python_version()}
    for name, module in (("numpy", "numpy"), ("opencv", "cv2"), ("scipy", "scipy")):
        loaded = sys.modules.get(module)  # only what this run actually used
        if loaded is not None and hasattr(loaded, "__version__"):
            versions[name] = str(loaded.__version__)
    return versions


def _input(path: str | Path) -> dict[str, str]:
    path = Path(path).resolve()
    entry = {"path": str(path)}
    if path.is_file():
        entry["sha256"] = hashlib.sha256(path.read_bytes()).hexdigest()
    return entry


def run_record(command: str, parameters: Mapping[str, Any], inputs: Mapping[str, str | Path | None],
               extra: Mapping[str, Any] | None = None) -> dict[str, Any]:
    """The run record document: ``parameters`` section name -> params dataclass (or a plain
    table); ``inputs`` name -> path (None: not used, left out)."""
    doc: dict[str, Any] = {
        "format": FORMAT,
        "version": VERSION,
        "command": command,
        "created": datetime.now(UTC).isoformat(timespec="seconds"),
        "versions": _versions(),
        "parameters": {name: p if isinstance(p, Mapping) else params_to_table(p) for name, p in parameters.items()},
        "inputs": {name: _input(path) for name, path in inputs.items() if path is not None},
    }
    doc.update(extra or {})
    return doc


def write_run_record(path: str | Path, command: str, parameters: Mapping[str, Any],
                     inputs: Mapping[str, str | Path | None], extra: Mapping[str, Any] | None = None) -> Path:
    """Write the run record to ``path`` (``<output folder>/run.json``, or
    :func:`run_record_beside` an output file), creating its folder; returns ``path``."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    atomic_write(path, json.dumps(run_record(command, parameters, inputs, extra), indent=2, default=str) + "\n")
    return path


def read_run_record(path: str | Path) -> dict[str, Any]:
    """Read a run record (a ``run.json`` or its folder)."""
    path = Path(path)
    if path.is_dir():
        path = path / RUN_FILE
    try:
        doc = json.loads(path.read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise ConfigError(f"{path}: run record not found") from None
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise ConfigError(f"{path}: not a run record: {exc}") from None
    if not isinstance(doc, dict) or doc.get("format") != FORMAT:
        raise ConfigError(f'{path}: not a run record ("format" must be "{FORMAT}")')
    return doc
