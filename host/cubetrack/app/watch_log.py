"""What a session keeps of the camera watching (issue 27, docs/calibration.md "Keeping what was
learnt"), live, in ``cubetrack fuse`` and in an offline replay alike: every event of
:class:`cubetrack.calib.recalibrate.WatchedFusion` as one JSON line in
``<out_dir>/camera_watch.jsonl`` (appended to), one status line in the log ("cam2 moved 2.1 cm /
0.9 deg at 12:03:41, re-calibrated from 212 sightings"), the run record's ``camera_watch`` list
(:meth:`WatchLog.summary`) and, at each rejoin and each step of a drift followed, a new versioned
extrinsics file beside the session (``extrinsics.watch-<n>.toml``: every camera, the re-calibrated
or followed one at its new pose; ``n`` after every such file already there, so an earlier
session's are never written over), written
over the user's extrinsics file only when asked (``update_path``, the CLI's
``--update-extrinsics``). A file that cannot be written is said in one error line and tracking
goes on: the event stays in the run record, with its pose. :meth:`WatchLog.attach` gives the
outputs each camera's watch state (the dashboard's camera tile: moved, re-calibrating, rejoined);
:func:`attach_watch_log` (live) also moves the re-calibration fits onto a background thread, so
that the tracking thread never waits for one, where a replay keeps them inline (reproducible).
"""

from __future__ import annotations

import dataclasses
import json
import logging
import re
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Any

from cubetrack.app.tracker import Tracker
from cubetrack.calib.recalibrate import WatchedFusion
from cubetrack.core.cameras import CameraExtrinsics
from cubetrack.fuse.camera_watch import EventKind, WatchEvent, clock_text, event_record
from cubetrack.io.config import write_extrinsics
from cubetrack.io.files import cannot_write
from cubetrack.sink.base import Outputs, Sink

log = logging.getLogger(__name__)

EVENTS_FILE = "camera_watch.jsonl"
EXTRINSICS_PATTERN = "extrinsics.watch-{n}.toml"
EXTRINSICS_NUMBER = re.compile(r"extrinsics\.watch-([0-9]+)\.toml")  # the <n> of a file of EXTRINSICS_PATTERN
RECALIBRATED_METHOD = "re-calibrated while tracking"
FOLLOWED_METHOD = "drift followed while tracking"


class WatchLog:
    """The listener a :class:`WatchedFusion` is given (:meth:`attach`; see the module doc).
    ``extrinsics``: the session's extrinsics, updated at each rejoin; ``written``: the versioned
    files written so far; ``lines``: the status lines so far; ``executor``: where the fusion runs
    its re-calibration fits (None: inline)."""

    def __init__(self, out_dir: str | Path, extrinsics: dict[str, CameraExtrinsics],
                 update_path: str | Path | None = None, executor: ThreadPoolExecutor | None = None):
        self.out_dir = Path(out_dir)
        self.extrinsics = dict(extrinsics)
        self.update_path = None if update_path is None else Path(update_path)
        self.executor = executor
        self.records: list[dict[str, Any]] = []
        self.written: list[Path] = []
        self.lines: list[str] = []
        self.attached = False
        self._moved: dict[str, WatchEvent] = {}
        self._events_failed = False

    def attach(self, tracker: Tracker, outputs: Outputs | Sink) -> bool:
        """Listen to ``tracker``'s watched fusion (its re-calibrations run on :attr:`executor`) and
        tell ``outputs`` what it says of each camera; False (nothing attached) when the tracker's
        fusion is not watched (``[camera_watch] enabled`` and calibrated cameras)."""
        fusion = tracker.fusion
        if not isinstance(fusion, WatchedFusion):
            return False
        fusion.executor = self.executor
        fusion.listeners.append(self)
        fusion.state_listeners.append(outputs.camera_watch)
        self.attached = True
        return True

    def __call__(self, event: WatchEvent) -> None:
        record = event_record(event)
        if event.kind is EventKind.MOVED:
            self._moved[event.camera] = event
            line = (f"{event.camera} moved {100 * event.offset_m:.1f} cm / {event.offset_deg:.1f} deg at "
                    f"{clock_text(event.time_s)}; set aside, re-calibrating")
        elif event.kind is EventKind.FOLLOWED:
            line = f"{event.camera} drifting: followed {1000 * event.offset_m:.1f} mm at {clock_text(event.time_s)}"
            record.update(self._write_extrinsics(event, FOLLOWED_METHOD))
        else:
            moved = self._moved.pop(event.camera, event)
            line = (f"{event.camera} moved {100 * event.offset_m:.1f} cm / {event.offset_deg:.1f} deg at "
                    f"{clock_text(moved.time_s)}, re-calibrated from {event.sightings} sightings")
            record.update(self._write_extrinsics(event, RECALIBRATED_METHOD))
        self.records.append(record)
        self._append_event(record)
        self.lines.append(line)
        log.log(logging.INFO if event.kind is EventKind.FOLLOWED else logging.WARNING, "%s", line)

    def _append_event(self, record: dict[str, Any]) -> None:
        """One line more in the events file; when it cannot be written, one error line (the first
        time) and the event stays in the run record only."""
        path = self.out_dir / EVENTS_FILE
        try:
            self.out_dir.mkdir(parents=True, exist_ok=True)
            with path.open("a", encoding="utf-8") as f:
                f.write(json.dumps(record) + "\n")
        except OSError as exc:
            if not self._events_failed:
                log.error("%s; the camera watching's events are in run.json only", cannot_write(path, exc))
            self._events_failed = True

    def _write_extrinsics(self, event: WatchEvent, method: str) -> dict[str, str]:
        """Write the session's extrinsics with ``event``'s camera at its new pose (found by
        ``method``) as the next versioned file beside the session (and over ``update_path`` when given). Returns the
        event record's addition: the file's name (``extrinsics``) or why it was not written
        (``extrinsics_error``; the pose is in the record)."""
        before = self.extrinsics.get(event.camera, CameraExtrinsics(event.T_world_cam))
        self.extrinsics[event.camera] = dataclasses.replace(before, T_world_cam=event.T_world_cam.copy(),
                                                            samples=event.sightings, method=method)
        path = self.out_dir / EXTRINSICS_PATTERN.format(n=self._next_number())
        try:
            self.out_dir.mkdir(parents=True, exist_ok=True)
            write_extrinsics(self.extrinsics, path)
        except OSError as exc:
            said = cannot_write(path, exc)
            log.error("%s; %s's new pose is in run.json's camera_watch", said, event.camera)
            added = {"extrinsics_error": said}
        else:
            self.written.append(path)
            added = {"extrinsics": path.name}
        if self.update_path is not None:
            try:
                write_extrinsics(self.extrinsics, self.update_path)
            except OSError as exc:
                log.error("%s; not updated with %s's new pose (--update-extrinsics)",
                          cannot_write(self.update_path, exc), event.camera)
            else:
                log.warning("%s: updated with %s's new pose (--update-extrinsics)", self.update_path, event.camera)
        return added

    def _next_number(self) -> int:
        """The <n> of the next versioned extrinsics file: after every one in the folder (an earlier
        session's too); 1 in a folder that cannot be listed (its writing will say why)."""
        try:
            names = [p.name for p in self.out_dir.iterdir()]
        except OSError:
            names = []
        return max((int(m.group(1)) for m in map(EXTRINSICS_NUMBER.fullmatch, names) if m), default=0) + 1

    def summary(self) -> dict[str, Any]:
        """The run record's entry: every event, in order."""
        return {"camera_watch": list(self.records)}

    def close(self) -> None:
        """Stop the background re-calibration (a fit under way is finished, its result dropped)."""
        if self.executor is not None:
            self.executor.shutdown(wait=True, cancel_futures=True)


def attach_watch_log(tracker: Tracker, outputs: Outputs, out_dir: str | Path,
                     extrinsics: dict[str, CameraExtrinsics] | None,
                     update_path: str | Path | None = None) -> WatchLog | None:
    """Live and in ``cubetrack fuse``: give a tracker's watched fusion (``[camera_watch] enabled``)
    a :class:`WatchLog`, a background thread for its re-calibrations, and the outputs what it says
    of each camera (:meth:`cubetrack.sink.base.Sink.camera_watch`: the dashboard's tile); None for
    a fusion that is not watched."""
    if not isinstance(tracker.fusion, WatchedFusion):
        return None
    watch_log = WatchLog(out_dir, extrinsics or {}, update_path,
                         ThreadPoolExecutor(max_workers=1, thread_name_prefix="recalibrate"))
    watch_log.attach(tracker, outputs)
    return watch_log
