"""Compile every numba kernel the tracker uses (the corner fits of every refinement, the filter's
and the association's) into numba's on-disk cache, so that the first ``track`` or live session
after an install starts at once instead of compiling for a minute or two (more on a busy
machine). Run it once after installing or upgrading, as the user who tracks; again it only loads
what is cached (seconds). The cache is where numba puts it: under NUMBA_CACHE_DIR if set, else
in __pycache__ beside the sources if writable, else in ~/.cache/numba (docs/live.md "Compiled kernels").

Example:
  pip install cubetrack && cubetrack compile
  NUMBA_CACHE_DIR=/var/cache/cubetrack cubetrack compile   # a read-only install: track with the same NUMBA_CACHE_DIR
"""

from __future__ import annotations

import argparse
import os

HELP = "compile the tracker's numba kernels into numba's cache (once after installing or upgrading)"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    pass


def run(args: argparse.Namespace) -> int:
    from cubetrack.core.errors import NO_NUMBA_CACHE_FOLDER, CubetrackError, caused_by_interrupt, no_numba_cache_folder
    from cubetrack.core.progress import StderrProgress

    try:  # importing the kernels' modules too: numba picks their cache folder then, and fails with no writable one
        from cubetrack.app.kernels import compile_all

        done = compile_all(StderrProgress())
    except Exception as exc:  # numba's own errors (typing, LLVM, no cache folder): one line, exit 1
        if caused_by_interrupt(exc):
            raise KeyboardInterrupt from None
        hint = f"; {NO_NUMBA_CACHE_FOLDER}" if no_numba_cache_folder(exc) else ""
        raise CubetrackError(f"numba failed: {type(exc).__name__}: {str(exc).strip().splitlines()[0]}{hint}") from exc
    for g in done.groups:
        print(f"{g.name}: {g.compiled} compiled, {g.loaded} loaded from the cache, {g.time_s:.1f} s")
    print(f"numba's cache: {os.path.commonpath(done.cache_dirs) if done.cache_dirs else 'none'}")
    return 0
