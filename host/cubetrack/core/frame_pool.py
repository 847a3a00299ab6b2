"""Per-frame work on every core for live tracking and replays; the fusion stays one ordered consumer.

The tracker (:class:`~cubetrack.app.tracker.Tracker`) splits a frame's work in three: ``admit``
plans it from the fusion's state (capture time, the regions where detection looks, which robots
need an estimate), a :class:`~cubetrack.app.tracker.FrameProcessor` does it (decode, detection,
per-camera estimates: no shared state), and ``fuse`` hands the sightings to the fusion. A
:class:`FramePool` runs the middle part on worker processes (the job, JPEG included, pickled
through a pipe, the result pickled back) or threads (OpenCV releases the GIL in decoding and
detection; the Python parts of detection and estimation hold it), and wakes the consumer when a
result is ready. Live, it takes a job only while a worker is free, so frames wait in the
source, where each camera keeps only its newest (:class:`~cubetrack.source.streams.LiveCameras`);
a replay (:func:`cubetrack.app.track.track_frames`) keeps a few jobs queued per worker.
"""

from __future__ import annotations

import enum
import gc
import multiprocessing
import os
import pickle
import queue
import threading
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass
from multiprocessing.connection import Connection
from typing import Protocol

import cv2

from cubetrack.core.errors import SourceError
from cubetrack.core.lifetime import end_with_parent
from cubetrack.core.params import check, param
from cubetrack.core.pipes import PipePoll
from cubetrack.core.records import FrameJob, FrameResult


@enum.unique
class WorkerKind(enum.Enum):
    AUTO = "auto"
    PROCESS = "process"
    THREAD = "thread"
    CAMERA_PROCESS = "camera-process"


_WAITING, _STARTED, _RECLAIMED = 0, 1, 2  # a job's claim flag (_ProcessLane)
CAMERA_PROCESSES_FROM = 12  # [live] worker_kind = "auto": camera worker processes from this many cameras on


class FrameWorker(Protocol):
    """The per-frame work a pool runs (:class:`cubetrack.app.tracker.FrameProcessor`): a job in, its
    result out, and the result's message between processes both ways (the codec of
    :mod:`cubetrack.io.frame_wire`, which leaves out what both ends hold)."""

    def work(self, job: FrameJob) -> FrameResult: ...

    def pack(self, result: FrameResult) -> tuple: ...

    def unpack(self, job: FrameJob, message: tuple) -> FrameResult: ...


@dataclass(frozen=True, slots=True)
class LiveParams:
    """The ``[live]`` section of the tracker config: how live frames are processed."""

    workers: int = param(0, "per-frame workers (decode, detection, per-camera estimate); 0: one per core")
    worker_kind: WorkerKind = param(
        WorkerKind.AUTO,
        "auto: camera-process from 12 cameras on (when not recording, on more than one core), else thread "
        "(measured, docs/live.md); thread: threads of the tracker's process; process: worker processes, each "
        "frame's JPEG handed over through a pipe; camera-process: worker processes that each read a share of the "
        "cameras and do their per-frame work, the fusion in the tracker's process (cubetrack.app.camera_workers; "
        "not while recording)")

    def __post_init__(self) -> None:
        check(self.workers >= 0, f"workers must not be negative, got {self.workers}")

    @property
    def worker_count(self) -> int:
        return self.workers or os.cpu_count() or 1

    def kind_for(self, cameras: int, recording: bool) -> WorkerKind:
        """The worker kind a live session of ``cameras`` cameras runs with (``recording``: it also
        records, which the tracker's process does: no camera worker processes then)."""
        kind = self.worker_kind
        if kind is WorkerKind.AUTO:
            kind = WorkerKind.CAMERA_PROCESS if cameras >= CAMERA_PROCESSES_FROM and self.worker_count > 1 \
                else WorkerKind.THREAD
        return WorkerKind.THREAD if kind is WorkerKind.CAMERA_PROCESS and recording else kind


class FramePool:
    """``count`` frame workers of ``kind``, each taking up to ``depth`` jobs at a time.
    :meth:`submit` a job while :meth:`idle` > 0; results come back through :meth:`take`
    (completion order) and ``wake`` is called as each is ready (None: :meth:`wait` for it).

    Worker processes start in the background (importing the stages takes a second or two): until
    the first is ready, :attr:`ready` is False and the consumer does the work itself. Use as a
    context manager; :meth:`close` ends the workers."""

    def __init__(self, make_worker: Callable[[], FrameWorker], count: int, kind: WorkerKind,
                 wake: Callable[[], None] | None = None, depth: int = 1):
        self.kind = kind
        self.count = count
        self.depth = depth
        self.submitted = 0  # jobs handed to workers so far
        self._event = threading.Event()
        # worker processes' results are read by the caller's wait() or poll() unless it has a wake
        self._wake = wake or (self._event.set if kind is WorkerKind.THREAD else _nothing)
        self._lock = threading.Lock()
        self._done: deque[FrameResult] = deque()
        self._idle: deque = deque()  # one entry per free job slot: its lane (worker process), or None (threads)
        self._failure: BaseException | None = None
        if kind is WorkerKind.THREAD:
            self._jobs: queue.SimpleQueue = queue.SimpleQueue()
            self._threads = [threading.Thread(target=self._thread_loop, args=(make_worker(),), daemon=True,
                                              name=f"cubetrack-frame-worker-{k}") for k in range(count)]
            for t in self._threads:
                t.start()
            self._idle.extend([None] * (count * depth))
            self._lanes: list[_ProcessLane] = []
        else:
            self.local_worker = make_worker()  # unpacks the results (it holds what their messages leave out)
            context = multiprocessing.get_context("spawn")  # fork would copy this process's threads' locks
            self._lanes = [_ProcessLane(context, make_worker, self, depth, threaded=wake is not None)
                           for _ in range(count)]
        # the worker processes' pipes, read by wait() and poll() (a lane that ended leaves)
        self._pipes = PipePoll({lane.conn: lane for lane in self._lanes})
        self.started = len(self._idle)

    def __enter__(self) -> FramePool:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    @property
    def ready(self) -> bool:
        """At least one worker has started."""
        with self._lock:
            return self.started > 0

    @property
    def all_started(self) -> bool:
        """Every worker has started."""
        with self._lock:
            return self.started == self.count * self.depth

    @property
    def process_ids(self) -> list[int]:
        """The worker processes' ids (none for threads)."""
        return [lane.process.pid for lane in self._lanes]

    def idle(self) -> int:
        """Free job slots of the started workers."""
        with self._lock:
            return len(self._idle)

    def busy(self) -> int:
        """Jobs handed out whose results have not been taken."""
        with self._lock:
            return self.started - len(self._idle)

    def submit(self, job: FrameJob) -> None:
        """Hand a job to a worker with a free slot (call only while :meth:`idle` > 0)."""
        with self._lock:
            if self._failure is not None:
                raise self._failure
            lane = self._idle.popleft()
            self.submitted += 1
        if lane is None:
            self._jobs.put(job)
            return
        try:
            lane.send(job)
        except OSError:  # the worker process is gone (BrokenPipeError)
            self._ended(lane)
            raise self._failure or SourceError("a frame worker process ended unexpectedly") from None

    def wait(self, timeout_s: float) -> None:
        """Without a ``wake`` of the caller's: wait up to ``timeout_s`` for a result or a started
        worker (worker processes' messages are read here, on the caller's thread)."""
        if self.kind is WorkerKind.THREAD:
            self._event.wait(timeout_s)
            self._event.clear()
            return
        self._read([self._pipes[conn] for conn in self._pipes.ready(timeout_s)])

    def poll(self) -> None:
        """Without a ``wake``: read the worker processes' messages that are already there (never blocks)."""
        self._read(list(self._pipes.values()))

    def _read(self, lanes: list[_ProcessLane]) -> None:
        for lane in lanes:
            try:
                while lane.conn in self._pipes.ready():
                    lane.receive()
            except (EOFError, OSError):
                self._ended(lane)

    def _ended(self, lane: _ProcessLane) -> None:
        self._pipes.pop(lane.conn, None)  # its pipe, at its end, is read no more
        lane.ended()

    def reclaim(self, job: FrameJob) -> bool:
        """Take a submitted job back if its worker process has not started it (then no result
        comes for it: the caller does it); False with threads or once started."""
        return any(lane.reclaim(job) for lane in self._lanes)

    def reclaim_newest(self) -> FrameJob | None:
        """Take back the job handed out last that no worker process has started (the caller does it
        rather than wait for a started one), or None (threads, or every job started)."""
        for lane in self._lanes:
            job = lane.reclaim_newest()
            if job is not None:
                return job
        return None

    def take(self) -> list[FrameResult]:
        """Every result ready now (completion order)."""
        with self._lock:
            if self._failure is not None:
                raise self._failure
            out = list(self._done)
            self._done.clear()
            return out

    def _lane_ready(self, lane: _ProcessLane) -> None:
        with self._lock:
            self.started += lane.depth
            self._idle.extend([lane] * lane.depth)
        self._wake()

    def _finished(self, result: FrameResult | BaseException | None, lane: _ProcessLane | None = None) -> None:
        """A worker's answer: a result, a failure, or None for a job taken back (its slot is free)."""
        with self._lock:
            if isinstance(result, BaseException):
                self._failure = self._failure or result
            else:
                if result is not None:
                    self._done.append(result)
                self._idle.append(lane)
        self._wake()

    def _thread_loop(self, worker: FrameWorker) -> None:
        while (job := self._jobs.get()) is not None:
            try:
                result = worker.work(job)
            except Exception as exc:  # a bug in a stage: stop the session, the consumer re-raises
                self._finished(exc)
                return
            self._finished(result)

    def close(self) -> None:
        if self.kind is WorkerKind.THREAD:
            for _ in self._threads:
                self._jobs.put(None)
            for t in self._threads:
                t.join(5.0)
        for lane in self._lanes:
            lane.close()


class _ProcessLane:
    """One worker process: a pipe for jobs (JPEG included, so that several can be queued) and
    results. With ``threaded``, a thread in this process waits for its results; without, the
    pool's :meth:`FramePool.wait` reads them on the caller's thread (no GIL hand-offs)."""

    def __init__(self, context, make_worker: Callable[[], FrameWorker], pool: FramePool, depth: int,
                 threaded: bool):
        self.conn, child = context.Pipe()
        # one flag per job on the way (a ring): whether the worker started it (_STARTED) or the
        # pool's caller took it back (_RECLAIMED, :meth:`FramePool.reclaim`) first
        self.claims, self.claim_lock = context.RawArray("b", depth + 1), context.Lock()
        self.process = context.Process(target=_process_main, args=(child, make_worker, self.claims, self.claim_lock),
                                       daemon=True, name="cubetrack-frame-worker")
        self.process.start()
        child.close()
        self.pool = pool
        self.depth = depth
        self.jobs: deque[FrameJob] = deque()  # sent, in order; the worker answers in the same order
        self.tickets: dict[FrameJob, int] = {}  # sent job -> its claim flag
        self.sent = 0
        self.started = False
        self.closing = False
        self.reader = None
        if threaded:
            self.reader = threading.Thread(target=self._read, daemon=True, name="cubetrack-frame-results")
            self.reader.start()

    def send(self, job: FrameJob) -> None:
        ticket = self.sent % len(self.claims)  # free: at most depth jobs are on the way
        self.sent += 1
        self.claims[ticket] = _WAITING
        self.jobs.append(job)
        self.tickets[job] = ticket
        # pickled by the C pickler alone (the bytes ``Connection.send``'s ForkingPickler makes, without the
        # dispatch table it copies per call: 72 -> 58 us per job of a 22 KB JPEG, session 22)
        self.conn.send_bytes(pickle.dumps((ticket, job.plain())))

    def reclaim(self, job: FrameJob) -> bool:
        """Take ``job`` back unless the worker has started it (its answer will be None)."""
        ticket = self.tickets.get(job)
        if ticket is None:
            return False
        with self.claim_lock:
            if self.claims[ticket] != _WAITING:
                return False
            self.claims[ticket] = _RECLAIMED
        return True

    def reclaim_newest(self) -> FrameJob | None:
        """The newest job sent that the worker has not started, taken back (:meth:`reclaim`), or None.
        The worker takes its jobs in the order sent: once the newest not taken back is started, all are."""
        with self.claim_lock:
            for job in reversed(self.jobs):
                flag = self.claims[self.tickets[job]]
                if flag == _STARTED:
                    return None
                if flag == _WAITING:
                    self.claims[self.tickets[job]] = _RECLAIMED
                    return job
        return None

    def receive(self) -> None:
        """Take one message of the worker process (blocks until one comes)."""
        message = self.conn.recv()
        if not self.started:
            if message != "ready":
                raise EOFError
            self.started = True
            self.pool._lane_ready(self)
            return
        job = self.jobs.popleft()
        del self.tickets[job]
        if message is None:  # taken back before the worker started it
            self.pool._finished(None, self)
        else:
            self.pool._finished(self.pool.local_worker.unpack(job, message), self)

    def ended(self) -> None:
        if not self.closing:
            self.closing = True
            self.pool._finished(SourceError(f"a frame worker process ended unexpectedly "
                                            f"(exit code {self.process.exitcode})"))

    def _read(self) -> None:
        try:
            while True:
                self.receive()
        except (EOFError, OSError):
            self.ended()

    def close(self) -> None:
        self.closing = True
        try:
            self.conn.send(None)
        except OSError:
            pass
        self.process.join(5.0)
        if self.process.is_alive():
            self.process.terminate()
            self.process.join()
        self.conn.close()
        if self.reader is not None:
            self.reader.join(5.0)


def _process_main(conn: Connection, make_worker: Callable[[], FrameWorker], claims, claim_lock) -> None:
    """A worker process: jobs in (plain values, :meth:`_ProcessLane.send`), results out, packed
    (:meth:`FrameWorker.pack`: without the job, which the other side keeps; None for a job taken back before it
    started), until None comes."""
    end_with_parent()
    cv2.setNumThreads(1)
    try:
        worker = make_worker()
        gc.freeze()  # start-up's objects (modules, compiled kernels) leave every later collection of this process
        conn.send("ready")
        while (message := conn.recv()) is not None:
            ticket, values = message
            with claim_lock:
                mine = claims[ticket] == _WAITING
                claims[ticket] = _STARTED if mine else claims[ticket]
            if not mine:
                conn.send(None)
                continue
            conn.send_bytes(pickle.dumps(worker.pack(worker.work(FrameJob.from_plain(values)))))  # as _ProcessLane.send
    except (EOFError, KeyboardInterrupt):
        pass


def _nothing() -> None:
    pass


def by_capture_time(results: list[FrameResult]) -> list[FrameResult]:
    """Results that are ready together, oldest capture first (fewer late sightings for the fusion)."""
    return sorted(results, key=lambda r: r.job.capture_time_s)
