"""Writing files so that a crash or a full disk never leaves half of something: a whole file
is either the old one or the whole new one (:func:`atomic_write`); a log of lines holds whole
lines only (:class:`LineFile`)."""

from __future__ import annotations

import contextlib
import os
from collections.abc import Iterator
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


@contextlib.contextmanager
def os_errors_as(error: type[Exception], path: str | Path) -> Iterator[None]:
    """An ``OSError`` inside (a full disk, a folder that cannot be made) becomes ``error`` with
    one line naming ``path`` and what the system said, e.g. ``No space left on device``."""
    try:
        yield
    except OSError as exc:
        raise error(cannot_write(path, exc)) from None


def cannot_write(path: str | Path, exc: OSError) -> str:
    """The one line :func:`os_errors_as` says for ``exc`` writing ``path``."""
    return f"{path}: cannot write: {exc.strerror or exc}"


class LineFile:
    """A new text file written one whole line at a time, for files that grow while a session
    runs (index rows, poses). The file appears with its ``header`` line whole (through
    :func:`atomic_write`); then each line goes to the operating system in one ``write`` call,
    with no buffer in this process, so a killed process leaves every line it had written and
    nothing of the next; a line the disk cannot take whole (full disk, quota) is cut off again
    before the ``OSError`` is raised, so the file still ends with a whole line."""

    def __init__(self, path: str | Path, header: str | None = None):
        self.path = Path(path)
        first = "" if header is None else header + "\n"
        atomic_write(self.path, first)
        self._fd: int | None = os.open(self.path, os.O_WRONLY | os.O_APPEND)
        self._size = len(first.encode("utf-8"))

    def write_line(self, line: str) -> None:
        """Append ``line`` (text without its newline) and a newline."""
        if self._fd is None:
            raise ValueError(f"{self.path}: written after close")
        data = (line + "\n").encode("utf-8")
        try:
            done = 0
            while done < len(data):
                done += os.write(self._fd, data[done:])
        except OSError:
            with contextlib.suppress(OSError):  # the file may already be gone: the first error is the one to tell
                os.ftruncate(self._fd, self._size)
            raise
        self._size += len(data)

    def close(self) -> None:
        if self._fd is not None:
            os.close(self._fd)
            self._fd = None
