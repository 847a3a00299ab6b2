"""``cubetrack``: the command-line entry point and its one error boundary.

Each command lives in ``cubetrack.cli.<module>`` (see :mod:`cubetrack.cli.command`). Command modules
import only argparse-level names at import time, so ``--help`` is fast; heavy modules (OpenCV,
SciPy) are imported inside ``run``.
"""

from __future__ import annotations

import argparse
import sys

from cubetrack import __version__
from cubetrack.cli import command

COMMANDS = {
    "demo": "demo",
    "simulate": "simulate",
    "calibrate": "calibrate",
    "calibrate-intrinsics": "calibrate_intrinsics",
    "calibrate-body": "calibrate_body",
    "make-body": "make_body",
    "import": "import_rig",
    "track": "track",
    "record": "record",
    "worker": "worker",
    "fuse": "fuse",
    "dashboard": "dashboard",
    "evaluate": "evaluate",
    "detect": "detect",
    "defaults": "defaults",
    "compile": "compile",
}


def build_parser() -> argparse.ArgumentParser:
    return command.build_parser("cubetrack", "Indoor robot tracking with Wi-Fi camera nodes and an ArUco cube.",
                            __version__, "cubetrack.cli", COMMANDS)


def main(argv: list[str] | None = None) -> int:
    return command.run_command(build_parser(), argv)


if __name__ == "__main__":
    sys.exit(main())
