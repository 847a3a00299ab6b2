"""Children that end with their parent (cubetrack.core.lifetime), with real processes: a parent
process starts a child that calls end_with_parent, then the parent is killed with SIGKILL."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import pytest

CHILD = """
import sys, time
import cubetrack.core.lifetime as lifetime
{setup}
lifetime.end_with_parent(int(sys.argv[1]))
print("ready", flush=True)
time.sleep(120)
"""


def alive(pid: int) -> bool:
    """Whether ``pid`` runs (a zombie, dead but not yet reaped by init, counts as ended)."""
    try:
        state = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
    except (FileNotFoundError, ProcessLookupError):
        return False
    return state != "Z"


def wait_gone(pid: int, timeout_s: float = 10.0) -> bool:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if not alive(pid):
            return True
        time.sleep(0.05)
    return False


def start_family(tmp_path: Path, setup: str = "", parent_pid_arg: str = "os.getpid()",
                 from_thread: bool = False) -> tuple[subprocess.Popen, int, str]:
    """A parent process that starts one child (from its main thread, or from a thread that ends
    at once) and then waits; returns the parent, the child's pid and "ready" once the child is
    (or "ended" when it ended first)."""
    child = tmp_path / "child.py"
    child.write_text(CHILD.format(setup=setup))
    parent = tmp_path / "parent.py"
    parent.write_text(textwrap.dedent(f"""
        import os, subprocess, sys, threading, time
        def start():
            p = subprocess.Popen([sys.executable, {str(child)!r}, str({parent_pid_arg})], stdout=subprocess.PIPE,
                                 text=True)
            print(p.pid, flush=True)
            print(p.stdout.readline().strip() or "ended", flush=True)
        if {from_thread}:
            t = threading.Thread(target=start)
            t.start()
            t.join()  # the thread that started the child has ended; this process lives on
        else:
            start()
        time.sleep(120)
    """))
    proc = subprocess.Popen([sys.executable, str(parent)], stdout=subprocess.PIPE, text=True)
    child_pid = int(proc.stdout.readline())
    return proc, child_pid, proc.stdout.readline().strip()


@pytest.mark.parametrize("setup", ["", "lifetime._parent_death_signal = lambda pid: False  # the fallback"],
                         ids=["prctl", "polling"])
def test_a_child_ends_when_its_parent_is_killed(tmp_path, setup):
    parent, child, state = start_family(tmp_path, setup)
    try:
        assert state == "ready" and alive(child)
        parent.kill()  # SIGKILL: the parent cannot stop its child itself
        parent.wait()
        assert wait_gone(child)
    finally:
        if alive(child):
            os.kill(child, signal.SIGKILL)


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="the thread rule is prctl's (Linux)")
def test_the_end_of_the_thread_that_started_a_child_does_not_end_it(tmp_path):
    parent, child, state = start_family(tmp_path, from_thread=True)
    try:
        assert state == "ready"
        time.sleep(1.0)  # the parent-death signal of the ended thread has come and gone by now
        assert alive(child) and parent.poll() is None
        parent.kill()
        parent.wait()
        assert wait_gone(child)  # and the parent's real death still ends it
    finally:
        if alive(child):
            os.kill(child, signal.SIGKILL)


def test_a_child_whose_parent_died_before_the_call_ends_at_once(tmp_path):
    parent, child, state = start_family(tmp_path, parent_pid_arg="1 << 22")  # a pid that is not its parent's
    try:
        assert state == "ended" and wait_gone(child)
    finally:
        parent.kill()
        parent.wait()
