"""The Tracker, the workflow layer over the stages: rendered frames of a static scene in, poses out.

Three calibrated cameras see the world marker and two robots: "red" carries the paper's cube (one
id on five faces), "blue" a cube with a distinct id per face. Frames come at 7.5 fps per camera,
staggered, arriving 50 ms after capture; the cameras' clocks run 1000 s behind the host's. A spy
between the tracker and its detector records what each frame was searched for (the whole image,
or the regions the fusion's predictions gave).
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest
from scenes import Camera, cube_solid, look_at, marker_on_paper
from scipy.spatial.transform import Rotation

from cubetrack.app.tracker import CameraPoseSource, StageParams, Tracker, TrackParams
from cubetrack.core.cameras import CameraExtrinsics, CameraIntrinsics, ClockSample, WorldConfig
from cubetrack.core.errors import ConfigError
from cubetrack.core.geometry import make_T, rotation_angle
from cubetrack.core.layout import paper_cube_layout
from cubetrack.core.records import Frame
from cubetrack.fuse.fusion import FusionMethod, FusionParams
from cubetrack.io.config import RobotConfig
from cubetrack.simulate.render import project_points

K = np.array([[600.0, 0.0, 319.5], [0.0, 600.0, 239.5], [0.0, 0.0, 1.0]])
INTR = CameraIntrinsics(640, 480, K, np.zeros(5))
WORLD = WorldConfig("DICT_4X4_50", 0, 0.25)
CUBE_M = 0.11
RED = RobotConfig("red", paper_cube_layout(cube_size_m=CUBE_M, marker_id=1), Path("red.toml"))
BLUE = RobotConfig("blue", paper_cube_layout(cube_size_m=CUBE_M, marker_id=10, distinct_ids=True), Path("blue.toml"))
TRUTH = {"red": make_T(Rotation.from_euler("z", 20, degrees=True).as_matrix(), [0.25, 0.15, 0.2]),
         "blue": make_T(Rotation.from_euler("z", -35, degrees=True).as_matrix(), [-0.25, -0.2, 0.2])}
T_WORLD_CAM = {"cam1": look_at([1.5, -0.4, 1.0], [0.0, 0.0, 0.1]),
               "cam2": look_at([-0.6, 1.5, 1.1], [0.0, 0.0, 0.1]),
               "cam3": look_at([-1.5, 0.3, 1.2], [0.0, 0.0, 0.1])}
EXTRINSICS = {name: CameraExtrinsics(T) for name, T in T_WORLD_CAM.items()}
INTRINSICS = {name: INTR for name in T_WORLD_CAM}
FPS = 7.5
LATENCY_S = 0.05
CLOCK_OFFSET_S = 1000.0  # host = device + this
START_S = 5000.0


@pytest.fixture(scope="module")
def scenes() -> dict[str, dict[str, bytes]]:
    """One JPEG per camera of each scene: "both" robots, "red" alone, "no_world" (both robots,
    no world marker), "empty" (the world marker alone)."""
    world = marker_on_paper(np.eye(4), WORLD.dictionary, WORLD.marker_id, WORLD.marker_size_m, 0.03)
    red = cube_solid(RED.layout, CUBE_M, TRUTH["red"])
    blue = cube_solid(BLUE.layout, CUBE_M, TRUTH["blue"])
    solids = {"both": [world, red, blue], "red": [world, red], "no_world": [red, blue], "empty": [world]}
    rng = np.random.default_rng(0)
    return {scene: {cam: Camera(INTR, T, parts, supersample=1).jpeg(90, noise_std=1.0, rng=rng)
                    for cam, T in T_WORLD_CAM.items()}
            for scene, parts in solids.items()}


def stream(jpegs: dict[str, bytes], first: int, count: int) -> list[Frame]:
    """Frames ``first .. first + count - 1`` of every camera, in arrival order."""
    names = sorted(jpegs)
    out = []
    for j in range(first, first + count):
        for cam in names:
            t = capture_time(cam, j)
            out.append(Frame(cam, j, t - CLOCK_OFFSET_S, t + LATENCY_S, jpegs[cam]))
    return out


def capture_time(camera: str, seq: int) -> float:
    return START_S + seq / FPS + sorted(T_WORLD_CAM).index(camera) / (FPS * len(T_WORLD_CAM))


class DetectorSpy:
    """Stands in for the tracker's detector: records each call's regions (None = whole image)."""

    def __init__(self, detector):
        self.detector = detector
        self.calls: list[list | None] = []
        self.predicted: list[tuple[int, bool]] = []  # per call: markers predicted, found at their predictions

    def find(self, gray, regions=None, lens=None, predicted=()):
        self.calls.append(None if regions is None else list(regions))
        found = self.detector.find(gray, regions, lens, predicted)
        self.predicted.append((len(predicted), found.predicted))
        return found


def corners_m(robot: str) -> np.ndarray:
    """The corners of ``robot``'s cube's markers, (M x 4, 3) in the cube's frame."""
    return {"red": RED, "blue": BLUE}[robot].layout.corners_m.reshape(-1, 3)


def tracker(params: StageParams, robots=(RED, BLUE), extrinsics=EXTRINSICS, **kw) -> Tracker:
    t = Tracker(INTRINSICS, WORLD, robots, extrinsics, params, **kw)
    t.processor.detector = DetectorSpy(t.processor.detector)
    return t


def run(t: Tracker, frames: list[Frame]) -> list[tuple[Frame, list, list]]:
    """Each frame with the detector calls it made and the poses it produced."""
    out = []
    for frame in frames:
        before = len(t.processor.detector.calls)
        poses = t.process(frame)
        out.append((frame, t.processor.detector.calls[before:], poses))
    return out


def kind(calls: list) -> str:
    """'R' regions only, 'F' whole frame only, 'RF' regions that found nothing then the whole frame."""
    return "".join("F" if c is None else "R" for c in calls)


MEAN = StageParams(fusion=FusionParams(method=FusionMethod.MEAN))
FILTER = StageParams(track=TrackParams(full_frame_every=4))


def assert_near_truth(pose, cm: float = 1.0, deg: float = 1.0) -> None:
    T = TRUTH[pose.robot]
    assert np.linalg.norm(pose.position_m - T[:3, 3]) < cm / 100.0, pose
    R = Rotation.from_quat(pose.quaternion_xyzw).as_matrix()
    assert rotation_angle(R, T[:3, :3], "deg") < deg, pose


# --------------------------------------------------------------------------- the camera clock


def test_frames_of_a_polled_camera_wait_for_its_clock(scenes):
    t = tracker(MEAN, synced_cameras=frozenset({"cam1"}))
    frames = [f for f in stream(scenes["both"], 0, 34) if f.camera in ("cam1", "cam2")]
    for frame, _calls, poses in run(t, frames):
        if frame.camera == "cam1":
            assert poses == []                      # held: its capture time is not known yet
        else:
            assert {p.robot for p in poses} == {"red", "blue"}   # cam2 is not polled: stamped at once
    assert t.stats.frames_before_clock_sync == 2   # 34 held, the oldest 2 given up
    held = len(t.processor.detector.calls)
    # a round trip too slow to bound the offset releases nothing
    slow = capture_time("cam1", 40)
    assert t.add_clock_sample("cam1", ClockSample(slow, slow + 0.1 - CLOCK_OFFSET_S, slow + 0.2)) == []
    # a fast one does: the 32 newest held frames, stamped with their true capture times
    send = capture_time("cam1", 40)
    released = t.add_clock_sample("cam1", ClockSample(send, send + 0.004 - CLOCK_OFFSET_S, send + 0.008))
    assert len(t.processor.detector.calls) - held == 32
    expected = {round(capture_time("cam1", j), 9) for j in range(2, 34)}
    assert {round(p.time_s, 9) for p in released} == expected
    assert {p.robot for p in released} == {"red", "blue"}
    for p in released:
        assert_near_truth(p, cm=2.0, deg=2.0)
    # from now on its frames are processed as they come
    (frame,) = [f for f in stream(scenes["both"], 34, 1) if f.camera == "cam1"]
    poses = t.process(frame)
    assert poses and all(abs(p.time_s - capture_time("cam1", 34)) < 1e-9 for p in poses)
    assert t.add_clock_sample("nope", ClockSample(send, send, send)) == []


# --------------------------------------------------------------------------- bad frames


def test_corrupt_frames_are_counted_and_skipped(scenes):
    t = tracker(MEAN)
    good = [f for f in stream(scenes["both"], 0, 2) if f.camera == "cam1"]
    jpeg = good[0].jpeg
    bad = [dataclasses.replace(good[0], seq=100 + i, jpeg=data)
           for i, data in enumerate((jpeg[: len(jpeg) // 2], b"\xff\xd8junk\xff\xd9", b""))]
    assert t.process(good[0])
    for frame in bad:
        assert t.process(frame) == []
    assert t.process(good[1])                       # nothing lost: the next good frame still tracks
    assert (t.stats.frames, t.stats.corrupt_frames) == (5, 3)
    assert len(t.processor.detector.calls) == 2               # corrupt frames never reach detection


# --------------------------------------------------------------------------- camera poses


def test_camera_poses_from_each_frames_world_marker(scenes):
    params = dataclasses.replace(MEAN, track=TrackParams(camera_poses=CameraPoseSource.WORLD_MARKER))
    t = tracker(params, extrinsics=None)
    results = run(t, stream(scenes["both"], 0, 3))
    poses = [p for _f, _c, ps in results for p in ps]
    assert {p.robot for p in poses} == {"red", "blue"}
    for p in poses:
        assert_near_truth(p, cm=2.0, deg=2.0)
    # a frame without the world marker has no camera pose: counted, no estimate made
    estimates = sum(t.stats.estimates.values())
    assert all(ps == [] for _f, _c, ps in run(t, stream(scenes["no_world"], 3, 2)))
    assert t.stats.frames_without_camera_pose == 6
    assert sum(t.stats.estimates.values()) == estimates
    with pytest.raises(ConfigError, match="no extrinsics for camera.*cam3"):
        Tracker(INTRINSICS, WORLD, (RED,), {c: EXTRINSICS[c] for c in ("cam1", "cam2")}, MEAN)


# --------------------------------------------------------------------------- regions of interest


def test_regions_while_every_robot_is_tracked_and_a_whole_frame_every_n(scenes):
    t = tracker(FILTER)
    results = run(t, stream(scenes["both"], 0, 24))
    by_camera = {cam: [kind(c) for f, c, _p in results if f.camera == cam] for cam in T_WORLD_CAM}
    for cam, kinds in by_camera.items():
        assert kinds[0] == "F", cam                 # nothing tracked yet: the whole image
        assert "RRRF" in "".join(kinds), cam        # tracked: regions, with a whole frame every 4th
        assert "RRRR" not in "".join(kinds), cam
    assert t.stats.region_detections == sum(k.count("R") for k in by_camera.values())
    # each region search came with the predicted cubes' markers, and found them there (no OpenCV search)
    searches = [p for c, p in zip(t.processor.detector.calls, t.processor.detector.predicted, strict=True) if c]
    assert searches and all(n > 0 for n, _ in searches) and all(found for _, found in searches), searches
    # every region search covered both predicted cubes, where the cubes really are
    for frame, calls, _poses in results:
        for boxes in (c for c in calls if c is not None):
            assert len(boxes) == 2
            for robot in ("red", "blue"):
                px = project_points(INTR, T_WORLD_CAM[frame.camera],
                                    (TRUTH[robot][:3, :3] @ corners_m(robot).T).T + TRUTH[robot][:3, 3])
                assert any(np.all((px >= (x0, y0)) & (px < (x1, y1))) for x0, y0, x1, y1 in boxes), (frame, robot)
    poses = [p for _f, _c, ps in results for p in ps]
    assert {p.robot for p in poses} == {"red", "blue"}
    for p in poses[-6:]:
        assert_near_truth(p)
    # the cubes vanish: regions find nothing and the same frame is searched whole
    gone = run(t, stream(scenes["empty"], 24, 3))
    kinds = [kind(c) for _f, c, _p in gone]
    assert "RF" in kinds and "R" not in kinds


def test_a_job_with_deferred_views_is_searched_where_a_planned_one_is(scenes):
    """With ``defer_views`` (a replay's worker processes) a job carries each robot's predicted pose in
    the camera instead of the regions; the per-frame work, given the job through its plain values as
    a worker process is, projects them into the same regions and predicted markers, and the poses are
    the same to the bit."""
    import pickle

    from cubetrack.core.records import FrameJob

    eager, deferred = tracker(FILTER), tracker(FILTER, defer_views=True)
    poses = {"eager": [], "deferred": []}
    for frame in stream(scenes["both"], 0, 16):
        planned, carried = eager.admit(frame), deferred.admit(frame)
        assert carried.regions is None and carried.predicted == ()
        assert (carried.views is None) == (planned.regions is None)
        sent = FrameJob.from_plain(pickle.loads(pickle.dumps(carried.plain())))
        for name, t, job in (("eager", eager, planned), ("deferred", deferred, sent)):
            poses[name] += [(p.robot, p.position_m.tobytes(), p.quaternion_xyzw.tobytes())
                            for p in t.fuse(t.processor.work(job), frame.host_time_s)]
    spies = eager.processor.detector, deferred.processor.detector
    assert spies[0].calls == spies[1].calls and spies[0].predicted == spies[1].predicted
    assert sum(c is not None for c in spies[0].calls) > 20  # region searches, with predicted markers
    assert len(poses["eager"]) > 20 and poses["eager"] == poses["deferred"]


def test_a_frame_whose_regions_are_empty_is_neither_decoded_nor_searched(scenes, monkeypatch):
    """Every robot predicted out of a camera's view gives that frame no regions: nothing to search,
    so its JPEG is not even decoded (issue 31); the others are, and tracking goes on."""
    import cubetrack.app.tracker as tracker_module
    from cubetrack.core.records import FrameJob, FrameOutcome

    t = tracker(FILTER)
    decoded: list[int] = []
    real_decode = tracker_module.decode_gray
    monkeypatch.setattr(tracker_module, "decode_gray", lambda jpeg, *a, **kw: decoded.append(1) or real_decode(
        jpeg, *a, **kw))
    frame = stream(scenes["both"], 0, 1)[0]
    result = t.processor.work(FrameJob(frame, capture_time(frame.camera, 0), (), frozenset()))
    assert (result.outcome, result.sightings, decoded, t.processor.detector.calls) == (FrameOutcome.REGIONS, (),
                                                                                      [], [])
    broken = dataclasses.replace(frame, jpeg=b"\xff\xd8junk\xff\xd9")  # not decoded, so not found corrupt
    assert t.processor.work(FrameJob(broken, capture_time(frame.camera, 0), (), frozenset())).outcome \
        is FrameOutcome.REGIONS
    whole = t.processor.work(FrameJob(frame, capture_time(frame.camera, 0), None, frozenset()))
    assert len(decoded) == 1 and whole.outcome is FrameOutcome.FULL_FRAME
    assert {s.robot for s in whole.sightings} == {"red", "blue"}


@pytest.mark.parametrize("case", ["paper fusion", "region detection off", "a robot never tracked",
                                  "world-marker camera poses"])
def test_the_whole_frame_is_searched_when_not_every_robot_is_predicted(scenes, case):
    params, robots, scene, extrinsics = FILTER, (RED, BLUE), "both", EXTRINSICS
    if case == "paper fusion":
        params = dataclasses.replace(FILTER, fusion=FusionParams(method=FusionMethod.MEAN))
    elif case == "region detection off":
        params = dataclasses.replace(FILTER, track=TrackParams(roi_detection=False))
    elif case == "a robot never tracked":
        scene = "red"                                # blue is configured but never seen
    else:
        params = dataclasses.replace(FILTER, track=TrackParams(full_frame_every=4,
                                                               camera_poses=CameraPoseSource.WORLD_MARKER))
        extrinsics = None
    t = tracker(params, robots=robots, extrinsics=extrinsics)
    results = run(t, stream(scenes[scene], 0, 12))
    assert [kind(c) for _f, c, _p in results] == ["F"] * len(results)
    assert t.stats.region_detections == 0
    assert any(p.robot == "red" for _f, _c, ps in results for p in ps)   # tracking itself works


# --------------------------------------------------------------------------- several robots


def test_each_robot_gets_its_own_detections_and_poses(scenes):
    t = tracker(FILTER)
    sightings = []
    add = t.fusion.add
    t.fusion.add = lambda sighting, now_s: sightings.append(sighting) or add(sighting, now_s)
    results = run(t, stream(scenes["both"], 0, 16))
    poses = [p for _f, _c, ps in results for p in ps] + t.finish()
    ids = {"red": RED.layout.ids, "blue": BLUE.layout.ids}
    assert {s.robot for s in sightings} == {"red", "blue"}
    for s in sightings:
        assert s.detections and all(d.marker_id in ids[s.robot] for d in s.detections), s.robot
    # the paper's cube shows several faces with one id: all of them reach its sighting
    assert max(len(s.detections) for s in sightings if s.robot == "red") >= 2
    assert {robot for robot, _cam in t.stats.estimates} == {"red", "blue"}
    for robot in ("red", "blue"):
        mine = [p for p in poses if p.robot == robot]
        assert len(mine) >= 10 and t.stats.poses[robot] == len(mine)
        for p in mine[-5:]:
            assert_near_truth(p)


# --------------------------------------------------------------------------- a cubetrack worker's message


def test_a_workers_message_gives_the_fusion_what_its_own_per_frame_work_gives(scenes):
    """``cubetrack fuse`` turns a worker's message (corners, no image) into the sightings the
    tracker's own per-frame work makes of the frame, estimates included exactly where the fusion
    asks for them: before the filter tracks the robots (both), and while it tracks them (none)."""
    from cubetrack.app.fusion_service import frame_result
    from cubetrack.app.worker import sighting_message
    from cubetrack.core.records import FrameJob
    from cubetrack.io.sighting_wire import decode_sighting, encode_sighting
    from cubetrack.source.clock import ClockSync
    from cubetrack.source.streams import CameraStats

    t = tracker(FILTER)
    frame = stream(scenes["both"], 0, 1)[0]
    for asks in ({"red", "blue"}, set()):
        assert {r.name for r in t.robots if t.fusion.needs_estimate(r.name)} == asks
        job = FrameJob(frame, capture_time(frame.camera, 0), None, frozenset())  # a worker's: no estimates
        message = decode_sighting(encode_sighting(sighting_message(t.processor.work(job), ClockSync(), CameraStats(),
                                                                   with_pose=False)))
        fused = frame_result(t, message)
        own = t.processor.work(FrameJob(frame, job.capture_time_s, None, frozenset(asks)))
        assert fused.job.estimate_robots == frozenset(asks) and fused.outcome is own.outcome
        assert [s.robot for s in fused.sightings] == [s.robot for s in own.sightings] == ["red", "blue"]
        for a, b in zip(fused.sightings, own.sightings, strict=True):
            assert (a.camera, a.seq, a.capture_time_s, a.arrival_time_s) == (b.camera, b.seq, b.capture_time_s,
                                                                              b.arrival_time_s)
            assert [d.marker_id for d in a.detections] == [d.marker_id for d in b.detections]
            assert all(np.array_equal(x.corners_px, y.corners_px)
                       for x, y in zip(a.detections, b.detections, strict=True))
            assert (a.estimate is None) == (b.estimate is None) == (a.robot not in asks)
            if a.estimate is not None:
                assert np.array_equal(a.estimate.T_world_cube, b.estimate.T_world_cube)
        run(t, stream(scenes["both"], 0, 16))  # now the filter tracks both robots


def test_a_camera_re_calibrated_while_tracking_is_planned_through_its_new_pose():
    """Issue 27: once the camera watching rejoins a camera at a new pose, its frames' regions are
    where the robots are predicted in the camera as it now stands (not through its calibrated
    pose, which would leave the cube to the whole-frame fallback); a camera worker process, which
    has no fusion, learns the new pose from the forecast it is sent."""
    import pickle

    from cubetrack.core.geometry import invert_T
    from cubetrack.detect.predicted import predicted_view
    from cubetrack.fuse.camera_watch import EventKind, WatchEvent, WatchParams
    from cubetrack.fuse.forecast import Forecast

    params = dataclasses.replace(FILTER, camera_watch=WatchParams(enabled=True))
    t = Tracker(INTRINSICS, WORLD, (RED,), EXTRINSICS, params)
    forecast = Forecast({"red": (START_S, TRUTH["red"], np.zeros(3), np.zeros(3))}, frozenset())
    frames = {cam: Frame(cam, 1, START_S - CLOCK_OFFSET_S, START_S + LATENCY_S, b"") for cam in T_WORLD_CAM}
    before = {cam: t.plan(frame, START_S, forecast).regions for cam, frame in frames.items()}
    bumped = T_WORLD_CAM["cam2"] @ make_T(Rotation.from_euler("y", 3, degrees=True).as_matrix(), [0.02, 0.0, 0.0])
    for listener in t.fusion.listeners:  # what the watcher tells at a rejoin
        listener(WatchEvent(EventKind.REJOINED, "cam2", START_S, 0.02, 3.0, bumped, 200))
    after = {cam: t.plan(frame, START_S, forecast).regions for cam, frame in frames.items()}
    expected = predicted_view(invert_T(bumped) @ TRUTH["red"], RED.layout, INTR, params.track.roi_margin_m,
                              params.detector)
    assert expected is not None and after["cam2"] == (expected.box,) != before["cam2"]
    assert after["cam1"] == before["cam1"] and after["cam3"] == before["cam3"]
    assert t.processor.T_world_cam["cam2"] is EXTRINSICS["cam2"].T_world_cam  # sightings: the fusion moves them

    worker = Tracker(INTRINSICS, WORLD, (RED,), EXTRINSICS, FILTER)
    sent = Forecast(forecast.motions, forecast.estimate_robots, t.recalibrated)
    received = Forecast.from_plain(pickle.loads(pickle.dumps(sent.plain())))
    assert worker.plan(frames["cam2"], START_S, received).regions == before["cam2"]  # until told
    worker.plan_cameras_at(received.camera_poses)
    assert worker.plan(frames["cam2"], START_S, received).regions == after["cam2"]


def test_a_robot_off_its_prediction_is_searched_for_whole_once_lost_whatever_full_frame_every(scenes):
    """The bound on how long a tracked robot that turns up away from its prediction waits, with no
    periodic whole-frame search at all: the other robot's box still finds its cube, so the frames
    are searched in regions only until the moved robot's track is lost (``[fusion] lost_after_s``);
    from then on every camera's whole frame is searched, and it is found in the first of them."""
    moved = make_T(TRUTH["blue"][:3, :3], TRUTH["blue"][:3, 3] + [0.0, 0.35, 0.0])
    world = marker_on_paper(np.eye(4), WORLD.dictionary, WORLD.marker_id, WORLD.marker_size_m, 0.03)
    parts = [world, cube_solid(RED.layout, CUBE_M, TRUTH["red"]), cube_solid(BLUE.layout, CUBE_M, moved)]
    rng = np.random.default_rng(1)
    jumped = {cam: Camera(INTR, T, parts, supersample=1).jpeg(90, noise_std=1.0, rng=rng)
              for cam, T in T_WORLD_CAM.items()}
    t = tracker(StageParams(track=TrackParams(full_frame_every=10**6)))
    before = run(t, stream(scenes["both"], 0, 12))
    assert "R" in [kind(c) for _f, c, _p in before]          # tracked: regions only, no periodic whole frame
    assert all(kind(c) != "F" for _f, c, _p in before[len(T_WORLD_CAM):])
    after = run(t, stream(jumped, 12, 12))
    kinds = [kind(c) for _f, c, _p in after]
    first_whole = kinds.index("F")
    lost_after_s = t.params.fusion.lost_after_s
    # regions while the old track lasts (at most lost_after_s after the last frame that saw it there) ...
    assert set(kinds[:first_whole]) <= {"R"}
    assert after[first_whole][0].host_time_s - LATENCY_S <= capture_time("cam3", 11) + lost_after_s + 1 / FPS
    # ... then the whole frame, where the moved robot is found at once
    found = [(f, p) for f, _c, ps in after for p in ps if p.robot == "blue"
             and np.linalg.norm(p.position_m - moved[:3, 3]) < 0.01]
    assert found and found[0][0] in [f for f, _c, _p in after[first_whole:first_whole + len(T_WORLD_CAM)]]
