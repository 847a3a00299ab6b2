"""The sink stage: the one small interface every output implements, and the fan-out that feeds them.

The pipeline hands each :class:`Sink` what it produced — fused poses, camera health snapshots,
processed camera frames — through :class:`Outputs`. Sinks never feed back into the pipeline and
never block it: a sink that talks to slow peers (a network server, a browser) is wrapped in a
:class:`Decoupled` queue of bounded size, served by its own thread, that drops the oldest item
when full and counts the drop. Files are written in line (a pose is on disk before the next one
is computed). Live tracking and offline replay drive the same calls in the same order.
"""

from __future__ import annotations

import abc
import dataclasses
import logging
import math
import threading
import time
from collections import deque
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from cubetrack.core.cameras import CameraIntrinsics, WorldConfig
from cubetrack.core.errors import CubetrackError
from cubetrack.core.layout import CubeLayout
from cubetrack.core.records import CameraHealth, CameraView, CameraWatchState, TrackedPose
from cubetrack.io.trajectory import PoseWriter

log = logging.getLogger(__name__)

QUEUE_ITEMS = 256  # per decoupled sink: about 8 s of poses of one robot at 30 Hz


class OutputError(CubetrackError):
    """An output (Zenoh, ROS 2, VRPN, Foxglove, MCAP) cannot start: a bad address, a port in use."""


def is_loopback_host(host: str) -> bool:
    """Whether ``host`` (a name or an IPv4/IPv6 address) is this machine's loopback."""
    import ipaddress

    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False


@dataclass(frozen=True, slots=True, eq=False)
class CameraSetup:
    """One camera as the session knows it: ``T_world_cam`` (None until calibrated) and intrinsics."""

    name: str
    T_world_cam: np.ndarray | None
    intrinsics: CameraIntrinsics | None


@dataclass(frozen=True, slots=True, eq=False)
class SessionInfo:
    """What does not change during a session, given to every sink when it opens."""

    world: WorldConfig
    cameras: tuple[CameraSetup, ...]
    robots: dict[str, CubeLayout] = field(default_factory=dict)

    def rejoined(self, state: CameraWatchState) -> SessionInfo | None:
        """The session with the camera ``state`` names at the new pose it rejoined at (issue 27:
        outputs publish a re-calibrated camera's pose); None when ``state`` carries no new pose
        of one of this session's cameras."""
        if state.T_world_cam is None or all(c.name != state.camera for c in self.cameras):
            return None
        cameras = tuple(dataclasses.replace(c, T_world_cam=np.array(state.T_world_cam, float))
                        if c.name == state.camera else c for c in self.cameras)
        return dataclasses.replace(self, cameras=cameras)


class Sink(abc.ABC):
    """An output of the pipeline. Calls come from one thread, in pipeline order; each returns
    quickly. Only :meth:`pose` is required; the others default to ignoring their input."""

    name: str = "sink"
    #: True for outputs that must see everything and are fast (files); False for peers that may
    #: be slow, which :class:`Outputs` runs behind a :class:`Decoupled` queue.
    in_line: bool = False

    def open(self, session: SessionInfo) -> None:
        """The session starts: static facts (world, cameras, robots)."""

    @abc.abstractmethod
    def pose(self, pose: TrackedPose) -> None:
        """One fused pose."""

    def camera_health(self, health: CameraHealth) -> None:
        """A camera's health snapshot (about once a second per camera, live only)."""

    def camera_view(self, view: CameraView) -> None:
        """A processed frame (only for sinks that ask for views: ``wants_views``)."""

    def camera_watch(self, state: CameraWatchState) -> None:
        """What the camera watching says of a camera, when it changes (``[camera_watch] enabled``)."""

    #: whether :meth:`camera_view` should be called (views carry JPEGs: only sinks that show images)
    wants_views: bool = False
    #: at most one view per camera per this many seconds of capture time (0: every view);
    #: :class:`Outputs` thins the views out before they reach the sink or its queue
    view_interval_s: float = 0.0
    #: where a user finds this output (one line for the command line), "" for none
    where: str = ""
    #: behind a :class:`Decoupled` queue: hand over all that is queued together (:meth:`deliver`),
    #: at most one batch per this long (an item after a quiet spell goes at once); 0: one by one
    batch_window_s: float = 0.0

    def deliver(self, items: list[tuple[str, object]]) -> None:
        """Several calls at once, as ``(method name, value)`` in order (what :class:`Decoupled`
        took from its queue); a sink that can send them together overrides this."""
        for kind, value in items:
            getattr(self, kind)(value)

    def close(self) -> None:
        """The session ends: flush and release everything."""


class FileSink(Sink):
    """``<out_dir>/<robot>.tum`` and ``.jsonl`` per robot (contracts §5), flushed pose by pose."""

    name = "files"
    in_line = True

    def __init__(self, out_dir: str | Path, robots: tuple[str, ...]):
        self.out_dir = Path(out_dir)
        self.writers = {robot: PoseWriter(self.out_dir, robot) for robot in robots}

    def pose(self, pose: TrackedPose) -> None:
        self.writers[pose.robot].write(pose)

    def close(self) -> None:
        for writer in self.writers.values():
            writer.close()

    @property
    def outputs(self) -> dict[str, tuple[Path, Path]]:
        """Robot -> (TUM path, JSONL path)."""
        return {robot: (w.tum_path, w.jsonl_path) for robot, w in self.writers.items()}


class Decoupled(Sink):
    """Runs ``inner`` on its own thread behind a bounded queue: the caller never waits. When the
    queue is full the oldest item is dropped and counted (``dropped``). An exception in ``inner``
    is logged once and the sink stops taking items (``failed``), never reaching the pipeline."""

    def __init__(self, inner: Sink, max_items: int = QUEUE_ITEMS):
        self.inner = inner
        self.name = inner.name
        self.wants_views = inner.wants_views
        self.view_interval_s = inner.view_interval_s
        self.dropped = 0
        self.failed: str | None = None
        self._queue: deque = deque()
        self._max_items = max_items
        self._ready = threading.Condition()
        self._closing = False
        self._thread = threading.Thread(target=self._serve, name=f"cubetrack-sink-{inner.name}", daemon=True)
        self._thread.start()

    def open(self, session: SessionInfo) -> None:
        self._put(("open", session))

    def pose(self, pose: TrackedPose) -> None:
        self._put(("pose", pose))

    def camera_health(self, health: CameraHealth) -> None:
        self._put(("camera_health", health))

    def camera_view(self, view: CameraView) -> None:
        self._put(("camera_view", view))

    def camera_watch(self, state: CameraWatchState) -> None:
        self._put(("camera_watch", state))

    def _put(self, item: tuple) -> None:
        with self._ready:
            if self.failed is not None or self._closing:
                return
            if item[0] != "open" and len(self._queue) >= self._max_items:
                self._queue.popleft()
                self.dropped += 1
            self._queue.append(item)
            self._ready.notify()

    def _serve(self) -> None:
        window_s = self.inner.batch_window_s
        last_s = float("-inf")  # when the last batch went
        while True:
            with self._ready:
                while not self._queue and not self._closing:
                    self._ready.wait()
                if not self._queue:
                    return
            if window_s > 0:  # a batching sink: at most one batch per window, so an item that comes
                wait_s = last_s + window_s - time.monotonic()  # after a quiet spell goes at once
                if wait_s > 0:  # and ones that follow it closely join the next batch
                    time.sleep(wait_s)  # (puts do not wake this thread)
                last_s = time.monotonic()
            with self._ready:
                if window_s > 0:
                    items = list(self._queue)
                    self._queue.clear()
                else:
                    items = [self._queue.popleft()]
            try:
                self.inner.deliver(items)
            except Exception as exc:  # an output's failure must not reach the pipeline
                with self._ready:
                    self.failed = _stopped(self.name, exc)
                    self._queue.clear()
                return

    def close(self, timeout_s: float = 5.0) -> None:
        """Deliver what is queued (up to ``timeout_s``), then close ``inner``."""
        with self._ready:
            self._closing = True
            self._ready.notify()
        if self._thread.is_alive():
            self._thread.join(timeout_s)
        if self._thread.is_alive():
            log.warning("output %s did not finish within %.0f s; %d item(s) left undelivered",
                        self.name, timeout_s, len(self._queue))
        if self.dropped:
            log.warning("output %s dropped %d item(s) it could not take in time", self.name, self.dropped)
        try:
            self.inner.close()
        except Exception as exc:
            log.error("output %s failed to close: %s", self.name, exc)


def _stopped(name: str, exc: Exception) -> str:
    """Log that output ``name`` failed with ``exc`` and is stopped; the reason, for ``failed``."""
    log.error("output %s failed and was stopped: %s", name, exc, exc_info=True)
    return str(exc) or type(exc).__name__


class Guarded(Sink):
    """Calls ``inner`` in line; an exception in it is logged once and ``inner`` is called no
    more (``failed``), never reaching the caller or the other sinks."""

    def __init__(self, inner: Sink):
        self.inner = inner
        self.name = inner.name
        self.in_line = True
        self.wants_views = inner.wants_views
        self.view_interval_s = inner.view_interval_s
        self.failed: str | None = None

    def deliver(self, items: list[tuple[str, object]]) -> None:
        if self.failed is None:
            try:
                self.inner.deliver(items)
            except Exception as exc:  # one output's failure stops that output only
                self.failed = _stopped(self.name, exc)

    def open(self, session: SessionInfo) -> None:
        self.deliver([("open", session)])

    def pose(self, pose: TrackedPose) -> None:
        self.deliver([("pose", pose)])

    def camera_health(self, health: CameraHealth) -> None:
        self.deliver([("camera_health", health)])

    def camera_view(self, view: CameraView) -> None:
        self.deliver([("camera_view", view)])

    def camera_watch(self, state: CameraWatchState) -> None:
        self.deliver([("camera_watch", state)])

    def close(self) -> None:
        try:
            self.inner.close()
        except Exception as exc:
            log.error("output %s failed to close: %s", self.name, exc)


class Outputs:
    """Every sink of a session: in-line sinks are called directly, the others through
    :class:`Decoupled` (``all_in_line``: every sink in line behind :class:`Guarded`, for a process
    that does nothing but feed outputs that never block). Use as a context manager around the
    session."""

    def __init__(self, sinks: list[Sink], all_in_line: bool = False):
        self.sinks = [Guarded(s) if all_in_line else s if s.in_line else Decoupled(s) for s in sinks]
        self._views = [s for s in self.sinks if s.wants_views]
        self._next_view_s: dict[tuple[int, str], float] = {}

    @property
    def wants_views(self) -> bool:
        return bool(self._views)

    def open(self, session: SessionInfo) -> None:
        for sink in self.sinks:
            sink.open(session)

    def pose(self, pose: TrackedPose) -> None:
        for sink in self.sinks:
            sink.pose(pose)

    def camera_health(self, health: CameraHealth) -> None:
        for sink in self.sinks:
            sink.camera_health(health)

    def camera_watch(self, state: CameraWatchState) -> None:
        for sink in self.sinks:
            sink.camera_watch(state)

    def camera_view(self, view: CameraView) -> None:
        for i, sink in enumerate(self._views):
            if sink.view_interval_s > 0 and not self._view_due(i, sink.view_interval_s, view):
                continue
            sink.camera_view(view)

    def _view_due(self, sink: int, interval_s: float, view: CameraView) -> bool:
        """Whether ``view`` is due for view sink ``sink`` (one per camera per ``interval_s``: the
        due time steps by ``interval_s`` so that the rate holds on average whatever the frames'
        jitter; after a gap it restarts from the view)."""
        key = (sink, view.camera)
        due_s = self._next_view_s.get(key, -math.inf)
        if view.time_s < due_s:
            return False
        self._next_view_s[key] = due_s + interval_s if view.time_s - due_s < interval_s else view.time_s + interval_s
        return True

    def dropped(self) -> dict[str, int]:
        """Sink name -> items it lost because it was slow."""
        return {s.name: s.dropped for s in self.sinks if isinstance(s, Decoupled)}

    def close(self) -> None:
        for sink in self.sinks:
            sink.close()

    def __enter__(self) -> Outputs:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
