"""Print every tunable section of a tracker config with its defaults, each key documented
(unit and meaning) in a comment. Paste a section into your config and change what you need;
keys you leave out keep these defaults.

Sections: every parameter section of the config, then ``outputs``: one ``[[outputs]]`` table per
output type (zenoh, ros2, vrpn, foxglove, mcap) with its keys; a config lists only the outputs it
wants (docs/outputs.md).

Example:
  cubetrack defaults > defaults.toml
  cubetrack defaults --section filter
"""

from __future__ import annotations

import argparse

HELP = "print the tracker config's tunable sections with defaults and documentation"


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--section", metavar="NAME", action="append",
                   help="only this section (repeatable; default: all)")


def render(sections: tuple[str, ...] | None = None) -> str:
    """The commented TOML text of ``sections`` (default: all, in the config's order)."""
    from cubetrack.app.config import SECTIONS, ConfigParams
    from cubetrack.core.errors import ConfigError
    from cubetrack.core.params import params_to_commented_toml
    from cubetrack.sink.output_params import OUTPUT_TYPES

    known = (*SECTIONS, "outputs")
    unknown = [s for s in sections or () if s not in known]
    if unknown:
        raise ConfigError(f"--section {unknown[0]}: no such section; sections: {', '.join(known)}")
    defaults = ConfigParams()
    texts = []
    for name in sections or known:
        if name != "outputs":
            texts.append(params_to_commented_toml(name, getattr(defaults, name)))
            continue
        for kind, cls in OUTPUT_TYPES.items():  # a table of the array: [[outputs]] and its type first
            table = params_to_commented_toml("outputs", cls()).removeprefix("[outputs]\n")
            texts.append(f'[[outputs]]\ntype = "{kind}"\n{table}')
    return "\n".join(texts)


def run(args: argparse.Namespace) -> int:
    print(render(tuple(args.section) if args.section else None), end="")
    return 0
