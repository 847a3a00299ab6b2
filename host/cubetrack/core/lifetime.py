"""Child processes that end with their parent, however the parent ends.

A process that ``cubetrack`` starts (the camera emulator of ``cubetrack demo``, the camera worker
and frame worker processes, the outputs' process) must not outlive the process that started it,
also when that one is killed with SIGKILL and cannot stop its children. The child calls
:func:`end_with_parent` first thing:

- **Linux**: ``prctl(PR_SET_PDEATHSIG, sig)`` asks the kernel to send the child ``sig`` when its
  parent dies (prctl(2)). The kernel counts the *thread* that created the child as its parent: the
  signal also comes when that thread ends while the rest of the process lives on. So ``sig`` is a
  signal of its own (a real-time one, :data:`PARENT_DEATH_SIGNAL`, not SIGTERM, which a user may
  send), and its handler ends the child only when its parent process is gone (the parent pid
  changed: the child was handed to init or a subreaper); otherwise it does nothing, and the kernel
  signals again when the thread the child was handed to ends. A parent that died before the call
  is caught by comparing the parent pid with the one the parent gave.
- **Elsewhere** (macOS, the BSDs, where no such call exists), a daemon thread looks every
  ``PARENT_POLL_S`` whether the parent pid changed and then sends this process SIGTERM.

Either way the child ends as a SIGTERM ends it (its own SIGTERM handling, if it has any, runs).
"""

from __future__ import annotations

import logging
import os
import signal
import sys
import threading
import time

log = logging.getLogger(__name__)

PR_SET_PDEATHSIG = 1  # <linux/prctl.h>
PARENT_DEATH_SIGNAL = signal.SIGRTMIN + 3 if hasattr(signal, "SIGRTMIN") else signal.SIGTERM  # Linux: SIGRTMIN+3
PARENT_POLL_S = 0.5  # the fallback's look at the parent pid, where prctl does not exist


def end_with_parent(parent_pid: int | None = None) -> None:
    """End this process (as SIGTERM does) when ``parent_pid`` ends: the process that started it,
    by default the multiprocessing parent (or ``os.getppid()`` for a plain child). Call it first
    thing in the child, from its main thread."""
    if parent_pid is None:
        import multiprocessing

        parent = multiprocessing.parent_process()
        parent_pid = parent.pid if parent is not None and parent.pid is not None else os.getppid()
    if not (sys.platform.startswith("linux") and _parent_death_signal(parent_pid)):
        threading.Thread(target=_watch_parent, args=(parent_pid,), daemon=True, name="cubetrack-parent-watch").start()
    if os.getppid() != parent_pid:  # the parent died before this call (or this is no child of it)
        _terminate_self()


def _parent_death_signal(parent_pid: int) -> bool:
    """Ask Linux for :data:`PARENT_DEATH_SIGNAL` at the parent's death, taken by a handler that
    ends this process when the parent is gone; False when prctl is not there (then the caller
    falls back to polling)."""
    import ctypes

    try:
        prctl = ctypes.CDLL(None, use_errno=True).prctl
    except (OSError, AttributeError):
        return False

    def on_parent_death(signum: int, frame: object) -> None:
        if os.getppid() != parent_pid:  # else only the thread that started this process ended
            _terminate_self()

    signal.signal(PARENT_DEATH_SIGNAL, on_parent_death)
    if prctl(PR_SET_PDEATHSIG, PARENT_DEATH_SIGNAL, 0, 0, 0) != 0:
        log.debug("prctl(PR_SET_PDEATHSIG) failed (errno %d); watching the parent instead", ctypes.get_errno())
        return False
    return True


def _watch_parent(parent_pid: int) -> None:
    while os.getppid() == parent_pid:
        time.sleep(PARENT_POLL_S)
    _terminate_self()


def _terminate_self() -> None:
    """SIGTERM to this process: its own SIGTERM handling (or the default: the end) applies."""
    os.kill(os.getpid(), signal.SIGTERM)
