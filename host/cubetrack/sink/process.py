"""Outputs in a process of their own, so that their work does not take the tracker's CPU.

The tracker's process is bound by Python's global interpreter lock: the live tracker uses about
1.3 of 2 cores, and every output thread in that process (encoding CDR, JSON, VRPN messages,
Foxglove annotations) takes its share of the same lock from the pipeline. :class:`OutputProcess`
runs a set of outputs in a child process instead; the pipeline's side only pickles items onto a
pipe (from the :class:`~cubetrack.sink.base.Decoupled` thread :class:`Outputs` gives it, so a
full pipe costs the pipeline nothing: the oldest items are dropped and counted there). Items go
in batches (at most one per ``BATCH_WINDOW_S``: an item after a quiet spell goes at once, and what
follows it within the window waits for the next batch: one wake-up, one pickle and one write for
several), each record as a compact tuple of plain values
(:func:`cubetrack.io.output_wire.pack_output`): pickling
the frozen dataclasses and their small numpy arrays as objects cost ten times more.

The child builds its outputs with ``factory`` (a picklable callable returning the sinks, e.g. a
``functools.partial`` of :func:`cubetrack.app.outputs.output_sinks`), reports how to reach them
and calls them in line, one item after another, from the thread that reads the pipe: none of
them waits for a peer (each server queues per client and drops for a slow one, Zenoh drops under
congestion, MCAP writes to a file), and a thread per output would cost a wake-up and a lock
hand-over per output and item, more than most of them spend on the item (benchmarks/outputs.py).
If the child falls behind, the pipe's queue in the tracker drops the oldest items and counts
them. It ignores Ctrl-C (the tracker closes it) and ends when the tracker's process goes away
(:func:`cubetrack.core.lifetime.end_with_parent`; its outputs are closed then, as on SIGTERM).
"""

from __future__ import annotations

import logging
import multiprocessing
import signal
from collections.abc import Callable
from multiprocessing.connection import Connection
from multiprocessing.process import BaseProcess

from cubetrack.core.errors import ConfigError, CubetrackError
from cubetrack.core.lifetime import end_with_parent
from cubetrack.io.output_wire import pack_output, unpack_output
from cubetrack.sink.base import OutputError, Outputs, Sink

log = logging.getLogger(__name__)

START_TIMEOUT_S = 60.0  # importing zenoh and foxglove-sdk on a loaded machine takes seconds
CLOSE_TIMEOUT_S = 30.0  # the child delivers what it holds (up to 5 s per output) and closes MCAP files
BATCH_WINDOW_S = 0.004  # at most one pipe write per this long; an item waits at most this long


def _exit(signum: int, frame: object) -> None:
    raise SystemExit(0)


def serve_outputs(factory: Callable[[], list[Sink]], conn: Connection, log_level: int) -> None:
    """The child process: build the outputs, say where they are, then pass on what arrives."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, _exit)  # as when the tracker closes it: outputs closed, files whole
    end_with_parent()
    logging.basicConfig(level=log_level, format="%(levelname)s %(name)s: %(message)s")
    try:
        sinks = factory()
    except CubetrackError as exc:
        conn.send(("error", isinstance(exc, ConfigError), str(exc)))
        return
    except Exception as exc:  # noqa: BLE001  (reported to the tracker as a one-line error)
        conn.send(("error", False, f"{type(exc).__name__}: {exc}"))
        return
    views = [s for s in sinks if s.wants_views]
    conn.send(("ready", [s.where for s in sinks if s.where], bool(views),
               min((s.view_interval_s for s in views), default=0.0)))
    outputs = Outputs(sinks, all_in_line=True)
    try:
        while True:
            try:
                batch = conn.recv()
            except (EOFError, OSError):  # the tracker's process is gone
                break
            if batch is None:  # the session closes
                break
            for item in batch:
                kind, value = unpack_output(*item)
                getattr(outputs, kind)(value)
    finally:  # a SIGTERM (or the parent's death) while closing must not cut an MCAP file short
        signal.signal(signal.SIGTERM, signal.SIG_IGN)
        outputs.close()  # each output says what it dropped


class OutputProcess(Sink):
    """The sinks ``factory`` builds, in a child process; starts (and reports a bad output) in the
    constructor, like the outputs themselves."""

    name = "outputs process"

    def __init__(self, factory: Callable[[], list[Sink]]):
        context = multiprocessing.get_context("spawn")  # fork would copy the tracker's threads' locks
        self._conn, child = context.Pipe()
        self._process: BaseProcess | None = context.Process(target=serve_outputs, name="cubetrack-outputs", daemon=True,
                                        args=(factory, child, logging.getLogger().getEffectiveLevel()))
        self._process.start()
        child.close()
        try:
            if not self._conn.poll(START_TIMEOUT_S):
                raise OutputError(f"the outputs' process did not start within {START_TIMEOUT_S:.0f} s")
            message = self._conn.recv()
        except (EOFError, OSError):
            self._stop()
            raise OutputError("the outputs' process ended while starting its outputs (see the log above)") from None
        except BaseException:
            self._stop()
            raise
        if message[0] == "error":
            self._stop()
            raise (ConfigError if message[1] else OutputError)(message[2])
        _, wheres, self.wants_views, self.view_interval_s = message
        self.where = "; ".join(wheres) + " (in a process of their own)" if wheres else ""

    batch_window_s = BATCH_WINDOW_S

    def deliver(self, items: list[tuple[str, object]]) -> None:
        try:
            self._conn.send([pack_output(kind, value) for kind, value in items])
        except (BrokenPipeError, OSError):
            raise OutputError("the outputs' process has ended") from None

    def open(self, session) -> None:
        self.deliver([("open", session)])

    def pose(self, pose) -> None:
        self.deliver([("pose", pose)])

    def camera_health(self, health) -> None:
        self.deliver([("camera_health", health)])

    def camera_view(self, view) -> None:
        self.deliver([("camera_view", view)])

    def camera_watch(self, state) -> None:
        self.deliver([("camera_watch", state)])  # a small frozen record: pickled as it is

    def close(self) -> None:
        """Let the child deliver what it holds and close its outputs (harmless twice)."""
        if self._process is None:
            return
        try:
            self._conn.send(None)
        except (BrokenPipeError, OSError):
            pass
        self._process.join(CLOSE_TIMEOUT_S)
        self._stop()

    def _stop(self) -> None:
        if self._process is None:
            return
        if self._process.is_alive():
            self._process.terminate()
            self._process.join(2.0)
        self._conn.close()
        self._process = None
