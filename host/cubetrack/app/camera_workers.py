"""Camera worker processes for live tracking (``[live] worker_kind = "camera-process"``).

Each worker process owns a share of the cameras end to end: it reads their streams and
``/time`` round trips on its one thread, between frames
(:class:`~cubetrack.source.streams.LiveCameras` without a thread of its own: non-blocking
sockets; frames in arrival order, the freshest first once behind, each camera's newest only),
stamps capture times with its own clock fits, plans each frame and does the per-frame work
(decode, detection, per-camera estimates) with a :class:`~cubetrack.app.tracker.Tracker` of its
own, whose plans come from a :class:`~cubetrack.fuse.forecast.Forecast`: each robot's motion as
the fusion predicts it, posted by the tracker's process after a batch of fused results into shared
memory (:class:`~cubetrack.core.pipes.LatestBytes`: it wakes no worker process; each takes the newest
when it plans a frame). Results
go back over a pipe without the JPEG (unless an output shows camera frames), with the clock
samples and the cameras' counters; the tracker's process only fuses them, in one ordered
consumer. No JPEG crosses processes, and the GIL of one process no longer limits the per-frame
work.
"""

from __future__ import annotations

import logging
import math
import multiprocessing
import pickle
import signal
import time
from collections.abc import Callable, Mapping, MutableSequence, Sequence
from dataclasses import dataclass
from multiprocessing.connection import Connection
from multiprocessing.process import BaseProcess

import cv2

from cubetrack.app.tracker import Tracker
from cubetrack.core.errors import SourceError
from cubetrack.core.lifetime import end_with_parent
from cubetrack.core.pipes import LatestBytes, PipePoll
from cubetrack.core.records import Frame, FrameJob, FrameOutcome, FrameResult
from cubetrack.fuse.forecast import Forecast
from cubetrack.io.frame_wire import pack_result
from cubetrack.source.streams import CameraStats, ClockReading, LiveCameras, SourceParams

log = logging.getLogger(__name__)

STATS_EVERY_S = 0.5  # a worker process sends its cameras' counters this often
FORECAST_EVERY_S = 0.01  # the tracker's process sends a new forecast at most this often
IN_FLIGHT = 4  # results a worker process may have sent that the fusion has not taken yet
WAKE = "wake"  # the message to a worker process that may wait for its results to be taken
MESSAGES_PER_TAKE = 64  # messages read from one worker process per take(), so that no process starves another
HOLD_S = 0.002  # a result newer than a frame some worker process is working on waits at most this long for it


def deal_cameras(urls: Mapping[str, str], count: int) -> list[dict[str, str]]:
    """The cameras dealt round-robin to ``count`` worker processes (none left empty)."""
    names = list(urls)
    shares = [{name: urls[name] for name in names[k::count]} for k in range(min(count, len(names)))]
    return [share for share in shares if share]


@dataclass(frozen=True, slots=True)
class WorkerUpdate:
    """What a camera worker process reports besides results: its cameras' counters, the frames it
    admitted and those it gave up before their camera's clock was known (since it started)."""

    cameras: dict[str, CameraStats]
    frames: int
    before_clock: int


class HeldResults:
    """Results on their way to the fusion, held back while an older frame is still in work, so
    that the fusion gets them in capture order (a sighting older than one fused before is folded
    in exactly, but that costs re-applying every newer one). A result waits at most ``hold_s``."""

    def __init__(self, hold_s: float = HOLD_S):
        self.hold_s = hold_s
        self._held: list[tuple[float, FrameResult]] = []  # (due at the latest, time.monotonic(); result)

    def __len__(self) -> int:
        return len(self._held)

    def wait_s(self, now: float) -> float:
        """Seconds until the first held result is due whatever is in work (inf: none held)."""
        return max(0.0, min((until for until, _ in self._held), default=math.inf) - now)

    def due(self, results: Sequence[FrameResult], working_s: float, now: float, *,
            everything: bool = False) -> list[FrameResult]:
        """Add ``results`` (come at ``now``) and take the ones to fuse now, oldest capture first:
        those older than ``working_s`` (the oldest capture time of a frame in work, inf: none);
        every one once one has waited ``hold_s``, or with ``everything``."""
        self._held += [(now + self.hold_s, r) for r in results]
        self._held.sort(key=lambda h: h[1].job.capture_time_s)
        n = 0
        if everything or any(until <= now for until, _ in self._held):
            n = len(self._held)
        while n < len(self._held) and self._held[n][1].job.capture_time_s < working_s:
            n += 1
        due = [r for _, r in self._held[:n]]
        del self._held[:n]
        return due


class CameraProcesses:
    """``count`` camera worker processes over ``urls`` (see the module doc), with the part of
    :class:`~cubetrack.source.streams.LiveCameras`' interface the live loop uses (``urls``,
    :meth:`stats`, :meth:`pending`, :meth:`stop`). ``make_tracker`` builds each process's
    tracker (picklable: a ``functools.partial``); its results come as
    :func:`cubetrack.io.frame_wire.pack_result` packs them (their jobs as ``FrameJob.plain`` values,
    without JPEG or predicted markers unless ``views``), and ``unpack`` (``unpack_result`` with
    the intrinsics and camera poses of a tracker made with the same arguments) turns them back.
    Wait for and take what came with :meth:`take` (on the caller's thread: no thread of this
    process reads the pipes, so none competes with the fusion for the GIL); send each new
    :class:`~cubetrack.fuse.forecast.Forecast` with :meth:`forecast`."""

    def __init__(self, urls: Mapping[str, str], source: SourceParams, make_tracker: Callable[[], Tracker],
                 count: int, unpack: Callable[[FrameJob, tuple], FrameResult], *, views: bool = False,
                 clock: Callable[[], float] = time.time):
        self.urls = dict(urls)
        self._unpack = unpack  # (job, a result as pack_result sent it) -> the FrameResult
        self.count = count
        self._told: list[int] = []  # per lane: the count of taken results when it was last sent a message
        self._stats = {name: CameraStats(url=url) for name, url in self.urls.items()}
        self._counts: dict[int, tuple[int, int]] = {}  # per worker process: frames admitted, given up before clock
        self._lanes: list[tuple[Connection, BaseProcess]] = []
        self._open = PipePoll[int]()  # the pipes of processes that have not finished -> lane
        self._held = HeldResults()
        context = multiprocessing.get_context("spawn")  # fork would copy this process's threads' locks
        shares = deal_cameras(self.urls, count)
        # per lane, in shared memory (written by one side, read by the other, never waited for): the capture
        # time of the frame its process is working on (inf: none), and how many of its results were taken
        self._working = context.RawArray("d", [math.inf] * len(shares))
        self._taken = context.RawArray("q", len(shares))
        self._forecasts = LatestBytes(context)  # the newest forecast, for every worker process
        for lane, share in enumerate(shares):
            parent, child = context.Pipe()
            process = context.Process(target=_worker_main, args=(child, share, source, make_tracker, views, clock,
                                                                 self._working, self._taken, lane, self._forecasts),
                                      daemon=True, name="cubetrack-camera-worker")
            process.start()
            child.close()
            self._open[parent] = len(self._lanes)
            self._lanes.append((parent, process))
            self._told.append(0)

    def take(self, timeout_s: float = 0.0) -> tuple[list[FrameResult], list[ClockReading]]:
        """The results and clock samples that came, waiting up to ``timeout_s`` for the first.
        Results come oldest capture first; one newer than a frame that a worker process is working
        on is held back until that frame's result has come too, ``HOLD_S`` at most, so that the
        fusion gets both in capture order instead of folding the older one in late (which costs
        re-applying every newer sighting). Raises :class:`SourceError` when a worker process failed."""
        timeout_s = min(timeout_s, self._held.wait_s(time.monotonic()))  # wake when a held result is due
        results: list[FrameResult] = []
        clocks: list[ClockReading] = []
        ready = self._open.ready(timeout_s)
        working = math.inf
        for _ in range(4):
            for conn in ready:
                self._read(conn, results, clocks)
            # a process marks its frame done only once its result is in the pipe: whatever is not
            # in work now has been read, or is read in the next round
            working = min((self._working[lane] for lane in self._open.values()), default=math.inf)
            ready = self._open.ready()
            if not ready:
                break
        return self._held.due(results, working, time.monotonic(), everything=not self._open), clocks

    def _read(self, conn: Connection, results: list[FrameResult], clocks: list[ClockReading]) -> None:
        """Up to ``MESSAGES_PER_TAKE`` messages of one worker process."""
        lane = self._open[conn]
        for _ in range(MESSAGES_PER_TAKE):
            try:
                kind, payload = conn.recv()
            except (EOFError, OSError):
                del self._open[conn]
                raise SourceError("a camera worker process ended unexpectedly "
                                  f"(exit code {self._lanes[lane][1].exitcode})") from None
            if kind == "result":
                job, packed = payload
                results.append(self._unpack(FrameJob.from_plain(job), packed))
                self._taken[lane] += 1
            elif kind == "clock":
                clocks.append(payload)
            elif kind == "update":
                self._stats.update(payload.cameras)
                self._counts[lane] = (payload.frames, payload.before_clock)
            elif kind == "failed":
                del self._open[conn]
                raise SourceError(f"a camera worker process failed: {payload}")
            if kind == "done":
                del self._open[conn]
                break
            if conn not in self._open.ready():
                break

    def forecast(self, forecast: Forecast | None) -> None:
        """Post the fusion's newest forecast for every worker process (None: no new one); one too
        large for the shared memory goes down every pipe instead. A worker process keeps at most
        ``IN_FLIGHT`` results that the fusion has not taken (when the fusion is behind, frames wait
        in the source, where each camera keeps only its newest); it reads how many were taken from
        shared memory, so only one that may be waiting for that count (``IN_FLIGHT`` taken since its
        last message: a process that waits sends nothing more, and :meth:`take` reads all it sent)
        is sent a message to wake it."""
        message = None if forecast is None else pickle.dumps(forecast.plain(), pickle.HIGHEST_PROTOCOL)  # once for all
        if message is not None and self._forecasts.post(message):
            message = None  # posted: the worker processes take it when they plan their next frames
        for conn, lane in self._open.items():
            if message is None and self._taken[lane] - self._told[lane] < IN_FLIGHT:
                continue
            self._told[lane] = self._taken[lane]
            try:
                if message is None:
                    conn.send(WAKE)
                else:
                    conn.send_bytes(message)
            except OSError:  # the process ended: take() reports it
                pass

    def stats(self) -> dict[str, CameraStats]:
        return {name: s.copy() for name, s in self._stats.items()}

    def frame_counts(self) -> tuple[int, int]:
        """Frames the worker processes admitted, and those they gave up before their camera's
        clock was known, so far."""
        return sum(f for f, _ in self._counts.values()), sum(b for _, b in self._counts.values())

    def pending(self) -> int:
        return len(self._open.ready()) + len(self._held)

    @property
    def running(self) -> bool:
        """Some worker process has not finished yet."""
        return bool(self._open)

    def stop(self, timeout_s: float = 10.0) -> None:
        """Ask every worker process to finish: each stops reading, works off the frames it had
        and sends its last counters; :attr:`running` turns False when :meth:`take` has had them all."""
        for conn in self._open:
            try:
                conn.send(None)
            except OSError:
                pass

    def close(self) -> None:
        self.stop()
        for conn, process in self._lanes:
            process.join(10.0)
            if process.is_alive():
                process.terminate()
                process.join()
            conn.close()
        self._open.clear()

    def start(self) -> CameraProcesses:
        """Nothing to do: the processes started with the object (for the live loop's sake)."""
        return self


def _worker_main(conn: Connection, urls: dict[str, str], source: SourceParams, make_tracker: Callable[[], Tracker],
                 views: bool, clock: Callable[[], float], working: MutableSequence[float],
                 taken: Sequence[int], lane: int, forecasts: LatestBytes) -> None:
    """A camera worker process: its cameras' frames in, results out, until None comes (Ctrl-C
    is the tracker's process's business: it ends the session, then this process)."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    end_with_parent()
    cv2.setNumThreads(1)
    try:
        work_cameras(conn, urls, source, make_tracker(), views, clock, working, taken, lane, forecasts)
    except (EOFError, BrokenPipeError):
        pass
    except Exception as exc:  # a bug or a broken camera source: the tracker's process re-raises it
        log.exception("camera worker process failed")
        conn.send(("failed", f"{type(exc).__name__}: {exc}"))


def work_cameras(conn: Connection, urls: dict[str, str], source: SourceParams, tracker: Tracker, views: bool,
                 clock: Callable[[], float], working: MutableSequence[float], taken: Sequence[int],
                 lane: int, forecasts: LatestBytes | None = None) -> None:
    """A camera worker process's loop on this thread (also ``benchmarks/live.py --worker-split``'s): read
    ``urls``, plan and work each frame with ``tracker``, send results on ``conn`` until it sends None;
    each frame is planned with the newest forecast posted to ``forecasts`` or sent on ``conn``."""
    forecast = Forecast({}, frozenset(r.name for r in tracker.robots))  # until the fusion sends one
    version = 0  # of the newest forecast taken from ``forecasts``
    inbox = PipePoll({conn: lane})
    live = LiveCameras(urls, source, clock=clock, thread=False)  # read on this thread, between frames
    live.start()
    live.wake_on(conn)
    next_update = time.monotonic() + STATS_EVERY_S
    stopping = False
    sent = 0
    job = None  # the next frame's, admitted before the result of the one before it went

    def planned_with(values: tuple) -> Forecast:
        tracker.plan_cameras_at((new := Forecast.from_plain(values)).camera_poses)
        return new

    def admitted(event: Frame | ClockReading | None) -> FrameJob | None:
        nonlocal forecast, version
        if isinstance(event, ClockReading):
            tracker.add_clock_sample(event.camera, event.sample)
            conn.send(("clock", event))
            return None
        if event is None:
            return None
        if forecasts is not None and (posted := forecasts.newer(version))[1] is not None:
            version, forecast = posted[0], planned_with(pickle.loads(posted[1]))
        return tracker.admit(event, hold=False, forecast=forecast)

    try:
        while True:
            while inbox.ready():
                message = conn.recv()
                if message is None:
                    stopping = True
                    live.stop()
                elif isinstance(message, tuple):  # a forecast too large to post; else a wake: the count taken changed
                    forecast = planned_with(message)
            if job is None:
                room = stopping or sent - taken[lane] < IN_FLIGHT
                # in arrival order: the fusion gets fewer late sightings to fold in (each costs re-applying the
                # newer ones) than freshest-first would give it; freshest first only once behind
                event = live.get(0 if stopping else 0.05, frames=room,  # or until a message comes
                                 newest_if_behind=True)
                if event is None and stopping:
                    break
                job = admitted(event)
            if job is not None:
                working[lane] = job.capture_time_s  # results newer than this wait for it (CameraProcesses.take)
                result = tracker.processor.work(job)
                if result.outcome is not FrameOutcome.CORRUPT:  # counted (and logged) by the fusion's tracker
                    tracker.count(result)  # when this camera's whole frame was last searched
                done = job.plain(jpeg=views, predicted=False)  # the fusion needs no markers, and no JPEG without views
                # the next frame, if one has come, is in work before this result goes: were it older, the
                # tracker's process holds this result for it rather than folding it in late
                job = None
                if stopping or sent + 1 - taken[lane] < IN_FLIGHT:
                    while (event := live.get(0, newest_if_behind=True)) is not None:
                        if (job := admitted(event)) is not None:
                            break
                working[lane] = math.inf if job is None else job.capture_time_s
                send_plain(conn, ("result", (done, pack_result(result, tracker.T_world_cam))))
                sent += 1
            if time.monotonic() >= next_update:
                next_update = time.monotonic() + STATS_EVERY_S
                conn.send(("update", _update(live, tracker)))
    finally:
        live.stop()
    conn.send(("update", _update(live, tracker)))
    conn.send(("done", None))


def send_plain(conn: Connection, message: tuple) -> None:
    """Send a message of plain values (read by ``recv()``), pickled by the C pickler alone:
    ``Connection.send``'s ``ForkingPickler`` copies a dispatch table per call."""
    conn.send_bytes(pickle.dumps(message, pickle.HIGHEST_PROTOCOL))


def _update(live: LiveCameras, tracker: Tracker) -> WorkerUpdate:
    return WorkerUpdate(live.stats(), tracker.stats.frames, tracker.stats.frames_before_clock_sync)
