"""Byte-identity check for refactors of the replay path (issue 23): the SHA-256 of every TUM / JSONL
file that ``cubetrack track --recording`` writes for the accuracy benchmark's scenes, tracked
several ways (the default filter, ``--smooth``, ``--fusion mean``, ``--uncalibrated``, one
thread and frame worker processes).

Run it on the code before a change (``--save before.json``) and after (``--compare before.json``):
the compare run prints every file whose digest changed and exits 1 if any did. The scenes are
rendered once into --work (``cubetrack simulate`` with a fixed seed gives byte-identical frames)
and reused. The JSONL's latency fields are computed from the recording, not the wall clock, so
a replay's files are deterministic.

    .venv/bin/python benchmarks/replay_digest.py --work /tmp/digest --save /tmp/digest/before.json
    .venv/bin/python benchmarks/replay_digest.py --work /tmp/digest --compare /tmp/digest/before.json
"""

from __future__ import annotations

import argparse
import hashlib
import json
import subprocess
import sys
from pathlib import Path

# (name, simulate arguments): the accuracy benchmark's 3 cams 1.0 m/30 deg (clean) and 5 cams 1.0 m/30 deg
# (realistic) arenas with its cube, frame rate and drop rate, seed 101 (none of the tests' seeds); the second
# is long enough (over 600 frames) for a replay to use frame worker processes
SCENES = (
    ("clean_c3_6s", ["--cameras", "3", "--height", "1.0", "--tilt", "30", "--duration", "6"]),
    ("real_c5_20s", ["--realistic", "--cameras", "5", "--height", "1.0", "--tilt", "30", "--duration", "20"]),
)
COMMON = ["--seed", "101", "--fps", "7.5", "--drop-rate", "0.05", "--jpeg-quality", "80",
          "--cube-size", "0.11", "--marker-size", "0.08", "--no-distinct-ids", "--calibration-frames", "0"]
# (name, track arguments besides --config/--recording/--out)
VARIANTS = (
    ("filter_threads", ["--extrinsics", "{rec}/true_extrinsics.toml", "--replay-workers", "0"]),
    ("filter_workers", ["--extrinsics", "{rec}/true_extrinsics.toml", "--replay-workers", "1"]),
    ("smooth", ["--extrinsics", "{rec}/true_extrinsics.toml", "--replay-workers", "0", "--smooth"]),
    ("mean", ["--extrinsics", "{rec}/true_extrinsics.toml", "--replay-workers", "0", "--fusion", "mean"]),
    ("uncalibrated", ["--uncalibrated", "--replay-workers", "0"]),
)


def cubetrack(*args: str) -> None:
    """Run one ``cubetrack`` command of this checkout's package; raise with its stderr on failure."""
    done = subprocess.run([sys.executable, "-m", "cubetrack.cli.main", *args], capture_output=True, text=True,
                          check=False)
    if done.returncode != 0:
        raise SystemExit(f"cubetrack {' '.join(args)} failed ({done.returncode}): {done.stderr.strip()[-2000:]}")


def digests(work: Path) -> dict[str, str]:
    """Render (or reuse) the scenes, track each every way; {relative file path: sha256}."""
    out: dict[str, str] = {}
    for scene, sim_args in SCENES:
        rec = work / scene
        if not (rec / "recording.json").exists():
            cubetrack("simulate", "--out", str(rec), "--force", *sim_args, *COMMON)
        for variant, track_args in VARIANTS:
            dest = work / "out" / scene / variant
            cubetrack("track", "--config", str(rec / "config.toml"), "--recording", str(rec), "--out", str(dest),
                      *(a.format(rec=rec) for a in track_args))
            for path in sorted(dest.rglob("*")):
                if path.suffix in (".tum", ".jsonl"):
                    out[str(path.relative_to(work / "out"))] = hashlib.sha256(path.read_bytes()).hexdigest()
    return out


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--work", type=Path, required=True, help="folder for the scenes and the replays' outputs")
    ap.add_argument("--save", type=Path, help="write the digests to this JSON file")
    ap.add_argument("--compare", type=Path, help="compare with the digests in this JSON file (exit 1 on a change)")
    args = ap.parse_args()
    now = digests(args.work)
    for name, digest in now.items():
        print(f"{digest}  {name}")
    if args.save:
        args.save.write_text(json.dumps(now, indent=1, sort_keys=True) + "\n", encoding="utf-8")
    if args.compare:
        before = json.loads(args.compare.read_text(encoding="utf-8"))
        changed = sorted(k for k in before.keys() | now.keys() if before.get(k) != now.get(k))
        for name in changed:
            print(f"CHANGED {name}: {before.get(name)} -> {now.get(name)}", file=sys.stderr)
        print(f"{len(now)} files, {len(changed)} changed", file=sys.stderr)
        return 1 if changed else 0
    return 0


if __name__ == "__main__":
    sys.exit(main())
