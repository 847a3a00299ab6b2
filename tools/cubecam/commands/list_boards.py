"""List the Spresense boards attached over USB (USB id 10C4:EA60) with their node names.

Each board is asked for its name over Improv serial (without resetting it); a board that
does not answer within --timeout is listed without one.

  cubecam list
"""

from __future__ import annotations

import argparse
import sys

HELP = "list attached boards (USB 10C4:EA60) and their node names"


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--no-names", action="store_true", help="do not open the ports to ask for names")
    p.add_argument("--timeout", type=float, default=2.0, metavar="S", help="wait per board for its name (default 2)")


def run(args: argparse.Namespace) -> int:
    from cubecam.boards import attached_boards, query_name

    boards = attached_boards()
    if not boards:
        print("cubecam list: no boards attached (looked for USB 10C4:EA60)", file=sys.stderr)
        return 0
    for b in boards:
        name = None if args.no_names else query_name(b.device, args.timeout)
        print(f"{b.device}\t{name or '-'}\t{b.serial_number or '-'}\t{b.description}", flush=True)
    return 0
