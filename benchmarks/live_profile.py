"""Where the live tracker's CPU goes, by process and by part (issue 31): runs ``benchmarks/live.py``
(its arguments after ``--``), and once the tracker's status line at --from-s has come, samples the
tracker's processes (the main one: fusion and outputs; each camera worker process: streams,
decode, detection, planning) with py-spy for --profile-s seconds, reads each process's CPU from
/proc over the same window, and prints per process its CPU per processed frame split by part.

py-spy samples wall time: a thread that waits in ``select`` is left out here, but a thread that
is runnable and not running (a busy machine's run queue, and often right after a system call
that woke another process) is sampled where it stands, so parts ending in a system call (pipe
and socket sends) are overcounted on a loaded machine; the CPU per process is exact.
py-spy is not a dependency: ``pip install py-spy``.

Example:
  flock /work/notes/bench.lock .venv/bin/python benchmarks/live_profile.py --out /tmp/lp -- --duration 45
"""

from __future__ import annotations

import argparse
import collections
import json
import os
import re
import shutil
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
TICK = os.sysconf("SC_CLK_TCK")
WAITS = ("PipePoll.ready (cubetrack/core/pipes.py", "EpollSelector.select", "select (", "sleep (")
# (the start of a frame's text, its part) for frames at the leaf: system calls
SYSCALLS = (("Connection._send (", "pipes: send (syscall)"), ("Connection._recv (", "pipes: receive, unpack"),
            ("HttpGet._recv (", "source: HTTP, MJPEG, sockets"), ("socket.close", "source: HTTP, MJPEG, sockets"),
            ("socket._real_close", "source: HTTP, MJPEG, sockets"), ("LineFile.write_line", "outputs: pose files"))
# (text in a frame's file, its part), the first match from the leaf up
PARTS = (("numba/", "numba (load)"), ("importlib", "imports"),
         ("cubetrack/source/mjpeg.py", "source: HTTP, MJPEG, sockets"),
         ("cubetrack/source/http_get.py", "source: HTTP, MJPEG, sockets"),
         ("cubetrack/source/", "source: streams, order, clocks"), ("cubetrack/detect/decode.py", "decode"),
         ("cubetrack/detect/", "detect"), ("cubetrack/estimate/", "estimate (association; planning's poses)"),
         ("cubetrack/fuse/forecast.py", "forecast"), ("cubetrack/fuse/", "fusion"),
         ("cubetrack/sink/", "outputs: sinks"), ("cubetrack/app/outputs.py", "outputs: sinks"),
         ("cubetrack/io/frame_wire.py", "pipes: receive, unpack"), ("cubetrack/io/", "outputs: pose files"),
         ("cubetrack/app/camera_workers.py", "pipes: receive, unpack"),
         ("cubetrack/app/tracker.py", "tracker: plan, admit, count"), ("cubetrack/app/", "session, status"),
         ("cubetrack/core/", "core (records, geometry, shared memory)"))


def parse_args(argv: list[str] | None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], epilog=__doc__.split("\n\n", 1)[1],
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--out", type=Path, required=True, help="benchmarks/live.py's --out (its recording is reused)")
    p.add_argument("--from-s", type=int, default=20, help="start at the tracker's status line of this second "
                   "(a multiple of 5; default 20: the worker processes are running)")
    p.add_argument("--profile-s", type=float, default=20.0, help="seconds sampled (default 20)")
    p.add_argument("--rate", type=int, default=97, help="py-spy samples per second (default 97)")
    p.add_argument("live_args", nargs="*", help="after --: benchmarks/live.py's arguments besides --out")
    return p.parse_args(argv)


def part(frames: list[str]) -> str:
    """The part a stack (root first) is in: waiting, a system call at the leaf, or the first module
    from the leaf up that PARTS names."""
    if frames and frames[-1].startswith(WAITS):
        return "waiting"
    for start, name in SYSCALLS:
        if frames and frames[-1].startswith(start):
            return name
    for frame in reversed(frames):
        if (m := re.search(r"\((.*?):\d+\)$", frame)) is not None:
            for key, name in PARTS:
                if key in m.group(1):
                    return name
    return "other"


def samples(raw: Path) -> dict[int, collections.Counter[str]]:
    """py-spy's raw stacks (``--subprocesses --threads``) counted by process id and part."""
    counts: dict[int, collections.Counter[str]] = collections.defaultdict(collections.Counter)
    for line in raw.read_text().splitlines():
        stack, n = line.rsplit(" ", 1)
        frames = stack.split(";")
        pid = int(re.match(r"process (\d+)", [f for f in frames if f.startswith("process ")][-1]).group(1))  # type: ignore[union-attr]
        counts[pid][part([f for f in frames if not f.startswith(("process ", "thread "))])] += int(n)
    return counts


def tree_cpu_s(pid: int) -> dict[int, float]:
    """CPU seconds (user + system) of ``pid`` and its children, by process id."""
    out = {}
    for entry in Path("/proc").iterdir():
        try:
            fields = (entry / "stat").read_text().rsplit(")", 1)[1].split()
        except (OSError, IndexError):
            continue
        if entry.name == str(pid) or fields[1] == str(pid):
            out[int(entry.name)] = (int(fields[11]) + int(fields[12])) / TICK
    return out


def processed_in(out: Path, begin_unix: float, end_unix: float) -> float:
    """Frames the live run in ``out`` processed between two moments, estimated from its fused poses
    handed out then (capture time + capture -> pose) and its summary's processed frames per pose."""
    summary = re.search(r"frames: (\d+), before their camera's clock was known: (\d+)",
                        (out.parent / "live_stdout.txt").read_text())
    if summary is None:
        raise SystemExit(f"cannot read the live run's summary in {out.parent / 'live_stdout.txt'}")
    poses = [json.loads(line) for line in (out / "robot.jsonl").read_text().splitlines()]
    fused = [p["time"] + p["latency"] for p in poses if not p.get("predicted")]
    inside = sum(begin_unix <= t <= end_unix for t in fused)
    return inside * (int(summary.group(1)) - int(summary.group(2))) / max(len(fused), 1)


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    spy = shutil.which("py-spy") or shutil.which("py-spy", path=str(Path(sys.executable).parent))
    if spy is None:
        raise SystemExit("py-spy not found: pip install py-spy")
    args.out.mkdir(parents=True, exist_ok=True)
    status = args.out / "live_stderr.txt"
    status.unlink(missing_ok=True)
    with open(args.out / "profile_report.txt", "w") as report:
        bench = subprocess.Popen([sys.executable, str(ROOT / "benchmarks" / "live.py"), "--out", str(args.out),
                                  *args.live_args], stdout=report, stderr=subprocess.STDOUT)
        marker = f"track --config {args.out}/live_config.toml"
        while (tracker := next((int(p.name) for p in Path("/proc").iterdir() if p.name.isdigit()
                                and marker in _cmdline(p)), None)) is None or not status.exists() \
                or not re.search(rf"track: *{args.from_s}s", status.read_text()):
            if bench.poll() is not None:
                raise SystemExit(f"benchmarks/live.py ended first: see {args.out / 'profile_report.txt'}")
            time.sleep(0.2)
        before, started, started_unix = tree_cpu_s(tracker), time.monotonic(), time.time()
        subprocess.run([spy, "record", "--pid", str(tracker), "--subprocesses", "--nonblocking", "--threads",
                        "-r", str(args.rate), "-d", f"{args.profile_s:g}", "--format", "raw",
                        "-o", str(args.out / "profile_raw.txt")], check=True, capture_output=True)
        after, window_s = tree_cpu_s(tracker), time.monotonic() - started
        bench.wait()
    frames = processed_in(args.out / "live", started_unix, started_unix + window_s)
    print(f"{window_s:.1f} s sampled from the status line at {args.from_s} s, ~{frames:.0f} frames processed in it; "
          f"load average {os.getloadavg()[0]:.1f}")
    for pid, counts in sorted(samples(args.out / "profile_raw.txt").items()):
        cpu_s = after.get(pid, float("nan")) - before.get(pid, float("nan"))
        busy = sum(n for name, n in counts.items() if name != "waiting")
        role = "main (fusion, outputs)" if pid == tracker else "camera worker"
        print(f"{role}, pid {pid}: {cpu_s:.2f} s CPU, {cpu_s / frames * 1000:.3f} ms per processed frame "
              f"({busy} of {sum(counts.values())} samples not waiting)")
        for name, n in sorted(counts.items(), key=lambda kv: -kv[1]):
            if name != "waiting":
                print(f"  {100 * n / busy:5.1f} %  {cpu_s * n / busy / frames * 1000:.3f} ms  {name}")
    return 0


def _cmdline(proc: Path) -> str:
    try:
        return (proc / "cmdline").read_bytes().replace(b"\0", b" ").decode(errors="replace")
    except OSError:
        return ""


if __name__ == "__main__":
    sys.exit(main())
