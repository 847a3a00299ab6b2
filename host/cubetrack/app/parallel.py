"""Per-frame work on every core for live tracking; the fusion stays one ordered consumer.

The tracker (:class:`~cubetrack.app.tracker.Tracker`) splits a frame's work in three: ``admit``
plans it from the fusion's state (capture time, the regions where detection looks, which robots
need an estimate), a :class:`~cubetrack.app.tracker.FrameWorker` does it (decode, detection,
per-camera estimates: no shared state), and ``fuse`` hands the sightings to the fusion. A
:class:`FramePool` runs the middle part on worker processes (the JPEG handed over in shared
memory, the result pickled back) or threads (OpenCV releases the GIL in decoding and detection;
the Python parts of detection and estimation hold it), and wakes the consumer when a result is
ready. It takes a job only while a worker is free, so frames wait in the source, where each
camera keeps only its newest (:class:`~cubetrack.source.streams.LiveCameras`).
"""

from __future__ import annotations

import dataclasses
import enum
import multiprocessing
import os
import queue
import threading
from collections import deque
from dataclasses import dataclass
from multiprocessing import shared_memory
from multiprocessing.connection import Connection
from typing import Callable

import cv2

from cubetrack.app.tracker import FrameJob, FrameOutcome, FrameResult, FrameWorker
from cubetrack.core.errors import SourceError
from cubetrack.core.params import check, param


@enum.unique
class WorkerKind(enum.Enum):
    PROCESS = "process"
    THREAD = "thread"
    CAMERA_PROCESS = "camera-process"


@dataclass(frozen=True, slots=True)
class LiveParams:
    """The ``[live]`` section of the tracker config: how live frames are processed."""

    workers: int = param(0, "per-frame workers (decode, detection, per-camera estimate); 0: one per core")
    worker_kind: WorkerKind = param(
        WorkerKind.THREAD,
        "thread: threads of the tracker's process (measured faster here, docs/live.md); process: worker "
        "processes, each frame's JPEG handed over in shared memory; camera-process: worker processes that each "
        "read a share of the cameras and do their per-frame work, the fusion in the tracker's process "
        "(cubetrack.app.camera_workers; not while recording)")

    def __post_init__(self) -> None:
        check(self.workers >= 0, f"workers must not be negative, got {self.workers}")

    @property
    def worker_count(self) -> int:
        return self.workers or os.cpu_count() or 1


class FramePool:
    """``count`` frame workers of ``kind``. :meth:`submit` a job while :meth:`idle` > 0; results
    come back through :meth:`take` (completion order) and ``wake`` is called as each is ready.

    Worker processes start in the background (importing the stages takes a second or two): until
    the first is ready, :attr:`ready` is False and the consumer does the work itself. Use as a
    context manager; :meth:`close` ends the workers."""

    def __init__(self, make_worker: Callable[[], FrameWorker], count: int, kind: WorkerKind,
                 wake: Callable[[], None] = lambda: None, max_frame_bytes: int = 4 * 1024 * 1024):
        self.kind = kind
        self.count = count
        self._wake = wake
        self._lock = threading.Lock()
        self._done: deque[FrameResult] = deque()
        self._idle: deque = deque()  # lanes (worker processes) or None per idle worker thread
        self._failure: BaseException | None = None
        if kind is WorkerKind.THREAD:
            self._jobs: queue.SimpleQueue = queue.SimpleQueue()
            self._threads = [threading.Thread(target=self._thread_loop, args=(make_worker(),), daemon=True,
                                              name=f"cubetrack-frame-worker-{k}") for k in range(count)]
            for t in self._threads:
                t.start()
            self._idle.extend([None] * count)
            self._lanes: list[_ProcessLane] = []
        else:
            context = multiprocessing.get_context("spawn")  # fork would copy this process's threads' locks
            self._lanes = [_ProcessLane(context, make_worker, max_frame_bytes, self) for _ in range(count)]
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

    def idle(self) -> int:
        """Started workers without a job."""
        with self._lock:
            return len(self._idle)

    def busy(self) -> int:
        """Jobs handed out whose results have not been taken."""
        with self._lock:
            return self.started - len(self._idle)

    def submit(self, job: FrameJob) -> None:
        """Hand a job to an idle worker (call only while :meth:`idle` > 0)."""
        with self._lock:
            if self._failure is not None:
                raise self._failure
            lane = self._idle.popleft()
        if lane is None:
            self._jobs.put(job)
        else:
            lane.send(job)

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
            self.started += 1
            self._idle.append(lane)
        self._wake()

    def _finished(self, result: FrameResult | BaseException, lane: _ProcessLane | None = None) -> None:
        with self._lock:
            if isinstance(result, BaseException):
                self._failure = self._failure or result
            else:
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
    """One worker process: a pipe for job headers and results, a shared-memory block for the
    JPEG, and a thread in this process that waits for its messages."""

    def __init__(self, context, make_worker: Callable[[], FrameWorker], max_frame_bytes: int, pool: FramePool):
        self.memory = shared_memory.SharedMemory(create=True, size=max_frame_bytes)
        self.conn, child = context.Pipe()
        self.process = context.Process(target=_process_main, args=(child, self.memory.name, make_worker),
                                       daemon=True, name="cubetrack-frame-worker")
        self.process.start()
        child.close()
        self.pool = pool
        self.job: FrameJob | None = None
        self.closing = False
        self.reader = threading.Thread(target=self._read, daemon=True, name="cubetrack-frame-results")
        self.reader.start()

    def send(self, job: FrameJob) -> None:
        size = len(job.frame.jpeg)
        self.job = job
        if size > self.memory.size:
            self.job = None
            self.pool._finished(FrameResult(job, FrameOutcome.CORRUPT, error=f"{size} bytes: larger than the "
                                            "frame buffer"), self)
            return
        self.memory.buf[:size] = job.frame.jpeg
        self.conn.send((dataclasses.replace(job, frame=dataclasses.replace(job.frame, jpeg=b"")), size))

    def _read(self) -> None:
        try:
            if self.conn.recv() != "ready":
                raise EOFError
            self.pool._lane_ready(self)
            while True:
                outcome, sightings, error = self.conn.recv()
                job, self.job = self.job, None
                self.pool._finished(FrameResult(job, outcome, sightings, error), self)
        except (EOFError, OSError):
            if not self.closing:
                self.pool._finished(SourceError(f"a frame worker process ended unexpectedly "
                                                f"(exit code {self.process.exitcode})"))

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
        self.reader.join(5.0)
        self.memory.close()
        self.memory.unlink()


def _process_main(conn: Connection, memory_name: str, make_worker: Callable[[], FrameWorker]) -> None:
    """A worker process: jobs in (the JPEG from shared memory), results out, until None comes."""
    cv2.setNumThreads(1)
    memory = shared_memory.SharedMemory(name=memory_name)
    try:
        worker = make_worker()
        conn.send("ready")
        while (message := conn.recv()) is not None:
            job, size = message
            jpeg = bytes(memory.buf[:size])
            result = worker.work(dataclasses.replace(job, frame=dataclasses.replace(job.frame, jpeg=jpeg)))
            conn.send((result.outcome, result.sightings, result.error))
    except (EOFError, KeyboardInterrupt):
        pass
    finally:
        memory.close()


def by_capture_time(results: list[FrameResult]) -> list[FrameResult]:
    """Results that are ready together, oldest capture first (fewer late sightings for the fusion)."""
    return sorted(results, key=lambda r: r.job.capture_time_s)
