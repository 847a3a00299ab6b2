"""Progress reporting for long work, as a callback the library calls and the CLI prints.

Library functions take ``progress: Progress | None``; they never print themselves.
"""

from __future__ import annotations

import sys
import time
from collections.abc import Callable
from typing import TextIO

Progress = Callable[[str, int, int], None]
"""``progress(stage, done, total)``; ``total`` may be 0 when unknown."""


class StderrProgress:
    """Prints ``stage: done/total`` to ``stream`` (default: the ``sys.stderr`` of the moment it
    prints) at most every ``interval_s`` seconds, and once at the end."""

    def __init__(self, stream: TextIO | None = None, interval_s: float = 1.0):
        self.stream = stream
        self.interval_s = interval_s
        self._last: dict[str, float] = {}

    def __call__(self, stage: str, done: int, total: int) -> None:
        now = time.monotonic()
        finished = total > 0 and done >= total
        if not finished and now - self._last.get(stage, -1e9) < self.interval_s:
            return
        self._last[stage] = now
        of = f"/{total}" if total else ""
        pct = f" ({100.0 * done / total:.0f}%)" if total else ""
        stream = self.stream if self.stream is not None else sys.stderr
        stream.write(f"{stage}: {done}{of}{pct}\n")
        stream.flush()
