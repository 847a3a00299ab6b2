"""Issue 26's "Done when" table: the README workflow with the default settings on every scene,
each figure against its fixed target and against the scene's measured floor.

Per scene (``--scenes PRESET:CONFIG:SEED:ROLE``; accuracy.py's presets and configuration
indices, ROLE ``preset`` / ``development`` / ``held-out``, reported apart):

- **the README workflow** (accuracy.py ``--workflow``): ``cubetrack calibrate --recording
  calibration --refine-with DRIVE`` (a separate drive of the same robot: the scene rendered for
  ``--duration`` + ``--drive`` s, only the frames after the session's end), then ``cubetrack
  track --extrinsics``, both as commands from this checkout's ``host/``; scored as accuracy.py
  scores (position and rotation RMSE against the truth at each pose's time, detection ratio);
- **the cameras** the workflow wrote against the truth (worst mm and °; Build item 2 asks 3 mm
  and 0.05° on clean renders);
- **the floor** (issue 26, Build item 6): what a per-instant fit with the true cameras and the
  body as built reaches with the corners the detector gives (``benchmarks/corner_ceiling.py
  --floor``'s edge-fit row over all sightings: every camera frame alone, RMS over sightings);
- **the workflow in the markers' frame** (reported, not a verdict): the same poses scored against
  the truth moved into the body frame the cube's markers define (:func:`markers_frame_truth`: the
  nominal layout's best fit to the cube as built, the frame ``calibrate-body`` gives). The truth's
  own body frame sits off it by the mean of the markers' build errors, which no image shows; the
  floor, fitted with the body as built, is the same in either frame (docs/history/accuracy.md, "Axes,
  cameras, time, and the truth's body frame").

Verdicts, per figure: **target** (realistic preset: position <= 0.6 cm, rotation <= 1.0°;
clean preset: <= 0.2 cm, <= 0.35°), **floor** (realistic only: the figure is above the target
but the floor is above the target too and the figure is within 15 % of the floor), **not met**.
The clean preset's targets are stated without a floor clause in the issue and are held as
written. Detection ratio: 1.000 to three decimals, or not met.

    nice -n 10 .venv/bin/python benchmarks/done_when.py [--out DIR] [--scenes realistic:1:101:preset ...]
        [--duration 8] [--drive 30] [--calibration-frames 12] [--json FILE]
    .venv/bin/python benchmarks/done_when.py --tables A.json B.json ...   (one table from separate runs)

Recordings under ``--out`` are reused when complete and of the same parameters (accuracy.py's
rule). The exit code is 0 for a completed run (a report); the last line counts the cells met.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import sys
import time
from dataclasses import dataclass
from pathlib import Path

BENCHMARKS = Path(__file__).resolve().parent
HOST = BENCHMARKS.parent / "host"
# preset -> (position cm, rotation °): issue 26's targets
TARGETS = {"realistic": (0.6, 1.0), "clean": (0.2, 0.35)}
FLOOR_CLAUSE = {"realistic": True, "clean": False}  # whether "within 15 % of the floor" may meet a target
FLOOR_MARGIN = 1.15
ROLES = ("preset", "development", "held-out")
# the scenes: the realistic and clean presets at 3 and 5 cameras (accuracy.py --quick's first seed),
# the development seeds 505/606 and the held-out seeds 717/828 (session 12) and 939 (session 13)
DEFAULT_SCENES = tuple(
    [f"{p}:{c}:101:preset" for p in ("realistic", "clean") for c in (1, 3)]
    + [f"{p}:1:{s}:development" for s in (505, 606) for p in ("realistic", "clean")]
    + [f"{p}:1:{s}:held-out" for s in (717, 828, 939) for p in ("realistic", "clean")])
MET_TARGET, MET_FLOOR, NOT_MET = "target", "floor", "NOT MET"


@dataclass(frozen=True)
class Scene:
    preset: str
    config: int
    seed: int
    role: str


def parse_scene(text: str) -> Scene:
    """``PRESET:CONFIG:SEED:ROLE`` -> a :class:`Scene` (ValueError when malformed)."""
    parts = text.split(":")
    if len(parts) != 4 or parts[0] not in TARGETS or parts[3] not in ROLES:
        raise ValueError(f"{text!r}: want PRESET:CONFIG:SEED:ROLE with PRESET in {sorted(TARGETS)}, "
                         f"ROLE in {ROLES}")
    return Scene(parts[0], int(parts[1]), int(parts[2]), parts[3])


def verdict(value: float, target: float, floor: float, floor_clause: bool) -> str:
    """Whether a figure meets its target: by the target itself, within 15 % of a floor that is
    above the target (where the preset allows it), or not (NaN: not met)."""
    if not math.isfinite(value):
        return NOT_MET
    if value <= target:
        return MET_TARGET
    if floor_clause and math.isfinite(floor) and floor > target and value <= FLOOR_MARGIN * floor:
        return MET_FLOOR
    return NOT_MET


def dr_verdict(dr: float) -> str:
    return MET_TARGET if math.isfinite(dr) and round(dr, 3) >= 1.0 else NOT_MET


def cell(scene: Scene, workflow: dict, floor: dict) -> dict:
    """One table row: the workflow's figures, the floor's, the ratios and the verdicts."""
    pos_t, rot_t = TARGETS[scene.preset]
    clause = FLOOR_CLAUSE[scene.preset]
    return {"scene": scene.__dict__, "workflow": workflow, "floor": floor,
            "pos_over_floor": workflow["pos_cm"] / floor["pos_cm"] if floor["pos_cm"] else math.nan,
            "rot_over_floor": workflow["rot_deg"] / floor["rot_deg"] if floor["rot_deg"] else math.nan,
            "verdict": {"position": verdict(workflow["pos_cm"], pos_t, floor["pos_cm"], clause),
                        "rotation": verdict(workflow["rot_deg"], rot_t, floor["rot_deg"], clause),
                        "dr": dr_verdict(workflow["dr"])}}


def markers_frame_truth(truth, nominal, built):
    """The truth trajectory (``Trajectory`` of T_world_cube, the cube's design frame) moved into the
    body frame the markers of the cube as built define: the frame in which the nominal layout
    fits them best (``calib.body``'s gauge, :func:`cubetrack.calib.body.best_fit_transform` of
    the built corners onto the nominal ones, T_markers_design). Each pose becomes
    T_world_design @ T_design_markers."""
    from scipy.spatial.transform import Rotation

    from cubetrack.calib.body import best_fit_transform
    from cubetrack.core.geometry import invert_T
    from cubetrack.io.trajectory import Trajectory

    T_design_markers = invert_T(best_fit_transform(built.corners_m.reshape(-1, 3), nominal.corners_m.reshape(-1, 3)))
    R_world_design = Rotation.from_quat(truth.quats_xyzw)
    return Trajectory(truth.times_s.copy(), truth.positions_m + R_world_design.apply(T_design_markers[:3, 3]),
                      (R_world_design * Rotation.from_matrix(T_design_markers[:3, :3])).as_quat())


def workflow_in_markers_frame(bench, rec: Path) -> dict:
    """The README workflow's poses of ``rec`` scored against :func:`markers_frame_truth`."""
    from cubetrack.core.layout import read_layout
    from cubetrack.io.config import read_tracker_config
    from cubetrack.io.trajectory import read_tum

    robot = read_tracker_config(rec / "config.toml").robots[0].name
    truth = markers_frame_truth(read_tum(rec / "ground_truth.tum"), read_layout(rec / "cube.toml"),
                                read_layout(rec / "true_cube.toml"))
    scores = bench.score(rec / "track" / bench.WORKFLOW / f"{robot}.tum", truth)
    return {"pos_cm": scores["pos_cm"], "rot_deg": scores["rot_deg"]}


def run_scene(bench, ceiling, scene: Scene, args: argparse.Namespace) -> dict:
    """Render (or reuse) a scene and its drive, run the README workflow, measure the floor."""
    from cubetrack.io.config import read_tracker_config
    from cubetrack.io.trajectory import read_tum

    name, cameras, height, tilt, _ = bench.CONFIGS[scene.config]
    work = args.out / f"w{scene.seed}"
    rec = bench.scene_dir(work, scene.config, scene.seed, scene.preset)
    bench.ensure_recording(bench.sim_params(scene.preset, cameras, height, tilt, scene.seed, args.duration,
                                            args.calibration_frames), rec, 2)
    full = rec.with_name(rec.name + "_drive")
    bench.ensure_recording(bench.sim_params(scene.preset, cameras, height, tilt, scene.seed,
                                            args.duration + args.drive, 0), full, 2)
    drive = bench.later_part(full, rec.with_name(rec.name + "_drive_after"),
                             bench.read_sim_start_s(full) + args.duration)
    robot = read_tracker_config(rec / "config.toml").robots[0].name
    t0 = time.monotonic()
    tum = rec / "track" / bench.WORKFLOW / f"{robot}.tum"
    if not (args.score_only and tum.exists()):
        tum = bench.readme_workflow(str(HOST), rec, drive, rec / "track" / bench.WORKFLOW, robot)
    workflow = bench.score(tum, read_tum(rec / "ground_truth.tum"))
    sightings = ceiling.cached(rec / ceiling.CACHE / "sightings.pkl", lambda: ceiling.capture_sightings(rec))
    truth = ceiling.Truth(rec)
    errors = ceiling.floor_errors(truth, sightings["sightings"], ceiling.true_markers(truth, sightings["sightings"]),
                                  None)
    floor = ceiling.floor_summary(errors)["all"]
    out = cell(scene, workflow, floor)
    out["cameras"] = camera_errors(rec / "track" / bench.WORKFLOW / "extrinsics.toml", rec / "true_extrinsics.toml")
    out["markers_frame"] = workflow_in_markers_frame(bench, rec)
    out["name"], out["seconds"] = name, time.monotonic() - t0
    return out


def camera_errors(extrinsics: Path, truth: Path) -> dict:
    """The workflow's cameras against the truth (issue 26 Build item 2: within 3 mm and 0.05° on
    clean renders): the worst position (mm) and rotation (°) error; NaN without the file."""
    from cubetrack.calib.extrinsics import extrinsics_errors
    from cubetrack.io.config import read_extrinsics

    if not extrinsics.exists():
        return {"worst_mm": math.nan, "worst_deg": math.nan}
    errors = extrinsics_errors(read_extrinsics(extrinsics), read_extrinsics(truth)).values()
    return {"worst_mm": 1000.0 * max(e[0] for e in errors), "worst_deg": max(e[1] for e in errors)}


def print_table(rows: list[dict]) -> None:
    """The markdown table, a block per role."""
    print("| role | preset | scene | seed | README workflow: position cm / rotation ° / DR | floor: position cm / "
          "rotation ° | workflow / floor | position | rotation | DR | cameras vs truth: worst mm / ° | workflow in "
          "the markers' frame: position cm / rotation ° (/ floor) |")
    print("| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |")
    for role in ROLES:
        for r in (r for r in rows if r["scene"]["role"] == role):
            w, f, v, s = r["workflow"], r["floor"], r["verdict"], r["scene"]
            cams = r.get("cameras", {"worst_mm": math.nan, "worst_deg": math.nan})
            m = r.get("markers_frame", {"pos_cm": math.nan, "rot_deg": math.nan})
            print(f"| {role} | {s['preset']} | {r['name']} | {s['seed']} | {w['pos_cm']:.2f} / {w['rot_deg']:.3f} / "
                  f"{w['dr']:.3f} | {f['pos_cm']:.2f} / {f['rot_deg']:.3f} | {r['pos_over_floor']:.2f}x / "
                  f"{r['rot_over_floor']:.2f}x | {v['position']} | {v['rotation']} | {v['dr']} | "
                  f"{cams['worst_mm']:.1f} / {cams['worst_deg']:.3f} | {m['pos_cm']:.2f} / {m['rot_deg']:.3f} "
                  f"({m['rot_deg'] / f['rot_deg']:.2f}x) |")


def parse_args(argv: list[str] | None) -> argparse.Namespace:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter, epilog=__doc__)
    ap.add_argument("--out", type=Path, default=Path("/tmp/done_when"),
                    help="folder of the recordings (reused when complete)")
    ap.add_argument("--scenes", nargs="+", default=list(DEFAULT_SCENES), metavar="PRESET:CONFIG:SEED:ROLE",
                    help="the scenes (default: the presets, development and held-out sets)")
    ap.add_argument("--duration", type=float, default=8.0, help="seconds of each scored session")
    ap.add_argument("--drive", type=float, default=30.0, help="seconds of the separate drive the workflow refines with")
    ap.add_argument("--calibration-frames", type=int, default=12, help="frames of the world-marker recording")
    ap.add_argument("--json", type=Path, help="also write the report here")
    ap.add_argument("--score-only", action="store_true",
                    help="score the workflow's files an earlier run left under --out instead of running its commands "
                         "again (a scene without them is run)")
    ap.add_argument("--tables", type=Path, nargs="+", metavar="JSON",
                    help="run nothing: print one table from these reports (--json of earlier runs)")
    args = ap.parse_args(argv)
    try:
        args.scenes = [parse_scene(s) for s in args.scenes]
    except ValueError as exc:
        ap.error(f"--scenes: {exc}")
    if args.duration <= 0 or args.drive <= 0 or args.calibration_frames <= 0:
        ap.error("--duration, --drive and --calibration-frames must be positive")
    return args


def print_summary(rows: list[dict]) -> None:
    cells = [v for r in rows for v in r["verdict"].values()]
    print(f"SUMMARY: {sum(v != NOT_MET for v in cells)} of {len(cells)} cells met "
          f"({sum(v == MET_FLOOR for v in cells)} by the floor clause)")


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    if args.tables:
        reports = [json.loads(p.read_text(encoding="utf-8")) for p in args.tables]
        sys.path.insert(0, str(BENCHMARKS))
        import accuracy

        for row in (row for r in reports for row in r["rows"]):  # a report from before: what it lacks, from --out
            s = row["scene"]
            rec = accuracy.scene_dir(args.out / f"w{s['seed']}", s["config"], s["seed"], s["preset"])
            if "cameras" not in row:
                row["cameras"] = camera_errors(rec / "track" / accuracy.WORKFLOW / "extrinsics.toml",
                                               rec / "true_extrinsics.toml")
            if "markers_frame" not in row and (rec / "true_cube.toml").exists():
                row["markers_frame"] = workflow_in_markers_frame(accuracy, rec)
        sources = (f"{p} ({r.get('code', 'code not recorded')}, load {r['load']})"
                   for p, r in zip(args.tables, reports, strict=True))
        print("issue 26 'Done when' from " + "; ".join(sources))
        print_table([row for r in reports for row in r["rows"]])
        print_summary([row for r in reports for row in r["rows"]])
        return 0
    sys.path.insert(0, str(BENCHMARKS))
    import accuracy
    import corner_ceiling

    args.out.mkdir(parents=True, exist_ok=True)
    load, code = " ".join(f"{v:.1f}" for v in os.getloadavg()), accuracy.code_version()  # the code the commands run
    rows = []
    for n, scene in enumerate(args.scenes, 1):
        rows.append(run_scene(accuracy, corner_ceiling, scene, args))
        r = rows[-1]
        print(f"[{n}/{len(args.scenes)}] {scene.preset} {r['name']} seed {scene.seed}: workflow "
              f"{r['workflow']['pos_cm']:.2f} cm / {r['workflow']['rot_deg']:.3f}°, floor {r['floor']['pos_cm']:.2f} "
              f"cm / {r['floor']['rot_deg']:.3f}° ({r['seconds']:.0f} s)", file=sys.stderr, flush=True)
    print(f"issue 26 'Done when': README workflow, default settings ({code}; {args.duration:g} s "
          f"sessions, {args.drive:g} s drive; load {load} -> "
          f"{' '.join(f'{v:.1f}' for v in os.getloadavg())}, {os.cpu_count()} cores)")
    print_table(rows)
    if args.json:
        args.json.write_text(json.dumps({"rows": rows, "load": load, "code": code}, indent=1),
                             encoding="utf-8")
    print_summary(rows)
    return 0


if __name__ == "__main__":
    sys.exit(main())
