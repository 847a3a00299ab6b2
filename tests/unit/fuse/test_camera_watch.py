"""The camera watcher (issue 27) on synthetic sightings: ground truth by construction (a cube
driving a circle, its corners projected through the cameras' TRUE poses plus noise, the watcher
told the poses the cameras had at calibration). A bumped camera is declared moved within
seconds, set aside, re-calibrated to its new pose and let back in; cameras that are only noisy
and imperfectly calibrated never are. The accuracy of the poses meanwhile is measured on
realistic simulated sessions (benchmarks/camera_watch.py): this synthetic scene's filter tracking
is not representative of it."""

from __future__ import annotations

import concurrent.futures
import dataclasses
import json
import math
import threading
from types import SimpleNamespace

import numpy as np
import pytest
from scipy.spatial.transform import Rotation
from test_joint_and_filter import CAMS, INTR, LAYOUT, detections, look_at

from cubetrack.calib.recalibrate import JOINT_MAX_RATIO, WatchedFusion, block_spread, extrapolation_ratio
from cubetrack.core.geometry import make_T, rotation_angle, transform_points
from cubetrack.core.records import CameraWatchState, CubeSighting
from cubetrack.estimate.pose import estimate_cube
from cubetrack.fuse import camera_watch
from cubetrack.fuse.camera_watch import CameraState, CameraWatch, EventKind, WatchEvent, WatchParams, WatchSample
from cubetrack.fuse.fusion import FilterFusion
from cubetrack.sink.base import Outputs

FPS = 7.5
SPEED_M_S = 0.5
RADIUS_M = 0.6
CAMERAS = {**CAMS, "cam4": look_at([1.2, 2.0, 1.1])}
# the bump session's bump, seconds after its start: 10 s and one lap (a camera is judged once its settled pose spans
# settle_span_s, from the baseline check at 15 s here)
BUMP_S = 10.0 + 2 * math.pi * RADIUS_M / SPEED_M_S


def cube_at(t_s: float) -> np.ndarray:
    """The cube driving a circle at SPEED_M_S, heading along it."""
    a = SPEED_M_S * t_s / RADIUS_M
    return make_T(Rotation.from_euler("z", a + math.pi / 2).as_matrix(),
                  [RADIUS_M * math.cos(a), RADIUS_M * math.sin(a), 0.305])


def bumped(T_world_cam: np.ndarray, step_m: float, turn_deg: float, rng: np.random.Generator) -> np.ndarray:
    """The camera moved by ``step_m`` in a random direction and turned by ``turn_deg`` about a random axis."""
    direction, axis = rng.normal(size=3), rng.normal(size=3)
    R = Rotation.from_rotvec(math.radians(turn_deg) * axis / np.linalg.norm(axis)).as_matrix()
    return make_T(R @ T_world_cam[:3, :3], T_world_cam[:3, 3] + step_m * direction / np.linalg.norm(direction))


def sightings(duration_s: float, true_pose, believed: dict[str, np.ndarray], rng: np.random.Generator,
              noise_px: float = 0.3) -> list[CubeSighting]:
    """Every camera's sightings in capture order: FPS each, own phase; ``true_pose(camera, t)`` is
    where the camera really is, ``believed`` what the tracker was told."""
    out = []
    for i, camera in enumerate(believed):
        phase = i / (len(believed) * FPS)
        for seq in range(int(duration_s * FPS)):
            t = phase + seq / FPS
            dets = detections(cube_at(t), true_pose(camera, t), rng, noise_px=noise_px)
            if dets:
                estimate = estimate_cube(dets, LAYOUT, INTR, believed[camera], camera=camera, robot="bot", seq=seq,
                                         capture_time_s=t, arrival_time_s=t + 0.05)
                out.append(CubeSighting(camera, "bot", seq, t, t + 0.05, dets, estimate, believed[camera], INTR))
    return sorted(out, key=lambda s: s.capture_time_s)


def _offset(T_a: np.ndarray, T_b: np.ndarray) -> tuple[float, float]:
    return float(np.linalg.norm(T_a[:3, 3] - T_b[:3, 3])), rotation_angle(T_a[:3, :3], T_b[:3, :3], unit="deg")


@pytest.fixture(scope="module")
def bump_session():
    """Four cameras for 48 s; cam2 bumped by 2 cm / 1 deg at BUMP_S."""
    rng = np.random.default_rng(7)
    moved = bumped(CAMERAS["cam2"], 0.02, 1.0, rng)

    def true_pose(camera: str, t: float) -> np.ndarray:
        return moved if camera == "cam2" and t >= BUMP_S else CAMERAS[camera]

    return moved, sightings(48.0, true_pose, dict(CAMERAS), rng)


@pytest.mark.slow
def test_a_bumped_camera_is_declared_moved_within_seconds_and_no_other(bump_session):
    moved, seen = bump_session
    watch = CameraWatch({"bot": LAYOUT}, CAMERAS, WatchParams(enabled=True))
    events, suspect_at = [], {}
    held: dict[str, list[tuple[float, bool]]] = {c: [] for c in CAMERAS}
    for s in seen:
        if s.capture_time_s >= BUMP_S + 10.0:
            break
        events += watch.add(s)
        if BUMP_S - 2.0 <= s.capture_time_s < BUMP_S + 0.5:  # as WatchedFusion asks, with a perfect prediction
            held[s.camera].append((s.capture_time_s, watch.off_prediction(s, cube_at(s.capture_time_s))))
        for camera, state in watch.state.items():
            if state is CameraState.SUSPECT:
                suspect_at.setdefault(camera, s.capture_time_s)
    assert [(e.kind, e.camera) for e in events] == [(EventKind.MOVED, "cam2")]
    (event,) = events
    assert BUMP_S < event.time_s < BUMP_S + 3.0, event.time_s
    # suspect (out of the fusion) within a second of the bump, before it is declared; no other camera
    assert list(suspect_at) == ["cam2"] and BUMP_S < suspect_at["cam2"] < min(BUMP_S + 1.0, event.time_s), suspect_at
    # before any check: cam2's sightings after the bump are held off the fusion's prediction, no other
    assert [t for t, h in held["cam2"] if h] and all(t > BUMP_S for t, h in held["cam2"] if h), held["cam2"]
    assert not any(h for c in ("cam1", "cam3", "cam4") for _, h in held[c])
    assert watch.excluded("cam2") and not watch.excluded("cam1")
    assert watch.state["cam2"] is CameraState.RECALIBRATING
    # the window's refit already knows about where the camera went
    step, turn = _offset(event.T_world_cam, moved)
    assert step < 0.01 and turn < 0.3, (step, turn)
    assert watch.stats["checked"] > 100


@pytest.mark.slow
def test_the_fusion_keeps_the_moved_camera_out_then_takes_it_back_at_its_new_pose(bump_session):
    moved, seen = bump_session
    executor = ThreadExecutor()  # as live (cubetrack.app.watch_log): the refit on another thread
    fused = WatchedFusion(FilterFusion({"bot": LAYOUT}), {"bot": LAYOUT}, CAMERAS, WatchParams(enabled=True),
                          executor=executor)
    told: list[CameraWatchState] = []  # what the dashboard's tiles are told
    fused.state_listeners.append(told.append)
    used: list[tuple[float, tuple[str, ...]]] = []  # each pose's time and the cameras it used
    suspect_from = math.inf  # when cam2 first went out of the fusion as suspect
    for s in seen:
        used += [(pose.time_s, pose.cameras) for pose in fused.add(s, s.arrival_time_s)]
        if fused.watch.state["cam2"] is CameraState.SUSPECT:
            suspect_from = min(suspect_from, s.capture_time_s)
        if len(fused.events) == 2 and s.capture_time_s > fused.events[1].time_s + 6.0:
            break  # enough poses after the rejoin (the rest of the session only costs time)
        assert not fused._running or fused.watch.excluded("cam2")  # a refit's result waits for the next call
    assert executor.threads and set(executor.threads) == {"refit"}
    kinds = [(e.kind, e.camera) for e in fused.events]
    assert kinds == [(EventKind.MOVED, "cam2"), (EventKind.REJOINED, "cam2")], kinds
    moved_at, rejoined_at = fused.events[0].time_s, fused.events[1].time_s
    assert rejoined_at - BUMP_S < 30.0
    step, turn = _offset(fused.watch.T_world_cam["cam2"], moved)
    assert step < 0.005 and turn < 0.15
    # set aside from the moment it was declared moved, and back after rejoining
    assert BUMP_S < suspect_from < min(BUMP_S + 1.0, moved_at) and fused.stats["suspect sighting"] > 3
    aside = [cameras for t, cameras in used if suspect_from + 0.2 < t < rejoined_at]
    back = [cameras for t, cameras in used if t > rejoined_at + 0.2]
    assert len(aside) > 30 and not any("cam2" in c for c in aside)
    assert sum("cam2" in c for c in back) > 30
    away = sum(s.camera == "cam2" and moved_at < s.capture_time_s < rejoined_at for s in seen)
    assert away > 10 and fused.stats["set-aside sighting"] >= 0.9 * away  # each of its sightings while it was away
    # the tile: cam2 settles, is watched, goes suspect and moved, re-calibrates in tenths, rejoins
    # (and is watched again once it has a settled pose at its new place)
    cam2 = [(x.state, x.progress) for x in told if x.camera == "cam2"]
    states = [state for state, _ in cam2]
    assert states[:4] == ["settling", "watched", "suspect", "moved"], states
    rejoined = states.index("rejoined")
    assert states[rejoined + 1:] in ([], ["watched"]), states
    # only the rejoin carries a pose: the one the fusion uses from then on (what outputs publish)
    posed = [x for x in told if x.T_world_cam is not None]
    assert [(x.camera, x.state) for x in posed] == [("cam2", "rejoined")]
    np.testing.assert_array_equal(posed[0].T_world_cam, fused.watch.T_world_cam["cam2"])
    progress = [p for state, p in cam2 if state == "re-calibrating"]
    assert states[4:rejoined] == ["re-calibrating"] * len(progress) and len(progress) >= 5, cam2
    # it grows towards the corners needed; a refused try raises the need (by RETRY_GROWTH) and it drops once
    drops = sum(b < a for a, b in zip(progress, progress[1:], strict=False))
    assert drops <= fused.stats["re-calibration refused"] and 0.0 < progress[0] < 0.5, (progress, fused.stats)
    assert max(progress) == 1.0, (progress, fused.stats)
    assert {(x.camera, x.state) for x in told if x.camera != "cam2"} == {(c, s) for c in ("cam1", "cam3", "cam4")
                                                                          for s in ("settling", "watched")}
    moved_told = next(x for x in told if x.state == "moved")
    assert moved_told.time_s == moved_at and moved_told.message == fused.events[0].message.removeprefix("cam2 ")


@pytest.mark.slow
def test_noisy_imperfectly_calibrated_cameras_are_never_declared_moved():
    """Each camera's pose as calibration leaves it (as cubetrack calibrate does on the simulated
    arena: up to 10 mm and 0.2 deg off, docs/simulation.md), corners with 0.6 px noise, 40 s: no
    event, and a camera is rarely and briefly suspect (the ten-minute sessions are
    benchmarks/camera_watch.py --long's)."""
    rng = np.random.default_rng(11)
    believed = {c: bumped(T, 0.01, 0.2, rng) for c, T in CAMERAS.items()}
    seen = sightings(40.0, lambda camera, t: CAMERAS[camera], believed, rng, noise_px=0.6)
    watch = CameraWatch({"bot": LAYOUT}, believed, WatchParams(enabled=True))
    events = [e for s in seen for e in watch.add(s)]
    assert events == [] and watch.stats["suspect"] <= 2
    assert watch.stats["checked"] > 700 and watch.stats["checked while suspect"] < 0.01 * watch.stats["checked"]


def small_bump(after_s: float) -> tuple[float, list[CubeSighting]]:
    """cam2 moved 2 cm along its optical axis and turned 0.35 deg three laps in: the bump's time and
    the sightings until ``after_s`` after it."""
    bump_s = 10.0 + 3 * 2 * math.pi * RADIUS_M / SPEED_M_S
    T = CAMERAS["cam2"]
    turn = Rotation.from_rotvec(math.radians(0.35) * T[:3, 0]).as_matrix()
    moved = make_T(turn @ T[:3, :3], T[:3, 3] + 0.02 * T[:3, 2])
    return bump_s, sightings(bump_s + after_s, lambda c, t: moved if c == "cam2" and t >= bump_s else CAMERAS[c],
                             dict(CAMERAS), np.random.default_rng(7))


@pytest.mark.slow
@pytest.mark.parametrize("moved_sigmas", [4.0, 0.0])
def test_a_small_bump_is_declared_against_the_cameras_own_noise(moved_sigmas):
    """cam2 moved 2 cm along its optical axis and turned 0.35 deg three laps in (its settled windows
    then shift its corners by 0.04-0.08 px): its windows shift by 2.5-3.2 px, under moved_px (5)
    but far out of its own noise, so it is declared within 3 s (issue 27's seeds 151 and 97: such
    bumps were never declared); with moved_sigmas 0, by moved_px alone, it is not."""
    bump_s, seen = small_bump(4.0)
    watch = CameraWatch({"bot": LAYOUT}, CAMERAS, WatchParams(enabled=True, moved_sigmas=moved_sigmas))
    events = [(e.kind, e.camera, bump_s < e.time_s < bump_s + 3.0) for s in seen for e in watch.add(s)]
    assert events == ([(EventKind.MOVED, "cam2", True)] if moved_sigmas else []), events


@pytest.mark.slow
@pytest.mark.parametrize("long_window_s", [6.0, 0.0])
def test_a_small_bump_under_the_windows_threshold_is_declared_by_the_long_window(long_window_s):
    """The small bump above (its 2 s windows shift its corners by 2.5-3.2 px) with the window's floor
    raised to 4 px, as a noisy camera's own noise raises it (issue 27's held-out seed 443: 1.5-3.5 px
    under 3.9-5 px): the 2 s window never declares it; the long window, against its own noise, does,
    within its length and a few checks (without it, never)."""
    bump_s, seen = small_bump(9.0)
    params = WatchParams(enabled=True, moved_min_px=4.0, long_window_s=long_window_s)
    watch = CameraWatch({"bot": LAYOUT}, CAMERAS, params)
    events = [(e.kind, e.camera, bump_s < e.time_s < bump_s + 9.0) for s in seen for e in watch.add(s)]
    assert events == ([(EventKind.MOVED, "cam2", True)] if long_window_s else []), events
    assert (watch.stats["moved by the long window"] > 0) == bool(long_window_s)


def test_one_other_camera_missing_the_prediction_does_not_let_a_bumped_cameras_sighting_in():
    """The prediction gate compares a sighting's miss with the other cameras' latest misses by
    their median: cam4's own sighting missed the prediction by several px (issue 27's seed 151: a
    stale miss of another camera), and cam2's first sighting after a 1 deg turn, which misses by
    more but not four times cam4's, is still held. When every other camera misses as much (the
    prediction is off: a hard turn), it is not."""
    rng = np.random.default_rng(3)
    watch = CameraWatch({"bot": LAYOUT}, CAMERAS, WatchParams(enabled=True))
    watch.settled.update(CAMERAS)
    turned = bumped(CAMERAS["cam2"], 0.0, 1.0, rng)
    t, truth = 5.0, cube_at(5.0)
    off = make_T(np.eye(3), [0.03, 0.0, 0.0]) @ truth  # a prediction 3 cm off

    def held(camera: str, seq: int, predicted: np.ndarray, true_pose: np.ndarray | None = None) -> tuple[bool, float]:
        dets = detections(truth, CAMERAS[camera] if true_pose is None else true_pose, rng, noise_px=0.2)
        sighting = CubeSighting(camera, "bot", seq, t + 0.01 * seq, t + 0.05, dets, None, CAMERAS[camera], INTR)
        watch.add(sighting, predicted)
        return watch.off_prediction(sighting, predicted), watch._off_prediction["bot"][camera][1]

    assert not held("cam1", 1, truth)[0] and not held("cam3", 2, truth)[0]
    cam4_miss = held("cam4", 3, off)[1]
    is_held, cam2_miss = held("cam2", 4, truth, turned)
    assert 3.0 < cam2_miss < 4.0 * cam4_miss, (cam2_miss, cam4_miss)  # the largest other would let it in
    assert is_held
    for seq, camera in enumerate(("cam1", "cam3"), start=5):  # every other camera misses as much
        held(camera, seq, off)
    assert not held("cam2", 7, off, turned)[0]


@pytest.mark.parametrize("hold_ratio", [2.0, 0.0])
def test_a_held_cameras_later_sightings_stay_held_while_they_miss_as_much(hold_ratio):
    """``gate_hold_ratio``: once cam2's sighting after a 1 deg turn is held off the prediction, its
    next ones are held too while they miss it by more than ``gate_prediction_px`` and twice its own
    misses before the hold, though two other cameras now miss the prediction as well (a bumped
    camera's second sighting, fused, dragged the track: issue 27's seeds 58, 263, 419); for
    ``window_s`` at most, and a sighting within ends the hold. Without it (0) only the first is held."""
    rng = np.random.default_rng(5)
    watch = CameraWatch({"bot": LAYOUT}, CAMERAS, WatchParams(enabled=True, gate_hold_ratio=hold_ratio))
    watch.settled.update(CAMERAS)
    turned = bumped(CAMERAS["cam2"], 0.0, 1.0, rng)
    truth = cube_at(5.0)
    off = make_T(np.eye(3), [0.03, 0.0, 0.0]) @ truth  # a prediction 3 cm off
    seq = iter(range(1000))

    def held(camera: str, t: float, predicted: np.ndarray, true_pose: np.ndarray | None = None) -> bool:
        dets = detections(truth, CAMERAS[camera] if true_pose is None else true_pose, rng, noise_px=0.2)
        sighting = CubeSighting(camera, "bot", next(seq), t, t + 0.05, dets, None, CAMERAS[camera], INTR)
        watch.add(sighting, predicted)
        return watch.off_prediction(sighting, predicted)

    for k in range(4):  # every camera agrees with the prediction: each one's own misses are small
        assert not any(held(c, 5.0 + 0.1 * k + 0.01 * i, truth) for i, c in enumerate(CAMERAS))
    assert held("cam2", 5.5, truth, turned)  # the first after the turn: four times the others' misses
    assert not held("cam1", 5.51, off) and not held("cam4", 5.52, off)  # two others now miss as much
    assert held("cam2", 5.6, truth, turned) is (hold_ratio > 0)
    assert held("cam2", 5.7, truth, turned) is (hold_ratio > 0)
    assert not held("cam2", 5.8, truth) and not held("cam2", 5.9, truth, turned)  # one within ends the hold
    assert not any(held(c, 6.0 + 0.01 * i, truth) for i, c in enumerate(("cam1", "cam3", "cam4")))
    assert held("cam2", 6.1, truth, turned)  # held again, as first
    held("cam1", 6.11, off), held("cam4", 6.12, off)  # two others miss as much again
    assert held("cam2", 6.2, truth, turned) is (hold_ratio > 0)
    assert not held("cam2", 6.1 + watch.params.window_s + 0.05, truth, turned)  # a hold lasts window_s at most


@pytest.mark.parametrize("iterations", [camera_watch.FIT_ITERATIONS, 1])
def test_a_position_only_refit_keeps_the_orientation_and_finds_the_shift(monkeypatch, iterations):
    """A drift's follow fits its step as a position alone (``refit_camera(position_only=True)``): a
    camera shifted 3 mm sideways, started from where it was, is found within 0.3 mm of where it went
    with the orientation kept to the bit, by Gauss-Newton and, where that gives up (one step
    allowed), by the trust-region solver."""
    rng = np.random.default_rng(8)
    T_cam = CAMERAS["cam1"]
    X = np.column_stack([rng.uniform(-0.6, 0.6, 200), rng.uniform(-0.6, 0.6, 200), rng.uniform(0.2, 0.4, 200)])
    moved = T_cam.copy()
    moved[:3, 3] += 0.003 * T_cam[:3, 0]  # along the camera's x axis: a turn about its y axis looks alike
    in_cam = (X - moved[:3, 3]) @ moved[:3, :3]
    uv = in_cam[:, :2] / in_cam[:, 2:] + rng.normal(0, 0.3 / INTR.K[0, 0], (200, 2))
    monkeypatch.setattr(camera_watch, "FIT_ITERATIONS", iterations)
    fit = camera_watch.refit_camera(X, uv, INTR.K[0, 0], T_cam, position_only=True)
    assert fit is not None and fit.sigma_deg == 0.0 and 0.0 < fit.sigma_m < 0.002
    np.testing.assert_array_equal(fit.T_world_cam[:3, :3], T_cam[:3, :3])
    assert np.linalg.norm(fit.T_world_cam[:3, 3] - moved[:3, 3]) < 0.0003, fit.T_world_cam[:3, 3] - moved[:3, 3]


@pytest.mark.slow
def test_a_drifting_camera_is_followed_and_published_and_no_still_camera_is(tmp_path):
    """With ``follow_m`` set (off by default). A clamp slipping: cam3 drifts 6 mm/min along a random
    direction for 100 s; the four cameras are as calibration leaves them (1 cm / 0.2 deg off), 0.6 px
    corners. Every camera's settled pose moves (cam3 sits in the others' references), but only cam3
    is followed: its pose in use moves with its true motion (the calibration's offset kept), the
    others' stay as calibrated, nothing is declared moved, and moving cam3 in the others' references
    took their settled poses back towards their anchors. Each step is published as a rejoin is
    (cubetrack.app.watch_log): a ``followed`` event, the outputs told the new pose, a versioned
    extrinsics file."""
    from cubetrack.app.watch_log import EVENTS_FILE, FOLLOWED_METHOD, WatchLog
    from cubetrack.core.cameras import CameraExtrinsics
    from cubetrack.io.config import read_extrinsics

    rng = np.random.default_rng(23)
    believed = {c: bumped(T, 0.01, 0.2, rng) for c, T in CAMERAS.items()}
    direction = rng.normal(size=3)
    direction /= np.linalg.norm(direction)
    rate_m_s = 0.006 / 60.0

    def true_pose(camera: str, t: float) -> np.ndarray:
        T = CAMERAS[camera].copy()
        if camera == "cam3":
            T[:3, 3] += direction * rate_m_s * t
        return T

    seen = sightings(100.0, true_pose, believed, rng, noise_px=0.6)
    fused = WatchedFusion(FilterFusion({"bot": LAYOUT}), {"bot": LAYOUT}, believed,
                          WatchParams(enabled=True, follow_m=0.002))
    log_ = WatchLog(tmp_path, {c: CameraExtrinsics(T, method="marker") for c, T in believed.items()})
    fused.listeners.append(log_)
    told: list[CameraWatchState] = []  # what the outputs are told
    fused.state_listeners.append(told.append)
    watch = fused.watch
    behind_mm = []  # cam3's pose in use against its calibrated pose moved as it truly moved
    for s in seen:
        fused.add(s, s.arrival_time_s)
        followed = believed["cam3"][:3, 3] + true_pose("cam3", s.capture_time_s)[:3, 3] - CAMERAS["cam3"][:3, 3]
        behind_mm.append((s.capture_time_s, 1000 * float(np.linalg.norm(watch.T_world_cam["cam3"][:3, 3] - followed))))
    assert watch.follows and {f.camera for f in watch.follows} == {"cam3"}, watch.follows
    assert all(f.others_after_px < f.others_px for f in watch.follows), watch.follows
    for c in ("cam1", "cam2", "cam4"):
        np.testing.assert_array_equal(watch.T_world_cam[c], believed[c])
    # unfollowed it would be 10 mm behind at the end; followed, what it drifted before its anchor (its first
    # settled pose over a whole baseline, ~2 mm) and up to a follow step (follow_px: ~2-3 mm here) behind:
    # 4.6-5.3 mm here, the step fitted as a shift or as a shift and a turn, fed to the watcher or to the fusion
    end_s, end_mm = behind_mm[-1]
    assert end_mm < 0.6 * 1000 * rate_m_s * end_s, behind_mm[-1]
    assert all(b < 6.0 for t, b in behind_mm if t > watch.follows[0].time_s + 1.0), watch.follows
    assert watch.stats["drift followed"] == len(watch.follows)
    # a step is a shift: the orientation in use stays the calibrated one
    np.testing.assert_allclose(watch.T_world_cam["cam3"][:3, :3], believed["cam3"][:3, :3], atol=1e-12)
    # published: one event per step, no alarm; the outputs told each new pose; a versioned file each
    assert [(e.kind, e.camera) for e in watch.events] == [(EventKind.FOLLOWED, "cam3")] * len(watch.follows)
    posed = [x for x in told if x.T_world_cam is not None]
    assert [(x.camera, x.state) for x in posed] == [("cam3", "watched")] * len(watch.follows)
    for state, step in zip(posed, watch.follows, strict=True):
        np.testing.assert_array_equal(state.T_world_cam, step.T_world_cam)
    lines = [json.loads(x) for x in (tmp_path / EVENTS_FILE).read_text().splitlines()]
    assert [x["event"] for x in lines] == ["followed"] * len(watch.follows)
    last = read_extrinsics(tmp_path / lines[-1]["extrinsics"])
    assert last["cam3"].method == FOLLOWED_METHOD and last["cam1"].method == "marker"
    assert np.allclose(last["cam3"].T_world_cam, watch.T_world_cam["cam3"], atol=1e-6)
    assert all(line.startswith("cam3 drifting: followed ") for line in log_.lines), log_.lines


def test_with_one_other_camera_the_watcher_says_so_and_waits():
    rng = np.random.default_rng(3)
    two = {c: CAMERAS[c] for c in ("cam1", "cam2")}
    watch = CameraWatch({"bot": LAYOUT}, two, WatchParams(enabled=True))
    for s in sightings(5.0, lambda camera, t: two[camera], two, rng):
        assert watch.add(s) == []
    assert watch.stats["checked"] == 0 and watch.stats["too few other cameras"] > 30


def test_a_reference_takes_the_other_cameras_nearest_in_time_at_most_reference_cameras_max(monkeypatch):
    """With many cameras a check stays a small fit: of the three other cameras, the two whose
    sightings are nearest in time to the checked one, of each its REFERENCE_SIGHTINGS sightings
    nearest in time within the span."""
    from cubetrack.fuse import camera_watch

    rng = np.random.default_rng(5)
    fits = []
    original = camera_watch.solve_joint
    monkeypatch.setattr(camera_watch, "solve_joint",
                        lambda sets, T, t, *a, **k: fits.append((t, sets)) or original(sets, T, t, *a, **k))
    params = WatchParams(enabled=True, reference_cameras_max=2, reference_span_s=0.3)  # more than 2 in the span
    watch = CameraWatch({"bot": LAYOUT}, CAMERAS, params)
    seen = sightings(3.0, lambda camera, t: CAMERAS[camera], dict(CAMERAS), rng)
    for s in seen:
        watch.add(s)
    assert watch.stats["checked"] > 30 and len(fits) == watch.stats["checked"]
    for t, sets in fits:
        checked = next(s.camera for s in seen if s.capture_time_s == t)
        span = [s for s in seen if s.camera != checked and abs(s.capture_time_s - t) <= params.reference_span_s]
        gap = {c: min(abs(s.capture_time_s - t) for s in span if s.camera == c) for c in {s.camera for s in span}}
        used = {s.camera for s in sets}
        assert len(used) == 2 and max(gap[c] for c in used) <= min(g for c, g in gap.items() if c not in used)
        for camera in used:  # a set per sighting: the nearest ones in time
            mine = sorted(abs(s.capture_time_s - t) for s in span if s.camera == camera)
            gaps = sorted(abs(s.time_s - t) for s in sets if s.camera == camera)
            assert gaps == mine[:camera_watch.REFERENCE_SIGHTINGS]
    assert any(sum(s.camera == c for s in span) > camera_watch.REFERENCE_SIGHTINGS
               for t, _ in fits for c in CAMERAS
               for span in [[s for s in seen if abs(s.capture_time_s - t) <= params.reference_span_s]])


def test_checks_are_shared_by_the_cameras_within_checks_per_s(monkeypatch):
    """checks_per_s bounds the checks over all cameras (each camera checked in turn, less often
    with more cameras), and a sighting given the fused prediction is matched by it: a cube
    estimate (the dear part: a pose search per marker) only for the checked sightings' own corners."""
    from cubetrack.fuse import camera_watch

    estimated = []
    original = camera_watch.estimate_cube
    monkeypatch.setattr(camera_watch, "estimate_cube", lambda *a, **k: estimated.append(1) or original(*a, **k))
    rng = np.random.default_rng(9)
    seen = [dataclasses.replace(s, estimate=None)  # as the live camera workers send them
            for s in sightings(4.0, lambda camera, t: CAMERAS[camera], dict(CAMERAS), rng)]
    counts = {}
    for checks_per_s in (40.0, 8.0):
        estimated.clear()
        watch = CameraWatch({"bot": LAYOUT}, CAMERAS, WatchParams(enabled=True, checks_per_s=checks_per_s))
        for s in seen:
            watch.add(s, cube_at(s.capture_time_s))
            watch.off_prediction(s, cube_at(s.capture_time_s))  # every sighting, as WatchedFusion asks
        counts[checks_per_s] = watch.stats["checked"]
    # 4 cameras at FPS (7.5 < samples_per_s 8): every sighting; within 8 a second: each camera every 0.5 s
    assert counts[40.0] > 0.9 * len(seen) and 4.0 * 8.0 - 8 <= counts[8.0] <= 4.0 * 8.0 + 4, (counts, len(seen))
    assert counts[8.0] <= len(estimated) <= counts[8.0] + 8, (len(estimated), counts)  # (+ the pending ones)


def test_with_three_cameras_the_camera_that_moved_is_named_not_its_partners():
    """Three cameras, each calibrated up to 1 cm / 0.2 deg off, 0.6 px corners; cam1 turned by
    1.5 deg at 10 s. Both others' references then hold the moved camera, and a partner's window
    says moved more loudly than its own (this seed named cam3 before): the one named is the
    camera whose new pose makes the others' references agree with them again. The windows'
    choice alone (no suspect: which camera goes suspect first is still chosen by disagreement)."""
    seed = 0
    rng = np.random.default_rng(seed)
    three = {c: CAMS[c] for c in ("cam1", "cam2", "cam3")}
    victim = ("cam1", "cam2", "cam3")[seed % 3]
    moved = bumped(three[victim], 0.0, 1.5, rng)
    believed = {c: bumped(T, 0.01, 0.2, rng) for c, T in three.items()}
    seen = sightings(12.5, lambda c, t: moved if c == victim and t >= 10.0 else three[c], believed, rng,
                     noise_px=0.6)
    watch = CameraWatch({"bot": LAYOUT}, believed, WatchParams(enabled=True, suspect_px=1000.0))
    events = [e for s in seen for e in watch.add(s)]
    assert [(e.camera, 10.0 < e.time_s < 13.0) for e in events] == [(victim, True)], events


@pytest.mark.parametrize(("newer_px", "named"), [
    ({"cam1": 1.06, "cam2": 1.25}, "cam2"),  # a near tie (issue 27's seed 263): the references' rise decides
    ({"cam1": 0.57, "cam2": 1.93}, "cam1"),  # a clear newer-pose choice (seed 58) stands, whatever the rise
])
def test_with_three_cameras_a_near_tie_is_decided_by_whose_references_still_agree(monkeypatch, newer_px, named):
    """Three cameras, cam1's and cam2's windows say moved. Put at its window's newer pose, each makes the
    others' references agree about as well: then the camera whose own checks' references (the two others)
    agree as they did before the window is named, not the one whose references now disagree more."""
    three = {c: CAMERAS[c] for c in ("cam1", "cam2", "cam3")}
    watch = CameraWatch({"bot": LAYOUT}, three, WatchParams(enabled=True))
    now_s, p = 100.0, watch.params
    for camera, rise_px in (("cam1", 1.5), ("cam2", 0.0), ("cam3", 1.5)):  # cam2's references: cam1 and cam3
        for k in range(40):
            t = now_s - 10.0 + 0.25 * (k + 1)
            before = t < now_s - p.window_s
            watch._reference_rms[camera].append((t, 1.0 + 0.1 * (k % 3) + (0.0 if before else rise_px)))
    monkeypatch.setattr(watch, "_others_miss_px", lambda camera, T, now: newer_px[camera])
    monkeypatch.setattr(watch, "_newer_pose", lambda camera, verdict, now: verdict.fit.T_world_cam)
    fit = camera_watch.CameraFit(CAMERAS["cam1"], 0.0, 0.0, 0.0, 8)
    verdicts = {c: camera_watch.Verdict(fit, 9.0, 0.02, 1.0, c != "cam3") for c in three}
    assert watch._references_rise_px("cam1", now_s) == pytest.approx(1.5)
    assert watch._references_rise_px("cam2", now_s) == pytest.approx(0.0)
    found = watch._culprit(verdicts, now_s)
    assert found is not None and found[0] == named


def _missing(camera: str, time_s: float, miss_px: float) -> WatchSample:
    """A checked sighting of ``camera`` whose corners all miss by ``miss_px`` at its pose in CAMERAS."""
    points = np.array([[0.1 * i, 0.05 * i, 0.2] for i in range(8)])
    in_cam = (points - CAMERAS[camera][:3, 3]) @ CAMERAS[camera][:3, :3]
    normalized = in_cam[:, :2] / in_cam[:, 2:] + miss_px / (math.sqrt(2.0) * INTR.K[0, 0])
    return WatchSample(camera, time_s, points, normalized, np.full(8, INTR.K[0, 0]))


@pytest.mark.parametrize(("fused", "suspect"), [
    # issue 27's seed 31 (3 cameras, cam2 bumped): cam1's checks miss more than cam2's (cam2 spoils cam1's
    # reference); the fused prediction, made before the bump, is missed by cam2 alone
    ({"cam1": 2.7, "cam2": 15.5, "cam3": 1.1}, "cam2"),
    ({}, "cam1"),  # no fused prediction (no track): the checks' misses decide
])
def test_the_camera_made_suspect_is_the_one_that_misses_most_now(fused, suspect):
    """Three cameras: cam1's two checks miss by 10.3 and 15.5 px, cam2's by 14.0 px each, cam3's by
    5.7 px. Only the camera that misses most now is made suspect: by the fused prediction where
    there is one (as CameraWatch.off_prediction leaves it), else by the checks."""
    three = {c: CAMERAS[c] for c in ("cam1", "cam2", "cam3")}
    watch = CameraWatch({"bot": LAYOUT}, three, WatchParams(enabled=True))
    watch.settled.update(three)
    t0 = 100.0
    watch._off_prediction["bot"].update({c: (t0 + 0.1, m) for c, m in fused.items()})
    for camera, time_s, miss_px in [("cam3", 0.0, 5.7), ("cam1", 0.0, 10.3), ("cam2", 0.05, 14.0),
                                    ("cam3", 0.13, 5.7), ("cam1", 0.14, 15.5), ("cam2", 0.18, 14.0)]:
        sample = _missing(camera, t0 + time_s, miss_px)
        residual = camera_watch.residuals_px(three[camera], sample.points_world_m, sample.normalized, sample.focal_px)
        assert np.median(np.linalg.norm(residual, axis=1)) == pytest.approx(miss_px)
        watch._judge(sample, "bot")
    assert [c for c, s in watch.state.items() if s is CameraState.SUSPECT] == [suspect], watch.state


@pytest.mark.parametrize("cameras", [3, 4])
def test_a_suspect_camera_serves_in_the_references_only_where_it_would_leave_the_others_unchecked(cameras):
    """With three cameras a suspect one stays in the others' references (set aside, each check of
    the other two would lack a second reference camera, and only the suspect's own window, against
    references holding whichever camera really moved, would be judged: issue 27's seed 58 named
    the wrong camera so), and a suspect whose window says moved is not declared for that alone;
    with four or more it is no one's reference. Out of the fusion either way; re-calibrating:
    no one's reference."""
    some = {c: CAMERAS[c] for c in list(CAMERAS)[:cameras]}
    watch = CameraWatch({"bot": LAYOUT}, some, WatchParams(enabled=True))
    watch.state["cam1"], watch.state["cam2"] = CameraState.SUSPECT, CameraState.RECALIBRATING
    assert watch.excluded("cam1") and watch.referee("cam1") is (cameras == 3)
    assert not watch.referee("cam2") and watch.referee("cam3")
    fit = camera_watch.CameraFit(CAMERAS["cam1"], 0.0, 0.0, 0.0, 8)
    verdicts = {c: camera_watch.Verdict(fit, 9.0, 0.02, 1.0, c == "cam1") for c in ("cam1", "cam3")}
    watch._disagreement["cam3"].append((0.0, 1.0))  # cam3 disagreed most: only the suspect shortcut names cam1
    named = watch._culprit(verdicts, 0.0)
    assert (named is not None and named[0] == "cam1") is (cameras > 3)


def test_several_suspect_cameras_stay_in_the_references_and_none_is_declared_for_being_suspect():
    """Four cameras: one suspect camera is no one's reference, but two suspect at once both serve in the
    others' references again (set aside together, they left two-camera references that every other camera
    missed, and still cameras were declared moved: seed 67, docs/calibration.md "Session 28"); both stay
    out of the fusion, and a suspect's window saying moved no longer names it on its own."""
    watch = CameraWatch({"bot": LAYOUT}, CAMERAS, WatchParams(enabled=True))
    watch.state["cam1"] = CameraState.SUSPECT
    assert not watch.referee("cam1") and watch.referee("cam2")
    watch.state["cam2"] = CameraState.SUSPECT
    assert watch.referee("cam1") and watch.referee("cam2") and watch.excluded("cam1") and watch.excluded("cam2")
    fit = camera_watch.CameraFit(CAMERAS["cam1"], 0.0, 0.0, 0.0, 8)
    verdicts = {c: camera_watch.Verdict(fit, 9.0, 0.02, 1.0, c == "cam1") for c in ("cam1", "cam3")}
    watch._disagreement["cam3"].append((0.0, 1.0))  # cam3 disagreed most: only the suspect shortcut names cam1
    assert watch._culprit(verdicts, 0.0) is None
    watch.state["cam2"] = CameraState.WATCHED
    named = watch._culprit(verdicts, 0.0)
    assert named is not None and named[0] == "cam1"


def test_a_second_camera_declared_moved_is_taken_out_of_the_first_ones_gathered_samples():
    """Two of five bumped 10 s apart (issue 27): cam2 re-calibrating since 22 s when cam4 is declared
    at 32 s. cam2 keeps what it gathered (every sample was dropped before: cam2 started over, 43 s to
    rejoin on seed 31's scene) with cam4 taken out of each sample's reference, but a sample left with
    one other camera; the watched cameras' windows restart; cam4 starts from its window's newer half."""
    watch = CameraWatch({"bot": LAYOUT}, CAMERAS, WatchParams(enabled=True))
    watch.settled.update(CAMERAS)
    watch.state["cam2"] = CameraState.RECALIBRATING

    def sample(camera: str, time_s: float, references: tuple[str, ...]) -> WatchSample:
        return dataclasses.replace(_missing(camera, time_s, 0.0),
                                   reference_sets=tuple(SimpleNamespace(camera=c) for c in references))

    held = {0.0: ("cam1", "cam3"), 0.25: ("cam1", "cam4", "cam4", "cam3"), 0.5: ("cam4", "cam3"), 0.75: ("cam4",)}
    times = np.arange(22.0, 32.0, 0.25)
    for t in times:
        watch.samples["cam2"].append(sample("cam2", t, held[t % 1.0]))
        for camera in ("cam1", "cam3", "cam4"):
            watch.samples[camera].append(sample(camera, t, ("cam1", "cam3", "cam4")))
    verdict = camera_watch.Verdict(camera_watch.CameraFit(CAMERAS["cam4"], 0.0, 0.0, 0.0, 8), 9.0, 0.02, 1.0, True)
    event = watch._declare("cam4", verdict, 32.0)
    assert (event.kind, event.camera, watch.state["cam4"]) == (EventKind.MOVED, "cam4", CameraState.RECALIBRATING)
    kept = [(s.time_s, tuple(r.camera for r in s.reference_sets)) for s in watch.samples["cam2"]]
    assert kept == [(t, ("cam1", "cam3")) for t in times if t % 1.0 in (0.0, 0.25)]
    assert not watch.samples["cam1"] and not watch.samples["cam3"]
    assert [s.time_s for s in watch.samples["cam4"]] == [t for t in times if t >= 31.0]


def test_the_joint_fits_extrapolation_takes_only_a_shrinking_step_along_the_last():
    """The re-calibration's rounds are extrapolated (Aitken) only where they contract: a step shorter
    than the last and along it. A growing step extrapolated 5x each round ran away (two of five,
    synthetic: cam2 4.8 m / 148 deg off after 13 rounds, never rejoined, and cam1 declared moved)."""
    last = np.array([2e-3, -1e-3, 0.0, 1e-4, 0.0, 2e-4])
    assert extrapolation_ratio(0.5 * last, last) == pytest.approx(0.5)
    assert extrapolation_ratio(0.95 * last, last) == JOINT_MAX_RATIO
    assert extrapolation_ratio(1.5 * last, last) == 0.0  # growing: the plain step
    turned = 0.5 * np.array([1e-3, 2e-3, 0.0, 0.0, 1e-4, 0.0])  # shorter, but at right angles
    assert abs(turned @ last) < 1e-12 and extrapolation_ratio(turned, last) == 0.0
    assert extrapolation_ratio(last, np.zeros(6)) == 0.0  # the first round


@pytest.mark.parametrize("seed", [0, 3])
def test_a_recalibrations_spread_is_what_its_sightings_leave_open_not_the_corner_noise(seed):
    """A re-calibration rejoins when its sightings pin its pose (``block_spread``: its fits leaving out
    each of 8 blocks of them in time, in turn), not only by the fit's own covariance, which takes every
    corner's error as independent. 80 sightings of cam2 (8 corners each, 0.3 px of corner noise): with
    independent noise alone the two agree; with each sighting's reference cube also off by its own few
    millimetres (shared by its 8 corners, as the other cameras' cube pose is) the covariance still says
    0.7 mm while the pose is several millimetres off, and the spread says so. With 2 blocks the spread
    is half the distance between the fits of the older and the newer half (the test it replaces)."""
    rng = np.random.default_rng(seed)
    T_cam, focal = CAMERAS["cam2"], INTR.K[0, 0]
    corners = np.array([[x, y, z] for x in (-0.05, 0.05) for y in (-0.05, 0.05) for z in (-0.05, 0.05)])

    def gathered(shared_m: float) -> list[WatchSample]:
        out = []
        for k in range(80):
            points = transform_points(cube_at(0.15 * k), corners)
            in_cam = (points - T_cam[:3, 3]) @ T_cam[:3, :3]
            normalized = in_cam[:, :2] / in_cam[:, 2:] + rng.normal(0.0, 0.3 / focal, (8, 2))
            out.append(WatchSample("cam2", 0.15 * k, points + rng.normal(0.0, shared_m, 3), normalized,
                                   np.full(8, focal)))
        return out

    for shared_m in (0.0, 0.005):
        samples = gathered(shared_m)
        fit = camera_watch.refit_camera(*camera_watch.stacked(samples), T_cam)
        assert fit is not None
        spread = block_spread(samples, fit.T_world_cam, 0.5)
        assert spread is not None
        error_m, _ = _offset(fit.T_world_cam, T_cam)
        if shared_m == 0.0:
            assert 0.5 * fit.sigma_m < spread[0] < 2.0 * fit.sigma_m and error_m < 2.0 * fit.sigma_m
        else:
            assert fit.sigma_m < 0.001 and spread[0] > 4.0 * fit.sigma_m and error_m < 3.0 * spread[0]
            assert error_m > 2.0 * fit.sigma_m, "the covariance alone would have passed a pose this far off"
    half = len(samples) // 2
    older, newer = (camera_watch.refit_camera(*camera_watch.stacked(part), fit.T_world_cam)
                    for part in (samples[:half], samples[half:]))
    assert older is not None and newer is not None
    apart_m, apart_deg = older.offset_from(newer.T_world_cam)
    two = block_spread(samples, fit.T_world_cam, 0.5, blocks=2)
    assert two is not None
    assert two[0] == pytest.approx(apart_m / 2, rel=1e-6) and two[1] == pytest.approx(apart_deg / 2, rel=0.01)
    assert block_spread(samples[:7], fit.T_world_cam, 0.5) is None  # fewer sightings than blocks


@pytest.mark.parametrize(("changes", "message"), [
    ({"moved_px": 0.0}, "moved_px"),
    ({"reference_cameras": 0}, "reference_cameras"),
    ({"window_s": 40.0}, "window_s"),
    ({"reference_cameras_max": 1}, "reference_cameras_max"),
    ({"follow_m": -0.001}, "follow_m"),
    ({"follow_px": 0.0}, "follow_px"),
    ({"gate_hold_ratio": -1.0}, "gate_hold_ratio"),
])
def test_bad_watch_settings_are_refused_with_a_clear_message(changes, message):
    from cubetrack.core.errors import ParamsError

    with pytest.raises(ParamsError, match=message):
        WatchParams(**changes)


def test_the_tracker_watches_only_when_enabled():
    import dataclasses

    from cubetrack.app.tracker import StageParams, Tracker
    from cubetrack.core.cameras import CameraExtrinsics, WorldConfig
    from cubetrack.io.config import RobotConfig

    robots = (RobotConfig("bot", LAYOUT),)
    extrinsics = {c: CameraExtrinsics(T) for c, T in CAMERAS.items()}
    intrinsics = dict.fromkeys(CAMERAS, INTR)
    world = WorldConfig("DICT_4X4_50", 0, 0.25)
    off = Tracker(intrinsics, world, robots, extrinsics, StageParams())
    on = Tracker(intrinsics, world, robots, extrinsics,
                 dataclasses.replace(StageParams(), camera_watch=WatchParams(enabled=True)))
    assert isinstance(on.fusion, WatchedFusion) and isinstance(on.fusion.fusion, FilterFusion)
    assert isinstance(off.fusion, FilterFusion)




class ThreadExecutor(concurrent.futures.Executor):
    """Runs each job on a thread of its own, to its end before returning the future (so the test
    is deterministic), and notes the threads' names and whether the caller had been told."""

    def __init__(self) -> None:
        self.threads: list[str] = []

    def submit(self, fn, /, *args, **kwargs):  # type: ignore[override]
        future: concurrent.futures.Future = concurrent.futures.Future()

        def run() -> None:
            self.threads.append(threading.current_thread().name)
            future.set_result(fn(*args))

        worker = threading.Thread(target=run, name="refit")
        worker.start()
        worker.join(timeout=60.0)
        return future


def _events(moved: np.ndarray) -> list[WatchEvent]:
    return [WatchEvent(EventKind.MOVED, "cam3", 1.75e9 + 3.0, 0.021, 0.9, moved),
            WatchEvent(EventKind.REJOINED, "cam3", 1.75e9 + 30.0, 0.02, 1.0, moved, 212)]


@pytest.mark.parametrize("update", [False, True])
def test_a_session_keeps_what_was_learnt(tmp_path, update):
    """cubetrack.app.watch_log: the events reach camera_watch.jsonl, the status lines and run.json's
    entry; the new pose goes to a versioned extrinsics file beside the session, and over the
    user's file only with --update-extrinsics."""
    from cubetrack.app.watch_log import EVENTS_FILE, RECALIBRATED_METHOD, WatchLog, attach_watch_log
    from cubetrack.core.cameras import CameraExtrinsics
    from cubetrack.io.config import read_extrinsics, write_extrinsics

    user_file = tmp_path / "extrinsics.toml"
    write_extrinsics({c: CameraExtrinsics(T, method="marker") for c, T in CAMERAS.items()}, user_file)
    before = user_file.read_bytes()
    new = bumped(CAMERAS["cam3"], 0.02, 1.0, np.random.default_rng(1))
    log_ = WatchLog(tmp_path / "out", read_extrinsics(user_file), update_path=user_file if update else None)
    for event in _events(new):
        log_(event)
    assert log_.lines == ["cam3 moved 2.1 cm / 0.9 deg at 15:06:43; set aside, re-calibrating",
                          "cam3 moved 2.0 cm / 1.0 deg at 15:06:43, re-calibrated from 212 sightings"]
    lines = [json.loads(x) for x in (tmp_path / "out" / EVENTS_FILE).read_text().splitlines()]
    assert [(x["event"], x["camera"], x["sightings"]) for x in lines] == [("moved", "cam3", 0),
                                                                          ("rejoined", "cam3", 212)]
    assert lines[1]["extrinsics"] == "extrinsics.watch-1.toml" and log_.summary() == {"camera_watch": lines}
    written = read_extrinsics(tmp_path / "out" / "extrinsics.watch-1.toml")
    assert np.allclose(written["cam3"].T_world_cam, new, atol=1e-6) and written["cam3"].method == RECALIBRATED_METHOD
    assert np.allclose(written["cam1"].T_world_cam, CAMERAS["cam1"], atol=1e-6)
    if update:
        assert np.allclose(read_extrinsics(user_file)["cam3"].T_world_cam, new, atol=1e-6)
    else:
        assert user_file.read_bytes() == before
    # only a watched fusion gets one
    assert attach_watch_log(SimpleNamespace(fusion=FilterFusion({"bot": LAYOUT})), Outputs([]), tmp_path, None) is None
