"""Session-wide test set-up."""

from __future__ import annotations

import pytest


def pytest_sessionstart(session: pytest.Session) -> None:
    """Compile the detector's and the filter's numba kernels (or load them from their on-disk cache) before any
    test runs: in a fresh checkout the first build compiles for 10-30 s, which would otherwise
    fall on whichever test first starts a tracker, perhaps a subprocess with a deadline."""
    from cubetrack.detect.edge_fit import compile_edge_fit
    from cubetrack.detect.template_fit import compile_template_fit
    from cubetrack.fuse.filter_kernels import compile_filter_kernels

    compile_edge_fit()
    compile_template_fit()
    compile_filter_kernels()
