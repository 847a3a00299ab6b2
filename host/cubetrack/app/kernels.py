"""Every numba kernel the live path and the replay use, compiled into numba's on-disk cache ahead
of the first frame (``cubetrack compile``, run after installing), so that no tracker start pays it.

Where the cache lives is numba's choice, made when a module's kernels are defined: under
``NUMBA_CACHE_DIR`` when it is set; else in ``__pycache__`` beside the sources when that folder is
writable (an editable install, a virtual environment the user owns); else in the user's own cache
(``~/.cache/numba``, e.g. for a read-only ``site-packages``). A cache is used only by a process
that finds the same folder: run ``cubetrack compile`` as the user who tracks, with the same
``NUMBA_CACHE_DIR`` (docs/live.md "Compiled kernels").
"""

from __future__ import annotations

import sys
import time
from collections.abc import Callable
from dataclasses import dataclass

from numba.core.dispatcher import Dispatcher

from cubetrack.core.progress import Progress
from cubetrack.detect.detector import compile_quad_checks, no_cold_cache_warning
from cubetrack.detect.edge_fit import compile_edge_fit
from cubetrack.detect.predicted import compile_cell_reader
from cubetrack.detect.template_fit import compile_template_fit
from cubetrack.fuse.filter_kernels import compile_filter_kernels

KERNEL_GROUPS: tuple[tuple[str, Callable[[], None]], ...] = (
    ("quad checks", compile_quad_checks),
    ("edge fit", compile_edge_fit),
    ("cell reader", compile_cell_reader),
    ("template fit", compile_template_fit),
    ("filter's and association's kernels", compile_filter_kernels),
)
"""What a tracker compiles before its first frame or sighting, by what it is for: the detector's
(every corner refinement's) and the fusion's."""


@dataclass(frozen=True, slots=True)
class CompiledGroup:
    """One of ``KERNEL_GROUPS`` made ready: how many kernel signatures numba compiled and how many
    it loaded from its cache (a kernel another group made ready counts in neither)."""

    name: str
    compiled: int
    loaded: int
    time_s: float


@dataclass(frozen=True, slots=True)
class CompiledKernels:
    """What :func:`compile_all` did, and the folders numba's cache of them is in."""

    groups: tuple[CompiledGroup, ...]
    cache_dirs: tuple[str, ...]

    @property
    def compiled(self) -> int:
        return sum(g.compiled for g in self.groups)

    @property
    def loaded(self) -> int:
        return sum(g.loaded for g in self.groups)


def kernels() -> list[Dispatcher]:
    """The numba kernels of every cubetrack module imported so far (each once)."""
    found = {id(v): v for name, module in list(sys.modules.items()) if name.startswith("cubetrack.")
             for v in vars(module).values() if isinstance(v, Dispatcher)}
    return list(found.values())


def _counts() -> tuple[int, int]:
    """Signatures compiled, and loaded from numba's cache, by this process's cubetrack kernels."""
    stats = [k.stats for k in kernels()]
    return sum(sum(s.cache_misses.values()) for s in stats), sum(sum(s.cache_hits.values()) for s in stats)


def compile_all(progress: Progress | None = None) -> CompiledKernels:
    """Compile every group of ``KERNEL_GROUPS`` into numba's cache (or load it from there), in
    order; ``progress(stage, done, total)`` before each. Whatever numba raises comes through."""
    no_cold_cache_warning()  # this is the compile the warning asks for
    groups = []
    for done, (name, compile_group) in enumerate(KERNEL_GROUPS):
        if progress is not None:
            progress(f"compiling the {name}", done, len(KERNEL_GROUPS))
        (compiled, loaded), started_s = _counts(), time.perf_counter()
        compile_group()
        now_compiled, now_loaded = _counts()
        groups.append(CompiledGroup(name, now_compiled - compiled, now_loaded - loaded,
                                    time.perf_counter() - started_s))
    dirs = {path for k in kernels() if k.signatures and (path := k.stats.cache_path) is not None}
    return CompiledKernels(tuple(groups), tuple(sorted(dirs)))
