"""The one CLI error boundary (cli/command.py run_command): known errors exit 1 with one line,
an interrupt exits 130 even when a C extension wrapped it, anything else is a bug (exit 2)."""

from __future__ import annotations

import argparse
from collections.abc import Callable

import pytest

from cubetrack.cli.command import run_command
from cubetrack.core.errors import CubetrackError


def _parser(run: Callable[[argparse.Namespace], int]) -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="cubetrack")
    parser.add_argument("-v", "--verbose", action="count", default=0)
    sub = parser.add_subparsers(dest="command", required=True)
    sub.add_parser("probe").set_defaults(_run=run)
    return parser


def _numba_interrupted(_args: argparse.Namespace) -> int:
    """What numba's dispatcher raises when Ctrl-C lands while it loads a kernel from its cache (seen
    in CI: a SIGHUP during a dashboard's start-up gave 'unexpected error' and exit 2)."""
    try:
        raise KeyboardInterrupt
    except KeyboardInterrupt as interrupt:
        raise SystemError("CPUDispatcher(<function _side_samples>) returned a result with an exception set") \
            from interrupt


def _interrupt_while_handling(_args: argparse.Namespace) -> int:
    try:
        raise KeyboardInterrupt
    except KeyboardInterrupt:
        raise RuntimeError("cleanup failed") from None   # the interrupt is suppressed: a bug


def _numba_failure(_args: argparse.Namespace) -> int:
    raise SystemError("a numba failure of its own")


def _no_numba_cache_folder(_args: argparse.Namespace) -> int:
    """What numba raises defining a cached kernel with no writable cache folder (a read-only install)."""
    raise RuntimeError("cannot cache function '_side_samples': no locator available for file '/usr/lib/x.py'")


def _bad_input(_args: argparse.Namespace) -> int:
    raise CubetrackError("no such camera 'cam9'")


@pytest.mark.parametrize("run,code,says", [
    (_numba_interrupted, 130, "cubetrack probe: interrupted"),
    (_numba_failure, 2, "unexpected error"),
    (_interrupt_while_handling, 2, "unexpected error"),
    (_bad_input, 1, "cubetrack probe: error: no such camera 'cam9'"),
    (_no_numba_cache_folder, 1, "cubetrack probe: error: cannot cache function '_side_samples': no locator available "
                                "for file '/usr/lib/x.py'; numba's cache needs a writable folder: NUMBA_CACHE_DIR"),
])
def test_the_boundary_maps_each_failure_to_its_exit_code(run, code, says, capsys, caplog):
    assert run_command(_parser(run), ["probe"]) == code
    assert says in capsys.readouterr().err + caplog.text
