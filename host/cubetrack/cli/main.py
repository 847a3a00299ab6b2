"""``cubetrack``: the command-line entry point and its one error boundary.

Each command lives in ``cubetrack.cli.<module>`` with ``HELP`` (one line), ``add_arguments(parser)``
and ``run(args) -> int``. Command modules import only argparse-level names at import time, so
``--help`` is fast; heavy modules (OpenCV, SciPy) are imported inside ``run``.
Known errors (:class:`cubetrack.errors.CubetrackError`) print one line and exit 1; anything
else prints a traceback and exits 2.
"""

from __future__ import annotations

import argparse
import importlib
import logging
import sys

from cubetrack import __version__
from cubetrack.errors import CubetrackError

COMMANDS = {
    "demo": "demo",
    "simulate": "simulate",
    "calibrate": "calibrate",
    "calibrate-intrinsics": "calibrate_intrinsics",
    "track": "track",
    "evaluate": "evaluate",
    "detect": "detect",
}


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="cubetrack",
        description="Indoor robot tracking with Wi-Fi camera nodes and an ArUco cube.",
    )
    parser.add_argument("--version", action="version", version=f"cubetrack {__version__}")
    parser.add_argument("-v", "--verbose", action="count", default=0,
                        help="more log output (-v info, -vv debug)")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)
    for name, module_name in COMMANDS.items():
        module = importlib.import_module(f"cubetrack.cli.{module_name}")
        p = sub.add_parser(name, help=module.HELP, description=module.__doc__,
                           formatter_class=argparse.RawDescriptionHelpFormatter)
        module.add_arguments(p)
        p.set_defaults(_run=module.run)
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    level = (logging.WARNING, logging.INFO, logging.DEBUG)[min(args.verbose, 2)]
    logging.basicConfig(level=level, format="%(levelname)s %(name)s: %(message)s")
    try:
        return int(args._run(args) or 0)
    except CubetrackError as exc:
        print(f"cubetrack {args.command}: error: {exc}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        print(f"cubetrack {args.command}: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
