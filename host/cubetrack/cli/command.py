"""The command-line skeleton shared by ``cubetrack`` and ``cubecam``: one parser built from
command modules, and the one error boundary.

A command module has a docstring (its ``--help`` text), ``HELP`` (one line), ``add_arguments``
and ``run(args) -> int``. Known errors (:class:`cubetrack.core.errors.CubetrackError`) print one line
and exit 1, as does numba finding no writable folder for its cache (an install's fault); Ctrl-C exits 130
(also when a C extension wrapped it in another exception); anything else is a bug: its traceback is
logged and the exit code is 2.
SIGTERM and SIGHUP (``kill``, a service manager, a closed terminal) stop a command as Ctrl-C does, so
that what it opened is closed and its temporary folders are removed (unless the signal is ignored,
e.g. under ``nohup``).
"""

from __future__ import annotations

import argparse
import importlib
import logging
import signal
import sys
import threading
from collections.abc import Mapping
from typing import Any

from cubetrack.core.errors import NO_NUMBA_CACHE_FOLDER, CubetrackError, caused_by_interrupt, no_numba_cache_folder


def build_parser(prog: str, description: str, version: str, package: str,
                 commands: Mapping[str, str]) -> argparse.ArgumentParser:
    """A parser with one subcommand per ``commands`` entry (name -> module in ``package``)."""
    parser = argparse.ArgumentParser(prog=prog, description=description)
    parser.add_argument("--version", action="version", version=f"{prog} {version}")
    parser.add_argument("-v", "--verbose", action="count", default=0,
                        help="more log output (-v info, -vv debug)")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)
    for name, module_name in commands.items():
        module = importlib.import_module(f"{package}.{module_name}")
        p = sub.add_parser(name, help=module.HELP, description=module.__doc__,
                           formatter_class=argparse.RawDescriptionHelpFormatter)
        module.add_arguments(p)
        p.set_defaults(_run=module.run)
    return parser


def run_command(parser: argparse.ArgumentParser, argv: list[str] | None) -> int:
    """Parse ``argv``, configure logging, run the command inside the error boundary."""
    args = parser.parse_args(argv)
    level = (logging.WARNING, logging.INFO, logging.DEBUG)[min(args.verbose, 2)]
    logging.basicConfig(level=level, format="%(levelname)s %(name)s: %(message)s")
    stop_signals = _stop_like_ctrl_c()
    try:
        return int(args._run(args) or 0)
    except CubetrackError as exc:
        print(f"{parser.prog} {args.command}: error: {exc}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        print(f"{parser.prog} {args.command}: interrupted", file=sys.stderr)
        return 130
    except Exception as exc:  # a bug, not bad input: keep the traceback for the report
        if caused_by_interrupt(exc):  # a C extension (numba's dispatcher) wrapped the interrupt
            print(f"{parser.prog} {args.command}: interrupted", file=sys.stderr)
            return 130
        if no_numba_cache_folder(exc):  # the install's, not a bug: where the cache may go
            print(f"{parser.prog} {args.command}: error: {str(exc).strip().splitlines()[0]}; {NO_NUMBA_CACHE_FOLDER}",
                  file=sys.stderr)
            return 1
        logging.getLogger(parser.prog).exception("%s %s: unexpected error (please report it)",
                                                 parser.prog, args.command)
        return 2
    finally:
        for number, handler in stop_signals.items():
            signal.signal(number, handler)


def _stop_like_ctrl_c() -> dict[int, Any]:
    """Make SIGTERM and SIGHUP raise KeyboardInterrupt in the main thread (where they are not
    ignored); returns the handlers they had, to put back."""
    if threading.current_thread() is not threading.main_thread():
        return {}
    previous: dict[int, Any] = {}  # signal number -> its handler, as signal.signal returned it
    for number in (signal.SIGTERM, signal.SIGHUP):
        if signal.getsignal(number) is signal.SIG_DFL:
            previous[number] = signal.signal(number, signal.default_int_handler)
    return previous
