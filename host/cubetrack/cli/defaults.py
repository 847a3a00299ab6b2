"""Print every tunable section of a tracker config with its defaults, each key documented
(unit and meaning) in a comment. Paste a section into your config and change what you need;
keys you leave out keep these defaults.

Example:
  cubetrack defaults > defaults.toml
  cubetrack defaults --section filter
"""

from __future__ import annotations

import argparse

HELP = "print the tracker config's tunable sections with defaults and documentation"

SECTIONS = ("detector", "estimator", "calibration", "fusion", "filter", "track", "source")


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--section", choices=SECTIONS, action="append",
                   help="only this section (repeatable; default: all)")


def default_sections() -> dict[str, object]:
    """Section name -> the default params of the stage that owns it."""
    from cubetrack.app.tracker import StageParams
    from cubetrack.calib.extrinsics import CalibrationParams
    from cubetrack.source.streams import SourceParams

    stages = StageParams()
    return {
        "detector": stages.detector,
        "estimator": stages.estimator,
        "calibration": CalibrationParams(),
        "fusion": stages.fusion,
        "filter": stages.filter,
        "track": stages.track,
        "source": SourceParams(),
    }


def render(sections: tuple[str, ...] = SECTIONS) -> str:
    """The commented TOML text of ``sections``."""
    from cubetrack.core.params import params_to_commented_toml

    defaults = default_sections()
    return "\n".join(params_to_commented_toml(name, defaults[name]) for name in sections)


def run(args: argparse.Namespace) -> int:
    print(render(tuple(args.section or SECTIONS)), end="")
    return 0
