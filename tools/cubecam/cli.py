"""``cubecam``: the command-line entry point and its one error boundary.

Each command lives in ``cubecam.commands.<module>`` with a module docstring (its ``--help``),
``HELP`` (one line), ``add_arguments(parser)`` and ``run(args) -> int``; heavy imports happen
inside ``run``. Known errors (:class:`cubecam.errors.CubecamError`, and any
:class:`cubetrack.errors.CubetrackError`) print one line and exit 1; anything else prints a
traceback and exits 2.
"""

from __future__ import annotations

import argparse
import importlib
import logging
import sys

from cubetrack.errors import CubetrackError

from cubecam import __version__

COMMANDS = {
    "emulate": "emulate",
    "provision": "provision",
    "monitor": "monitor",
    "list": "list_boards",
    "flash": "flash",
}


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="cubecam",
        description="Camera-node tools for cubetrack: emulate nodes, provision and flash Spresense boards.",
    )
    parser.add_argument("--version", action="version", version=f"cubecam {__version__}")
    parser.add_argument("-v", "--verbose", action="count", default=0,
                        help="more log output (-v info, -vv debug)")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)
    for name, module_name in COMMANDS.items():
        module = importlib.import_module(f"cubecam.commands.{module_name}")
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
        print(f"cubecam {args.command}: error: {exc}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        print(f"cubecam {args.command}: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
