"""Session-wide test set-up."""

from __future__ import annotations

import signal

import pytest


@pytest.fixture(autouse=True)
def _ctrl_c_delivered() -> None:
    """SIGINT as a terminal's Ctrl-C delivers it, before every test. A suite started in the
    background of a non-interactive shell (``.ci/run &``) inherits SIGINT ignored (bash ignores it
    in asynchronous commands), and so would every process the tests start, which keeps an ignored
    signal ignored (``nohup``); a test that sends SIGINT, as Ctrl-C does, then waits for an end
    that never comes (session 20's clean-clone run: the session test hung an xdist worker, seven
    e2e tests failed)."""
    if signal.getsignal(signal.SIGINT) is signal.SIG_IGN:
        signal.signal(signal.SIGINT, signal.default_int_handler)


def pytest_sessionstart(session: pytest.Session) -> None:
    """Compile every numba kernel a tracker uses (or load them from their on-disk cache: tests/install.sh
    runs ``cubetrack compile``) before any test runs: in a fresh checkout the first build compiles for a
    minute or more, which would otherwise fall on whichever test first starts a tracker, perhaps a
    subprocess with a deadline."""
    from cubetrack.app.kernels import compile_all

    compile_all()
