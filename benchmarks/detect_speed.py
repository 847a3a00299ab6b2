"""Per-frame cost of detection + estimation against the naive loop (issue 5), and corner accuracy.

(a) naive: ``cv2.imdecode`` in colour, a default ``cv2.aruco.ArucoDetector`` (the cube's
    dictionary), ``solvePnP(SOLVEPNP_IPPE_SQUARE)`` per detected marker.
(b) ours: ``Detector.detect_jpeg`` (world and cube dictionaries, default ``[detector]``, i.e.
    ``edge`` corners) and ``estimate_cube`` (default ``[estimator]``) with the true extrinsics,
    as the tracker runs them per frame.

Both run on the same frames of a simulated recording (the paper's 3-camera setup), on one thread
(``cv2.setNumThreads(1)``), interleaved round by round so that load from other jobs hits both
alike. Printed: ms per frame of each (median over rounds), and the ratio naive / ours (>= 1 means
ours keeps up with the naive loop's frame rate). The absolute times depend on the machine; the
ratio is the number to compare.

With the simulation's truth, it also prints the corner error (px) of both detectors against the
projected true corners (cube markers, matched to the nearest true face) and the position error of
our cube estimates, so a speed change can be checked for an accuracy change on the same frames.

    .venv/bin/python benchmarks/detect_speed.py [--duration 10] [--rounds 5] [--seed 0]

``--stages`` instead replays a recording's frames (``--recording DIR``: a folder with
``config.toml`` and ``extrinsics.toml`` or ``true_extrinsics.toml``, e.g. one made by
``benchmarks/live.py``; default: the simulated one above) through the tracker on one thread, a
fresh tracker per round, so detection searches the regions the tracker's own forecasts give. It
prints the thread CPU time per frame of each stage (decode, OpenCV's search, the edge refinement,
the per-camera estimate, planning, fusion; median of rounds), the estimate/ functions the fusion
calls (in place, then each alone on the calls it made in the first ``--micro-frames`` frames),
the naive loop on the same frames as the ratio, the frames whose regions were empty (every robot
predicted out of the camera's view) and what decoding them cost, the frames searched whole (no regions: a robot
not predicted, or every ``[track] full_frame_every``-th frame of a camera; or regions that found nothing) and their
per-frame work against the other frames', the CPU of ways to decode the first
``--micro-frames`` frames (colour, gray, DCT-scaled to 1/2, 1/4, 1/8, and the tracker's own top-rows decode)
against the full gray decode, the CPU and markers kept of those frames' region searches as configured, at half
size and with fewer adaptive-threshold passes, and whether the poses were bit-identical across rounds (exit 1 if not).
Frames are stamped by their arrival times (clock.csv is not used).

    nice -n 19 .venv/bin/python benchmarks/detect_speed.py --stages --recording /tmp/lb16q/rec_c16_f30_d20_s7 \
        --frames 600 --rounds 3
"""

from __future__ import annotations

import argparse
import hashlib
import sys
import tempfile
import time
from pathlib import Path

import cv2
import numpy as np

from cubetrack.core.layout import marker_corners_m
from cubetrack.detect.detector import Detector, DetectorParams
from cubetrack.estimate.pose import estimate_cube
from cubetrack.io.recording import Recording
from cubetrack.simulate import SimulationParams, simulate
from cubetrack.simulate.render import project_points


def naive_frame(jpeg: bytes, detector, K: np.ndarray, dist: np.ndarray, obj: np.ndarray) -> list:
    """The loop issue 5 compares against: colour decode, default ArUco, IPPE per marker."""
    image = cv2.imdecode(np.frombuffer(jpeg, np.uint8), cv2.IMREAD_COLOR)
    corners, ids, _rejected = detector.detectMarkers(image)
    out = []
    if ids is not None:
        for c, marker_id in zip(corners, ids.ravel(), strict=True):
            _ok, rvec, tvec = cv2.solvePnP(obj, c.reshape(4, 1, 2), K, dist, flags=cv2.SOLVEPNP_IPPE_SQUARE)
            out.append((int(marker_id), c.reshape(4, 2).astype(float), rvec, tvec))
    return out


def true_corners(sim, camera: str, seq: int) -> list[np.ndarray]:
    """Projected true corners (4, 2) of the cube markers facing the camera in frame ``seq``."""
    cam = sim.camera(camera)
    capture = next(c for c in cam.captures if c.seq == seq)
    T_world_cube = sim.T_world_cube(capture.capture_host_s)
    out = []
    for m in sim.layout.markers:
        T_world_marker = T_world_cube @ m.T_cube_marker
        to_cam = cam.T_world_cam[:3, 3] - T_world_marker[:3, 3]
        if float(to_cam @ T_world_marker[:3, 2]) > 0.0:
            corners = marker_corners_m(m.size_m) @ T_world_marker[:3, :3].T + T_world_marker[:3, 3]
            out.append(project_points(cam.intrinsics, cam.T_world_cam, corners))
    return out


def corner_errors(found: list[np.ndarray], truth: list[np.ndarray]) -> list[float]:
    """Per corner distance (px) of each detected cube marker to the true face it lies on (the
    nearest by centre; same corner order), skipping detections more than 5 px from any."""
    errs = []
    for c in found:
        if not truth:
            break
        t = min(truth, key=lambda t: float(np.linalg.norm(t.mean(axis=0) - c.mean(axis=0))))
        e = np.linalg.norm(c - t, axis=1)
        if e.max() < 5.0:
            errs.extend(e.tolist())
    return errs


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--duration", type=float, default=10.0, help="seconds of simulated recording (default 10)")
    ap.add_argument("--rounds", type=int, default=5, help="timing rounds over all frames (default 5)")
    ap.add_argument("--seed", type=int, default=0, help="simulation seed (default 0)")
    ap.add_argument("--stages", action="store_true", help="per-stage CPU per frame through the tracker (see above)")
    ap.add_argument("--recording", help="--stages: recording folder (default: a simulated one)")
    ap.add_argument("--frames", type=int, default=0, help="--stages: the first N frames only (default all)")
    ap.add_argument("--micro-frames", type=int, default=200,
                    help="--stages: frames whose estimate/ calls are timed alone (default 200)")
    args = ap.parse_args(argv)
    if args.stages:
        return stage_costs(args)
    cv2.setNumThreads(1)

    with tempfile.TemporaryDirectory() as tmp:
        sim = simulate(SimulationParams(duration_s=args.duration, seed=args.seed, calibration_frames=0),
                       Path(tmp) / "rec")
        rec = Recording.open(sim.path)
        frames = [f for name in rec.camera_names for f in rec.frames(name)]
    layout, world = sim.layout, sim.world
    intr = sim.intrinsics
    T_world_cam = sim.T_world_cam
    print(f"{len(frames)} frames, {len(rec.camera_names)} cameras, "
          f"{sim.params.image_width_px}x{sim.params.image_height_px}, one thread")

    naive_detector = cv2.aruco.ArucoDetector(cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, layout.dictionary)),
                                             cv2.aruco.DetectorParameters())
    obj = marker_corners_m(layout.markers[0].size_m).reshape(4, 1, 3)
    ours_detector = Detector(DetectorParams(), [world.dictionary, layout.dictionary])

    def naive(f):
        return naive_frame(f.jpeg, naive_detector, intr[f.camera].K, intr[f.camera].dist, obj)

    def ours(f):
        dets = ours_detector.detect_jpeg(f.jpeg)
        est = estimate_cube(dets, layout, intr[f.camera], T_world_cam[f.camera], camera=f.camera,
                            robot="robot", seq=f.seq, capture_time_s=f.host_time_s, arrival_time_s=f.host_time_s)
        return dets, est

    # CPU time of this (single-threaded) process; each frame's result is dropped at once, as a
    # tracker drops it after fusion (keeping all of them would time the garbage collector too)
    times = {"naive": [], "ours": []}
    for r in range(args.rounds):
        for name, fn in (("naive", naive), ("ours", ours)) if r % 2 == 0 else (("ours", ours), ("naive", naive)):
            t0 = time.process_time()
            for f in frames:
                fn(f)
            times[name].append((time.process_time() - t0) / len(frames) * 1000.0)
    results = {"naive": [naive(f) for f in frames], "ours": [ours(f) for f in frames]}
    naive_ms, ours_ms = float(np.median(times["naive"])), float(np.median(times["ours"]))
    print(f"(a) naive loop : {naive_ms:6.2f} ms/frame  ({1000.0 / naive_ms:5.1f} frames/s)   rounds: "
          + " ".join(f"{t:.2f}" for t in times["naive"]))
    print(f"(b) ours       : {ours_ms:6.2f} ms/frame  ({1000.0 / ours_ms:5.1f} frames/s)   rounds: "
          + " ".join(f"{t:.2f}" for t in times["ours"]))
    print(f"ratio naive/ours (frame-rate ratio, >= 1.0 is the target): {naive_ms / ours_ms:.2f}")

    naive_err, ours_err = [], []
    for f, found, (dets, _est) in zip(frames, results["naive"], results["ours"], strict=True):
        truth = true_corners(sim, f.camera, f.seq)
        cube_ids = set(layout.ids)
        naive_err += corner_errors([c for i, c, _r, _t in found if i in cube_ids], truth)
        ours_err += corner_errors([d.corners_px for d in dets if d.marker_id in cube_ids
                                   and d.dictionary == layout.dictionary], truth)
    position_mm = []
    for f, (_dets, est) in zip(frames, results["ours"], strict=True):
        if est is not None:
            capture = next(c for c in sim.camera(f.camera).captures if c.seq == f.seq)
            position_mm.append(1000.0 * np.linalg.norm(est.T_world_cube[:3, 3]
                                                       - sim.T_world_cube(capture.capture_host_s)[:3, 3]))
    estimates = len(position_mm)
    for name, e in (("naive", naive_err), ("ours", ours_err)):
        e = np.array(e)
        print(f"corner error {name:<5}: {len(e) // 4:4d} markers, mean {e.mean():.3f} px, median "
              f"{np.median(e):.3f}, p95 {np.percentile(e, 95):.3f}")
    print(f"cube estimates: {estimates} of {len(frames)} frames, position error median "
          f"{np.median(position_mm):.1f} mm, p95 {np.percentile(position_mm, 95):.1f} mm")
    return 0


# --------------------------------------------------------------------------- per-stage CPU (issue 9)

# Per-frame stages, timed by wrapping the functions the tracker calls (module attribute, key);
# the detector's own ``detect`` is wrapped on the worker's instance.
_FRAME_HOOKS = (("cubetrack.app.tracker", "decode_gray", "decode"),
                ("cubetrack.detect.detector", "refine_corners_edges", "edge"))
# What the search of predicted markers calls besides the edge fit (module attribute, name printed).
_PREDICTED_HOOKS = (("cubetrack.detect.detector", "marker_reads"),)
# What the fusion calls per sighting (module attribute, name printed).
_FUSION_HOOKS = (("cubetrack.fuse.fusion", "match_faces"), ("cubetrack.fuse.fusion", "corner_set"),
                 ("cubetrack.fuse.fusion", "estimate_cube"),
                 ("cubetrack.fuse.corner_filter", "solve_update"), ("cubetrack.fuse.corner_filter", "packed_sets"),
                 ("cubetrack.fuse.corner_filter", "predicted_covariance"),
                 ("cubetrack.fuse.corner_filter", "perturbed"), ("cubetrack.fuse.corner_filter", "moved_pose"),
                 ("cubetrack.fuse.multi_view_fit", "joint_fit"), ("cubetrack.fuse.multi_view_fit", "packed_sets"))
# Per-frame estimate/ functions of the frame worker, micro-benchmarked like the fusion's.
_WORKER_HOOKS = (("cubetrack.app.tracker", "estimate_cube"), ("cubetrack.app.tracker", "body_detections"))


def ms_median(key: str, rounds: list[dict[str, float]]) -> float:
    return float(np.median([c[key] for c in rounds]))


def full_collection() -> None:
    """What one full collection costs this process now (the stages imported, the kernels loaded, a tracker's
    state around): tracked objects and CPU ms, before and after ``gc.freeze()`` (start-up's objects moved out
    of every later collection); the objects are unfrozen again afterwards."""
    import gc

    costs = []
    for freeze in (False, True):
        if freeze:
            gc.freeze()
        objects, t0 = len(gc.get_objects()), time.thread_time()
        gc.collect()
        costs.append((objects, (time.thread_time() - t0) * 1000.0))
    gc.unfreeze()
    (before, before_ms), (after, after_ms) = costs
    print(f"a full collection here: {before} tracked objects, {before_ms:.1f} ms CPU; after gc.freeze() {after} "
          f"objects, {after_ms:.1f} ms")


class _GcPauses:
    """Python's garbage collections while it is installed (``gc.callbacks``): how many, of which of
    the oldest generation, and their wall-clock milliseconds (a collection pauses the thread: a
    latency spike live)."""

    def __init__(self) -> None:
        import gc

        self._gc, self._started = gc, 0.0
        self.ms: list[tuple[int, float]] = []   # (generation, ms)
        gc.callbacks.append(self._callback)

    def _callback(self, phase: str, info: dict) -> None:
        if phase == "start":
            self._started = time.perf_counter()
        else:
            self.ms.append((info["generation"], (time.perf_counter() - self._started) * 1000.0))

    def stop(self) -> None:
        self._gc.callbacks.remove(self._callback)

    def summary(self) -> dict[str, float]:
        return {"gc_count": len(self.ms), "gc2_count": sum(g == 2 for g, _ in self.ms),
                "gc_ms": sum(m for _, m in self.ms), "gc_max_ms": max((m for _, m in self.ms), default=0.0)}


class _Hooks:
    """Thread-CPU timers (and, while ``recording``, argument capture) wrapped around module
    functions; ``restore`` puts the originals back."""

    def __init__(self) -> None:
        self.cpu_s: dict[str, float] = {}
        self.calls: dict[str, list] = {}
        self.recording = False
        self._undo: list = []

    def wrap(self, owner, attr: str, key: str) -> None:
        original = getattr(owner, attr)
        self.cpu_s.setdefault(key, 0.0)
        self.calls.setdefault(key, [])
        clock, cpu, calls = time.thread_time, self.cpu_s, self.calls[key]

        def timed(*args, **kwargs):
            if self.recording:
                calls.append((original, args, kwargs))
            t0 = clock()
            try:
                return original(*args, **kwargs)
            finally:
                cpu[key] += clock() - t0

        setattr(owner, attr, timed)
        self._undo.append((owner, attr, original))

    def restore(self) -> None:
        for owner, attr, original in reversed(self._undo):
            setattr(owner, attr, original)
        self._undo.clear()


def _stage_inputs(args: argparse.Namespace, tmp: Path):
    """(frames, intrinsics, world, robots, extrinsics, stage params, source description)."""
    from cubetrack.app.config import load_config, recording_intrinsics
    from cubetrack.io.config import read_extrinsics

    if args.recording is None:
        sim = simulate(SimulationParams(duration_s=args.duration, seed=args.seed, calibration_frames=0), tmp / "rec")
        path, extrinsics_file = Path(sim.path), Path(sim.path) / "true_extrinsics.toml"
    else:
        path = Path(args.recording)
        extrinsics_file = path / "extrinsics.toml"
        if not extrinsics_file.exists():
            extrinsics_file = path / "true_extrinsics.toml"
    config, settings = load_config(path / "config.toml")
    recording = Recording.open(path)
    frames = list(recording.merged_frames())
    if args.frames:
        frames = frames[: args.frames]
    intrinsics = recording_intrinsics(config, recording)
    return (frames, intrinsics, config.world, config.robots, read_extrinsics(extrinsics_file), settings.stages,
            f"{path} ({len(recording.camera_names)} cameras, extrinsics {extrinsics_file.name})")


def _pose_digest(poses) -> str:
    """sha256 of the poses' robot, time, markers, position and orientation (exact bytes)."""
    h = hashlib.sha256()
    for p in poses:
        h.update(repr((p.robot, p.time_s, p.markers)).encode())
        h.update(np.asarray(p.position_m, dtype=np.float64).tobytes())
        h.update(np.asarray(p.quaternion_xyzw, dtype=np.float64).tobytes())
    return h.hexdigest()


def stage_costs(args: argparse.Namespace) -> int:
    """Replay a recording's frames through the tracker's stages on one thread and print the CPU
    per frame of each (thread CPU time, median over rounds), the estimate/ functions the fusion
    calls (timed in place, then each alone on the calls it made), and the naive loop on the same
    frames for the ratio."""
    import importlib
    import os

    from cubetrack.app.tracker import Tracker
    from cubetrack.core.records import FrameOutcome

    cv2.setNumThreads(1)
    with tempfile.TemporaryDirectory() as tmp:
        frames, intrinsics, world, robots, extrinsics, stages, source = _stage_inputs(args, Path(tmp))
    print(f"{source}: {len(frames)} frames, one thread, {args.rounds} rounds, {os.cpu_count()} cores, "
          f"load average {' '.join(f'{x:.2f}' for x in os.getloadavg())}")

    naive_detector = cv2.aruco.ArucoDetector(cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, world.dictionary)),
                                             cv2.aruco.DetectorParameters())
    obj = marker_corners_m(robots[0].layout.markers[0].size_m).reshape(4, 1, 3)

    def naive_round() -> float:
        t0 = time.thread_time()
        for f in frames:
            naive_frame(f.jpeg, naive_detector, intrinsics[f.camera].K, intrinsics[f.camera].dist, obj)
        return time.thread_time() - t0

    def ours_round(micro: bool) -> tuple[dict[str, float], list, dict]:
        """One pass of a fresh tracker (so every round does the same work): CPU s per stage, the
        poses, and (``micro``) the estimate/ calls made in the first frames."""
        tracker = Tracker(intrinsics, world, robots, extrinsics, stages)
        hooks = _Hooks()
        for module, attr, key in _FRAME_HOOKS:
            hooks.wrap(importlib.import_module(module), attr, key)
        hooks.wrap(tracker.processor.detector, "find", "detect")
        timed_find = tracker.processor.detector.find

        def find(*a, **kw):   # counts the region searches skipped for verified predicted markers
            found = timed_find(*a, **kw)
            cpu["predicted_frames"] += found.predicted
            return found

        tracker.processor.detector.find = find
        for module, attr in _FUSION_HOOKS + _WORKER_HOOKS + _PREDICTED_HOOKS:
            hooks.wrap(importlib.import_module(module), attr, f"{module.rsplit('.', 1)[1]}.{attr}")
        cpu = {"plan": 0.0, "work": 0.0, "fuse": 0.0, "decode_empty": 0.0, "empty_frames": 0.0, "predicted_frames": 0.0,
               "region_frames": 0.0, "whole_frames": 0.0, "whole_work": 0.0}
        poses = []
        clock = time.thread_time
        pauses = _GcPauses()
        try:
            for i, frame in enumerate(frames):
                hooks.recording = micro and i < args.micro_frames
                t0 = clock()
                job = tracker.admit(frame)
                t1 = clock()
                cpu["plan"] += t1 - t0
                if job is None:
                    continue
                decoded_s = hooks.cpu_s["decode"]
                result = tracker.processor.work(job)
                t2 = clock()
                cpu["region_frames"] += bool(job.regions)
                if result.outcome is FrameOutcome.FULL_FRAME:   # no regions, or regions that found nothing
                    cpu["whole_frames"] += 1
                    cpu["whole_work"] += t2 - t1
                if job.regions == ():   # every robot predicted out of view: nothing to search
                    cpu["empty_frames"] += 1
                    cpu["decode_empty"] += hooks.cpu_s["decode"] - decoded_s
                poses += tracker.fuse(result, frame.host_time_s)
                cpu["work"] += t2 - t1
                cpu["fuse"] += clock() - t2
            t0 = clock()
            poses += tracker.finish()
            cpu["fuse"] += clock() - t0
        finally:
            hooks.restore()
            pauses.stop()
        cpu.update(hooks.cpu_s)
        cpu.update(pauses.summary())
        cpu["detect"] -= cpu["edge"]                       # exclusive times
        cpu["estimate"] = cpu["work"] - cpu["decode"] - cpu["detect"] - cpu["edge"]
        return cpu, poses, hooks.calls

    rounds: list[dict[str, float]] = []
    naive_s: list[float] = []
    digests = set()
    calls = {}
    for r in range(args.rounds):
        order = (True, False) if r % 2 == 0 else (False, True)
        for is_naive in order:
            if is_naive:
                naive_s.append(naive_round())
                continue
            cpu, poses, recorded = ours_round(micro=r == 0)
            rounds.append(cpu)
            calls = calls or recorded
            digests.add(_pose_digest(poses))
    n = len(frames)

    def ms(values) -> float:
        return float(np.median(values)) / n * 1000.0

    total = ms([c["plan"] + c["work"] + c["fuse"] for c in rounds])
    naive = ms(naive_s)
    rows = [("decode (JPEG -> gray)", "decode"), ("detect (OpenCV search, quads)", "detect"),
            ("edge refinement", "edge"), ("per-camera estimate", "estimate"), ("planning (regions)", "plan"),
            ("fusion", "fuse")]
    print(f"{'stage':<34} {'CPU ms/frame':>12} {'share':>6}   rounds")
    for label, key in rows:
        value = ms([c[key] for c in rounds])
        print(f"{label:<34} {value:12.3f} {100.0 * value / total:5.1f}%   "
              + " ".join(f"{c[key] / n * 1000.0:.3f}" for c in rounds))
    print(f"{'total (ours, one thread)':<34} {total:12.3f}")
    print(f"{'naive loop (same frames)':<34} {naive:12.3f}          ratio naive/ours {naive / total:.2f}")
    print(f"frames whose regions are empty (every robot predicted out of view): "
          f"{rounds[0]['empty_frames']:.0f} of {n}; decoding them costs {ms([c['decode_empty'] for c in rounds]):.3f} "
          f"ms/frame (of all frames), what skipping their decode would save")
    print(f"frames with regions: {rounds[0]['region_frames']:.0f} of {n}; of them found at their predicted markers, "
          f"verified, without OpenCV's search: {rounds[0]['predicted_frames']:.0f}")
    whole = rounds[0]["whole_frames"]
    if whole:
        whole_ms = ms([c["whole_work"] for c in rounds])
        others_ms = ms([c["work"] - c["whole_work"] for c in rounds])
        print(f"frames searched whole (no regions, or regions that found nothing; [track] full_frame_every "
              f"{stages.track.full_frame_every}): {whole:.0f} of {n}; their decode + detect + estimate "
              f"{whole_ms * n / whole:.3f} ms each against {others_ms * n / max(n - whole, 1):.3f} for the other "
              f"frames: {whole_ms:.3f} ms/frame, {100.0 * whole_ms / total:.1f}% of the total")
    inside = [k for k in rounds[0] if "." in k]
    print("in place (inclusive, incl. timer overhead):")
    for key in inside:
        value = ms([c[key] for c in rounds])
        if value > 0.0:
            print(f"  {key:<40} {value:8.3f} ms/frame")
    print(f"alone, on the calls of the first {min(args.micro_frames, n)} frames (median of {args.rounds} rounds):")
    micro_frames = min(args.micro_frames, n)
    for key, recorded in calls.items():
        if not recorded or key in ("decode", "detect", "edge"):
            continue
        times = []
        for _ in range(args.rounds):
            t0 = time.thread_time()
            for fn, a, kw in recorded:
                fn(*a, **kw)
            times.append(time.thread_time() - t0)
        per_call = float(np.median(times)) / len(recorded)
        print(f"  {key:<40} {len(recorded) / micro_frames:6.2f} calls/frame {per_call * 1e6:8.1f} us/call "
              f"{per_call * len(recorded) / micro_frames * 1000.0:7.3f} ms/frame")
    decode_variants(frames[:micro_frames], calls.get("decode", []), args.rounds)
    region_variants(calls.get("detect", []), stages.detector, world.dictionary, robots, args.rounds)
    print(f"garbage collections in a round (median of rounds): {ms_median('gc_count', rounds):.0f}, of which "
          f"{ms_median('gc2_count', rounds):.0f} of the oldest generation; {ms_median('gc_ms', rounds):.1f} ms in all "
          f"({ms_median('gc_ms', rounds) / n:.4f} ms per frame), the longest {max(c['gc_max_ms'] for c in rounds):.2f} "
          "ms (wall clock: a pause of the thread)")
    full_collection()
    print(f"poses: {len(poses)}; replay "
          f"{'bit-identical across rounds' if len(digests) == 1 else 'DIFFERS across rounds'} (sha256 "
          f"{min(digests)[:16]})")
    return 0 if len(digests) == 1 else 1


def decode_variants(frames: list, tracker_calls: list, rounds: int) -> None:
    """Thread CPU per frame of ways to decode the same frames (issue 31's decode levers), against the
    full-resolution gray decode: the naive loop's colour decode, OpenCV's gray and DCT-scaled gray
    decodes (``IMREAD_REDUCED_GRAYSCALE_N``), simplejpeg's gray decode at full and DCT-scaled sizes
    (libjpeg-turbo's scaled IDCT; the entropy decoding is the same), and the tracker's own decode
    (``decode_gray`` with the rows its regions needed, ``tracker_calls``: the calls it made)."""
    import simplejpeg

    from cubetrack.detect.decode import decode_gray

    def opencv(flag: int):
        return lambda jpeg: cv2.imdecode(np.frombuffer(jpeg, np.uint8), flag)

    def scaled(k: int):
        def decode(jpeg: bytes) -> np.ndarray:
            height, width = simplejpeg.decode_jpeg_header(jpeg)[:2]
            return simplejpeg.decode_jpeg(jpeg, colorspace="GRAY", min_height=height // k, min_width=width // k)
        return decode

    ways = {"colour, full size (the naive loop's)": opencv(cv2.IMREAD_COLOR),
            "gray, full size (simplejpeg)": scaled(1),
            "gray, full size (OpenCV)": opencv(cv2.IMREAD_GRAYSCALE),
            **{f"gray, 1/{k} size (OpenCV IMREAD_REDUCED_GRAYSCALE_{k})":
               opencv(getattr(cv2, f"IMREAD_REDUCED_GRAYSCALE_{k}")) for k in (2, 4, 8)},
            **{f"gray, 1/{k} size (simplejpeg, scaled IDCT)": scaled(k) for k in (2, 4, 8)}}
    jpegs = [f.jpeg for f in frames]
    ms = {}
    for label, decode in ways.items():
        times = []
        for _ in range(rounds):
            t0 = time.thread_time()
            for jpeg in jpegs:
                decode(jpeg)
            times.append(time.thread_time() - t0)
        ms[label] = float(np.median(times)) / len(jpegs) * 1000.0
    if tracker_calls:
        times = []
        for _ in range(rounds):
            t0 = time.thread_time()
            for _fn, a, kw in tracker_calls:
                decode_gray(*a, **kw)
            times.append(time.thread_time() - t0)
        ms["the tracker's (rows down to its regions' lowest edge)"] = float(np.median(times)) / len(jpegs) * 1e3
    full = ms["gray, full size (simplejpeg)"]
    print(f"decode, the first {len(jpegs)} frames ({rounds} rounds; thread CPU ms per frame, / the full gray decode):")
    for label, value in ms.items():
        print(f"  {label:<58} {value:7.3f} ms  {value / full:5.2f}")


def region_variants(find_calls: list, params: DetectorParams, world_dictionary: str, robots, rounds: int) -> None:
    """Thread CPU per region search and markers kept (``Detector.find`` on the regions the tracker searched
    in ``find_calls``, edge fit included) as configured and with issue 31's levers: the image at half size
    (``cv2.resize`` INTER_AREA, the boxes halved) and fewer adaptive-threshold passes."""
    import dataclasses

    searches = [(a[0], tuple(a[1]), kw.get("lens", a[2] if len(a) > 2 else None)) for _fn, a, kw in find_calls
                if len(a) > 1 and a[1]]
    if not searches:
        return
    dictionaries = [world_dictionary, *(d for r in robots for d in r.layout.dictionaries)]
    windows = {"as configured": {}, "threshold windows 13, 23 px": {"adaptive_thresh_win_size_min_px": 13},
               "threshold windows 8, 18 px": {"adaptive_thresh_win_size_min_px": 8,
                                              "adaptive_thresh_win_size_max_px": 18}}
    ways = {label: (Detector(dataclasses.replace(params, **change), dictionaries), 1)
            for label, change in windows.items()}
    ways["the image at half size (INTER_AREA)"] = (ways["as configured"][0], 2)
    print(f"region searches of those frames: {len(searches)} ({rounds} rounds; thread CPU ms per search, edge fit "
          "included; markers kept):")
    for label, (detector, k) in ways.items():
        inputs = [(gray, regions, lens) if k == 1 else
                  (cv2.resize(gray, (gray.shape[1] // k, gray.shape[0] // k), interpolation=cv2.INTER_AREA),
                   tuple(tuple(v // k for v in box) for box in regions), lens) for gray, regions, lens in searches]
        times, kept = [], 0
        for _ in range(rounds):
            kept, t0 = 0, time.thread_time()
            for gray, regions, lens in inputs:
                kept += len(detector.find(gray, regions, lens).detections)
            times.append(time.thread_time() - t0)
        print(f"  {label:<40} {float(np.median(times)) / len(inputs) * 1000.0:7.3f} ms  {kept:6d} markers")


if __name__ == "__main__":
    sys.exit(main())
