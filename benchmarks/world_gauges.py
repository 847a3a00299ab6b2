"""Issue 26: the two gauges of the refined world's tilt, across seeds, without rendering.

``cubetrack calibrate --refine-with DRIVE`` takes the world's tilt from two sources: the world
marker's corners, and (ground robots, ``[bundle_adjustment] planar_motion`` and
``upright_sigma_deg``) the drive's cube held at one height and upright, i.e. the floor under the
drive taken as the marker's plane. With the default priors the second outweighs the first about
200:1 (400 instants at 2 mm), so the refined world is the plane of the drive's floor
(docs/calibration.md, "What turns the refined world: the truth put in"). This script measures, per
seed of a simulated scene and from the simulator's truth alone (no image is rendered), how far
each gauge is from the truth's world (the world marker's plane, z = 0):

- **floor**: the plane fitted to the cube's true positions over the drive (scene time
  ``--duration`` to ``--duration`` + ``--drive`` s, as ``done_when.py`` renders it), as the world
  turn that would make it level (what the one-height prior does to a world whose floor slopes);
- **marker**: each camera's pose from the world marker's four exact corners (projected through
  the true lens and pose) solved through the intrinsics the tracker is told (``camera_info``,
  ``cv2.solvePnP``), the cameras' mean rotation error: the tilt the marker gauge carries from the
  intrinsics alone (no corner noise, no blur).

Both as rotation vectors of the true-from-estimated world about world x and y, degrees (the sign
``R_true R_est^T``; a refined world that is the floor's plane shows the floor column). Printed per
seed and, over the seeds, the RMS tilt of each and how often the floor's is the larger.

    .venv/bin/python benchmarks/world_gauges.py [--preset realistic] [--config 1] [--seeds 1 2 3 ...]
                                                 [--duration 8] [--drive 30]
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import cv2
import numpy as np
from scipy.spatial.transform import Rotation

sys.path.insert(0, str(Path(__file__).resolve().parent))

SAMPLE_HZ = 30.0  # the cube's true pose is sampled this often over the drive


def floor_tilt_deg(scene, start_s: float, end_s: float) -> np.ndarray:
    """(x, y) world turn, degrees, that makes the plane through the cube's true positions over
    ``start_s``..``end_s`` (scene time) level: ``(atan(dz/dy), -atan(dz/dx))``."""
    times = np.arange(start_s, end_s, 1.0 / SAMPLE_HZ)
    P = np.array([scene.T_world_cube(t)[:3, 3] for t in times])
    A = np.column_stack([np.ones(len(P)), P[:, 0] - P[:, 0].mean(), P[:, 1] - P[:, 1].mean()])
    _, dz_dx, dz_dy = np.linalg.lstsq(A, P[:, 2], rcond=None)[0]
    return np.degrees([np.arctan(dz_dy), -np.arctan(dz_dx)])


def marker_tilt_deg(scene) -> np.ndarray:
    """(x, y) of the cameras' mean rotation error, degrees, when each camera's pose is solved from
    the world marker's exact corners through its ``camera_info`` intrinsics."""
    half = scene.params.world_marker_size_m / 2.0
    corners = np.array([[-half, half, 0.0], [half, half, 0.0], [half, -half, 0.0], [-half, -half, 0.0]])
    errors = []
    for cam in scene.cameras:
        T_cam_world = np.linalg.inv(cam.T_world_cam)
        true = cam.intrinsics
        px, _ = cv2.projectPoints(corners, cv2.Rodrigues(T_cam_world[:3, :3])[0], T_cam_world[:3, 3], true.K,
                                  np.asarray(true.dist, float))
        info = cam.camera_info
        ok, rvec, _ = cv2.solvePnP(corners, px, info.K, np.asarray(info.dist, float), flags=cv2.SOLVEPNP_IPPE)
        if not ok:
            raise RuntimeError(f"{cam.name}: the world marker's pose has no solution")
        R_world_cam_est = cv2.Rodrigues(rvec)[0].T
        errors.append(cam.T_world_cam[:3, :3] @ R_world_cam_est.T)
    return np.degrees(Rotation.from_matrix(np.array(errors)).mean().as_rotvec()[:2])


def gauges(preset: str, config: int, seed: int, duration_s: float, drive_s: float) -> tuple[np.ndarray, np.ndarray]:
    """(floor tilt, marker tilt), each (x, y) degrees, of one seed of accuracy.py's scene."""
    import accuracy as bench

    from cubetrack.simulate.scenario import build_scene

    _, cameras, height, tilt, _ = bench.CONFIGS[config]
    scene = build_scene(bench.sim_params(preset, cameras, height, tilt, seed, duration_s + drive_s, 0))
    return floor_tilt_deg(scene, duration_s, duration_s + drive_s), marker_tilt_deg(scene)


def parse_args(argv: list[str] | None) -> argparse.Namespace:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                 epilog="Per seed of accuracy.py's scene: the floor under the drive and the "
                                        "world marker through camera_info, as tilts of the world (deg).")
    ap.add_argument("--preset", default="realistic", help="accuracy.py's preset (default realistic)")
    ap.add_argument("--config", type=int, default=1, help="accuracy.py's configuration index (default 1: 3 "
                                                          "cameras 1.0 m / 30 deg)")
    ap.add_argument("--seeds", type=int, nargs="+", default=list(range(1, 41)), help="scene seeds (default 1-40)")
    ap.add_argument("--duration", type=float, default=8.0, help="seconds of the scored session (the drive follows)")
    ap.add_argument("--drive", type=float, default=30.0, help="seconds of the drive the workflow refines with")
    return ap.parse_args(argv)


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    rows = []
    for seed in args.seeds:
        floor, marker = gauges(args.preset, args.config, seed, args.duration, args.drive)
        rows.append(np.concatenate([floor, marker]))
        print(f"seed {seed:5d}: floor ({floor[0]:+.3f}, {floor[1]:+.3f}) |{np.hypot(*floor):.3f}| deg; "
              f"marker through camera_info ({marker[0]:+.3f}, {marker[1]:+.3f}) |{np.hypot(*marker):.3f}| deg",
              flush=True)
    r = np.array(rows)
    floor_abs, marker_abs = np.hypot(r[:, 0], r[:, 1]), np.hypot(r[:, 2], r[:, 3])
    print(f"{args.preset}, config {args.config}, {len(r)} seeds: RMS tilt floor {np.sqrt(np.mean(floor_abs ** 2)):.3f} "
          f"deg (median {np.median(floor_abs):.3f}), marker {np.sqrt(np.mean(marker_abs ** 2)):.3f} deg (median "
          f"{np.median(marker_abs):.3f}); the floor's the larger on {int(np.sum(floor_abs > marker_abs))} of {len(r)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
