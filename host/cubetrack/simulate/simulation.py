"""Running a simulation: render every camera's frames and write the recording folder, the
calibration recording and the files a tracker run needs (see docs/simulation.md).
"""

from __future__ import annotations

import logging
import math
import os
import threading
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import tomli_w

from cubetrack.core.cameras import CameraExtrinsics, CameraIntrinsics, WorldConfig
from cubetrack.core.errors import RecordingError
from cubetrack.core.geometry import position_quat_from_T
from cubetrack.core.layout import CubeLayout, write_layout
from cubetrack.core.params import params_to_table
from cubetrack.core.progress import Progress
from cubetrack.io.camera_info import write_camera_info
from cubetrack.io.config import CameraConfig, tracker_config_to_table, write_extrinsics, write_toml
from cubetrack.io.recording import CameraEntry, RecordingWriter
from cubetrack.io.trajectory import Trajectory, write_tum
from cubetrack.simulate.camera_motion import CameraMotion
from cubetrack.simulate.imperfections import auto_exposure_gains
from cubetrack.simulate.motion import PERSON_SPEED_M_S
from cubetrack.simulate.params import SimulationParams
from cubetrack.simulate.render import Exposure, Renderer, View, encode_jpeg, form_image, lighting_gain
from cubetrack.simulate.scenario import (
    STREAM_CAL_EXPOSURE,
    STREAM_CAL_GAIN,
    STREAM_CAL_IMAGE,
    STREAM_CAL_SYNC,
    STREAM_CAL_TIMING,
    STREAM_EXPOSURE,
    STREAM_GAIN,
    STREAM_IMAGE,
    STREAM_SYNC,
    STREAM_TIMING,
    CameraSetup,
    Scene,
    build_scene,
    rng_for,
)
from cubetrack.simulate.timing import CaptureTruth, DeviceClock, plan_captures, plan_clock_samples

log = logging.getLogger(__name__)

CONFIG_FILE = "config.toml"
LAYOUT_FILE = "cube.toml"
TRUE_LAYOUT_PREFIX = "true_"  # true_cube.toml (true_cube_<robot>.toml): the cube as built
TRUE_CAMERA_INFO_DIR = "true_camera_info"  # true_camera_info/<cam>.yaml: the intrinsics rendered with
TRUE_EXTRINSICS_FILE = "true_extrinsics.toml"
SIMULATION_FILE = "simulation.toml"
CALIBRATION_DIR = "calibration"
GROUND_TRUTH_DIR = "ground_truth"  # with several robots: ground_truth/<robot>.tum
_GAP_BEFORE_RECORDING_S = 20.0  # the calibration recording ends this long before the tracking one
_MAX_STEP_PX = 0.5    # rolling shutter: the robot moves at most this far between two rendered instants
_PROBE_S = 0.005      # ... as measured from its projection at instants this far apart
_KEEP_RENDERERS = 6   # a moving camera: renderers of its latest poses kept (each holds a supersampled canvas)
TRUE_CAMERA_POSES_DIR = "true_camera_poses"  # <cam>.tum: each frame's true camera pose, when a camera moves


@dataclass(frozen=True, slots=True, eq=False)
class SimulatedCamera:
    """The truth about one simulated camera node: intrinsics, the pose of its optical frame in
    the world, its clock, every frame it captured in each recording (delivered or not), the
    intrinsics the tracker is told (``camera_info``) and its rolling-shutter readout (s)."""

    name: str
    intrinsics: CameraIntrinsics
    T_world_cam: np.ndarray
    clock: DeviceClock
    captures: tuple[CaptureTruth, ...]
    calibration_captures: tuple[CaptureTruth, ...]
    camera_info: CameraIntrinsics
    readout_s: float = 0.0
    motion: CameraMotion = CameraMotion()

    @property
    def frames_written(self) -> int:
        return sum(c.delivered for c in self.captures)

    def T_world_cam_at(self, t_s: float) -> np.ndarray:
        """The camera's true pose ``t_s`` seconds after the recording's start: ``T_world_cam``
        moved by its bumps and drift (docs/simulation.md); before the start, ``T_world_cam``."""
        return self.motion.T_world_cam(self.T_world_cam, t_s)


@dataclass(frozen=True, slots=True, eq=False)
class SimulationResult:
    """What :func:`simulate` wrote, and the truth behind it (for tests and benchmarks)."""

    path: Path
    calibration_path: Path | None
    config_path: Path
    params: SimulationParams
    cameras: tuple[SimulatedCamera, ...]
    world: WorldConfig
    ground_truths: dict[str, Trajectory]
    scene: Scene

    @property
    def layout(self) -> CubeLayout:
        """The first robot's cube layout as the tracker is told (the only one unless ``params.robots > 1``)."""
        return self.scene.robots[0].layout

    @property
    def true_layout(self) -> CubeLayout:
        """The first robot's cube as built (also ``true_cube.toml``); the layout unless the cube is imperfect."""
        return self.scene.robots[0].true_layout

    @property
    def ground_truth(self) -> Trajectory:
        """The first robot's 100 Hz ground truth (also ``ground_truth.tum``)."""
        return next(iter(self.ground_truths.values()))

    def camera(self, name: str) -> SimulatedCamera:
        for c in self.cameras:
            if c.name == name:
                return c
        raise KeyError(name)

    @property
    def T_world_cam(self) -> dict[str, np.ndarray]:
        """True pose of each camera's optical frame in the world frame."""
        return {c.name: c.T_world_cam.copy() for c in self.cameras}

    @property
    def intrinsics(self) -> dict[str, CameraIntrinsics]:
        """True intrinsics of each camera (also in ``true_camera_info/<camera>.yaml``)."""
        return {c.name: c.intrinsics for c in self.cameras}

    @property
    def camera_infos(self) -> dict[str, CameraIntrinsics]:
        """The intrinsics the tracker is told (``camera_info/<camera>.yaml``): the truth unless
        calibration errors are simulated."""
        return {c.name: c.camera_info for c in self.cameras}

    def T_world_cube(self, host_time_s: float, robot: int = 0) -> np.ndarray:
        """True pose of a robot's cube frame in the world at a host (Unix) time, exact (not sampled)."""
        return self.scene.T_world_cube(host_time_s - self.params.start_unix_s, robot)

    def T_world_cam_at(self, name: str, host_time_s: float) -> np.ndarray:
        """True pose of a camera at a host (Unix) time: where a frame captured then was rendered from."""
        return self.camera(name).T_world_cam_at(host_time_s - self.params.start_unix_s)


def _motion_offsets_s(p: SimulationParams) -> np.ndarray:
    """Instants within the exposure (relative to mid-exposure) averaged for motion blur."""
    if p.exposure_s <= 0:
        return np.zeros(1)
    fastest = max(p.speed_m_s, PERSON_SPEED_M_S[1]) if p.people else p.speed_m_s
    n = max(2, math.ceil(fastest * p.exposure_s / 0.002)) + 1
    return p.exposure_s * (np.arange(n) / (n - 1) - 0.5)


def _gains(p: SimulationParams, n: int, rng: np.random.Generator) -> np.ndarray:
    """Slowly varying exposure gain per delivered frame (AR(1) with std ``gain_jitter``)."""
    if p.gain_jitter <= 0 or n == 0:
        return np.ones(n)
    x = np.empty(n)
    x[0] = rng.normal(0.0, p.gain_jitter)
    innov = rng.normal(0.0, p.gain_jitter * math.sqrt(1 - 0.9**2), n)
    for k in range(1, n):
        x[k] = 0.9 * x[k - 1] + innov[k]
    return 1.0 + x


def _check_free(path: Path, overwrite: bool) -> None:
    """Refuse a folder holding a recording; with ``overwrite`` remove that recording's frames and
    clock files (they would linger beside the new ones), nothing else."""
    if not (path / "recording.json").exists():
        return
    if not overwrite:
        raise RecordingError(f"{path}: already holds a recording; choose another folder or overwrite it (--force)")
    for camera_dir in path.iterdir():
        if camera_dir.is_dir() and (camera_dir / "index.csv").exists():
            for f in [*camera_dir.glob("*.jpg"), *camera_dir.glob("*.jpg.part"), camera_dir / "clock.csv"]:
                f.unlink(missing_ok=True)


@dataclass(frozen=True, slots=True, eq=False)
class _FrameJob:
    """One frame to render: the camera, its capture, its exposure gain, whether the robot is there."""

    camera: int
    capture: CaptureTruth
    gain: float
    moving: bool
    stream: int


def _frame_jobs(scene: Scene, index: int, captures: tuple[CaptureTruth, ...], moving: bool,
                stream: int, gain_stream: int, exposure_stream: int) -> list[_FrameJob]:
    p = scene.params
    delivered = [c for c in captures if c.delivered]
    gains = _gains(p, len(delivered), rng_for(p.seed, gain_stream, index))
    if p.exposure_steps_per_s > 0 and captures:
        times = np.array([c.capture_host_s for c in delivered])
        gains = gains * auto_exposure_gains(p, times, captures[0].capture_host_s, captures[-1].capture_host_s,
                                            rng_for(p.seed, exposure_stream, index))
    return [_FrameJob(index, c, float(g), moving, stream) for c, g in zip(delivered, gains, strict=True)]


class _FrameMaker:
    """Renders and encodes frames; each frame has its own random stream (seed, stream, camera,
    seq), so frames can be made in any order and on any thread with identical bytes."""

    def __init__(self, scene: Scene, renderers: list[Renderer]):
        p = scene.params
        self.scene = scene
        self.renderers = renderers
        self._moved: dict[tuple[int, tuple[int, int]], Renderer] = {}  # (camera, pose segment) -> renderer
        self._lock = threading.Lock()
        self.light = [lighting_gain(p.image_width_px, p.image_height_px, p.light_gradient,
                                    c.light_direction_rad, p.vignetting) for c in scene.cameras]
        self.offsets = _motion_offsets_s(p)

    def renderer(self, camera: int, t_s: float) -> Renderer:
        """Camera ``camera``'s renderer for a frame ``t_s`` seconds after the start: the one built
        at its original pose, or (a moved camera) one per piece of its pose, the last few kept."""
        setup = self.scene.cameras[camera]
        segment = setup.motion.segment(t_s)
        if segment == (0, 0):
            return self.renderers[camera]
        with self._lock:
            found = self._moved.get((camera, segment))
            if found is None:
                base = self.renderers[camera]
                found = Renderer(base.view.moved(setup.T_world_cam_at(t_s)), self.scene.floor,
                                 (self.scene.world_marker,))
                mine = [key for key in self._moved if key[0] == camera]
                for key in mine[:max(0, len(mine) - _KEEP_RENDERERS + 1)]:
                    del self._moved[key]
                self._moved[(camera, segment)] = found
            return found

    def __call__(self, job: _FrameJob) -> bytes:
        p = self.scene.params
        t = job.capture.capture_host_s - p.start_unix_s
        renderer = self.renderer(job.camera, t) if job.moving else self.renderers[job.camera]
        if job.moving:
            camera = self.scene.cameras[job.camera]
            position = renderer.view.position_world
            if camera.readout_s > 0:
                exposure = Exposure(t, p.exposure_s, camera.row_s, camera.reference_row)
                albedo = renderer.render_exposure(lambda ts: self.scene.moving_solids(ts, position), exposure,
                                                  self._step_s(renderer.view, camera, exposure),
                                                  _band_rows(camera, exposure))
            else:
                albedo = renderer.render([self.scene.moving_solids(t + dt, position) for dt in self.offsets])
        else:
            albedo = renderer.background
        rng = np.random.default_rng(np.random.SeedSequence([p.seed, job.stream, job.camera, job.capture.seq]))
        image = form_image(albedo, self.light[job.camera] * np.float32(job.gain), p.blur_px, p.noise_std, rng)
        return encode_jpeg(image, p.jpeg_quality)

    def _step_s(self, view: View, camera: CameraSetup, exposure: Exposure) -> float:
        """Time between rendered instants: the robots' projected corners (body, mast, cube) move
        at most _MAX_STEP_PX between two, as measured over the frame's exposure."""
        p = self.scene.params
        first, last = exposure.row_times(np.array([0.0, camera.intrinsics.height - 1.0]))
        times = np.arange(first - p.exposure_s / 2, last + p.exposure_s / 2 + _PROBE_S, _PROBE_S)
        corners = []
        for t in times:
            pts = np.concatenate([solid.corners_world() for k in range(len(self.scene.robots))
                                  for solid in self.scene.robot_solids_at(self.scene.T_world_robot(t, k),
                                                                          self.scene.robots[k].layout)])
            corners.append(pts)
        stacked = np.array(corners)
        if np.any(view.depth(stacked.reshape(-1, 3)) <= 0.05):
            return 1e-4
        uv = view.project(stacked.reshape(-1, 3)).reshape(len(times), -1, 2)
        speed = float(np.linalg.norm(np.diff(uv, axis=0), axis=2).max()) / _PROBE_S
        return float(np.clip(_MAX_STEP_PX / max(speed, 1e-9), 1e-4, max(p.exposure_s, 1e-3)))


def _band_rows(camera: CameraSetup, exposure: Exposure) -> int:
    """Rows per band of a rolling-shutter render: a band's readout about half the exposure."""
    return int(np.clip(round(0.5 * max(exposure.exposure_s, 1e-3) / camera.row_s), 8, 64))


def _write_frames(writer: RecordingWriter, scene: Scene, jobs: list[_FrameJob], make: _FrameMaker,
                  workers: int, stage: str, progress: Progress | None) -> None:
    """Render jobs (in parallel threads: OpenCV and NumPy release the GIL) and write them in order."""
    def write(job: _FrameJob, jpeg: bytes, done: int) -> None:
        c = job.capture
        assert c.arrival_host_s is not None  # jobs are delivered frames only
        writer.add_frame(scene.cameras[job.camera].name, c.seq, c.device_time_s, c.arrival_host_s, jpeg)
        if progress is not None:
            progress(f"simulate {stage}", done, len(jobs))

    if workers <= 1:
        for done, job in enumerate(jobs, start=1):
            write(job, make(job), done)
        return
    with ThreadPoolExecutor(max_workers=workers) as pool:
        for done, (job, jpeg) in enumerate(zip(jobs, pool.map(make, jobs), strict=True), start=1):
            write(job, jpeg, done)


def simulate(params: SimulationParams, out: str | Path, progress: Progress | None = None,
             overwrite: bool = False, workers: int | None = None) -> SimulationResult:
    """Render a simulated session into the recording folder ``out`` (contracts §3) and return
    the truth behind it.

    Writes ``out/recording.json``, ``out/<cam>/index.csv``, JPEGs and ``clock.csv``,
    ``out/camera_info/<cam>.yaml``, ``out/ground_truth.tum`` (100 Hz, host clock; the first
    robot's, and with several robots every robot's in ``out/ground_truth/<robot>.tum``),
    ``out/cube.toml``, ``out/config.toml``, ``out/true_extrinsics.toml``, ``out/simulation.toml``
    and, unless ``params.calibration_frames`` is 0, the empty-arena recording
    ``out/calibration/``. Refuses a folder that already holds a recording unless ``overwrite``.
    ``workers`` threads render frames (default: up to 4, one per core); the output does not
    depend on it.
    """
    p = params
    out = Path(out)
    cal_dir = out / CALIBRATION_DIR if p.calibration_frames > 0 else None
    for folder in (out, out / CALIBRATION_DIR):
        if folder.is_dir():
            _check_free(folder, overwrite)
    if cal_dir is None and (out / CALIBRATION_DIR / "recording.json").exists():
        # overwriting: an old calibration recording would not match the new cameras
        for f in (out / CALIBRATION_DIR).rglob("*"):
            if f.is_file() and f.suffix in (".csv", ".yaml", ".json"):
                f.unlink()
    scene = build_scene(p)
    entries = [CameraEntry(c.name, f"simulated:{c.name}") for c in scene.cameras]
    start, end = p.start_unix_s, p.start_unix_s + p.duration_s

    # timing plans first (cheap), so progress knows the totals
    plans = [plan_captures(p, c.clock, c.capture_phase_s, rng_for(p.seed, STREAM_TIMING, i), start, end)
             for i, c in enumerate(scene.cameras)]
    clock_plans = [plan_clock_samples(p, c.clock, rng_for(p.seed, STREAM_SYNC, i), start, end)
                   for i, c in enumerate(scene.cameras)]
    if cal_dir is not None:
        cal_plans, cal_clock_plans = _calibration_plans(p, scene, start)
    else:
        cal_plans, cal_clock_plans = [() for _ in scene.cameras], [() for _ in scene.cameras]

    if workers is None:
        workers = min(4, os.cpu_count() or 1)
    with RecordingWriter(out, entries, overwrite=overwrite) as writer:
        for c in scene.cameras:
            write_camera_info(c.camera_info, writer.camera_info_path(c.name))
        _write_session_files(out, scene)
        renderers = [Renderer(View(c.intrinsics, c.T_world_cam, p.supersample), scene.floor,
                              (scene.world_marker,)) for c in scene.cameras]
        make = _FrameMaker(scene, renderers)
        for i, c in enumerate(scene.cameras):
            for sample in clock_plans[i]:
                writer.add_clock_sample(c.name, sample)
        jobs = [job for i in range(len(scene.cameras))
                for job in _frame_jobs(scene, i, plans[i], True, STREAM_IMAGE, STREAM_GAIN, STREAM_EXPOSURE)]
        _write_frames(writer, scene, jobs, make, workers, "recording", progress)
        ground_truths = _ground_truths(p, scene)
        write_tum(next(iter(ground_truths.values())), writer.ground_truth_path)
        if len(scene.robots) > 1:
            (out / GROUND_TRUTH_DIR).mkdir(exist_ok=True)
            for name, trajectory in ground_truths.items():
                write_tum(trajectory, out / GROUND_TRUTH_DIR / f"{name}.tum")

    if cal_dir is not None:
        with RecordingWriter(cal_dir, entries, overwrite=overwrite) as writer:
            for i, c in enumerate(scene.cameras):
                write_camera_info(c.camera_info, writer.camera_info_path(c.name))
                for sample in cal_clock_plans[i]:
                    writer.add_clock_sample(c.name, sample)
            jobs = [job for i in range(len(scene.cameras))
                    for job in _frame_jobs(scene, i, cal_plans[i], False, STREAM_CAL_IMAGE, STREAM_CAL_GAIN,
                                           STREAM_CAL_EXPOSURE)]
            _write_frames(writer, scene, jobs, make, workers, "calibration", progress)

    cameras = tuple(
        SimulatedCamera(c.name, c.intrinsics, c.T_world_cam, c.clock, plans[i], cal_plans[i], c.camera_info,
                        c.readout_s, c.motion)
        for i, c in enumerate(scene.cameras)
    )
    _write_camera_poses(out, p, cameras)
    log.info("simulated %d cameras: %d frames in %s", len(cameras), sum(c.frames_written for c in cameras), out)
    return SimulationResult(out, cal_dir, out / CONFIG_FILE, p, cameras, scene.world, ground_truths, scene)


def _calibration_plans(p: SimulationParams, scene: Scene, start: float
                       ) -> tuple[list[tuple[CaptureTruth, ...]], list[tuple]]:
    """Each camera's captures and clock samples of the empty-arena calibration recording, which
    ends ``_GAP_BEFORE_RECORDING_S`` before the tracking recording's ``start``."""
    cal_plans: list[tuple[CaptureTruth, ...]] = [() for _ in scene.cameras]
    cal_clock_plans: list[tuple] = [() for _ in scene.cameras]
    # long enough for the wanted number of frames even with drops and skips
    span = p.calibration_frames / p.fps / max(0.2, 1.0 - p.drop_rate - 2 * p.spike_rate) * 1.5 + 5.0
    cal_start = start - _GAP_BEFORE_RECORDING_S - span
    for i, c in enumerate(scene.cameras):
        cal_plans[i] = plan_captures(p, c.clock, c.capture_phase_s, rng_for(p.seed, STREAM_CAL_TIMING, i),
                                     cal_start, start - _GAP_BEFORE_RECORDING_S, p.calibration_frames)
        got = [x.arrival_host_s for x in cal_plans[i] if x.arrival_host_s is not None]  # delivered
        if len(got) < p.calibration_frames:
            log.warning("%s: only %d of %d calibration frames arrive at drop_rate %g",
                        c.name, len(got), p.calibration_frames, p.drop_rate)
        last = max(got, default=cal_start)
        cal_clock_plans[i] = plan_clock_samples(p, c.clock, rng_for(p.seed, STREAM_CAL_SYNC, i),
                                                cal_start, last + 0.5)
    return cal_plans, cal_clock_plans


def _ground_truths(p: SimulationParams, scene: Scene) -> dict[str, Trajectory]:
    """Each robot's cube trajectory at ``ground_truth_hz`` over the tracking recording."""
    start = p.start_unix_s
    times = start + np.arange(int(round(p.duration_s * p.ground_truth_hz)) + 1) / p.ground_truth_hz
    ground_truths = {}
    for k, robot in enumerate(scene.robots):
        poses = [position_quat_from_T(scene.T_world_cube(t - start, k)) for t in times]
        ground_truths[robot.name] = Trajectory(times, np.array([q[0] for q in poses]),
                                               np.array([q[1] for q in poses]))
    return ground_truths


def _write_session_files(out: Path, scene: Scene) -> None:
    """cube.toml, config.toml, true_extrinsics.toml, simulation.toml and the truth the tracker
    is not told: true_cube.toml (the cube as built) and true_camera_info/ (true intrinsics)."""
    p = scene.params
    robots = []
    for robot in scene.robots:
        layout_file = LAYOUT_FILE if len(scene.robots) == 1 else f"cube_{robot.name}.toml"
        write_layout(robot.layout, out / layout_file)
        write_layout(robot.true_layout, out / (TRUE_LAYOUT_PREFIX + layout_file))
        robots.append((robot.name, layout_file))
    (out / TRUE_CAMERA_INFO_DIR).mkdir(exist_ok=True)
    for c in scene.cameras:
        write_camera_info(c.intrinsics, out / TRUE_CAMERA_INFO_DIR / f"{c.name}.yaml")
    cameras = [CameraConfig(c.name, "", out / "camera_info" / f"{c.name}.yaml") for c in scene.cameras]
    config = tracker_config_to_table(scene.world, cameras, robots, relative_to=out)
    if p.inverted_markers:
        config["detector"] = {"detect_inverted_marker": True}
    write_toml(config, out / CONFIG_FILE)
    write_extrinsics({c.name: CameraExtrinsics(c.T_world_cam, method="ground truth (simulated)")
                      for c in scene.cameras}, out / TRUE_EXTRINSICS_FILE)
    truth = {}
    for c in scene.cameras:
        position, q = position_quat_from_T(c.T_world_cam)
        truth[c.name] = {
            "position": [float(v) for v in position],
            "quaternion_xyzw": [float(v) for v in q],
            "boot_host_s": float(c.clock.boot_host_s),
            "drift_ppm": float(c.clock.drift_ppm),
            "capture_phase_s": float(c.capture_phase_s),
            "exposure_s": float(p.exposure_s),
            "readout_s": float(c.readout_s),
            "row_time_s": float(c.row_s),
            "reference_row": float(c.reference_row),
        }
        if not c.motion.still:
            truth[c.name]["motion"] = _motion_table(c.motion)
    doc = {"params": params_to_table(p), "cameras": truth}
    (out / SIMULATION_FILE).write_text(tomli_w.dumps(doc), encoding="utf-8")


def _motion_table(motion: CameraMotion) -> dict[str, object]:
    """simulation.toml's record of a moving camera: each bump (time after the start, world
    translation, world rotation vector about the optical centre) and the drift's rates and axes."""
    table: dict[str, object] = {
        "bumps": [{"at_s": b.time_s, "translation_m": [float(v) for v in b.translation_m],
                   "rotvec_rad": [float(v) for v in b.rotvec_rad]} for b in motion.bumps],
        "drift_m_per_s": motion.drift_m_per_s, "drift_rad_per_s": motion.drift_rad_per_s}
    if motion.drift_direction is not None and motion.drift_axis is not None:
        table["drift_direction"] = [float(v) for v in motion.drift_direction]
        table["drift_axis"] = [float(v) for v in motion.drift_axis]
    return table


def _write_camera_poses(out: Path, p: SimulationParams, cameras: tuple[SimulatedCamera, ...]) -> None:
    """``true_camera_poses/<cam>.tum``: every camera's true pose (T_world_cam, TUM rows) at the
    capture time (host clock) of each frame it delivered: the pose that frame was rendered from;
    nothing when every camera stands still."""
    if all(c.motion.still for c in cameras):
        return
    folder = out / TRUE_CAMERA_POSES_DIR
    folder.mkdir(exist_ok=True)
    for c in cameras:
        times = np.array([x.capture_host_s for x in c.captures if x.delivered])
        poses = [position_quat_from_T(c.T_world_cam_at(t - p.start_unix_s)) for t in times]
        write_tum(Trajectory(times, np.array([q[0] for q in poses]).reshape(-1, 3),
                             np.array([q[1] for q in poses]).reshape(-1, 4)), folder / f"{c.name}.tum")
