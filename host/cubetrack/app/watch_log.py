"""What a live session keeps of the camera watching (issue 27, docs/calibration.md "Keeping what
was learnt"): every event of :class:`cubetrack.calib.recalibrate.WatchedFusion` as one JSON line
in ``<out_dir>/camera_watch.jsonl``, one status line in the log ("cam2 moved 2.1 cm / 0.9 deg at
12:03:41, re-calibrated from 212 sightings"), the run record's ``camera_watch`` list
(:meth:`WatchLog.summary`) and, at each rejoin, a new versioned extrinsics file beside the
session (``extrinsics.watch-<n>.toml``: every camera, the re-calibrated one at its new pose),
written over the user's extrinsics file only when asked (``update_path``, the CLI's
``--update-extrinsics``). :func:`attach_watch_log` also moves the re-calibration fits onto a
background thread, so that the tracking thread never waits for one, and gives the outputs each
camera's watch state (the dashboard's camera tile: moved, re-calibrating, rejoined).
"""

from __future__ import annotations

import dataclasses
import json
import logging
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Any

from cubetrack.app.tracker import Tracker
from cubetrack.calib.recalibrate import WatchedFusion
from cubetrack.core.cameras import CameraExtrinsics
from cubetrack.fuse.camera_watch import EventKind, WatchEvent, clock_text, event_record
from cubetrack.io.config import write_extrinsics
from cubetrack.sink.base import Outputs

log = logging.getLogger(__name__)

EVENTS_FILE = "camera_watch.jsonl"
EXTRINSICS_PATTERN = "extrinsics.watch-{n}.toml"
RECALIBRATED_METHOD = "re-calibrated while tracking"


class WatchLog:
    """The listener :func:`attach_watch_log` gives a :class:`WatchedFusion` (see the module doc).
    ``extrinsics``: the session's extrinsics, updated at each rejoin; ``written``: the versioned
    files written so far; ``lines``: the status lines so far."""

    def __init__(self, out_dir: str | Path, extrinsics: dict[str, CameraExtrinsics],
                 update_path: str | Path | None = None, executor: ThreadPoolExecutor | None = None):
        self.out_dir = Path(out_dir)
        self.extrinsics = dict(extrinsics)
        self.update_path = None if update_path is None else Path(update_path)
        self.executor = executor
        self.records: list[dict[str, Any]] = []
        self.written: list[Path] = []
        self.lines: list[str] = []
        self._moved: dict[str, WatchEvent] = {}

    def __call__(self, event: WatchEvent) -> None:
        record = event_record(event)
        self.out_dir.mkdir(parents=True, exist_ok=True)
        if event.kind is EventKind.MOVED:
            self._moved[event.camera] = event
            line = (f"{event.camera} moved {100 * event.offset_m:.1f} cm / {event.offset_deg:.1f} deg at "
                    f"{clock_text(event.time_s)}; set aside, re-calibrating")
        else:
            moved = self._moved.pop(event.camera, event)
            line = (f"{event.camera} moved {100 * event.offset_m:.1f} cm / {event.offset_deg:.1f} deg at "
                    f"{clock_text(moved.time_s)}, re-calibrated from {event.sightings} sightings")
            record["extrinsics"] = self._write_extrinsics(event).name
        self.records.append(record)
        with (self.out_dir / EVENTS_FILE).open("a", encoding="utf-8") as f:
            f.write(json.dumps(record) + "\n")
        self.lines.append(line)
        log.warning("%s", line)

    def _write_extrinsics(self, event: WatchEvent) -> Path:
        """Write the session's extrinsics with ``event``'s camera at its new pose as the next
        versioned file beside the session (and over ``update_path`` when given); returns its path."""
        before = self.extrinsics.get(event.camera, CameraExtrinsics(event.T_world_cam))
        self.extrinsics[event.camera] = dataclasses.replace(before, T_world_cam=event.T_world_cam.copy(),
                                                            samples=event.sightings, method=RECALIBRATED_METHOD)
        path = self.out_dir / EXTRINSICS_PATTERN.format(n=len(self.written) + 1)
        write_extrinsics(self.extrinsics, path)
        self.written.append(path)
        if self.update_path is not None:
            write_extrinsics(self.extrinsics, self.update_path)
            log.warning("%s: updated with %s's new pose (--update-extrinsics)", self.update_path, event.camera)
        return path

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
    """Give a tracker's watched fusion (``[camera_watch] enabled``) a :class:`WatchLog`, a
    background thread for its re-calibrations, and the outputs what it says of each camera
    (:meth:`cubetrack.sink.base.Sink.camera_watch`: the dashboard's tile); None for a fusion
    that is not watched."""
    fusion = tracker.fusion
    if not isinstance(fusion, WatchedFusion):
        return None
    executor = ThreadPoolExecutor(max_workers=1, thread_name_prefix="recalibrate")
    watch_log = WatchLog(out_dir, extrinsics or {}, update_path, executor)
    fusion.executor = executor
    fusion.listeners.append(watch_log)
    fusion.state_listeners.append(outputs.camera_watch)
    return watch_log
