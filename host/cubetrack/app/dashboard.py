"""``cubetrack dashboard``: a live session of the config's cameras shown in the browser, with the
guided calibration and the session controls (docs/dashboard.md).

:class:`DashboardApp` runs one live session after another (:func:`cubetrack.app.live.track_live`,
the same code as ``cubetrack track --live``) and feeds each to a
:class:`~cubetrack.sink.dashboard.server.DashboardServer`. Sessions are restarted when the page
asks for something else:

``watch``        the default: the cameras are read and the robots tracked, nothing is kept;
``record``       "Start recording": trajectories in ``<out>/sessions/<stamp>/``, the frames in
                 its ``recording/`` (replayable with ``cubetrack track --recording``);
``calibration``  collecting world-marker samples: the frames go to ``<out>/calibration/<stamp>/world``;
``drive``        "drive the robot around": the frames go to ``<out>/calibration/<stamp>/drive``.

Before the cameras are calibrated the robots are tracked in the paper's uncalibrated mode (each
frame's own world-marker pose, ``[track] camera_poses = "world-marker"``).

The calibration steps call what ``cubetrack calibrate`` calls,
:func:`cubetrack.app.calibrate.run_calibration` on the recordings just made (``--refine-with``
for the drive), and write what it writes (the extrinsics and their run record in the
calibration folder). Around it, this module adds what a person at the cameras needs: whether
each camera sees the world marker now (:class:`_Watcher` searches the newest frames for it),
the samples collected so far, each camera's reprojection error on its own recording
(:func:`cubetrack.calib.check.world_marker_reprojection`) and a verdict with advice
(:func:`cubetrack.sink.dashboard.calibration.calibration_advice`).
"""

from __future__ import annotations

import dataclasses
import logging
import math
import shutil
import tempfile
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

from cubetrack.app.calibrate import CalibrationRun, run_calibration
from cubetrack.app.config import ConfigParams
from cubetrack.app.live import track_live
from cubetrack.app.tracker import CameraPoseSource
from cubetrack.calib.check import world_marker_reprojection
from cubetrack.calib.extrinsics import CalibrationReport, world_detector
from cubetrack.core.cameras import CameraExtrinsics, CameraIntrinsics, WorldConfig
from cubetrack.core.errors import ConfigError, CubetrackError, ImageError
from cubetrack.core.records import CameraView, Detection, TrackedPose
from cubetrack.detect.detector import DetectorParams, decode_gray
from cubetrack.estimate.match import detections_of
from cubetrack.io.config import TrackerConfig, write_extrinsics
from cubetrack.io.recording import Recording
from cubetrack.io.run import run_record_beside
from cubetrack.sink.base import Sink
from cubetrack.sink.dashboard.calibration import InstantCounter, calibration_advice, missing_advice
from cubetrack.sink.dashboard.server import (
    TRAJECTORY_FILES,
    DashboardError,
    DashboardServer,
    DashboardSink,
    Download,
    folder_downloads,
)
from cubetrack.sink.dashboard.state import DashboardParams

log = logging.getLogger(__name__)


# --- judging a calibration ---------------------------------------------------------------------


def camera_result(report: CalibrationReport, name: str, recording: Recording, intrinsics: CameraIntrinsics,
                  world: WorldConfig, detector_params: DetectorParams, params: DashboardParams) -> dict:
    """One calibrated camera's row of the calibration panel: position, spread, reprojection
    error on its own recording, and the verdict with advice."""
    cal = report.cameras[name]
    e = cal.extrinsics
    rms_px, side_px, used = world_marker_reprojection(recording.frames(name), e.T_world_cam, intrinsics, world,
                                                      detector_params, params.check_frames)
    advice = calibration_advice(100 * e.spread_position_m, e.spread_rotation_deg, rms_px, side_px, cal.inliers,
                                cal.sightings, params)
    return {"calibrated": True, "samples": e.samples, "sightings": cal.sightings, "frames": cal.frames_read,
            "position_m": [float(v) for v in e.T_world_cam[:3, 3]], "spread_cm": 100 * e.spread_position_m,
            "spread_deg": e.spread_rotation_deg, "reprojection_px": rms_px if math.isfinite(rms_px) else None,
            "marker_side_px": side_px if math.isfinite(side_px) else None, "checked_frames": used,
            "poor": bool(advice), "advice": advice, "error": ""}


# --- the session loop --------------------------------------------------------------------------


@dataclass(frozen=True, slots=True)
class SessionPlan:
    """One live session: what it is for, where its trajectories go, where its frames are
    recorded (None: not recorded), and the camera poses it tracks with."""

    kind: str
    out_dir: Path
    record_to: Path | None
    extrinsics: dict[str, CameraExtrinsics]


class _Watcher(Sink):
    """The workflow's own output of each session: searches the newest frames for the world
    marker (every frame while collecting, else every ``check_every_s`` per camera) and counts the
    poses several cameras took part in. It runs behind the session's queue, so it never slows
    the tracker (frames it has no time for are dropped)."""

    name = "dashboard-guide"
    wants_views = True

    def __init__(self, app: DashboardApp, plan: SessionPlan):
        self.app = app
        self.plan = plan
        self.detector = world_detector(app.config.world, app.settings.detector)

    def pose(self, pose: TrackedPose) -> None:
        self.app.pose_seen(pose, self.plan)

    def camera_view(self, view: CameraView) -> None:
        if not self.app.wants_marker_check(view.camera):
            return
        try:
            gray = decode_gray(view.jpeg, f"{view.camera} frame {view.seq}")
        except ImageError:
            return
        world = self.app.config.world
        found = detections_of(self.detector.detect(gray), world.dictionary, (world.marker_id,))
        self.app.marker_checked(view.camera, found[0] if len(found) == 1 else None, self.plan)


def _stamp(parent: Path, clock: Callable[[], float]) -> Path:
    """A new folder name under ``parent`` from the local time (``20250101-120000``, ``-2`` ...)."""
    base = time.strftime("%Y%m%d-%H%M%S", time.localtime(clock()))
    path, n = parent / base, 1
    while path.exists():
        n += 1
        path = parent / f"{base}-{n}"
    return path


class DashboardApp:
    """The dashboard's workflow (module doc). ``out_dir`` holds the sessions and calibrations;
    ``extrinsics_path`` is where "Save" writes (an earlier file there is kept beside it, renamed
    with its time) and ``extrinsics`` what the cameras are calibrated with now (may be partial)."""

    def __init__(self, config: TrackerConfig, settings: ConfigParams, server: DashboardServer, out_dir: Path,
                 extrinsics_path: Path, extrinsics: dict[str, CameraExtrinsics] | None = None,
                 clock: Callable[[], float] = time.time):
        from cubetrack.app.live import live_camera_urls, live_intrinsics

        self.config = config
        self.settings = settings
        self.server = server
        self.out_dir = Path(out_dir)
        self.extrinsics_path = Path(extrinsics_path)
        self.params = settings.dashboard  # the guide's limits; the display's went to the server
        self.clock = clock
        self.urls = live_camera_urls(config)
        self.intrinsics = live_intrinsics(config)
        self.extrinsics = dict(extrinsics or {})
        self._lock = threading.RLock()
        self._stop = threading.Event()
        self._session_stop = threading.Event()
        self._scratch = tempfile.TemporaryDirectory(prefix="cubetrack-dashboard-")
        self._plan = self._watch_plan()
        self._running: SessionPlan | None = None  # the session running now (its files are still growing)
        self._since_s = self.clock()
        self._message = ""
        self._dirty = threading.Event()
        self._worker: threading.Thread | None = None
        # the calibration panel's state
        self.step = "check"
        self.target = settings.calibration.samples
        self.samples = {c: 0 for c in self.urls}
        # camera -> (checked, seen (host s), side px)
        self.marker: dict[str, tuple[float, float, float | None]] = {
            c: (-math.inf, -math.inf, None) for c in self.urls}
        self.results: dict[str, dict] = {}
        self.refined: dict[str, dict] = {}
        self.warnings: list[str] = []
        self.progress: tuple[str, int, int] | None = None
        self.drive = self._drive_counter()
        self.calibration_dir: Path | None = None
        self.candidate: CalibrationRun | None = None
        self.saved: dict | None = None
        self.step_message = "Point every camera at the world marker; each row below says whether it sees it."
        server.add_actions("calibration", {"collect": self._collect, "stop": self._stop_collecting,
                                           "cancel": self._cancel, "save": self._save, "drive": self._drive,
                                           "refine": self._refine})
        server.add_actions("recording", {"start": self._start_recording, "stop": self._stop_recording})
        server.set_downloads(self.downloads)
        self._publish()

    # --- sessions ---

    def _watch_plan(self) -> SessionPlan:
        return SessionPlan("watch", Path(self._scratch.name), None, dict(self.extrinsics))

    def _stage_params(self, extrinsics: dict[str, CameraExtrinsics]):
        """The tracker's parameters; the uncalibrated mode while some camera has no extrinsics."""
        stages = self.settings.stages
        if set(self.intrinsics) <= set(extrinsics):
            return stages
        return dataclasses.replace(stages, track=dataclasses.replace(stages.track,
                                                                     camera_poses=CameraPoseSource.WORLD_MARKER))

    def run(self, duration_s: float | None = None) -> None:
        """Run sessions until :meth:`stop`, ``duration_s`` or Ctrl-C."""
        timer = None
        if duration_s is not None:
            timer = threading.Timer(duration_s, self.stop)
            timer.daemon = True
            timer.start()
        publisher = threading.Thread(target=self._publish_loop, name="cubetrack-dashboard-panels", daemon=True)
        publisher.start()
        try:
            while not self._stop.is_set():
                with self._lock:
                    plan = self._running = self._plan
                    self._session_stop = threading.Event()
                    stop = self._session_stop
                    self._since_s = self.clock()
                    self._dirty.set()
                interrupted = self._run_session(plan, stop)
                with self._lock:
                    self._running = None
                    self._dirty.set()  # its files can be downloaded now
                self._session_ended(plan)
                if interrupted:
                    break
        except KeyboardInterrupt:
            pass
        finally:
            self._stop.set()
            if timer is not None:
                timer.cancel()
            self._scratch.cleanup()

    def _run_session(self, plan: SessionPlan, stop: threading.Event) -> bool:
        """One live session; returns whether Ctrl-C ended it. A session that cannot start (e.g.
        its folder cannot be written) is reported on the page and the plain watch session follows."""
        try:
            result = track_live(self.config, plan.extrinsics or None, plan.out_dir, self._stage_params(plan.extrinsics),
                                self.settings.source, stop=stop, record_to=plan.record_to,
                                sinks=[DashboardSink(self.server), _Watcher(self, plan)],
                                live_params=self.settings.live,
                                extrinsics_path=self.extrinsics_path if self.extrinsics_path.exists() else None,
                                command="dashboard")
        except CubetrackError as exc:
            log.error("dashboard: the %s session failed: %s", plan.kind, exc)
            with self._lock:
                self._message = f"the {plan.kind} session failed: {exc}"
                self._plan = self._watch_plan()
                if self.step in ("collecting", "driving"):  # back to where the step began
                    self.step = "check" if self.step == "collecting" else "result"
                    self.step_message = self._message
            self._stop.wait(1.0)
            return False
        return result.interrupted

    def _restart(self, plan: SessionPlan) -> None:
        """End the running session; ``plan`` runs next (caller holds the lock)."""
        self._plan = plan
        self._session_stop.set()

    def _candidate(self) -> CalibrationRun:
        """The calibration the page shows (there once a step past calibrating was reached)."""
        if self.candidate is None:
            raise DashboardError("no calibration to use yet: collect and calibrate first")
        return self.candidate

    def _calibration_folder(self) -> Path:
        """This calibration's folder (made when collecting starts)."""
        if self.calibration_dir is None:
            raise DashboardError("no calibration started yet: start collecting first")
        return self.calibration_dir

    def _session_ended(self, plan: SessionPlan) -> None:
        """After a collecting or driving session, compute from what it recorded."""
        with self._lock:
            if self._stop.is_set():
                return
            if plan.record_to is None:
                return
            if plan.kind == "calibration" and self.step == "calibrating":
                self._start_worker(self._calibrate, plan.record_to)
            elif plan.kind == "drive" and self.step == "refining":
                self._start_worker(self._refine_with, plan.record_to)

    def stop(self) -> None:
        self._stop.set()
        self._session_stop.set()

    # --- what the watcher reports (from the session's output thread) ---

    def wants_marker_check(self, camera: str) -> bool:
        with self._lock:
            if self.step == "collecting":
                return True
            return self.clock() - self.marker[camera][0] >= self.params.check_every_s

    def _recording(self, kind: str, plan: SessionPlan | None = None) -> bool:
        """Whether the session of ``kind`` the step waits for is the one running (and, with
        ``plan``, the one that reported): a step's counts come from its own session only, not
        from the one still ending when the step began."""
        return self._running is not None and self._running.kind == kind and plan in (None, self._running)

    def marker_checked(self, camera: str, detection: Detection | None, plan: SessionPlan) -> None:
        with self._lock:
            now, (_, seen_s, side) = self.clock(), self.marker[camera]
            if detection is not None:
                seen_s, side = now, math.sqrt(detection.area_px2)
            self.marker[camera] = (now, seen_s, side)
            if self.step == "collecting" and detection is not None and self._recording("calibration", plan):
                self.samples[camera] = self.samples.get(camera, 0) + 1
                if self._collected_enough():
                    self._finish_collecting()
            self._dirty.set()

    def _drive_counter(self) -> InstantCounter:
        adjust = self.settings.bundle_adjustment
        return InstantCounter(adjust.max_span_s, adjust.min_cameras)

    def pose_seen(self, pose: TrackedPose, plan: SessionPlan) -> None:
        """While driving: count the instants the bundle adjustment can use (:class:`InstantCounter`)."""
        if pose.predicted or not pose.cameras:
            return
        with self._lock:
            if self.step != "driving" or not self._recording("drive", plan):
                return
            if self.drive.add(pose.robot, pose.time_s, pose.cameras):
                self._dirty.set()

    def _camera_status(self, camera: str) -> tuple[str, str]:
        cam = self.server.state.camera_json(camera) or {}
        health = cam.get("health") or {}
        return cam.get("status", "waiting"), health.get("last_error") or cam.get("reason", "")

    def _collected_enough(self) -> bool:
        """Every camera that is up has its samples (and one camera at least)."""
        up = [c for c in self.urls if self._camera_status(c)[0] == "ok"]
        return bool(up) and all(self.samples[c] >= self.target for c in up)

    # --- actions (HTTP threads) ---

    def _require(self, *steps: str) -> None:
        if self.step not in steps:
            raise DashboardError(f"not now: the calibration is at step {self.step!r}")
        if self._plan.kind == "record":
            raise DashboardError("a recording is running: stop it first")

    def _collect(self, body: dict) -> dict:
        samples = body.get("samples", self.settings.calibration.samples)
        if isinstance(samples, bool) or not isinstance(samples, int) or not 1 <= samples <= 100000:
            raise ConfigError(f"samples must be a whole number from 1 to 100000, got {samples!r}")
        with self._lock:
            self._require("check", "result", "refined", "failed")
            self.calibration_dir = _stamp(self.out_dir / "calibration", self.clock)
            self.target = samples
            self.samples = {c: 0 for c in self.urls}
            self.results, self.refined, self.warnings, self.candidate, self.progress = {}, {}, [], None, None
            self._go("collecting", f"Collecting {samples} world-marker sightings per camera into "
                     f"{self._calibration_folder() / 'world'}; keep the cameras and the marker still.",
                     SessionPlan("calibration", self._plan.out_dir, self._calibration_folder() / "world",
                                 dict(self.extrinsics)))
            self._publish()
            return {"recording": str(self._calibration_folder() / "world"), "samples": samples}

    def _go(self, step: str, message: str, plan: SessionPlan | None = None) -> None:
        """Move the calibration to ``step``; ``plan`` (default: watching) runs next (caller holds the lock)."""
        self.step, self.step_message = step, message
        self._restart(plan or self._watch_plan())
        self._dirty.set()

    def _finish_collecting(self) -> None:
        self._go("calibrating", "Calibrating every camera from the samples just recorded...")

    def _stop_collecting(self, body: dict) -> dict:
        with self._lock:
            self._require("collecting")
            if not self._recording("calibration"):
                raise DashboardError("not yet: the cameras are still being connected for the collection")
            self._finish_collecting()
            self._publish()
            return {}

    def _cancel(self, body: dict) -> dict:
        with self._lock:
            self._require("collecting", "driving")
            self._go("check" if self.step == "collecting" else "result", "Cancelled; what was recorded stays on disk.")
            self._publish()
            return {}

    def _save(self, body: dict) -> dict:
        with self._lock:
            self._require("result", "refined")
            run = self._candidate()
            kind = "refined" if self.step == "refined" else "calibration"
            target = self.extrinsics_path
            target.parent.mkdir(parents=True, exist_ok=True)
            kept = None
            if target.exists():  # nothing saved before is lost: the old file stays beside, with its time
                stamp = time.strftime("%Y%m%d-%H%M%S", time.localtime(target.stat().st_mtime))
                kept = target.with_name(f"{target.stem}.{stamp}{target.suffix}")
                shutil.copy2(target, kept)
            write_extrinsics(run.extrinsics, target)  # atomically
            if run.run_record_path.exists():
                shutil.copyfile(run.run_record_path, run_record_beside(target))
            self.extrinsics = dict(run.extrinsics)
            self.saved = {"path": str(target), "what": kind, "cameras": sorted(run.extrinsics),
                          "previous": str(kept) if kept else None}
            self.step_message = (f"Saved to {target}" + (f" (the earlier file is now {kept.name})" if kept else "")
                                 + ". Tracking now uses these camera poses.")
            if self._plan.kind == "watch":
                self._restart(self._watch_plan())
            self._publish()
            return dict(self.saved)

    def _drive(self, body: dict) -> dict:
        with self._lock:
            self._require("result", "refined")
            self.drive, self.refined = self._drive_counter(), {}
            extrinsics = {**self.extrinsics, **self._candidate().report.extrinsics}
            self._go("driving", "Drive the robot around where several cameras see it; the frames go to "
                     f"{self._calibration_folder() / 'drive'}.",
                     SessionPlan("drive", self._plan.out_dir, self._calibration_folder() / "drive", extrinsics))
            self._publish()
            return {"recording": str(self._calibration_folder() / "drive")}

    def _refine(self, body: dict) -> dict:
        with self._lock:
            self._require("driving")
            if not self._recording("drive"):
                raise DashboardError("not yet: the cameras are still being connected for the drive")
            self._go("refining", "Refining the camera poses with the robot's cube (bundle adjustment)...")
            self._publish()
            return {}

    def _start_recording(self, body: dict) -> dict:
        with self._lock:
            if self._plan.kind != "watch" or self.step in ("collecting", "driving"):
                raise DashboardError(f"not now: the cameras are busy ({self._plan.kind})")
            out = _stamp(self.out_dir / "sessions", self.clock)
            self._restart(SessionPlan("record", out, out / "recording", dict(self.extrinsics)))
            self._message = ""
            self._publish()
            return {"out_dir": str(out), "recording": str(out / "recording")}

    def _stop_recording(self, body: dict) -> dict:
        with self._lock:
            if self._plan.kind != "record":
                raise DashboardError("no recording is running")
            out = self._plan.out_dir
            self._restart(self._watch_plan())
            self._message = f"recorded into {out}"
            self._publish()
            return {"out_dir": str(out)}

    # --- computing (a worker thread) ---

    def _start_worker(self, target: Callable[[Path], None], recording: Path) -> None:
        self._worker = threading.Thread(target=target, args=(recording,), name="cubetrack-dashboard-calibrate",
                                        daemon=True)
        self._worker.start()

    def _progress(self, stage: str, done: int, total: int) -> None:
        with self._lock:
            self.progress = (stage, done, total)
            self._dirty.set()

    def _computed(self, step: str, message: str) -> None:
        """A computation ended at ``step``."""
        with self._lock:
            self.step, self.progress, self.step_message = step, None, message
            self._publish()

    def _calibrate(self, recording_path: Path) -> None:
        try:
            recording, empty = Recording.open(recording_path).with_frames()
            run = run_calibration(self.config, recording, self._calibration_folder() / "extrinsics.toml", self.settings,
                                  allow_missing=True, progress=self._progress)
            results = {}
            for name in run.report.cameras:
                results[name] = camera_result(run.report, name, recording, self.intrinsics[name], self.config.world,
                                              self.settings.detector, self.params)
            for name, reason in run.report.missing.items():
                status, error = self._camera_status(name)
                results[name] = {"calibrated": False, "poor": True, "advice": missing_advice(reason, status, error),
                                 "error": reason}
            for name in set(self.urls) - set(results):
                results[name] = {"calibrated": False, "poor": True, "error": empty.get(name, "no frames recorded"),
                                 "advice": missing_advice("", "down", self._camera_status(name)[1])}
        except CubetrackError as exc:
            return self._computed("failed", f"Calibration failed: {exc}")
        with self._lock:
            self.candidate, self.results = run, results
            poor = sorted(n for n, r in results.items() if r["poor"])
            self._computed("result", "Every camera is calibrated well: save the extrinsics." if not poor else
                           f"{', '.join(poor)}: see the advice; collect again, or save what is good.")

    def _refine_with(self, drive_path: Path) -> None:
        try:
            run = run_calibration(self.config, Recording.open(self._calibration_folder() / "world").with_frames()[0],
                                  self._calibration_folder() / "refined.toml", self.settings,
                                  adjust_with=Recording.open(drive_path).with_frames()[0], allow_missing=True,
                                  progress=self._progress)
        except CubetrackError as exc:
            return self._computed("result", f"Refinement failed: {exc}")
        adjusted = run.adjusted
        if adjusted is None:
            return self._computed("result", "Refinement failed: the drive gave no bundle adjustment")
        refined = {name: {"shift_cm": 100 * r.shift_m, "shift_deg": r.shift_deg, "moved": r.moved,
                          "rms_px": r.rms_px, "world_rms_px": r.world_rms_px if math.isfinite(r.world_rms_px) else None,
                          "instants": r.instants}
                   for name, r in adjusted.cameras.items()}
        with self._lock:
            self.candidate, self.refined, self.warnings = run, refined, list(adjusted.warnings)
            moved = [n for n, r in refined.items() if r["moved"]]
            self._computed("refined", "Refinement refused (see the warning): saving keeps the world-marker poses."
                           if adjusted.refused else f"Refined with {adjusted.instants} instants. "
                           + (f"{', '.join(moved)} moved since the world-marker calibration. " if moved else "")
                           + "Save to use the refined poses.")

    # --- panels ---

    def _publish_loop(self) -> None:
        while not self._stop.is_set():
            if self._dirty.wait(0.25):
                self._dirty.clear()
                with self._lock:
                    self._publish()
                self._stop.wait(0.25)

    def _publish(self) -> None:
        """Both panels, as the page and ``GET /api/calibration`` / ``/api/recording`` show them
        (caller holds the lock, or is the constructor)."""
        self.server.state.set_panel("calibration", self.calibration_json())
        self.server.state.set_panel("recording", self.recording_json())

    def calibration_json(self) -> dict:
        with self._lock:
            now = self.clock()
            cameras = []
            for name in self.urls:
                checked_s, seen_s, side = self.marker[name]
                status = self._camera_status(name)[0]
                recent = max(4 * self.params.check_every_s, 2.0)  # one frame without the marker is not enough
                sees = (now - seen_s <= recent) if status == "ok" and now - checked_s <= recent else None
                cameras.append({"name": name, "status": status, "sees_marker": sees,
                                "marker_side_px": side if sees else None, "samples": self.samples.get(name, 0),
                                "result": self.results.get(name), "refined": self.refined.get(name)})
            actions = {"check": ["collect"], "failed": ["collect"], "collecting": ["stop", "cancel"],
                       "result": ["collect", "save", "drive"], "refined": ["collect", "save", "drive"],
                       "driving": ["refine", "cancel"]}.get(self.step, [])
            if self._plan.kind == "record":
                actions = []
            if self.step in ("collecting", "driving") and not self._recording(self._plan.kind):
                actions = ["cancel"]  # its session is starting
            if self.step in ("result", "refined") and not (self.candidate and self.candidate.extrinsics):
                actions = [a for a in actions if a not in ("save", "drive")]
            progress = None
            if self.progress is not None:
                progress = {"label": self.progress[0], "done": self.progress[1], "total": self.progress[2]}
            return {"step": self.step, "message": self.step_message, "target_samples": self.target,
                    "save_to": str(self.extrinsics_path), "saved": self.saved, "progress": progress,
                    "drive": {"instants": self.drive.count, "target": self.params.drive_instants}
                    if self.step in ("driving", "refining") else None,
                    "folder": str(self.calibration_dir) if self.calibration_dir else None,
                    "cameras": cameras, "warnings": self.warnings, "actions": actions}

    def recording_json(self) -> dict:
        with self._lock:
            plan = self._plan
            recording = plan.kind == "record"
            return {"mode": plan.kind, "recording": recording, "since_s": self._since_s,
                    "out_dir": str(plan.out_dir) if recording else None,
                    "recording_dir": str(plan.record_to) if plan.record_to else None,
                    "message": self._message, "controls": True,
                    "actions": ["stop"] if recording else (["start"] if plan.kind == "watch" and self.step not in
                                                           ("collecting", "driving") else [])}

    def downloads(self) -> list[Download]:
        """Every recorded session's trajectory files (once the session has ended) and every
        calibration's extrinsics."""
        with self._lock:
            growing = self._running.out_dir if self._running is not None else None
        files = []
        for folder, group, patterns in (("sessions", "session", TRAJECTORY_FILES),
                                        ("calibration", "calibration", ("extrinsics.toml", "refined.toml"))):
            root = self.out_dir / folder
            for session in sorted(p for p in root.iterdir() if p.is_dir() and p != growing) if root.is_dir() else ():
                files += folder_downloads(session, f"{group} {session.name}", patterns, f"{folder}/{session.name}/")
        return files
