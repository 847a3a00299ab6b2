"""Issue 26: does ``cubetrack calibrate --refine-with`` put the cameras where they are? The
refined cameras' error against the truth, and the constellation's scale, ours against a baseline
commit's code in the same run.

Scenes: ``benchmarks/accuracy.py``'s (``--presets`` clean / realistic, ``--configs`` its
configuration indices: default 1 = 3 cameras 1.0 m / 30°, 3 = 5 cameras, 0 = 3 cameras 0.8 m /
20°), ``--seeds``, ``--duration`` s of driving with ``--calibration-frames`` frames of the empty
arena; a complete recording of the same parameters under ``--out`` is reused (accuracy.py's
rule). Each scene's calibration is made the README's way, by the code under test, in a process
of its own: :func:`cubetrack.app.calibrate.run_calibration` (what ``cubetrack calibrate
--recording calibration --refine-with REC`` runs: the world-marker calibration, then the bundle
adjustment over the drive's cube sightings; default settings, the scene's ``config.toml``). The
**baseline** (``--baseline COMMIT``, default the commit before the refinement took template
corners) runs the same function from that commit's ``host/`` (``git archive`` into a temporary
folder, ``PYTHONPATH``) on the same recordings. Rows per scene:

- **world marker**: the world-marker calibration alone (ours; the baseline's is the same code);
- **baseline refined** and **ours refined**: the cameras the refinement writes
  (``run_calibration`` without the bodies);
- **ours refined + body** (``--bodies``): the cameras ``cubetrack calibrate --refine-with`` writes
  today, the body calibrated from the drive first and the refinement on it
  (``run_calibration(..., with_bodies=True)``).

Each row: every camera's position error (mm) and rotation error (°) against
``true_extrinsics.toml``, its radial error (mm: how much farther from the world origin than the
truth), and the constellation's **scale**: the least-squares s of ``p_est ≈ s p_true`` over the
camera positions about the world origin (1.0 = no scale bias). Issue 26's target on clean
renders: every refined camera within 3 mm and 0.05°.

    nice -n 10 .venv/bin/python benchmarks/refine_bias.py [--out DIR] [--presets clean realistic]
        [--seeds 202 303] [--configs 1 3] [--duration 15] [--calibration-frames 200]
        [--baseline COMMIT | --no-baseline] [--json FILE]

The exit code is 0 for a completed run (this is a report); a scene whose calibration fails is
reported as failed.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
BASELINE = "0585352^"  # the refinement on edge-fitted corners (before issue 26's template corners)
WORLD, BASE, OURS, BODIES = "world marker", "baseline refined", "ours refined", "ours refined + body"
TARGET_MM, TARGET_DEG = 3.0, 0.05  # issue 26, clean renders


def say(text: str) -> None:
    print(text, file=sys.stderr, flush=True)


# --------------------------------------------------------------------------------- the calibration under test


def calibrate_scene(rec: Path, out: Path, with_bodies: bool = False) -> None:
    """In the worker process (the code under test on ``sys.path``): ``rec``'s calibration made
    the README's way into ``out`` (extrinsics TOML, its run record; ``with_bodies``: the bodies
    calibrated too), and ``out``'s ``.json`` with the world-marker and the refined camera poses
    (4x4 lists) and the CPU seconds it took."""
    from cubetrack.app.calibrate import run_calibration
    from cubetrack.io.config import read_tracker_config
    from cubetrack.io.recording import Recording

    t0 = time.process_time()
    config = read_tracker_config(rec / "config.toml")
    run = run_calibration(config, Recording.open(rec / "calibration"), out, adjust_with=Recording.open(rec),
                          **({"with_bodies": True} if with_bodies else {}))
    poses = {name: {c: np.asarray(e.T_world_cam, float).tolist() for c, e in ext.items()}
             for name, ext in ((WORLD, run.report.extrinsics), ("refined", run.extrinsics))}
    doc = {"poses": poses, "cpu_s": time.process_time() - t0,
           "warnings": list(run.adjusted.warnings) if run.adjusted is not None else []}
    out.with_suffix(".json").write_text(json.dumps(doc), encoding="utf-8")


def run_worker(host: Path, rec: Path, out: Path, with_bodies: bool = False) -> dict:
    """:func:`calibrate_scene` in a process importing ``cubetrack`` from ``host``; its JSON, or
    {"error": the last line of its stderr}."""
    env = dict(os.environ, PYTHONPATH=str(host))
    proc = subprocess.run([sys.executable, str(Path(__file__).resolve()), "--worker", str(rec), str(out),
                           *(["--worker-bodies"] if with_bodies else [])],
                          env=env, capture_output=True, text=True, check=False)
    if proc.returncode != 0:
        lines = [line for line in proc.stderr.splitlines() if line.strip()] or ["(no output)"]
        return {"error": lines[-1]}
    return json.loads(out.with_suffix(".json").read_text(encoding="utf-8"))


def commit_tree(commit: str, into: Path) -> Path:
    """``host/`` of ``commit`` extracted under ``into`` (``git archive``); its path."""
    into.mkdir(parents=True, exist_ok=True)
    archive = subprocess.run(["git", "-C", str(ROOT), "archive", commit, "host"], capture_output=True, check=True)
    subprocess.run(["tar", "-x", "-C", str(into)], input=archive.stdout, check=True)
    return into / "host"


# --------------------------------------------------------------------------------- scoring


def constellation_errors(poses: dict[str, list], truth: dict[str, np.ndarray]) -> dict:
    """Per camera (position mm, rotation °, radial mm) against ``truth`` (camera -> T_world_cam),
    and the constellation's least-squares scale about the world origin."""
    from cubetrack.core.geometry import rotation_angle

    cams, est, true = {}, [], []
    for name, T in poses.items():
        T, T_true = np.asarray(T, float), truth[name]
        p, q = T[:3, 3], T_true[:3, 3]
        cams[name] = (float(np.linalg.norm(p - q)) * 1000.0, rotation_angle(T[:3, :3], T_true[:3, :3], "deg"),
                      float(np.linalg.norm(p) - np.linalg.norm(q)) * 1000.0)
        est.append(p)
        true.append(q)
    e, t = np.array(est), np.array(true)
    return {"cameras": cams, "scale": float(np.sum(e * t) / np.sum(t * t)),
            "max_mm": max(c[0] for c in cams.values()), "max_deg": max(c[1] for c in cams.values()),
            "mean_mm": float(np.mean([c[0] for c in cams.values()])),
            "mean_deg": float(np.mean([c[1] for c in cams.values()]))}


def run_scene(acc, work: Path, preset: str, config_index: int, seed: int, duration: float, calibration_frames: int,
              trees: dict[str, Path]) -> dict:
    """Render (or reuse) one scene and calibrate it with each tree; its rows."""
    from cubetrack.io.config import read_extrinsics

    _, cameras, height, tilt, _ = acc.CONFIGS[config_index]
    rec = acc.scene_dir(work, config_index, seed, preset)
    params = acc.sim_params(preset, cameras, height, tilt, seed, duration, calibration_frames)
    render_s, _ = acc.ensure_recording(params, rec, max(1, os.cpu_count() or 1))
    truth = {c: e.T_world_cam for c, e in read_extrinsics(rec / "true_extrinsics.toml").items()}
    scene = {"preset": preset, "config": acc.CONFIGS[config_index][0], "seed": seed, "render_s": render_s, "rows": {}}
    for label, host in trees.items():
        result = run_worker(host, rec, rec / f"refine_bias_{label.replace(' ', '_').replace('+', '')}.toml",
                            label == BODIES)
        if "error" in result:
            scene["rows"][label] = {"error": result["error"]}
            continue
        if label == OURS:
            scene["rows"][WORLD] = constellation_errors(result["poses"][WORLD], truth)
        scene["rows"][label] = dict(constellation_errors(result["poses"]["refined"], truth),
                                    cpu_s=result["cpu_s"], warnings=result["warnings"])
    return scene


def print_scene(scene: dict) -> None:
    print(f"\n{scene['preset']} {scene['config']}, seed {scene['seed']}")
    print("| calibration | per camera: mm / ° (radial mm) | max mm / ° | mean mm / ° | scale | CPU s |")
    print("| --- | --- | --- | --- | --- | --- |")
    for label in (WORLD, BASE, OURS, BODIES):
        row = scene["rows"].get(label)
        if row is None:
            continue
        if "error" in row:
            print(f"| {label} | FAILED: {row['error']} | | | | |")
            continue
        cams = ", ".join(f"{c} {mm:.1f} / {deg:.3f} ({rad:+.1f})" for c, (mm, deg, rad) in row["cameras"].items())
        cpu = f"{row['cpu_s']:.0f}" if "cpu_s" in row else ""
        print(f"| {label} | {cams} | {row['max_mm']:.1f} / {row['max_deg']:.3f} | {row['mean_mm']:.1f} / "
              f"{row['mean_deg']:.3f} | {row['scale']:.4f} | {cpu} |")


def print_summary(scenes: list[dict]) -> None:
    print("\nsummary (worst over the scenes of each preset): max camera error mm / °, scale farthest from 1")
    for preset in dict.fromkeys(s["preset"] for s in scenes):
        for label in (WORLD, BASE, OURS, BODIES):
            rows = [s["rows"][label] for s in scenes if s["preset"] == preset and label in s["rows"]]
            ok = [r for r in rows if "error" not in r]
            if not rows:
                continue
            failed = len(rows) - len(ok)
            if not ok:
                print(f"  {preset:<10} {label:<17} all {failed} failed")
                continue
            mm, deg = max(r["max_mm"] for r in ok), max(r["max_deg"] for r in ok)
            scale = max((r["scale"] for r in ok), key=lambda s: abs(s - 1.0))
            target = ""
            if preset == "clean" and label != WORLD:
                met = mm <= TARGET_MM and deg <= TARGET_DEG
                target = f"  target {TARGET_MM:g} mm / {TARGET_DEG:g}°: {'met' if met else 'NOT met'}"
            print(f"  {preset:<10} {label:<17} {mm:5.1f} mm / {deg:.3f}°  scale {scale:.4f}"
                  f"{f'  ({failed} failed)' if failed else ''}{target}")


# --------------------------------------------------------------------------------- main


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", type=Path, help="keep the recordings here (default: a temporary folder, deleted); "
                    "complete recordings with the same parameters are reused")
    ap.add_argument("--presets", nargs="+", choices=("clean", "realistic"), default=["clean", "realistic"])
    ap.add_argument("--seeds", type=int, nargs="+", default=[202, 303])
    ap.add_argument("--configs", type=int, nargs="+", default=[1, 3], metavar="I",
                    help="accuracy.py's configuration indices (0: 3 cameras 0.8 m, 1: 3 cameras 1.0 m, 2: 3 cameras "
                    "1.2 m, 3: 5 cameras 1.0 m; default 1 3)")
    ap.add_argument("--duration", type=float, default=15.0, help="seconds of driving (default 15)")
    ap.add_argument("--calibration-frames", type=int, default=200, help="frames of the empty arena (default 200)")
    ap.add_argument("--baseline", default=BASELINE, help=f"commit whose code is the baseline (default {BASELINE}: "
                    "the refinement on edge-fitted corners)")
    ap.add_argument("--no-baseline", action="store_true", help="only ours and the world marker")
    ap.add_argument("--ours", metavar="COMMIT", help="take ours from this commit's host/ too (default: the working "
                    "tree's; a commit keeps a long run's code fixed while the tree changes)")
    ap.add_argument("--bodies", action="store_true", help="also ours with the bodies calibrated from the drive "
                    "first (what cubetrack calibrate --refine-with does; costs a body calibration per scene)")
    ap.add_argument("--json", type=Path, help="write the scenes' rows here")
    ap.add_argument("--worker", nargs=2, type=Path, metavar=("REC", "OUT"), help=argparse.SUPPRESS)
    ap.add_argument("--worker-bodies", action="store_true", help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.worker is not None:  # one calibration, with whichever cubetrack PYTHONPATH names
        calibrate_scene(*args.worker, with_bodies=args.worker_bodies)
        return 0
    if args.duration <= 0 or args.calibration_frames < 5:
        ap.error("--duration must be positive and --calibration-frames at least 5")
    sys.path.insert(0, str(Path(__file__).resolve().parent))  # accuracy.py: its scenes, rendering and reuse rule
    import accuracy as acc
    bad = [c for c in args.configs if not 0 <= c < len(acc.CONFIGS)]
    if bad:
        ap.error(f"--configs: no configuration {bad[0]} (0-{len(acc.CONFIGS) - 1})")
    with tempfile.TemporaryDirectory(prefix="cubetrack-refine-bias-") as tmp:
        wanted = {OURS: args.ours, **({} if args.no_baseline else {BASE: args.baseline})}
        trees = {OURS: ROOT / "host"}
        for label, commit in wanted.items():
            try:
                if commit is not None:
                    trees[label] = commit_tree(commit, Path(tmp) / label.split()[0])
            except subprocess.CalledProcessError as exc:
                flag = "--ours" if label == OURS else "--baseline"
                ap.error(f"{flag} {commit}: git archive failed ({exc.stderr.decode().strip()})")
        trees = {label: trees[label] for label in (BASE, OURS) if label in trees}  # the baseline first
        if args.bodies:
            trees[BODIES] = trees[OURS]
        work = args.out or Path(tmp) / "scenes"
        work.mkdir(parents=True, exist_ok=True)
        t0 = time.monotonic()
        scenes = []
        for preset in args.presets:
            for seed in args.seeds:
                for ci in args.configs:
                    say(f"{preset} {acc.CONFIGS[ci][0]} seed {seed} ...")
                    scenes.append(run_scene(acc, work, preset, ci, seed, args.duration, args.calibration_frames,
                                            trees))
                    print_scene(scenes[-1])
        print_summary(scenes)
        ours = f"ours {args.ours}" if args.ours else f"code {acc.code_version()}"
        print(f"\nbaseline {args.baseline if not args.no_baseline else '(none)'}; {ours}; "
              f"{os.cpu_count()} cores, load {' '.join(f'{x:.1f}' for x in os.getloadavg())}; "
              f"total {time.monotonic() - t0:.0f} s")
        if args.json:
            args.json.write_text(json.dumps({"scenes": scenes, "baseline": args.baseline}, indent=1,
                                            default=float), encoding="utf-8")
    return 0


if __name__ == "__main__":
    sys.exit(main())
