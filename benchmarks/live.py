"""Issue 9's benchmark: the live tracker on N emulated cameras x fps, over HTTP, as a user runs it.

A simulated recording (``cubetrack simulate``: N cameras at --fps, a short transfer latency so
each camera really delivers --fps) is calibrated (``cubetrack calibrate``) and served on 127.0.0.1
by the camera emulator in its own process (``cubecam emulate --loop``, through
:class:`cubetrack.app.emulated.EmulatedCameras`). The tracker runs as its own process too:
``cubetrack track --live`` for --duration seconds (with --record it also records the session, as
``--record`` does for a user: that costs the tracker's process a file per frame). Meanwhile
this script samples the tracker's process tree (its frame workers included) for CPU time and
RSS. Then it reports:

- frames/s offered (what the tracker received), processed, and dropped by the tracker (a camera's
  frame replaced by its next before a worker was free, or given up before its clock was known);
- CPU per processed frame and cores used (the tracker's processes; the emulator's shown apart);
- p50 / p95 / p99 of arrival -> pose and capture -> pose (the JSONL's ``arrival_latency`` and
  ``latency``: up to the moment each pose was handed to the outputs);
- the run interval by interval (between the tracker's status lines, every 5 s): frames dropped,
  poses, arrival -> pose p95 and cores used in each, so that a run missing the targets shows
  whether it missed them at the start, in a burst or throughout (issue 31's run-to-run spread);
- RSS of the tracker's processes at the start (after --warmup seconds), half-way and at the end,
  and the time from the tracker's command to its first pose (start-up);
- accuracy against the ground truth (moved onto the live clock, repeated per loop of the
  replay; poses from 0.05 s before to 0.5 s after the replay jumps back to its start are not
  scored, the robot teleports there) and against the offline replay (``cubetrack track
  --recording``) of the same frames: the simulated recording the emulator serves, or with
  --record the recorded session; the two must agree within 10 %;
- on the same frames (all of that recording, or its first --speed-frames), in this run: the
  naive loop (``cv2.imdecode`` colour + default ``ArucoDetector`` + ``solvePnP`` per marker, one
  thread), our tracker on one thread, and ours replaying them as fast as it can as ``cubetrack
  track --recording`` does here (one frame worker process per idle core beyond the first,
  started before the clock runs; this thread plans, fuses and does the jobs no worker has), with the CPU
  per frame of both sides, and with the live run's processed rate: the throughput ratios
  against the naive loop (--speed-rounds N: N interleaved rounds, medians), and the CPU per frame
  ours / naive (ours as replayed, and the live run's per processed frame);
- the machine's core count (``nproc``);
- with --outputs (issue 10): a second live session on the same cameras with every output on
  (``--zenoh --ros2 --vrpn --foxglove --mcap``, servers on free loopback ports, no client
  attached) and its processed frames/s, CPU per frame and arrival -> pose p95 against the
  first session's (pose files only), as ratios.
- with --watch (issue 27): a second live session with ``[camera_watch] enabled`` and its
  processed frames/s, CPU per frame, latency, dropped frames and events against the first's
  (watching off), as ratios; the live targets are checked on it too, and a moved event is a
  false alarm (nobody bumps a camera).

Targets (issues 9 and 31, on a 2-core machine at 16 cameras x 30 fps): <= 1 % of frames dropped
by the tracker; p95 arrival -> pose <= 15 ms and p99 <= 30 ms; throughput >= 4x the naive loop's
(>= 2.5x with --template: every run of ours with template corners); the live CPU per processed
frame <= 0.25x the naive loop's; live accuracy within 10 % of the offline replay's. The last line
lists the targets missed.

    .venv/bin/python benchmarks/live.py [--cameras 16] [--fps 30] [--duration 60] [--out DIR]
    .venv/bin/python benchmarks/live.py --quick        # 2 cameras x 10 fps for 5 s (the CI smoke run)
    .venv/bin/python benchmarks/live.py --outputs      # and the cost of every output (issue 10)
    .venv/bin/python benchmarks/live.py --speed-only --speed-rounds 5 --out /tmp/lb16   # naive / ours only
    .venv/bin/python benchmarks/live.py --template ...  # with corner_refinement = "template"
    .venv/bin/python benchmarks/live.py --watch        # and the cost of the camera watching (issue 27)
    .venv/bin/python benchmarks/live.py --worker-split --duration 15 --out /tmp/lb16   # a camera worker's CPU
    .venv/bin/python benchmarks/live.py --wake-cost 3 --speed-rounds 2 --out /tmp/lb16   # what waking per frame costs

--out keeps the recording, the calibration, the live poses and ``live_report.json``
(``speed_report.json`` with --speed-only; a recording made with the same parameters is reused).
Exit code 0 for a completed run (this is a report).
"""

from __future__ import annotations

import argparse
import contextlib
import itertools
import json
import os
import re
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    from cubetrack.app.kernels import CompiledKernels

ROOT = Path(__file__).resolve().parents[1]
REPORT_FILE = "live_report.json"
SPEED_REPORT_FILE = "speed_report.json"  # --speed-only
TARGET_DROPPED = 0.01
TARGET_P95_MS, TARGET_P99_MS = 15.0, 30.0
TARGET_SPEED = 4.0            # issue 31: throughput ours / naive on the same frames
TARGET_SPEED_TEMPLATE = 2.5   # the same with --template
TARGET_CPU = 0.25             # issue 31: CPU per processed live frame / the naive loop's CPU per frame
TARGET_ACCURACY = 0.10
STATUS_EVERY_S = 5.0          # the tracker's status lines (``--status-every``): the report's intervals
TICK = os.sysconf("SC_CLK_TCK")
PAGE = os.sysconf("SC_PAGE_SIZE")


def parse_args(argv: list[str] | None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], epilog=__doc__.split("\n\n", 1)[1],
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--cameras", type=int, default=16, help="emulated cameras (default 16)")
    p.add_argument("--fps", type=float, default=30.0, help="frames per second per camera (default 30)")
    p.add_argument("--duration", type=float, default=60.0, help="seconds of live tracking (default 60)")
    p.add_argument("--recording-s", type=float, default=20.0,
                   help="seconds of simulated recording, looped by the emulator (default 20)")
    p.add_argument("--warmup", type=float, default=5.0, help="seconds before the RSS 'start' sample (default 5)")
    p.add_argument("--speed-frames", type=int, help="frames of the session for the naive-loop comparison "
                   "(default: the whole recording, as `track --recording` replays it; its first seconds, where "
                   "the track starts and the cameras' clocks are first read, weigh more in a shorter part)")
    p.add_argument("--speed-rounds", type=int, default=1,
                   help="rounds of the same-frames comparison, interleaved (medians reported; default 1)")
    p.add_argument("--speed-only", action="store_true",
                   help="only the same-frames comparison (naive / one thread / ours), on the recording of --out "
                        "made with the same parameters (or a new one): no live run, no accuracy")
    p.add_argument("--worker-split", action="store_true",
                   help="only where a camera worker process's CPU goes: its loop in this process over half the "
                        "cameras for --duration s, fed by the emulator, the fusion in a thread standing in for the "
                        "tracker's process (no live run, no accuracy, no same-frames comparison)")
    p.add_argument("--wake-cost", type=float, metavar="GAP_MS",
                   help="only what waking per frame costs the same work (issue 31): the first --speed-frames frames "
                        "(default 2000) on one thread as the replay plans, works and fuses them, back to back and with "
                        "a sleep of GAP_MS before each frame (as a live worker process sleeps between frames), "
                        "--speed-rounds rounds interleaved (no live run, no accuracy)")
    p.add_argument("--frames-per-wake", type=int, default=1, metavar="N",
                   help="with --wake-cost: sleep before every Nth frame only (N frames per wake; default 1)")
    p.add_argument("--seed", type=int, default=7, help="scene seed (default 7)")
    p.add_argument("--out", type=Path, help="keep everything here (default: a temporary folder, deleted)")
    p.add_argument("--quick", action="store_true", help="smoke run: 2 cameras x 10 fps, 5 s, small recording")
    p.add_argument("--record", action="store_true",
                   help="the tracker records the session too; the offline replay and the speed comparison use it")
    p.add_argument("--worker-kind", choices=("auto", "process", "thread", "camera-process"),
                   help="the tracker's [live] worker_kind (default: the config's, i.e. the package default)")
    p.add_argument("--workers", type=int, help="the tracker's [live] workers (default: the config's, one per core)")
    p.add_argument("--outputs", action="store_true",
                   help="issue 10: a second live session with every output on (--zenoh --ros2 --vrpn --foxglove "
                        "--mcap), compared with the first (pose files only)")
    p.add_argument("--watch", action="store_true",
                   help="issue 27: a second live session with [camera_watch] enabled (every camera watched against "
                        "the others), compared with the first (watching off)")
    p.add_argument("--template", action="store_true",
                   help='[detector] corner_refinement = "template" for every run of ours (live, offline, same frames)')
    p.add_argument("--tracker-arg", action="append", default=[], metavar="ARG",
                   help="extra argument for `cubetrack track` (repeatable)")
    args = p.parse_args(argv)
    if args.worker_split and (args.speed_only or args.record or args.outputs or args.watch):
        p.error("--worker-split runs alone: no --speed-only, --record, --outputs or --watch")
    if args.wake_cost is not None and (args.worker_split or args.speed_only or args.record or args.outputs
                                       or args.watch or not args.wake_cost > 0):
        p.error("--wake-cost (positive) runs alone: no --worker-split, --speed-only, --record, --outputs or --watch")
    if args.speed_only and (args.record or args.outputs or args.watch):
        p.error("--speed-only replays the simulated recording: no --record, --outputs or --watch")
    if args.quick:
        args.cameras, args.fps, args.duration, args.recording_s = 2, 10.0, 5.0, 3.0
        args.warmup, args.speed_frames = 1.5, 60
    for name in ("cameras", "fps", "duration", "recording_s", "speed_frames", "speed_rounds", "workers",
                 "frames_per_wake"):
        if getattr(args, name) is not None and not getattr(args, name) > 0:
            p.error(f"--{name.replace('_', '-')} must be positive")
    return args


def cubetrack(*argv: str) -> None:
    """A cubetrack command in-process (setup steps); its output goes to stderr."""
    from cubetrack.cli.main import main

    with contextlib.redirect_stdout(sys.stderr):
        code = main(list(argv))
    if code != 0:
        raise SystemExit(f"cubetrack {argv[0]} failed ({code})")


def ensure_recording(args: argparse.Namespace, work: Path) -> Path:
    rec = work / f"rec_c{args.cameras}_f{args.fps:g}_d{args.recording_s:g}_s{args.seed}"
    if (rec / "extrinsics.toml").exists():
        return rec
    cubetrack("simulate", "--out", str(rec), "--force", "--cameras", str(args.cameras), "--fps", str(args.fps),
              "--duration", str(args.recording_s), "--seed", str(args.seed),
              "--latency-ms", "8", "--latency-jitter-ms", "2", "--spike-rate", "0", "--drop-rate", "0",
              "--calibration-frames", "30" if args.quick else "60")
    cubetrack("calibrate", "--config", str(rec / "config.toml"), "--recording", str(rec / "calibration"),
              "--out", str(rec / "extrinsics.toml"))
    return rec


def tracker_config(args: argparse.Namespace, rec: Path, work: Path) -> Path:
    """The recording's tracker config, or with --template a copy (paths made absolute) whose
    ``[detector]`` asks for template corners."""
    if not args.template:
        return rec / "config.toml"
    from cubetrack.app.demo import write_live_config
    from cubetrack.io.config import read_tracker_config

    config = read_tracker_config(rec / "config.toml")
    if "detector" in config.sections:
        raise SystemExit(f"{rec / 'config.toml'} has a [detector] section: --template would overrule it")
    out = write_live_config(rec / "config.toml", {c.name: c.url for c in config.cameras}, work / "template_config.toml")
    out.write_text(out.read_text(encoding="utf-8") + '\n[detector]\ncorner_refinement = "template"\n', encoding="utf-8")
    return out


# --------------------------------------------------------------------------- process sampling


def _children(pid: int) -> list[int]:
    out = []
    with contextlib.suppress(OSError):
        for task in os.listdir(f"/proc/{pid}/task"):
            with open(f"/proc/{pid}/task/{task}/children") as f:
                out += [int(c) for c in f.read().split()]
    return out


def _tree(pid: int) -> list[int]:
    pids, todo = [], [pid]
    while todo:
        p = todo.pop()
        pids.append(p)
        todo += _children(p)
    return pids


def process_cpu_rss(pid: int) -> tuple[float, int] | None:
    """User + system CPU seconds (all threads) and resident bytes of process ``pid`` (None: gone).
    benchmarks/outputs.py reads its child's CPU with it too."""
    try:
        with open(f"/proc/{pid}/stat") as f:
            fields = f.read().rsplit(")", 1)[1].split()
        with open(f"/proc/{pid}/statm") as f:
            rss_pages = int(f.read().split()[1])
    except (OSError, IndexError, ValueError):
        return None
    return (int(fields[11]) + int(fields[12])) / TICK, rss_pages * PAGE


RSS_EVERY_S = 30.0  # the report's RSS over time: one sample this often


class TreeSampler:
    """Samples a process and its descendants every ``period_s``: CPU seconds (each process's last
    value is kept, so processes that ended still count) and the summed RSS."""

    def __init__(self, pid: int, period_s: float = 0.25):
        self.pid, self.period_s = pid, period_s
        self.cpu: dict[int, float] = {}
        self.samples: list[tuple[float, float, int, int]] = []  # (monotonic s, CPU s, RSS bytes, processes)
        self.main_cpu: list[float] = []  # the first process's own CPU s, per sample
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while not self._stop.is_set():
            rss, alive = 0, 0
            for p in _tree(self.pid):
                got = process_cpu_rss(p)
                if got is not None:
                    self.cpu[p], r = got   # an ended process's CPU still counts; a zombie (no RSS) is not alive
                    rss, alive = rss + r, alive + (r > 0)
            if rss:
                self.samples.append((time.monotonic(), sum(self.cpu.values()), rss, alive))
                self.main_cpu.append(self.cpu.get(self.pid, 0.0))
            self._stop.wait(self.period_s)

    def stop(self) -> None:
        self._stop.set()
        self._thread.join()

    def at(self, t: float) -> tuple[float, float, int, int]:
        return min(self.samples, key=lambda s: abs(s[0] - t))

    def last_full(self) -> tuple[float, float, int, int]:
        """The last sample with every process (frame workers included) still running."""
        most = max(s[3] for s in self.samples)
        return [s for s in self.samples if s[3] == most][-1]


_STATUS_DROPPED = re.compile(r"^track:\s+[\d.]+s \|.* dropped (\d+)")


class StatusFollower:
    """Follows the tracker's stderr file as the tracker writes it, every ``period_s``: the moment
    (``time.monotonic()``) each status line appeared, with the frames dropped by the tracker so far
    that it gives; the moments are what put the drops beside the poses and the CPU samples
    (:func:`over_time`)."""

    def __init__(self, path: Path, period_s: float = 0.05):
        self.path, self.period_s = path, period_s  # (0.25 s made the start-up a multiple of it, give or take)
        self.lines: list[tuple[float, int]] = []  # (monotonic s, dropped so far)
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _run(self) -> None:
        offset, partial = 0, ""
        while True:
            stopping = self._stop.wait(self.period_s)
            with contextlib.suppress(OSError), open(self.path, encoding="utf-8", errors="replace") as f:
                f.seek(offset)
                text = partial + f.read()
                offset = f.tell()
                *complete, partial = text.split("\n")
                now = time.monotonic()
                for line in complete:
                    if (m := _STATUS_DROPPED.match(line)) is not None:
                        self.lines.append((now, int(m.group(1))))
            if stopping:
                return

    def stop(self) -> None:
        self._stop.set()
        self._thread.join()


def over_time(status: list[tuple[float, int]], poses: list[dict], samples: list[tuple[float, float, int, int]],
              start_s: float, unix_minus_monotonic: float) -> list[dict]:
    """The live run interval by interval, from the tracker's command (``start_s``, monotonic) to each
    status line's moment in turn (``status``: :class:`StatusFollower`'s lines): frames dropped by the
    tracker in it, poses handed to the outputs in it (a pose's capture time + its capture -> pose
    latency, Unix s) and their arrival -> pose p95, and the tracker's cores used in it (the
    :class:`TreeSampler` samples nearest its ends). A run that misses the drop or latency targets then
    shows when: at the start (start-up), in a burst (a pause), or throughout (short of CPU)."""
    handed = np.array([p["time"] + p["latency"] - unix_minus_monotonic for p in poses])
    arrival_ms = np.array([p["arrival_latency"] * 1000.0 for p in poses])
    out, begin, dropped_before = [], start_s, 0
    for end, dropped in status:
        inside = (handed >= begin) & (handed < end)
        (t0, cpu0, _, _), (t1, cpu1, _, _) = (min(samples, key=lambda s, t=t: abs(s[0] - t)) for t in (begin, end))
        out.append({"from_s": begin - start_s, "to_s": end - start_s, "dropped": dropped - dropped_before,
                    "poses": int(inside.sum()),
                    "arrival_p95_ms": float(np.percentile(arrival_ms[inside], 95)) if inside.any() else float("nan"),
                    "cores": (cpu1 - cpu0) / (t1 - t0) if t1 > t0 else float("nan")})
        begin, dropped_before = end, dropped
    return out


# --------------------------------------------------------------------------- the live run


def warm_kernels() -> CompiledKernels:
    """Every kernel a tracker compiles (as ``cubetrack compile`` does), here, before the timed run: numba
    compiles them into its on-disk cache, or loads them from it, so that the tracker's processes load them
    instead of compiling during the run. A cold cache (the first run after an install, an upgrade or a
    change to a kernel's source) costs each of those processes seconds of CPU on the cores the run needs:
    a first run's drops that a second run does not have."""
    from cubetrack.app.kernels import compile_all

    return compile_all()


def live_section(args: argparse.Namespace) -> str:
    """The ``[live]`` section --worker-kind and --workers ask for (empty: the config's)."""
    keys = ([f'worker_kind = "{args.worker_kind}"'] if args.worker_kind else []) + \
        ([f"workers = {args.workers}"] if args.workers else [])
    return "\n[live]\n" + "".join(f"{k}\n" for k in keys) if keys else ""


def run_live(args: argparse.Namespace, rec: Path, work: Path, name: str = "live",
             outputs: tuple[str, ...] = (), sections: str = "") -> dict:
    """One live session of the tracker (``name``: its folder in ``work`` and the prefix of its log
    files; ``outputs``: output flags for ``cubetrack track``, none: the pose files only;
    ``sections``: TOML appended to its config)."""
    from cubetrack.app.demo import write_live_config
    from cubetrack.app.emulated import EmulatedCameras

    out, session = work / name, work / "session"
    for path in (out, session):
        if path.exists():
            subprocess.run(["rm", "-rf", str(path)], check=True)
    with EmulatedCameras(rec, ("--loop",)) as emu:
        config = write_live_config(tracker_config(args, rec, work), emu.urls, work / "live_config.toml")
        sections += live_section(args)
        if sections:
            config.write_text(config.read_text(encoding="utf-8") + sections, encoding="utf-8")
        command = [sys.executable, "-m", "cubetrack.cli.main", "track", "--config", str(config),
                   "--extrinsics", str(rec / "extrinsics.toml"), "--live", "--out", str(out),
                   "--duration", str(args.duration), "--status-every", f"{STATUS_EVERY_S:g}",
                   *(["--record", str(session)] if args.record and name == "live" else []), *outputs,
                   *args.tracker_arg]
        emulator = TreeSampler(emu._process.pid, 1.0)
        started = time.monotonic()
        unix_minus_monotonic = time.time() - started
        with open(work / f"{name}_stdout.txt", "w") as stdout, open(work / f"{name}_stderr.txt", "w") as stderr:
            proc = subprocess.Popen(command, stdout=stdout, stderr=stderr, cwd=ROOT)
            sampler, status = TreeSampler(proc.pid), StatusFollower(work / f"{name}_stderr.txt")
            code = proc.wait(args.duration + 300)
        ended = time.monotonic()
        sampler.stop()
        status.stop()
        emulator.stop()
        shift_s, period_s = emu.clock_shift_s, emu.period_s
    if code != 0:
        raise SystemExit(f"the live tracker failed ({code}): {(work / f'{name}_stderr.txt').read_text()[-2000:]}")
    text = (work / f"{name}_stdout.txt").read_text()
    cams = [tuple(map(int, m)) for m in re.findall(r": (\d+) frames, (\d+) dropped", text)]
    summary = re.search(r"tracked live for ([\d.]+) s: frames: (\d+), before their camera's clock was known: (\d+)",
                        text)
    if summary is None or len(cams) != args.cameras:
        raise SystemExit(f"cannot read the tracker's summary:\n{text}")
    duration_s = float(summary.group(1))
    taken, before_clock = int(summary.group(2)), int(summary.group(3))
    offered = sum(f for f, _ in cams)
    dropped_behind = sum(d for _, d in cams)
    processed = taken - before_clock
    first, last, full = sampler.samples[0], sampler.samples[-1], sampler.last_full()
    warm = sampler.at(started + args.warmup)
    main_cpu = (sampler.main_cpu[sampler.samples.index(full)] - sampler.main_cpu[sampler.samples.index(warm)])
    cpu_emulator = emulator.samples[-1][1] - emulator.samples[0][1] if len(emulator.samples) > 1 else float("nan")
    poses = [json.loads(line) for line in (out / "robot.jsonl").read_text().splitlines()]
    fused = [p for p in poses if not p.get("predicted")]
    # CPU per frame after the warm-up (worker processes importing the stages excluded): frames
    # processed in that window estimated from the poses captured in it
    window = (warm[0] + unix_minus_monotonic, full[0] + unix_minus_monotonic)
    window_frames = sum(window[0] <= p["time"] <= window[1] for p in fused) * processed / max(len(fused), 1)
    # the first pose's moment (capture + capture -> pose) after the tracker's command started: start-up
    first_pose_s = (min((p["time"] + p["latency"] for p in fused), default=float("nan"))
                    - (started + unix_minus_monotonic))
    arrival = np.array([p["arrival_latency"] for p in fused]) * 1000.0
    capture = np.array([p["latency"] for p in fused]) * 1000.0
    return {
        "command": " ".join(command[1:]),
        "duration_s": duration_s,
        "wall_s": ended - started,
        "offered_frames": offered,
        "processed_frames": processed,
        "dropped_behind": dropped_behind,
        "dropped_before_clock": before_clock,
        "offered_fps": offered / duration_s,
        "processed_fps": processed / duration_s,
        "dropped_fps": (dropped_behind + before_clock) / duration_s,
        "dropped_fraction": (dropped_behind + before_clock) / max(offered, 1),
        "cpu_s": last[1] - first[1],
        "cpu_ms_per_frame": (last[1] - first[1]) / max(processed, 1) * 1000.0,
        "cpu_ms_per_frame_warm": (full[1] - warm[1]) / max(window_frames, 1) * 1000.0,
        "processed_fps_warm": window_frames / max(full[0] - warm[0], 1e-9),
        "offered_fps_warm": offered_after(args.warmup, (work / f"{name}_stderr.txt").read_text()),
        "cores_used": (full[1] - warm[1]) / max(full[0] - warm[0], 1e-9),
        "main_cores_used": main_cpu / max(full[0] - warm[0], 1e-9),
        "emulator_cores_used": cpu_emulator / max(emulator.samples[-1][0] - emulator.samples[0][0], 1e-9)
        if len(emulator.samples) > 1 else float("nan"),
        # yardsticks of the machine's speed in this run, from code that is the same in every tree compared: the
        # emulator's CPU per frame it served, and the tracker's start-up (its command to the start of its session,
        # the first status line's moment less the status interval: before any frame is read; an upper bound, as
        # a busy loop prints its first status line late)
        "emulator_ms_per_frame": cpu_emulator / max(offered, 1) * 1000.0,
        "startup_s": status.lines[0][0] - started - STATUS_EVERY_S if status.lines else float("nan"),
        "rss_start_mb": warm[2] / 1e6,
        "rss_mid_mb": sampler.at(started + 0.5 * (warm[0] - started + full[0] - started))[2] / 1e6,
        "rss_end_mb": full[2] / 1e6,
        # (s from the tracker's command, MB, processes) every RSS_EVERY_S: flat or not, and whether a
        # change is a process starting or ending rather than one growing
        "rss_over_time": [(round(t - started, 1), round(rss / 1e6, 1), alive)
                          for t, _cpu, rss, alive in sampler.samples[::max(1, round(RSS_EVERY_S / sampler.period_s))]],
        "first_pose_s": first_pose_s,
        "poses": len(fused),
        "arrival_ms": percentiles(arrival),
        "capture_ms": percentiles(capture),
        "clock_shift_s": shift_s,
        "period_s": period_s,
        "over_time": over_time(status.lines, fused, sampler.samples, started, unix_minus_monotonic),
    }


def offered_after(warmup_s: float, stderr: str, every_s: float = STATUS_EVERY_S) -> float:
    """Frames/s received from all cameras after ``warmup_s``: the mean over the tracker's status
    lines (every ``every_s``) whose interval began after it; NaN when there is none."""
    rates = [sum(float(v) for v in re.findall(r" ([\d.]+) fps", rest))
             for at, rest in re.findall(r"^track:\s+(\d+)s \|(.*)$", stderr, re.MULTILINE)
             if int(at) - every_s >= warmup_s - 0.5]
    return float(np.mean(rates)) if rates else float("nan")


def free_port() -> int:
    """A TCP port of 127.0.0.1 free right now."""
    import socket

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def outputs_cost(args: argparse.Namespace, rec: Path, work: Path, files_only: dict) -> dict:
    """Issue 10's check: a second live session on the same cameras with every output on (Zenoh
    JSON, ROS 2 over Zenoh, VRPN, Foxglove WebSocket, MCAP with every camera frame) against
    ``files_only`` (the session with the pose files only): processed frames/s, CPU per frame
    and arrival -> pose latency of both, and their ratios."""
    mcap = work / "live_outputs.mcap"
    flags = ("--zenoh", "--ros2", "--vrpn", f"127.0.0.1:{free_port()}", "--foxglove", f"127.0.0.1:{free_port()}",
             "--mcap", str(mcap))
    on = run_live(args, rec, work, "live_outputs", flags)
    mcap_mb = mcap.stat().st_size / 1e6 if mcap.exists() else 0.0
    mcap.unlink(missing_ok=True)  # every camera frame: large
    return {"flags": " ".join(flags), "mcap_mb": mcap_mb, "files_only": {k: files_only[k] for k in COMPARED},
            "all_outputs": {k: on[k] for k in COMPARED}, **ratios(files_only, on)}


COMPARED = ("processed_fps", "dropped_fraction", "cpu_ms_per_frame", "cores_used", "arrival_ms", "poses")
WATCH_SECTION = "\n[camera_watch]\nenabled = true\n"


def ratios(off: dict, on: dict) -> dict:
    """A second live session ``on`` against the first, ``off``: processed frames/s, CPU per frame,
    p95 arrival -> pose."""
    return {"processed_ratio": on["processed_fps"] / max(off["processed_fps"], 1e-9),
            "cpu_ratio": on["cpu_ms_per_frame"] / max(off["cpu_ms_per_frame"], 1e-9),
            "p95_ratio": on["arrival_ms"]["p95"] / max(off["arrival_ms"]["p95"], 1e-9)}


def watch_cost(args: argparse.Namespace, rec: Path, work: Path, off: dict) -> dict:
    """Issue 27's check: a second live session on the same cameras with ``[camera_watch] enabled``
    against ``off`` (the first, watching off): the same figures, their ratios, the live targets
    the watched session misses and the watcher's events (none expected: nobody bumps a camera)."""
    on = run_live(args, rec, work, "live_watched", sections=WATCH_SECTION)
    events_file = work / "live_watched" / "camera_watch.jsonl"
    events = events_file.read_text(encoding="utf-8").splitlines() if events_file.exists() else []
    return {"watch_off": {k: off[k] for k in COMPARED}, "watch_on": {k: on[k] for k in COMPARED},
            "events": [json.loads(line) for line in events], "failures": live_failures(on), **ratios(off, on)}


def compared_text(r: dict, off: dict, on: dict, off_name: str, on_name: str) -> str:
    """Two live sessions' figures and their :func:`ratios` ``r``, as one line of the report."""
    return (f"{off_name} {off['processed_fps']:.1f} frames/s processed, {off['cpu_ms_per_frame']:.2f} ms CPU per "
            f"frame, arrival -> pose p95 {off['arrival_ms']['p95']:.1f} ms; {on_name} {on['processed_fps']:.1f} "
            f"frames/s, {on['cpu_ms_per_frame']:.2f} ms, p95 {on['arrival_ms']['p95']:.1f} ms; on/off: processed "
            f"{r['processed_ratio']:.2f}, CPU per frame {r['cpu_ratio']:.2f}, p95 {r['p95_ratio']:.2f}")


def live_failures(live: dict) -> list[str]:
    """The live targets (dropped frames, arrival -> pose p95 and p99) a session misses."""
    a, failures = live["arrival_ms"], []
    if live["dropped_fraction"] > TARGET_DROPPED:
        failures.append(f"dropped {live['dropped_fraction'] * 100:.1f} % > {TARGET_DROPPED * 100:g} %")
    if not a["p95"] <= TARGET_P95_MS:
        failures.append(f"p95 arrival->pose {a['p95']:.1f} ms > {TARGET_P95_MS:g}")
    if not a["p99"] <= TARGET_P99_MS:
        failures.append(f"p99 arrival->pose {a['p99']:.1f} ms > {TARGET_P99_MS:g}")
    return failures


def percentiles(values: np.ndarray) -> dict:
    if not len(values):
        return {"p50": float("nan"), "p95": float("nan"), "p99": float("nan")}
    p50, p95, p99 = np.percentile(values, [50, 95, 99])
    return {"p50": float(p50), "p95": float(p95), "p99": float(p99)}


# --------------------------------------------------------------------------- accuracy


SEAM_S = (0.05, 0.5)  # not scored: this long before and after the replay jumps back to its start


def live_truth(rec: Path, shift_s: float, period_s: float, span_s: tuple[float, float]):
    """The recording's ground truth on the live clock, repeated for every loop of the replay,
    within ``span_s`` (the live session's first and last frame), and the loops' seams (where the
    robot jumps back to where the recording started: poses around them are not scored)."""
    from cubetrack.io.trajectory import Trajectory, read_tum

    truth = read_tum(rec / "ground_truth.tum")
    first = float(truth.times_s[0]) + shift_s
    loops = int(np.ceil((span_s[1] - first) / period_s)) + 1
    times = np.concatenate([truth.times_s + shift_s + k * period_s for k in range(loops)])
    seams = first + period_s * np.arange(1, loops)
    keep = (times >= span_s[0]) & (times <= span_s[1])
    return Trajectory(times[keep], np.tile(truth.positions_m, (loops, 1))[keep],
                      np.tile(truth.quats_xyzw, (loops, 1))[keep]), seams


def away_from_seams(trajectory, seams: np.ndarray):
    """The part of ``trajectory`` that is scored."""
    from cubetrack.io.trajectory import Trajectory

    keep = scored(trajectory.times_s, seams)
    return Trajectory(trajectory.times_s[keep], trajectory.positions_m[keep], trajectory.quats_xyzw[keep])


def scored(times: np.ndarray, seams: np.ndarray) -> np.ndarray:
    """Which times are far enough from every seam to be scored."""
    ok = np.ones(len(times), dtype=bool)
    for seam in seams:
        ok &= (times < seam - SEAM_S[0]) | (times > seam + SEAM_S[1])
    return ok


def replayed(args: argparse.Namespace, rec: Path, work: Path) -> tuple[Path, Path]:
    """(config, recording) of the frames the live run was given: the recorded session with
    --record, else the simulated recording the emulator served."""
    return (work / "live_config.toml", work / "session") if args.record else (tracker_config(args, rec, work), rec)


def accuracy(args: argparse.Namespace, rec: Path, work: Path, live: dict) -> dict:
    from cubetrack.evaluate.metrics import evaluate
    from cubetrack.io.recording import Recording
    from cubetrack.io.trajectory import read_tum

    offline = work / "offline"
    config, recording = replayed(args, rec, work)
    cubetrack("track", "--config", str(config), "--extrinsics", str(rec / "extrinsics.toml"),
              "--recording", str(recording), "--out", str(offline))
    if args.record:
        session = Recording.open(recording)
        arrivals = [f.host_time_s for c in session.camera_names for f in session.index(c)]
        span = (min(arrivals), max(arrivals))
    else:
        times = read_tum(work / "live" / "robot.tum").times_s
        span = (float(times[0]) - 1.0, float(times[-1]))
    truth, seams = live_truth(rec, live["clock_shift_s"], live["period_s"], span)
    offline_truth = (read_tum(rec / "ground_truth.tum"), np.zeros(0))
    out = {}
    runs = (("live", work / "live" / "robot.tum", (truth, seams)),
            ("offline", offline / "robot.tum", (truth, seams) if args.record else offline_truth))
    for name, path, (gt, cuts) in runs:
        poses = read_tum(path)
        r = evaluate(away_from_seams(poses, cuts), away_from_seams(gt, cuts))
        out[name] = {"pos_cm": r.position_rmse_m * 100.0, "rot_deg": r.rotation_rmse_deg,
                     "detection_ratio": evaluate(poses, gt).detection_ratio, "poses": len(poses)}
    out["pos_ratio"] = out["live"]["pos_cm"] / out["offline"]["pos_cm"]
    out["rot_ratio"] = out["live"]["rot_deg"] / out["offline"]["rot_deg"]
    return out


# --------------------------------------------------------------------------- the same frames, naive and ours


def speed(args: argparse.Namespace, rec: Path, work: Path, live: dict | None) -> dict:
    """The naive loop (one thread), our tracker on one thread frame by frame (without the clock
    round trips: the latency budget's processing part), the replay on one thread (``track
    --recording --replay-workers 0``) and ours as ``cubetrack track --recording`` replays here
    (its frame worker processes, started before the clock runs, and its thread planning, fusing
    and doing the jobs no worker has) over the same frames (:func:`replayed`), in memory:
    --speed-rounds rounds, interleaved; the figures are the medians over the rounds (each
    round's in ``rounds``). ``live``: the live run, for the live processed / naive ratio (None:
    --speed-only)."""
    import cv2

    from cubetrack.app.config import load_config, recording_intrinsics
    from cubetrack.app.track import replay_pool, replay_workers, track_frames
    from cubetrack.app.tracker import Tracker
    from cubetrack.core.layout import marker_corners_m
    from cubetrack.io.config import read_extrinsics
    from cubetrack.io.recording import Recording

    config_path, recording_path = replayed(args, rec, work)
    config, settings = load_config(config_path)
    recording = Recording.open(recording_path)
    frames = list(itertools.islice(recording.merged_frames(), args.speed_frames))
    intrinsics = recording_intrinsics(config, recording)
    extrinsics = read_extrinsics(rec / "extrinsics.toml")
    layouts = {r.name: r.layout for r in config.robots}
    clock = {c: recording.clock_samples(c) for c in recording.camera_names}

    cv2.setNumThreads(1)
    sizes = {config.world.marker_id: config.world.marker_size_m}
    for robot in config.robots:
        for m in robot.layout.markers:
            sizes.setdefault(m.marker_id, m.size_m)
    objects = {i: marker_corners_m(s).astype(np.float64) for i, s in sizes.items()}
    detector = cv2.aruco.ArucoDetector(cv2.aruco.getPredefinedDictionary(cv2.aruco.DICT_4X4_50))

    def naive() -> tuple[float, float]:
        """Frames/s and CPU ms per frame (this process: the loop runs on one thread)."""
        t0, cpu0 = time.perf_counter(), time.process_time()
        for frame in frames:
            img = cv2.imdecode(np.frombuffer(frame.jpeg, np.uint8), cv2.IMREAD_COLOR)
            corners, ids, _ = detector.detectMarkers(img)
            if ids is None:
                continue
            intr = intrinsics[frame.camera]
            for c, marker_id in zip(corners, ids.reshape(-1), strict=True):
                if int(marker_id) in objects:
                    cv2.solvePnP(objects[int(marker_id)], c.reshape(4, 2), intr.K, intr.dist,
                                 flags=cv2.SOLVEPNP_IPPE_SQUARE)
        return len(frames) / (time.perf_counter() - t0), (time.process_time() - cpu0) / len(frames) * 1000.0

    def inline() -> tuple[float, list[float], list[float]]:
        """One thread, frame by frame: the processing part of the latency budget."""
        tracker = Tracker(intrinsics, config.world, config.robots, extrinsics, settings.stages)
        work_ms, fuse_ms = [], []
        t0 = time.perf_counter()
        for frame in frames:
            job = tracker.admit(frame)
            if job is None:
                continue
            t1 = time.perf_counter()
            result = tracker.processor.work(job)
            t2 = time.perf_counter()
            tracker.fuse(result, frame.host_time_s)
            work_ms.append((t2 - t1) * 1000.0)
            fuse_ms.append((time.perf_counter() - t2) * 1000.0)
        return len(frames) / (time.perf_counter() - t0), work_ms, fuse_ms

    def ours(workers: int) -> tuple[float, float, float, int]:
        """The replay with ``workers`` frame worker processes (0: one thread): frames/s, CPU ms per
        frame of this process and of the worker processes, jobs they did."""
        pool = replay_pool(intrinsics, config.world, layouts, extrinsics, settings.stages, workers) \
            if workers else None
        with pool or contextlib.nullcontext():
            while pool is not None and not pool.all_started:
                pool.wait(0.2)
                pool.take()  # raises if a worker process failed to start
            pids = pool.process_ids if pool is not None else []
            cpu0, main0, t0 = sum(process_cpu_rss(p)[0] for p in pids), time.process_time(), time.perf_counter()
            track_frames(frames, intrinsics, config.world, layouts, extrinsics, _NoSink(), settings.stages,
                         clock_samples=clock, pool=pool)
            wall = time.perf_counter() - t0
            main_ms, workers_ms = ((time.process_time() - main0) / len(frames) * 1000.0,
                                   (sum(process_cpu_rss(p)[0] for p in pids) - cpu0) / len(frames) * 1000.0)
        return len(frames) / wall, main_ms, workers_ms, pool.submitted if pool is not None else 0

    workers = replay_workers()
    rounds = []
    for k in range(args.speed_rounds):
        print(f"  speed round {k + 1} of {args.speed_rounds} ...", file=sys.stderr, flush=True)
        naive_fps, naive_cpu_ms = naive()
        inline_fps, work_ms, fuse_ms = inline()
        one_thread_fps = ours(0)[0] if workers else None
        ours_fps, main_ms, workers_ms, jobs = ours(workers)
        one_thread_fps = one_thread_fps or ours_fps
        rounds.append({"naive_fps": naive_fps, "inline_fps": inline_fps, "ours_fps": ours_fps,
                       "one_thread_fps": one_thread_fps, "ratio": ours_fps / naive_fps,
                       "one_thread_ratio": one_thread_fps / naive_fps, "inline_ratio": inline_fps / naive_fps,
                       "ours_cpu_ms": {"main": main_ms, "workers": workers_ms}, "worker_jobs": jobs,
                       "naive_cpu_ms": naive_cpu_ms, "cpu_ratio": (main_ms + workers_ms) / naive_cpu_ms,
                       "load_average": os.getloadavg()[0]})

    def median(key, sub=None) -> float:
        return float(np.median([r[key][sub] if sub else r[key] for r in rounds]))

    naive_fps, naive_cpu_ms = median("naive_fps"), median("naive_cpu_ms")
    return {"corner_refinement": settings.stages.detector.corner_refinement.value,
            "naive_cpu_ms": naive_cpu_ms, "cpu_ratio": median("cpu_ratio"),
            "live_cpu_ratio": live["cpu_ms_per_frame"] / naive_cpu_ms if live is not None else None,
            "frames": len(frames), "naive_fps": naive_fps, "ours_fps": median("ours_fps"), "ratio": median("ratio"),
            "inline_fps": median("inline_fps"), "inline_ratio": median("inline_ratio"), "replay_workers": workers,
            "one_thread_fps": median("one_thread_fps"), "one_thread_ratio": median("one_thread_ratio"),
            "work_ms": percentiles(np.array(work_ms)), "fuse_ms": percentiles(np.array(fuse_ms)),
            "live_ratio": live["processed_fps"] / naive_fps if live is not None else None,
            "ours_cpu_ms": {"main": median("ours_cpu_ms", "main"), "workers": median("ours_cpu_ms", "workers")},
            "worker_jobs": median("worker_jobs"), "rounds": rounds}


def worker_split(args: argparse.Namespace, rec: Path, work: Path) -> dict:
    """Where a camera worker process's CPU goes (issue 31): the loop of one camera worker process
    (:func:`cubetrack.app.camera_workers.work_cameras`, as each of the live run's runs it) on this
    process's main thread over half the emulated cameras (the live run deals them to 2 processes), for
    --duration seconds; a second thread stands for the tracker's process: it fuses the results as they
    come, in the same process, and sends a new forecast after each. Thread CPU per processed frame of
    the per-frame work (``FrameProcessor.work``), the planning (``Tracker.admit``), sending the results
    (pickling, the pipe) and the rest of the loop (reading and parsing the streams, the clock round
    trips), and the stand-in's unpickling + unpacking + fusion + forecast (until session 17 without the
    unpickling)."""
    import functools
    import math
    import multiprocessing
    import pickle

    import cv2

    from cubetrack.app import camera_workers
    from cubetrack.app.camera_workers import work_cameras
    from cubetrack.app.config import load_config, recording_intrinsics
    from cubetrack.app.emulated import EmulatedCameras
    from cubetrack.app.tracker import Tracker
    from cubetrack.core import pipes
    from cubetrack.core.records import FrameJob
    from cubetrack.fuse.forecast import forecast_of
    from cubetrack.io.config import read_extrinsics
    from cubetrack.io.frame_wire import unpack_result
    from cubetrack.io.recording import Recording

    cv2.setNumThreads(1)
    config, settings = load_config(tracker_config(args, rec, work))
    intrinsics, extrinsics = recording_intrinsics(config, Recording.open(rec)), read_extrinsics(rec / "extrinsics.toml")
    cpu_s = {"work": 0.0, "plan": 0.0, "send": 0.0, "fusion": 0.0}

    def timed(fn, key: str):
        def call(*a, **kw):
            t0 = time.thread_time()
            try:
                return fn(*a, **kw)
            finally:
                cpu_s[key] += time.thread_time() - t0
        return call

    with EmulatedCameras(rec, ("--loop",)) as emu:
        urls = dict(list(emu.urls.items())[: max(1, args.cameras // 2)])
        make = functools.partial(Tracker, {c: intrinsics[c] for c in urls}, config.world, config.robots,
                                 {c: extrinsics[c] for c in urls}, settings.stages, synced_cameras=frozenset(urls))
        worker, fusing = make(), make()
        worker.processor.work = timed(worker.processor.work, "work")   # type: ignore[method-assign]
        worker.admit = timed(worker.admit, "plan")   # type: ignore[method-assign]
        ours, theirs = multiprocessing.Pipe()
        # forecasts as the tracker's process hands them over: posted to shared memory (since session 24), or sent
        board = pipes.LatestBytes(multiprocessing.get_context()) if hasattr(pipes, "LatestBytes") else None
        theirs.send = timed(theirs.send, "send")   # type: ignore[method-assign]
        camera_workers.send_plain = timed(camera_workers.send_plain, "send")   # a result: pickled and sent
        working, taken = multiprocessing.RawArray("d", [math.inf]), multiprocessing.RawArray("q", 1)
        robots = [r.name for r in config.robots]
        received = [0]   # frames the worker's cameras delivered, as its last counters say

        def tracker_process() -> None:   # the tracker's process, standing in: fuse, forecast
            stop_at, stopped = time.monotonic() + args.duration, False
            while True:
                if not stopped and time.monotonic() > stop_at:
                    ours.send(None)
                    stopped = True
                if not ours.poll(0.05):
                    continue
                t0 = time.thread_time()
                kind, payload = ours.recv()  # the unpickling counted: the tracker's process does it too
                if kind == "done":
                    return
                if kind == "update":
                    received[0] = sum(c.frames for c in payload.cameras.values())
                if kind == "clock":
                    fusing.add_clock_sample(payload.camera, payload.sample)
                elif kind == "result":
                    job, packed = payload
                    fusing.fuse(unpack_result(FrameJob.from_plain(job), packed, intrinsics=fusing.intrinsics,
                                              T_world_cam=fusing.T_world_cam),
                                time.time())
                    taken[0] += 1
                    plain = forecast_of(fusing.fusion, robots, time.time()).plain()
                    if board is None:
                        ours.send(plain)
                    else:
                        board.post(pickle.dumps(plain, pickle.HIGHEST_PROTOCOL))
                cpu_s["fusion"] += time.thread_time() - t0

        side = threading.Thread(target=tracker_process, daemon=True)
        side.start()
        t0 = time.thread_time()
        work_cameras(theirs, urls, settings.source, worker, False, time.time, working, taken, 0,
                     *(() if board is None else (board,)))
        total_s = time.thread_time() - t0
        side.join()
    frames = max(int(taken[0]), 1)
    per = {k: v / frames * 1000.0 for k, v in cpu_s.items()}
    per["rest"] = (total_s - cpu_s["work"] - cpu_s["plan"] - cpu_s["send"]) / frames * 1000.0
    return {"cameras": len(urls), "frames": int(taken[0]), "received": received[0], "ms": per,
            "load_average": os.getloadavg()[0]}


WAKE_COST_FRAMES = 2000  # --wake-cost's frames when --speed-frames is not given


def wake_cost(args: argparse.Namespace, rec: Path, work: Path) -> dict:
    """What waking per frame costs the same work (issue 31: the live premium): the recording's first
    frames on this thread, planned (``Tracker.admit``), worked (``FrameProcessor.work``) and fused
    (``Tracker.fuse``) as the replay does them, each step's thread CPU summed; back to back, and with a
    sleep of --wake-cost ms before each frame, or each --frames-per-wake'th (a live camera worker process
    sleeps until its next frame comes: its caches then hold what ran meanwhile). A new tracker per pass;
    --speed-rounds rounds of both, interleaved, the order alternating. Thread CPU per frame of each step,
    medians over the rounds."""
    import cv2

    from cubetrack.app.config import load_config, recording_intrinsics
    from cubetrack.app.tracker import Tracker
    from cubetrack.io.config import read_extrinsics
    from cubetrack.io.recording import Recording

    cv2.setNumThreads(1)
    config, settings = load_config(tracker_config(args, rec, work))
    recording = Recording.open(rec)
    frames = list(itertools.islice(recording.merged_frames(), args.speed_frames or WAKE_COST_FRAMES))
    intrinsics, extrinsics = recording_intrinsics(config, recording), read_extrinsics(rec / "extrinsics.toml")

    def one_pass(gap_s: float) -> dict[str, float]:
        tracker = Tracker(intrinsics, config.world, config.robots, extrinsics, settings.stages)
        cpu_s, jobs = {"plan": 0.0, "work": 0.0, "fuse": 0.0}, 0
        for k, frame in enumerate(frames):
            if gap_s and k % args.frames_per_wake == 0:
                time.sleep(gap_s)
            t0 = time.thread_time()
            job = tracker.admit(frame)
            t1 = time.thread_time()
            cpu_s["plan"] += t1 - t0
            if job is None:
                continue
            result = tracker.processor.work(job)
            t2 = time.thread_time()
            tracker.fuse(result, frame.host_time_s)
            cpu_s["work"] += t2 - t1
            cpu_s["fuse"] += time.thread_time() - t2
            jobs += 1
        per = {k: v / max(jobs, 1) * 1000.0 for k, v in cpu_s.items()}
        return {**per, "all": sum(per.values())}

    rounds: dict[str, list[dict[str, float]]] = {"back_to_back": [], "woken": []}
    for k in range(args.speed_rounds):
        order = ("back_to_back", "woken") if k % 2 == 0 else ("woken", "back_to_back")
        for name in order:
            rounds[name].append(one_pass(args.wake_cost / 1000.0 if name == "woken" else 0.0))
    ms = {name: {key: float(np.median([r[key] for r in runs])) for key in runs[0]} for name, runs in rounds.items()}
    return {"frames": len(frames), "gap_ms": args.wake_cost, "frames_per_wake": args.frames_per_wake, "ms": ms,
            "ratio": {key: ms["woken"][key] / ms["back_to_back"][key] for key in ms["woken"]},
            "load_average": os.getloadavg()[0]}


def print_wake_cost(args: argparse.Namespace, wc: dict) -> None:
    ms, ratio = wc["ms"], wc["ratio"]
    steps = ("plan", "work", "fuse", "all")
    print(f"waking per frame: the first {wc['frames']} frames on one thread, nproc {os.cpu_count()} (load average "
          f"{wc['load_average']:.1f}), {args.speed_rounds} round(s) interleaved, medians; thread CPU ms per frame "
          "(planning, decode + detection + estimates, fusion, all):")
    each = "before each" if wc["frames_per_wake"] == 1 else f"per {wc['frames_per_wake']} frames"
    for name, label in (("back_to_back", "back to back"), ("woken", f"a {wc['gap_ms']:g} ms sleep {each}")):
        print(f"  {label}: " + ", ".join(f"{ms[name][k]:.3f}" for k in steps))
    print("  woken / back to back: " + ", ".join(f"{ratio[k]:.2f}" for k in steps))


class _NoSink:
    def pose(self, pose) -> None:
        pass


# --------------------------------------------------------------------------- report


def print_speed(sp: dict) -> None:
    """The same-frames lines of the report."""
    cpu, rounds = sp["ours_cpu_ms"], len(sp["rounds"])
    how = "one thread" if not sp["replay_workers"] else f"{sp['replay_workers']} frame worker process(es) + its thread"
    live = "" if sp["live_ratio"] is None else f"; live processed / naive {sp['live_ratio']:.2f}"
    print(f"  same {sp['frames']} frames ({'median of ' + str(rounds) + ' rounds' if rounds > 1 else 'one round'}, "
          f"load average {min(r['load_average'] for r in sp['rounds']):.1f}-"
          f"{max(r['load_average'] for r in sp['rounds']):.1f}): naive loop {sp['naive_fps']:.1f} frames/s "
          f"(one thread), ours {sp['ours_fps']:.1f} frames/s (as track --recording replays here: {how}; CPU per frame "
          f"{cpu['main']:.2f} ms in its thread (planning, fusing, {1 - sp['worker_jobs'] / sp['frames']:.0%} of the "
          f"frames' work) + {cpu['workers']:.2f} ms in the workers), the replay on one thread "
          f"{sp['one_thread_fps']:.1f}, one thread frame by frame without clock round trips {sp['inline_fps']:.1f}: "
          f"ratio {sp['ratio']:.2f} (replay on one thread {sp['one_thread_ratio']:.2f}, frame by frame "
          f"{sp['inline_ratio']:.2f}){live}")
    live_cpu = "" if sp["live_cpu_ratio"] is None else (
        f"; the live run's CPU per processed frame / naive {sp['live_cpu_ratio']:.2f}")
    print(f"  CPU per frame: naive loop {sp['naive_cpu_ms']:.2f} ms (one thread), ours as replayed "
          f"{cpu['main'] + cpu['workers']:.2f} ms: ours / naive {sp['cpu_ratio']:.2f}{live_cpu}")
    w, f = sp["work_ms"], sp["fuse_ms"]
    print(f"  per frame, one thread: decode + detect + estimate p50 {w['p50']:.2f} ms p95 {w['p95']:.2f} ms; "
          f"fusion p50 {f['p50']:.2f} ms p95 {f['p95']:.2f} ms")


def print_worker_split(args: argparse.Namespace, split: dict) -> None:
    ms = split["ms"]
    print(f"one camera worker process's loop over {split['cameras']} cameras x {args.fps:g} fps for {args.duration:g} "
          f"s, nproc {os.cpu_count()} (load average {split['load_average']:.1f}): {split['frames']} frames processed "
          f"of {split['received']} received; thread CPU per processed frame: work (decode, detection, estimates) "
          f"{ms['work']:.3f} ms, planning {ms['plan']:.3f} ms, sending the result {ms['send']:.3f} ms, the rest of "
          f"the loop (reading the streams, clock round trips) {ms['rest']:.3f} ms; the tracker's process standing "
          f"in (unpickle, unpack, fuse, forecast) {ms['fusion']:.3f} ms")


def speed_failures(args: argparse.Namespace, sp: dict) -> list[str]:
    """The same-frames targets missed (issue 31): throughput ours / naive (a lower bar with
    --template) and, after a live run, its CPU per processed frame against the naive loop's."""
    target = TARGET_SPEED_TEMPLATE if args.template else TARGET_SPEED
    failures = [] if sp["ratio"] >= target else [f"throughput ours/naive {sp['ratio']:.2f} < {target:g}"]
    if sp["live_cpu_ratio"] is not None and not sp["live_cpu_ratio"] <= TARGET_CPU:
        failures.append(f"live CPU per frame / naive {sp['live_cpu_ratio']:.2f} > {TARGET_CPU:g}")
    return failures


SHOWN_FIRST, SHOWN_WORST = 4, 4   # a long run's report line: its first intervals and those with the most drops


def shown_intervals(intervals: list[dict]) -> list[dict]:
    """The intervals of :func:`over_time` the report line shows, in time order: all of a short run's; of
    a long one (a 10-minute run has 120) the first ``SHOWN_FIRST`` (start-up) and the ``SHOWN_WORST``
    others with the most frames dropped (then the highest arrival -> pose p95)."""
    if len(intervals) <= SHOWN_FIRST + SHOWN_WORST:
        return intervals
    rest = sorted(range(SHOWN_FIRST, len(intervals)), key=lambda k: (
        -intervals[k]["dropped"], -np.nan_to_num(intervals[k]["arrival_p95_ms"], nan=-1.0)))
    return [intervals[k] for k in sorted([*range(SHOWN_FIRST), *rest[:SHOWN_WORST]])]


def print_report(args: argparse.Namespace, report: dict) -> list[str]:
    live, acc, sp = report["live"], report["accuracy"], report["speed"]
    a, c = live["arrival_ms"], live["capture_ms"]
    before, after = report["load_average"]
    print(f"live benchmark: {args.cameras} cameras x {args.fps:g} fps, {live['duration_s']:.0f} s, "
          f"{'template' if args.template else 'default'} corners, "
          f"nproc {report['nproc']} (load average before {before[0]:.1f}, after {after[0]:.1f}: other "
          "programs' share of the cores)")
    print(f"  command: {live['command']}")
    print(f"  after the first {args.warmup:g} s (worker processes start while the cameras send): frames/s offered "
          f"{live['offered_fps_warm']:.1f}, processed {live['processed_fps_warm']:.1f}")
    print(f"  frames/s: offered {live['offered_fps']:.1f}, processed {live['processed_fps']:.1f}, dropped by the "
          f"tracker {live['dropped_fps']:.1f} ({live['dropped_fraction'] * 100:.2f} %: {live['dropped_behind']} "
          f"replaced by a newer frame, {live['dropped_before_clock']} before the camera's clock was known)")
    print(f"  CPU: {live['cpu_ms_per_frame']:.2f} ms per processed frame ({live['cpu_ms_per_frame_warm']:.2f} after "
          f"the first {args.warmup:g} s), {live['cores_used']:.2f} cores, of "
          f"which the main process {live['main_cores_used']:.2f} (with thread workers everything but the emulator; "
          f"with camera-process workers the fusion and outputs) "
          f"(the emulator: {live['emulator_cores_used']:.2f} cores)")
    print(f"  the machine's speed in this run (code the same in every tree): the emulator's CPU "
          f"{live['emulator_ms_per_frame']:.3f} ms per frame served, the tracker's start-up {live['startup_s']:.2f} s; "
          f"the tracker's CPU per processed frame (after the first {args.warmup:g} s) / the emulator's "
          f"{live['cpu_ms_per_frame_warm'] / live['emulator_ms_per_frame']:.1f}")
    print(f"  arrival -> pose ms: p50 {a['p50']:.1f}  p95 {a['p95']:.1f}  p99 {a['p99']:.1f}   "
          f"capture -> pose ms: p50 {c['p50']:.1f}  p95 {c['p95']:.1f}  p99 {c['p99']:.1f}  ({live['poses']} poses)")
    intervals = live["over_time"]
    shown = shown_intervals(intervals)
    print("  over time (seconds from the tracker's command: dropped, poses, arrival -> pose p95 ms, cores"
          + (f"; {len(shown)} of {len(intervals)} intervals: the first {SHOWN_FIRST} and those with the most drops"
             if len(shown) < len(intervals) else "") + "): "
          + " | ".join(f"{i['from_s']:.1f}-{i['to_s']:.1f}: {i['dropped']}, {i['poses']}, {i['arrival_p95_ms']:.1f}, "
                       f"{i['cores']:.2f}" for i in shown))
    print("  RSS over time (s: MB, processes): "
          + ", ".join(f"{t:.0f}: {mb:.0f}, {n}" for t, mb, n in live["rss_over_time"]))
    print(f"  RSS: {live['rss_start_mb']:.0f} MB at {args.warmup:g} s, {live['rss_mid_mb']:.0f} MB half-way after it, "
          f"{live['rss_end_mb']:.0f} MB at the end ({(live['rss_end_mb'] / live['rss_start_mb'] - 1) * 100:+.1f} %); "
          f"first pose {live['first_pose_s']:.2f} s after the tracker's command started; before it, the kernels "
          + (f"compiled (numba's cache was cold: {live['kernels_compiled']} signatures)" if live["kernels_compiled"]
             else "loaded")
          + f" in {live['kernels_warm_s']:.1f} s")
    print(f"  accuracy vs ground truth: live {acc['live']['pos_cm']:.2f} cm / {acc['live']['rot_deg']:.2f} deg "
          f"(detection ratio {acc['live']['detection_ratio']:.3f}); offline replay of the same frames "
          f"{acc['offline']['pos_cm']:.2f} cm / {acc['offline']['rot_deg']:.2f} deg; live/offline "
          f"{acc['pos_ratio']:.2f} / {acc['rot_ratio']:.2f}")
    print_speed(sp)
    failures = live_failures(live) + speed_failures(args, sp)
    if not max(acc["pos_ratio"], acc["rot_ratio"]) <= 1.0 + TARGET_ACCURACY:
        failures.append(f"live accuracy {max(acc['pos_ratio'], acc['rot_ratio']):.2f}x the offline replay's")
    if "outputs" in report:
        o = report["outputs"]
        off, on = o["files_only"], o["all_outputs"]
        print(f"  outputs: {compared_text(o, off, on, 'files only', 'every output on')} (MCAP {o['mcap_mb']:.0f} MB)")
    if "watch" in report:
        w = report["watch"]
        off, on = w["watch_off"], w["watch_on"]
        print(f"  camera watching: {compared_text(w, off, on, 'off', 'on')}; with it on p99 "
              f"{on['arrival_ms']['p99']:.1f} ms, dropped {on['dropped_fraction'] * 100:.2f} %, events "
              f"{[(e['event'], e['camera']) for e in w['events']]}")
        failures += [f"watching on: {f}" for f in w["failures"]]
        failures += [f"watching on: false alarm {e['camera']}" for e in w["events"] if e["event"] == "moved"]
    print("SUMMARY: " + ("all targets met" if not failures else f"{len(failures)} target(s) missed: "
                         + "; ".join(failures)))
    return failures


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    with contextlib.ExitStack() as stack:
        work = args.out or Path(stack.enter_context(tempfile.TemporaryDirectory(prefix="cubetrack-live-bench-")))
        work.mkdir(parents=True, exist_ok=True)
        print(f"preparing {args.cameras} cameras x {args.fps:g} fps ...", file=sys.stderr, flush=True)
        rec = ensure_recording(args, work)
        if args.worker_split:
            print_worker_split(args, worker_split(args, rec, work))
            return 0
        if args.wake_cost is not None:
            print_wake_cost(args, wake_cost(args, rec, work))
            return 0
        if args.speed_only:
            load = os.getloadavg()
            sp = speed(args, rec, work, None)
            print(f"same-frames comparison: {args.cameras} cameras x {args.fps:g} fps recording, "
                  f"{'template' if args.template else 'default'} corners, "
                  f"nproc {os.cpu_count()} (load average before {load[0]:.1f})")
            print_speed(sp)
            failures = speed_failures(args, sp)
            print("SUMMARY: " + ("throughput target met" if not failures else "; ".join(failures)))
            (work / SPEED_REPORT_FILE).write_text(json.dumps({"nproc": os.cpu_count(), "speed": sp}, indent=2)
                                                 + "\n", encoding="utf-8")
            return 0
        print(f"tracking live for {args.duration:g} s ...", file=sys.stderr, flush=True)
        load = os.getloadavg()
        kernels = warm_kernels()
        live = run_live(args, rec, work)
        live["kernels_warm_s"] = sum(g.time_s for g in kernels.groups)
        live["kernels_compiled"] = kernels.compiled
        outputs = None
        if args.outputs:
            print("tracking live again with every output on ...", file=sys.stderr, flush=True)
            outputs = outputs_cost(args, rec, work, live)
        watch = None
        if args.watch:
            print("tracking live again with the camera watching on ...", file=sys.stderr, flush=True)
            watch = watch_cost(args, rec, work, live)
        print("replaying the frames offline and timing the naive loop ...", file=sys.stderr, flush=True)
        after = os.getloadavg()
        report = {"nproc": os.cpu_count(), "load_average": [load, after],
                  "args": {k: (str(v) if isinstance(v, Path) else v) for k, v in vars(args).items()},
                  "live": live, "accuracy": accuracy(args, rec, work, live), "speed": speed(args, rec, work, live)}
        if outputs is not None:
            report["outputs"] = outputs
        if watch is not None:
            report["watch"] = watch
        report["failures"] = print_report(args, report)
        (work / REPORT_FILE).write_text(json.dumps(report, indent=2) + "\n", encoding="utf-8")
    return 0


if __name__ == "__main__":
    sys.exit(main())
