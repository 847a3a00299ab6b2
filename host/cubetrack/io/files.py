"""Writing a file so that it is either the old one or the whole new one, never half written."""

from __future__ import annotations

import os
from pathlib import Path


def atomic_write(path: str | Path, data: bytes | str) -> None:
    """Write ``data`` (bytes, or text as UTF-8) to ``path`` through a ``.part`` file in the same
    folder that then replaces ``path``: a crash leaves the previous file intact."""
    path = Path(path)
    tmp = path.with_name(path.name + ".part")
    if isinstance(data, str):
        data = data.encode("utf-8")
    try:
        with open(tmp, "wb") as f:
            f.write(data)
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)
