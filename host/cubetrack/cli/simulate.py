"""Render a simulated multi-camera recording of the paper's arena, with exact ground truth.

A floor world marker (the world frame), N camera nodes around it, and a robot carrying the
ArUco cube along a closed path. Each node has its own clock (offset, drift), frame rate, capture
jitter, transfer latency with spikes, dropped frames, JPEG quality, noise, blur and lighting.

Writes into --out (contracts §3): recording.json, <cam>/index.csv + JPEGs + clock.csv,
camera_info/<cam>.yaml, ground_truth.tum (cube pose, 100 Hz, host clock), cube.toml,
config.toml (a tracker config), true_extrinsics.toml, simulation.toml (parameters and clock
truth), run.json (the version and the parameters) and calibration/ (an empty-arena recording for
`cubetrack calibrate`).
The same --seed gives byte-identical frames and files. Details: docs/simulation.md.

--realistic switches on what real cameras and robots add (a wide-angle lens, intrinsics off by
a calibration's error, rolling shutter, motion blur, sharp turns on an uneven floor, a hand-built
cube, auto-exposure steps, stronger lighting gradients and vignetting, people walking through);
single effects can then be switched off, e.g. --realistic --readout-ms 0 --people 0. The truth
the tracker is not told is written beside it: true_camera_info/, true_cube.toml.
"""

from __future__ import annotations

import argparse
import dataclasses
import typing

from cubetrack.simulate.params import PATHS, REALISTIC, RIG, SimulationParams

HELP = "render a simulated multi-camera recording with ground truth"

_UNIT_SUFFIXES = ("_m_s2", "_deg_s", "_m_s", "_deg", "_m", "_s")


def _flag(name: str) -> str:
    if name.endswith("_per_s"):  # a rate keeps its unit: --exposure-steps-per-s
        return "--" + name.replace("_", "-")
    for suffix in _UNIT_SUFFIXES:
        if name.endswith(suffix):
            name = name[: -len(suffix)]
            break
    return "--" + name.replace("_", "-")


def _fields() -> list[tuple[dataclasses.Field, typing.Any]]:
    hints = typing.get_type_hints(SimulationParams)
    return [(f, hints[f.name]) for f in dataclasses.fields(SimulationParams)]


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--out", required=True, metavar="REC", help="recording folder to write")
    parser.add_argument("--force", action="store_true",
                        help="overwrite a recording already in REC (its old frames are deleted)")
    parser.add_argument("--workers", type=int, default=None, metavar="N",
                        help="rendering threads (default: one per core, at most 4; the output does not depend on it)")
    parser.add_argument("--realistic", action="store_true",
                        help="the realistic preset: every effect of real cameras and robots on (options given "
                             "explicitly still win; e.g. --readout-ms 0 switches the rolling shutter off)")
    parser.add_argument("--rig", action="store_true",
                        help="the real-rig preset: the realistic one plus 1280x720 webcams at 6 fps and inverted "
                             "markers with distinct ids (docs/simulation.md)")
    group = parser.add_argument_group("scenario (units in the option descriptions)")
    for f, hint in _fields():
        default = f.default
        realistic = f"; realistic: {_show(REALISTIC[f.name])}" if f.name in REALISTIC else ""
        help_text = f"{f.metadata['doc']} (default: {_show(default)}{realistic})".replace("%", "%%")
        kwargs: dict[str, typing.Any] = {"dest": f.name, "default": None, "help": help_text}
        if hint is bool:
            kwargs["action"] = argparse.BooleanOptionalAction
        elif typing.get_origin(hint) is tuple:
            assert isinstance(default, tuple)  # a tuple field's default
            item = typing.get_args(hint)[0]
            kwargs.update(type=item, nargs=len(default) if default and f.name != "distortion" else "+",
                          metavar=_metavar(f.name, item))
        elif f.name == "path":
            kwargs.update(choices=PATHS)
        else:
            kwargs.update(type=hint, metavar=_metavar(f.name, hint))
        group.add_argument(_flag(f.name), **kwargs)


def _metavar(name: str, hint: typing.Any) -> str:
    if hint is int:
        return "N"
    if hint is str:
        return "NAME"
    if name == "fps":
        return "FPS"
    for suffix, unit in (("_m_s2", "M/S2"), ("_deg_s", "DEG/S"), ("_per_s", "N/S"), ("_m_s", "M/S"), ("_deg", "DEG"),
                         ("_hz", "HZ"), ("_mm", "MM"), ("_ms", "MS"), ("_px", "PX"), ("_ppm", "PPM"), ("_m", "M"),
                         ("_s", "S")):
        if name.endswith(suffix):
            return unit
    return "X"


def _show(value: typing.Any) -> str:
    if isinstance(value, tuple):
        return " ".join(f"{v:g}" for v in value) or "none"
    if isinstance(value, bool):
        return "on" if value else "off"
    if isinstance(value, float):
        return f"{value:g}" if abs(value) < 1e9 else f"{value:.0f}"
    return str(value)


def params_from_args(args: argparse.Namespace) -> SimulationParams:
    """The scenario from the parsed options (options not given keep their defaults, or the
    realistic preset's with --realistic)."""
    rig = getattr(args, "rig", False)
    given: dict[str, typing.Any] = dict(REALISTIC) if getattr(args, "realistic", False) or rig else {}
    if rig:
        given.update(RIG)
    for f, _ in _fields():
        value = getattr(args, f.name, None)
        if value is not None:
            given[f.name] = tuple(value) if isinstance(value, list) else value
    return SimulationParams(**given)


def run(args: argparse.Namespace) -> int:
    from cubetrack.core.progress import StderrProgress
    from cubetrack.io.run import RUN_FILE, write_run_record
    from cubetrack.simulate import simulate

    params = params_from_args(args)
    result = simulate(params, args.out, progress=StderrProgress(), overwrite=args.force, workers=args.workers)
    write_run_record(result.path / RUN_FILE, "simulate", {"simulation": params}, {})
    frames = sum(c.frames_written for c in result.cameras)
    cal = sum(sum(x.delivered for x in c.calibration_captures) for c in result.cameras)
    print(f"wrote {result.path}: {len(result.cameras)} cameras, {frames} frames over {params.duration_s:g} s, "
          f"ground truth {result.path / 'ground_truth.tum'}")
    if result.calibration_path is not None:
        print(f"wrote {result.calibration_path}: {cal} empty-arena frames for calibration")
        print(f"next: cubetrack calibrate --config {result.config_path} --recording {result.calibration_path} "
              f"--out {result.path / 'extrinsics.toml'}")
    return 0
