"""benchmarks/live.py's run interval by interval (issue 31's run-to-run spread): the tracker's status lines
followed as they are written, and the drops, poses, latency and cores put in the intervals between them.
No live run here (test_live_smoke.py has one): a status file written by the test, and made-up poses and
CPU samples whose intervals are known by construction."""

import math
import subprocess
import sys
import time

import pytest

from tests.helpers.benchmarks import load_benchmark

STATUS = ("track:     5s | robot 264.8 poses/s | cam1 21.2 fps cam2 18.2 fps | latency 7/9 ms | bad 0 reconnects 0 "
          "dropped {} clock 4/3")


def _pose(handed_unix_s: float, arrival_ms: float) -> dict:
    """A pose handed to the outputs at ``handed_unix_s`` (capture 20 ms before)."""
    return {"time": handed_unix_s - 0.020, "latency": 0.020, "arrival_latency": arrival_ms / 1000.0}


def test_intervals_hold_the_drops_poses_latency_and_cores_between_status_lines():
    live = load_benchmark("live")
    start, shift = 100.0, 1_700_000_000.0   # the command's monotonic start; Unix = monotonic + shift
    status = [(105.0, 17), (110.0, 17), (115.0, 40)]     # cumulative drops as the status lines give them
    poses = ([_pose(shift + 101.0 + 0.01 * k, 8.0) for k in range(100)]    # 101-102 s: 100 poses at 8 ms
             + [_pose(shift + 107.0, 8.0 + k) for k in range(21)]          # 107 s: 8..28 ms
             + [_pose(shift + 116.0, 50.0)])                                # after the last status line
    samples = [(100.0 + t, 1.5 * t if t <= 10 else 15.0 + 0.5 * (t - 10), 1, 1) for t in range(0, 17)]
    rows = live.over_time(status, poses, samples, start, shift)
    assert [(r["from_s"], r["to_s"]) for r in rows] == [(0.0, 5.0), (5.0, 10.0), (10.0, 15.0)]
    assert [r["dropped"] for r in rows] == [17, 0, 23]
    assert [r["poses"] for r in rows] == [100, 21, 0]      # the one after the last line is in none
    assert rows[0]["arrival_p95_ms"] == pytest.approx(8.0)
    assert rows[1]["arrival_p95_ms"] == pytest.approx(27.0)  # p95 of 8..28
    assert math.isnan(rows[2]["arrival_p95_ms"])
    assert [r["cores"] for r in rows] == pytest.approx([1.5, 1.5, 0.5])


def test_follower_takes_status_lines_as_they_are_written_and_skips_the_rest(tmp_path):
    live = load_benchmark("live")
    path = tmp_path / "live_stderr.txt"
    follower = live.StatusFollower(path, period_s=0.01)   # the file does not exist yet: nothing, no error
    try:
        with open(path, "w", encoding="utf-8") as f:
            f.write("tracking live into /tmp/x\n" + STATUS.format(17) + "\n")
            f.flush()
            deadline = time.monotonic() + 30.0
            while not follower.lines and time.monotonic() < deadline:
                time.sleep(0.01)
            f.write(STATUS.format(36)[:40])   # half a line: taken once it is complete
            f.flush()
            time.sleep(0.05)
            assert [d for _, d in follower.lines] == [17]
            f.write(STATUS.format(36)[40:] + "\nWARNING something else dropped 99\n")
            f.flush()
            while len(follower.lines) < 2 and time.monotonic() < deadline:
                time.sleep(0.01)
    finally:
        follower.stop()
    assert [d for _, d in follower.lines] == [17, 36]
    assert follower.lines[0][0] <= follower.lines[1][0]


def test_a_long_runs_line_shows_its_start_and_its_worst_intervals_in_time_order():
    live = load_benchmark("live")
    short = [{"dropped": 0, "arrival_p95_ms": 5.0, "from_s": 5.0 * k}
             for k in range(live.SHOWN_FIRST + live.SHOWN_WORST)]
    assert live.shown_intervals(short) == short
    drops = [9, 0, 0, 1, 0, 7, 0, 3, 0, 0, 12, 0, 2, 0, 0]   # intervals 0-3 are the start; then 10, 5, 7, 12
    p95 = [5.0] * len(drops)
    p95[13] = 80.0                                          # no drop, but the slowest: a tie of 0 drops goes by p95
    rows = [{"dropped": d, "arrival_p95_ms": q, "from_s": 5.0 * k} for k, (d, q) in enumerate(zip(drops, p95,
                                                                                                     strict=True))]
    shown = live.shown_intervals(rows)
    assert [r["from_s"] / 5.0 for r in shown] == [0, 1, 2, 3, 5, 7, 10, 12]
    rows[12]["dropped"] = 0                                 # now interval 13's p95 beats the other no-drop ones
    assert [r["from_s"] / 5.0 for r in live.shown_intervals(rows)] == [0, 1, 2, 3, 5, 7, 10, 13]


def test_a_child_that_ended_is_not_counted_alive_by_the_tree_sampler():
    """The end-of-run RSS is the last sample with every process alive: a worker that has exited but
    is not yet reaped (a zombie, no resident memory) must not count, or that sample reads the tree
    half torn down (a 16 x 30 run printed 249 MB "at the end" after 719 MB with four processes)."""
    live = load_benchmark("live")
    parent = subprocess.Popen([sys.executable, "-c", "import subprocess, sys, time\n"
                               "subprocess.Popen([sys.executable, '-c', 'pass'])\ntime.sleep(30)"])
    try:
        deadline = time.monotonic() + 20.0
        while time.monotonic() < deadline:   # until the child has exited, unreaped
            children = live._children(parent.pid)
            if children and _state(children[0]) == "Z":
                break
            time.sleep(0.02)
        else:
            pytest.fail("the child never became a zombie")
        sampler = live.TreeSampler(parent.pid, period_s=0.01)
        while not sampler.samples and time.monotonic() < deadline:
            time.sleep(0.01)
        sampler.stop()
        assert sampler.samples[-1][3] == 1   # the parent alone
    finally:
        parent.kill()
        parent.wait()


def _state(pid: int) -> str:
    with open(f"/proc/{pid}/stat") as f:
        return f.read().rsplit(")", 1)[1].split()[0]
