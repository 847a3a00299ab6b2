"""Issue 26: CPU per marker of tracking's template fit
(:func:`cubetrack.detect.template_fit.fast_template_corners`) as a ratio against another commit's
(``--base``, default the commit before issue 26's work) in the same run, and both fits' corner
error against the truth.

The markers are every detection the tracker made on ``benchmarks/corner_ceiling.py``'s scenes
(``--configs``, seed ``--seed``, ``--preset``; rendered and cached there under ``--out``, reused),
each with its frame and its oracle corners (the cube as built at the true pose at each corner's
row instant, through the true lens: corner_ceiling.py's ``Truth``). The base commit's
``detect/template_fit.py`` is read with ``git show`` into a temporary module: the old path is
reachable from this benchmark only. Both fits run on one thread (``cv2.setNumThreads(1)``),
marker by marker, alternating which goes first each round; printed: median thread CPU per marker
of each and their ratio (base / current: > 1 means the current fit is cheaper), the corner error
(RMS per coordinate against the oracle) by the face's view angle, failures, how far the current
fit's corners are from the base's (the largest difference; 0 when every corner is the same to the
bit), the core count and the load average at the start and the end. Each fit keeps one lens map
per camera across the rounds, as a Detector keeps them (the first round fills them).

``--recording DIR`` (session 28) takes the markers instead from a recording's frames as the
tracker's default detector finds them (the first ``--frames`` of every camera, its camera_info),
e.g. the live benchmark's 16 x 30 scene (``benchmarks/live.py --out OUT``: ``OUT/rec_c16_f30_d20_s7``);
no oracle there, so no corner error.

    nice -n 10 .venv/bin/python benchmarks/template_speed.py [--out /tmp/corner_ceiling] [--configs 1 3]
                                                             [--preset realistic] [--base 12ee071] [--rounds 2]
    nice -n 10 .venv/bin/python benchmarks/template_speed.py --recording OUT/rec_c16_f30_d20_s7 [--frames 20]

The exit code is 0 for a completed run.
"""

from __future__ import annotations

import argparse
import importlib.util
import itertools
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
BASE = "12ee071"  # main before issue 26's work
MODULE = "host/cubetrack/detect/template_fit.py"


def base_module(commit: str):
    """``detect/template_fit.py`` as it was at ``commit``, imported as a module of its own."""
    source = subprocess.run(["git", "-C", str(HERE), "show", f"{commit}:{MODULE}"], capture_output=True, text=True,
                            check=True).stdout
    path = Path(tempfile.mkdtemp()) / "base_template_fit.py"
    path.write_text(source, encoding="utf-8")
    spec = importlib.util.spec_from_file_location("base_template_fit", path)
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    sys.modules["base_template_fit"] = module  # dataclasses look their module up
    spec.loader.exec_module(module)
    return module


def markers(ceiling, bench, args) -> list[dict]:
    """Every detection of the scenes with its frame, lens, oracle corners and view angle."""
    from cubetrack.core.layout import read_layout
    from cubetrack.detect.detector import decode_gray
    from cubetrack.io.recording import Recording

    ceiling_args = ceiling.parse_args(["--out", str(args.out), "--seed", str(args.seed), "--preset", args.preset,
                                       "--no-template", "--configs", *map(str, args.configs)])
    out = []
    for c in args.configs:
        sc = ceiling.load_scene(bench, ceiling_args, c)
        dictionary = read_layout(sc["rec"] / "cube.toml").dictionary
        recording = Recording.open(sc["rec"])
        wanted = {(s.camera, s.seq) for s, _ in sc["sightings"]}
        jpegs = {(cam, f.seq): f.jpeg for cam in recording.camera_names for f in recording.frames(cam)
                 if (cam, f.seq) in wanted}
        for k, (s, _) in enumerate(sc["sightings"]):
            gray = decode_gray(jpegs[(s.camera, s.seq)])
            for d, (oracle, angle) in zip(s.detections, sc["oracle"][k], strict=True):
                out.append({"gray": gray, "corners": d.corners_px, "dictionary": d.dictionary or dictionary,
                            "marker_id": d.marker_id, "intrinsics": s.intrinsics, "camera": (sc["rec"], s.camera),
                            "oracle": oracle, "angle": angle})
    return out


def recording_markers(path: Path, frames: int) -> list[dict]:
    """Every marker the default detector finds in the first ``frames`` frames of each camera of the
    recording at ``path``, with its frame and the camera's intrinsics (no oracle)."""
    from cubetrack.detect.detector import Detector, decode_gray
    from cubetrack.io.camera_info import read_camera_info
    from cubetrack.io.recording import Recording

    recording = Recording.open(path)
    detector = Detector()
    out = []
    for cam in recording.camera_names:
        info = recording.camera_info_path(cam)
        intrinsics = None if info is None else read_camera_info(info)
        for f in itertools.islice(recording.frames(cam), frames):
            gray = decode_gray(f.jpeg)
            out += [{"gray": gray, "corners": d.corners_px, "dictionary": d.dictionary, "marker_id": d.marker_id,
                     "intrinsics": intrinsics, "camera": (path, cam), "oracle": None, "angle": None}
                    for d in detector.detect(gray)]
    return out


def timed(fits: dict, items: list[dict], rounds: int) -> tuple[dict, dict]:
    """Per fit: the thread CPU (s) of each call over ``rounds`` rounds (the order alternating) and
    the corners of the last round."""
    cpu: dict = {name: [] for name in fits}
    corners: dict = {}
    for fit in fits.values():  # warm the caches (templates, lens maps)
        for m in items[:10]:
            fit(m)
    for r in range(rounds):
        for name in (list(fits) if r % 2 == 0 else list(fits)[::-1]):
            got = []
            for m in items:
                c0 = time.thread_time()
                got.append(fits[name](m))
                cpu[name].append(time.thread_time() - c0)
            corners[name] = got
    return cpu, corners


def error_row(items: list[dict], corners: list, bins_deg: tuple[float, ...]) -> str:
    """RMS corner error against the oracle, over all and by view-angle bin."""
    ok = [(c, m) for c, m in zip(corners, items, strict=True) if c is not None and m["oracle"] is not None]
    if not ok:
        return "- | " + " | ".join("-" for _ in itertools.pairwise(bins_deg))
    err = np.array([c - m["oracle"] for c, m in ok]).reshape(-1, 4, 2)
    angle = np.array([m["angle"] for _, m in ok])
    cells = []
    for lo, hi in itertools.pairwise(bins_deg):
        e = err[(angle >= lo) & (angle < hi)]
        cells.append(f"{np.sqrt(np.mean(e ** 2)):.3f}" if len(e) else "-")
    return f"{np.sqrt(np.mean(err ** 2)):.4f} px | " + " | ".join(cells)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter, epilog=__doc__)
    ap.add_argument("--out", type=Path, default=Path("/tmp/corner_ceiling"), help="corner_ceiling.py's scene folder")
    ap.add_argument("--configs", type=int, nargs="+", default=[1, 3], help="accuracy.py's configuration indices")
    ap.add_argument("--seed", type=int, default=101)
    ap.add_argument("--preset", choices=("clean", "realistic", "rig"), default="realistic")
    ap.add_argument("--base", default=BASE, help="the commit whose template fit is the baseline")
    ap.add_argument("--rounds", type=int, default=2, help="timed rounds over all markers")
    ap.add_argument("--recording", type=Path, help="markers from this recording's frames instead of the scenes")
    ap.add_argument("--frames", type=int, default=20, help="with --recording: the first frames of each camera")
    args = ap.parse_args(argv)
    import cv2

    from cubetrack.detect import template_fit

    sys.path.insert(0, str(HERE))
    import accuracy as bench
    import corner_ceiling as ceiling

    cv2.setNumThreads(1)
    load_start = " ".join(f"{v:.1f}" for v in os.getloadavg())
    base = base_module(args.base)
    items = recording_markers(args.recording, args.frames) if args.recording else markers(ceiling, bench, args)
    lenses: dict = {}

    def fit_with(module):
        def fit(m: dict):
            key = (module.__name__, m["camera"])
            if key not in lenses:  # one lens map per camera and module, as a Detector keeps them
                lenses[key] = module.LensMap(m["intrinsics"])
            lens = lenses[key]
            return module.fast_template_corners(m["gray"], m["corners"], m["dictionary"], m["marker_id"], lens)
        return fit

    fits = {f"base {args.base}": fit_with(base), "current": fit_with(template_fit)}
    cpu, corners = timed(fits, items, args.rounds)
    source = (f"{args.recording} (first {args.frames} frames per camera)" if args.recording
              else f"{args.preset} configs {args.configs} seed {args.seed}")
    print(f"template fit, {len(items)} markers of {source}, "
          f"{args.rounds} rounds, one thread; {os.cpu_count()} cores, load average {load_start} at the start, "
          f"{' '.join(f'{v:.1f}' for v in os.getloadavg())} at the end")
    bins = " | ".join(f"{lo:g}-{hi:g}°" for lo, hi in itertools.pairwise(ceiling.VIEW_BINS_DEG))
    print(f"| fit | CPU median / p90 ms per marker | failed | corner error RMS | {bins} |")
    print("| --- | --- | --- | --- |" + " --- |" * (len(ceiling.VIEW_BINS_DEG) - 1))
    for name in fits:
        ms = 1000.0 * np.array(cpu[name])
        failed = sum(c is None for c in corners[name])
        print(f"| {name} | {np.median(ms):.2f} / {np.percentile(ms, 90):.2f} | {failed} | "
              f"{error_row(items, corners[name], ceiling.VIEW_BINS_DEG)} |")
    names = list(fits)
    ratio = np.median(cpu[names[0]]) / np.median(cpu[names[1]])
    print(f"ratio {names[0]} / current (median CPU per marker): {ratio:.2f}")
    both = list(zip(corners[names[0]], corners[names[1]], strict=True))
    pairs = [(a, b) for a, b in both if a is not None and b is not None]
    moved = max((float(np.abs(a - b).max()) for a, b in pairs), default=0.0)
    same_failures = all((a is None) == (b is None) for a, b in both)
    print(f"current corners against the base's: largest difference {moved:.3g} px over {len(pairs)} markers; "
          f"{'the same' if same_failures else 'different'} failures")
    return 0


if __name__ == "__main__":
    sys.exit(main())
