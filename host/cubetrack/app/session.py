"""The session runtime: what every run loop of the package shares (replay, ``track --live`` with
frame threads or camera processes, ``cubetrack record``, ``cubetrack worker``, ``cubetrack fuse``
and the dashboard's sessions).

A loop supplies one ``step(timeout_s)``: wait at most that long for frames (or sightings, or
results), then hand what came to the tracker. The runtime owns the rest:

- :class:`Session`: the deadline (``duration_s``), the caller's ``stop`` event, periodic ticks
  (:meth:`Session.every`, among them the status line), the stop path, and the run record. Ctrl-C,
  SIGTERM and SIGHUP all take the stop path while the session runs: the loop ends at its next turn,
  works off what had arrived and finishes, exactly as at the end of the duration (a second signal
  gives up the draining). ``run.json`` is written when the session starts, so a session killed
  outright still says how it was made, and again when it ends, with a ``session`` table: how it
  ended and the loop's summary. Every command's record has the same shape.
- :class:`PoseStream`: the tracker's side of a live session: fuse a result, take a clock
  sample, release the poses a fixed lag held whose time is up, output each robot's pose
  predicted to now at ``[fusion] output_rate_hz``, finish, and every pose handed to the outputs
  with its latencies moved to that moment (session medians kept in fixed memory).
"""

from __future__ import annotations

import dataclasses
import logging
import math
import signal
import threading
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from types import FrameType
from typing import Any

from cubetrack.app.tracker import StageParams, Tracker, TrackStats
from cubetrack.core.cameras import ClockSample
from cubetrack.core.geometry import quat_xyzw_from_R
from cubetrack.core.median import SessionMedian
from cubetrack.core.records import FrameResult, TrackedPose
from cubetrack.fuse.base import Fusion
from cubetrack.io.run import write_run_record
from cubetrack.sink.base import Outputs

log = logging.getLogger(__name__)

STOP_SIGNALS = ("SIGINT", "SIGTERM", "SIGHUP")  # each ends a running session like Ctrl-C (where not ignored)
IDLE_WAIT_S = 0.1  # a loop waits at most this long for work between its periodic duties


def idle_wait_s(params: StageParams) -> float:
    """How long a live loop waits for work at most: ``IDLE_WAIT_S``, or with a fixed lag half its
    ``smooth_margin_s`` (so a held pose whose time is up leaves within that of it, even while no
    frame comes)."""
    fp = params.filter
    return IDLE_WAIT_S if fp.smooth_lag_s == 0 else min(IDLE_WAIT_S, max(0.005, fp.smooth_margin_s / 2))


@dataclass(frozen=True, slots=True)
class RunSpec:
    """What a session's ``run.json`` records besides how the session ended: where it goes, the
    command, the resolved parameters (section -> params dataclass or table), the inputs (name
    -> path, None left out) and extra top-level entries."""

    path: Path
    command: str
    parameters: Mapping[str, Any]
    inputs: Mapping[str, str | Path | None]
    extra: Mapping[str, Any] = dataclasses.field(default_factory=dict)


class _Tick:
    """An action due every ``period_s`` on ``clock``, first at ``first_s`` (on the period's grid
    of that clock with ``grid``)."""

    def __init__(self, period_s: float, action: Callable[[], None], clock: Callable[[], float], first_s: float,
                 grid: bool):
        self.period_s, self.action, self.clock, self.next_s, self.grid = period_s, action, clock, first_s, grid

    def wait_s(self) -> float:
        return max(0.0, self.next_s - self.clock())

    def run_if_due(self) -> None:
        if self.clock() < self.next_s:
            return
        if not self.grid:
            self.next_s += self.period_s
        self.action()
        if self.grid:  # the multiple after the action's end: an action that reads the clock late (a loaded
            # machine) has its cell, and the next one runs in a later cell, never twice in one
            self.next_s = (math.floor(self.clock() / self.period_s) + 1) * self.period_s


class Session:
    """One run of a loop (see the module doc). ``duration_s`` None: until ``stop`` is set or a
    stop signal comes; ``status``: called every ``status_every_s`` (it reports the status line);
    ``record``: the run record written at the start and the end."""

    def __init__(self, *, duration_s: float | None = None, stop: threading.Event | None = None,
                 status: Callable[[], None] | None = None, status_every_s: float = 2.0,
                 record: RunSpec | None = None):
        self.duration_s = duration_s
        self.status_every_s = status_every_s
        self.stop_event = stop if stop is not None else threading.Event()
        self.record = record
        self.started = time.monotonic()
        self.ended_by: str | None = None  # the signal that stopped the session (Ctrl-C: "SIGINT")
        self.completed = False  # the loop's input ended (a replay's last frame)
        self._ticks: list[_Tick] = []
        self._turns: list[Callable[[], None]] = []
        if record is not None:
            write_run_record(record.path, record.command, record.parameters, record.inputs, record.extra)
        if status is not None:
            self.every(status_every_s, status, first_s=self.started + status_every_s)

    @property
    def elapsed_s(self) -> float:
        return time.monotonic() - self.started

    @property
    def interrupted(self) -> bool:
        """A signal (Ctrl-C, SIGTERM, SIGHUP) ended the session."""
        return self.ended_by is not None

    def every(self, period_s: float, action: Callable[[], None], *, clock: Callable[[], float] = time.monotonic,
              first_s: float | None = None, grid: bool = False) -> None:
        """Call ``action`` every ``period_s`` of ``clock`` while the loop runs (first at ``first_s``,
        default now; ``grid``: then at the multiples of ``period_s``)."""
        self._ticks.append(_Tick(period_s, action, clock, clock() if first_s is None else first_s, grid))

    def each_turn(self, action: Callable[[], None]) -> None:
        """Call ``action`` after every step of the loop (e.g. releasing what a fixed lag held)."""
        self._turns.append(action)

    def complete(self) -> None:
        """The loop's input has ended (a replay's last frame): the session is over."""
        self.completed = True

    def over(self) -> bool:
        return (self.completed or self.stop_event.is_set()
                or (self.duration_s is not None and self.elapsed_s >= self.duration_s))

    def run(self, step: Callable[[float], None], idle_s: float = IDLE_WAIT_S,
            draining: Callable[[], bool] | None = None, drained: Callable[[], None] | None = None) -> None:
        """The loop: ``step(timeout_s)`` (waiting at most ``idle_s`` or until the next tick), the
        per-turn actions and the due ticks, until the session is over; then ``drained()`` (e.g.
        stop the sources) and ``step(0.05)`` while ``draining()`` (the work that had arrived). A
        stop signal, or KeyboardInterrupt, ends it the same way; a second one ends the draining."""
        previous = self._catch_stop_signals()
        try:
            try:
                while not self.over():
                    step(min([idle_s] + [t.wait_s() for t in self._ticks]))
                    for action in self._turns:
                        action()
                    for tick in self._ticks:
                        tick.run_if_due()
                if drained is not None:
                    drained()
                while draining is not None and draining():
                    step(0.05)
            except KeyboardInterrupt:
                self.ended_by = self.ended_by or "SIGINT"
                log.info("interrupted: finishing with what has arrived")
        finally:
            for number, handler in previous.items():
                signal.signal(number, handler)

    def _catch_stop_signals(self) -> dict[int, Any]:
        """While the loop runs, a stop signal sets the stop event (a second raises KeyboardInterrupt);
        returns the handlers to put back. Signals are only caught in the main thread, and ignored
        ones (``nohup``) stay ignored."""
        if threading.current_thread() is not threading.main_thread():
            return {}

        def handler(number: int, frame: FrameType | None) -> None:
            if self.ended_by is not None:
                raise KeyboardInterrupt
            self.ended_by = signal.Signals(number).name
            self.stop_event.set()

        previous = {}
        for name in STOP_SIGNALS:
            number = getattr(signal, name, None)
            if number is not None and signal.getsignal(number) is not signal.SIG_IGN:
                previous[number] = signal.signal(number, handler)
        return previous

    def finish(self, summary: Mapping[str, Any]) -> None:
        """Record how the session ended (the signal's name, ``end of input``, ``stopped`` or
        ``duration``), how long it ran and the loop's ``summary`` in ``run.json``."""
        if self.record is None:
            return
        ended = self.ended_by or ("end of input" if self.completed else
                                  "stopped" if self.stop_event.is_set() else "duration")
        session = {"ended": ended, "duration_s": round(self.elapsed_s, 3), **summary}
        r = self.record
        write_run_record(r.path, r.command, r.parameters, r.inputs, {**r.extra, "session": session})


def predicted_poses(fusion: Fusion, robots: Sequence[str], now_s: float) -> list[TrackedPose]:
    """Each tracked robot's pose predicted to ``now_s`` by the fusion's motion model (none for a
    robot that is not tracked or no longer seen; none from fusions without a motion model)."""
    out = []
    for robot in robots:
        T = fusion.predicted_pose(robot, now_s)
        if T is not None:
            out.append(TrackedPose(robot, now_s, T[:3, 3].copy(), quat_xyzw_from_R(T[:3, :3]), (), (), 0.0,
                                   predicted=True))
    return out


class PoseStream:
    """The tracker's side of a live session: every pose it makes goes to ``outputs`` with its
    latencies moved to the moment it is handed over (``clock``), and ``on_poses`` sees them too
    (e.g. a status line's rates). :meth:`attach` adds the per-turn release of held poses and, with
    ``[fusion] output_rate_hz``, the predicted poses on that rate's grid of ``clock``."""

    def __init__(self, tracker: Tracker, outputs: Outputs, clock: Callable[[], float] = time.time,
                 on_poses: Callable[[list[TrackedPose]], None] | None = None):
        self.tracker, self.outputs, self.clock = tracker, outputs, clock
        self.on_poses = on_poses
        self.robots = [r.name for r in tracker.robots]
        self.latencies, self.arrival_latencies = SessionMedian(), SessionMedian()

    def attach(self, session: Session) -> None:
        """Release held poses after every step; predicted poses at ``[fusion] output_rate_hz``."""
        session.each_turn(self.release)
        rate_hz = self.tracker.params.fusion.output_rate_hz
        if rate_hz > 0:
            session.every(1.0 / rate_hz, self.predict, clock=self.clock, grid=True)

    def emit(self, poses: list[TrackedPose], now_s: float) -> None:
        """Output poses the tracker made for ``now_s``, their latencies moved to this moment."""
        if not poses:
            return
        delay_s = self.clock() - now_s
        poses = [pose if pose.predicted else dataclasses.replace(
            pose, latency_s=pose.latency_s + delay_s,
            arrival_latency_s=None if pose.arrival_latency_s is None else pose.arrival_latency_s + delay_s)
            for pose in poses]
        for pose in poses:
            self.outputs.pose(pose)
            if not pose.predicted:
                self.latencies.add(pose.latency_s)
            if pose.arrival_latency_s is not None:
                self.arrival_latencies.add(pose.arrival_latency_s)
        if self.on_poses is not None:
            self.on_poses(poses)

    def fuse(self, result: FrameResult) -> None:
        now_s = self.clock()
        self.emit(self.tracker.fuse(result, now_s), now_s)

    def clock_sample(self, camera: str, sample: ClockSample) -> None:
        self.emit(self.tracker.add_clock_sample(camera, sample), sample.host_recv_s)

    def release(self) -> None:
        """A fixed lag's poses whose time is up, frames or not."""
        now_s = self.clock()
        self.emit(self.tracker.release(now_s), now_s)

    def predict(self) -> None:
        now_s = self.clock()
        self.emit(predicted_poses(self.tracker.fusion, self.robots, now_s), now_s)

    def finish(self) -> None:
        """The poses the fusion still holds."""
        now_s = self.clock()
        self.emit(self.tracker.finish(now_s), now_s)

    def summary(self, stats: TrackStats) -> dict[str, Any]:
        """The run record's summary of a tracking session."""
        return {"frames": stats.frames, "poses": dict(stats.poses), "corrupt_frames": stats.corrupt_frames,
                "frames_before_clock_sync": stats.frames_before_clock_sync,
                "median_latency_s": self.latencies.median(),
                "median_arrival_latency_s": self.arrival_latencies.median()}
