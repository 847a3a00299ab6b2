"""``cubecam``: the command-line entry point and its one error boundary.

Each command lives in ``cubecam.commands.<module>`` with a module docstring (its ``--help``),
``HELP`` (one line), ``add_arguments(parser)`` and ``run(args) -> int``; heavy imports happen
inside ``run``. The error boundary is :func:`cubetrack.cli.command.run_command`: known errors
(:class:`cubecam.errors.CubecamError`, and any :class:`cubetrack.core.errors.CubetrackError`) print one
line and exit 1; anything else logs its traceback and exits 2.
"""

from __future__ import annotations

import argparse
import sys

from cubecam import __version__
from cubetrack.cli import command

COMMANDS = {
    "emulate": "emulate",
    "provision": "provision",
    "monitor": "monitor",
    "list": "list_boards",
    "flash": "flash",
}


def build_parser() -> argparse.ArgumentParser:
    return command.build_parser(
        "cubecam", "Camera-node tools for cubetrack: emulate nodes, provision and flash Spresense boards.",
        __version__, "cubecam.commands", COMMANDS)


def main(argv: list[str] | None = None) -> int:
    return command.run_command(build_parser(), argv)


if __name__ == "__main__":
    sys.exit(main())
