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
"""

from __future__ import annotations

import argparse
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
        for c, marker_id in zip(corners, ids.ravel()):
            ok, rvec, tvec = cv2.solvePnP(obj, c.reshape(4, 1, 2), K, dist, flags=cv2.SOLVEPNP_IPPE_SQUARE)
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
    args = ap.parse_args(argv)
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
    for f, found, (dets, _est) in zip(frames, results["naive"], results["ours"]):
        truth = true_corners(sim, f.camera, f.seq)
        cube_ids = set(layout.ids)
        naive_err += corner_errors([c for i, c, _r, _t in found if i in cube_ids], truth)
        ours_err += corner_errors([d.corners_px for d in dets if d.marker_id in cube_ids
                                   and d.dictionary == layout.dictionary], truth)
    position_mm = []
    for f, (_dets, est) in zip(frames, results["ours"]):
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


if __name__ == "__main__":
    sys.exit(main())
