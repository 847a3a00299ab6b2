"""The dashboard's model: camera statuses (red within 2 s of the last frame, with the reason),
trails, which cameras see a robot, the event queues of the page's clients."""

import math

import numpy as np
import pytest
from sink_helpers import tracked

from cubetrack.core.records import CameraHealth, CameraView
from cubetrack.sink.dashboard.state import DashboardParams, DashboardState, EventHub, camera_status, health_json


class Clock:
    def __init__(self, now: float = 1_700_000_000.0):
        self.now = now

    def __call__(self) -> float:
        return self.now


def health(camera="cam-a", time_s=0.0, connected=True, frames=10, error="", **kw) -> CameraHealth:
    return CameraHealth(camera, time_s, connected, 7.5, frames, 0, 0, 0, last_error=error, **kw)


def view(camera="cam-a", seq=1, time_s=0.0) -> CameraView:
    return CameraView(camera, seq, time_s, b"\xff\xd8jpeg\xff\xd9", ())


def test_camera_status_rules():
    assert camera_status(None, None, 10.0, 1.0) == ("waiting", "no answer from the camera yet")
    assert camera_status(health(frames=0), None, 10.0, 1.0) == ("waiting", "connected, no frame yet")
    assert camera_status(health(connected=False, error="connection refused"), None, 10.0, 1.0) == \
        ("down", "connection refused")
    assert camera_status(health(connected=False, frames=0), None, 10.0, 1.0) == ("waiting", "connecting")
    assert camera_status(health(connected=False), 9.9, 10.0, 1.0) == ("down", "not connected")
    assert camera_status(health(), 9.5, 10.0, 1.0) == ("ok", "")
    status, reason = camera_status(health(error="read timed out"), 8.0, 10.0, 1.0)
    assert status == "stale" and reason == "no frame for 2.0 s; last error: read timed out"
    assert camera_status(None, 9.8, 10.0, 1.0) == ("ok", "")  # frames without health (offline feeds)


def test_a_camera_that_stops_sending_turns_red_within_two_seconds_and_says_why():
    clock = Clock()
    state = DashboardState(DashboardParams(), clock)
    sub = state.events.subscribe()
    state.camera_health(health(time_s=clock.now))
    for i in range(10):  # frames at 7.5 fps
        clock.now += 1 / 7.5
        state.camera_view(view(seq=i, time_s=clock.now))
        state.tick()
    assert state.camera_json("cam-a")["status"] == "ok"
    last_frame_s = clock.now
    red_at = None
    while clock.now < last_frame_s + 5:  # the server ticks every tick_s; health keeps coming once a second
        clock.now += state.params.tick_s
        if round((clock.now - last_frame_s) / state.params.tick_s) % 4 == 0:
            state.camera_health(health(time_s=clock.now, frames=10))  # the counter does not move
        state.tick()
        if state.camera_json("cam-a")["status"] == "stale":
            red_at = clock.now
            break
    assert red_at is not None and red_at - last_frame_s <= 2.0
    cam = state.camera_json("cam-a")
    assert cam["reason"].startswith("no frame for ") and cam["frame_age_s"] == pytest.approx(red_at - last_frame_s)
    statuses = [data["status"] for kind, data in sub.take(0) if kind == "camera"]
    assert statuses[-1] == "stale"  # the page was told
    # frames again: back to ok at once
    state.camera_view(view(seq=99, time_s=clock.now))
    assert state.camera_json("cam-a")["status"] == "ok"


def test_an_answer_is_current_even_when_the_tick_is_late():
    """A loaded machine runs the tick thread late: the API still never calls a camera ok whose
    newest frame is older than stale_after_s, and says stale as soon as it is."""
    clock = Clock()
    state = DashboardState(DashboardParams(), clock)
    state.camera_health(health(time_s=clock.now))
    state.camera_view(view(time_s=clock.now))
    state.tick()
    clock.now += 0.9
    cam = state.camera_json("cam-a")
    assert cam["status"] == "ok" and cam["frame_age_s"] == pytest.approx(0.9)
    clock.now += 0.2  # no tick since the frame
    for cam in (state.camera_json("cam-a"), state.cameras_json()[0]):
        assert cam["status"] == "stale"
        assert cam["reason"] == "no frame for 1.1 s — is the node still on and in Wi-Fi range?"
        assert cam["frame_age_s"] == pytest.approx(1.1)


def test_health_counters_alone_keep_a_camera_green_and_a_lost_one_is_down_with_its_error():
    clock = Clock()
    state = DashboardState(DashboardParams(), clock)
    for i in range(4):  # no views (nobody processes frames), the counter moves
        clock.now += 0.6
        state.camera_health(health(time_s=clock.now, frames=10 * (i + 1)))
        state.tick()
        assert state.camera_json("cam-a")["status"] == "ok"
    state.camera_health(health(time_s=clock.now, connected=False, frames=40, error="connection refused"))
    cam = state.camera_json("cam-a")
    assert (cam["status"], cam["reason"]) == ("down", "connection refused")
    assert cam["health"]["last_error"] == "connection refused"


def test_health_json_has_every_field_and_no_nan():
    out = health_json(health(clock_offset_s=0.5))
    assert out["clock_offset_s"] == 0.5 and out["clock_drift_ppm"] is None and out["transfer_latency_s"] is None
    assert set(out) == {"camera", "time_s", "connected", "frames_per_s", "frames", "dropped", "bad", "reconnects",
                        "clock_offset_s", "clock_drift_ppm", "transfer_latency_s", "jpeg_bytes", "last_error", "timing"}


def test_trails_cover_trail_s_and_seen_by_lists_recent_cameras(session_info):
    clock = Clock()
    state = DashboardState(DashboardParams(trail_s=2.0, trail_points=10, seen_within_s=1.0), clock)
    state.open_session(session_info)
    for i in range(100):  # 5 s of poses at 20 Hz
        state.pose(tracked("robot 1!", i))
    robot = next(r for r in state.robots_json() if r["name"] == "robot 1!")
    times = [t for t, _, _ in robot["trail"]]
    assert len(times) <= 10 and times[-1] == pytest.approx(tracked("robot 1!", 99).time_s)
    assert times[-1] - times[0] <= 2.0 and times[-1] - times[0] > 1.5
    assert robot["seen_by"] == ["cam b", "cam-a"]
    assert robot["yaw_deg"] == pytest.approx(math.degrees(0.5 * 0.05 * 99))
    assert robot["position_m"] == pytest.approx([0.99, 0.5, 0.06])
    clock.now += 1.5  # no pose since: no camera sees it now
    robot = next(r for r in state.robots_json() if r["name"] == "robot 1!")
    assert robot["seen_by"] == []
    other = next(r for r in state.robots_json() if r["name"] == "2nd")
    assert other["position_m"] is None and other["trail"] == []


def test_a_new_session_keeps_what_the_page_shows_and_counts_frames_afresh(session_info):
    clock = Clock()
    state = DashboardState(DashboardParams(), clock)
    state.open_session(session_info)
    state.camera_health(health(time_s=clock.now, frames=500))
    state.camera_view(view())
    state.close_session()
    assert state.session_json()["state"] == "ended"
    state.open_session(session_info)
    assert state.camera_json("cam-a")["view"]["seq"] == 1  # the last frame stays on the tile
    clock.now += 3.0
    state.camera_health(health(time_s=clock.now, frames=8))  # the new session's counter starts again
    state.tick()
    assert state.camera_json("cam-a")["status"] == "ok"
    assert state.session_json()["calibrated"] is False  # cam_c has no extrinsics


def test_views_are_announced_at_most_views_per_s():
    clock = Clock()
    state = DashboardState(DashboardParams(views_per_s=2.0), clock)
    sub = state.events.subscribe()
    for i in range(30):  # 3 s at 10 fps
        clock.now += 0.1
        state.camera_view(view(seq=i))
    announced = [d["seq"] for kind, d in sub.take(0) if kind == "view"]
    assert 5 <= len(announced) <= 7 and announced == sorted(announced)


def test_a_slow_client_loses_old_events_and_is_told_to_resync():
    hub = EventHub(max_events=4)
    slow, fast = hub.subscribe(), hub.subscribe()
    for i in range(3):
        hub.publish("camera", {"i": i})
    assert [d["i"] for _, d in fast.take(0)] == [0, 1, 2]
    for i in range(3, 10):
        hub.publish("camera", {"i": i})
        assert fast.take(0) == [("camera", {"i": i})]
    events = slow.take(0)
    assert events[0][0] == "resync" and events[-1] == ("camera", {"i": 9}) and len(events) <= 5
    assert slow.lost >= 1 and fast.lost == 0
    hub.close()
    assert slow.take(1.0) == [] and slow.closed


def test_params_refuse_bad_values():
    from cubetrack.core.errors import ParamsError

    with pytest.raises(ParamsError, match="stale_after_s must be positive"):
        DashboardParams(stale_after_s=0)
    with pytest.raises(ParamsError, match="jpeg_quality"):
        DashboardParams(jpeg_quality=0)
    assert np.isfinite(DashboardParams().tick_s)


def test_what_the_camera_watching_says_reaches_the_tile_through_the_outputs_queue():
    """Sink.camera_watch through Outputs (behind its Decoupled queue) to the state: the camera's JSON
    carries it and every change is announced to the page at once, transient states included."""
    from cubetrack.core.records import CameraWatchState
    from cubetrack.sink.base import Outputs
    from cubetrack.sink.dashboard.server import DashboardServer, DashboardSink

    server = DashboardServer(port=0)
    try:
        sub = server.state.events.subscribe()
        with Outputs([DashboardSink(server)]) as outputs:
            for state, progress in [("watched", 0.0), ("moved", 0.0), ("re-calibrating", 0.3), ("rejoined", 0.0)]:
                outputs.camera_watch(CameraWatchState("cam-a", 5.0, state, progress, f"{state} message"))
        told = [data["watch"]["state"] for kind, data in sub.take(5.0) if kind == "camera"]
        assert told == ["watched", "moved", "re-calibrating", "rejoined"]
        assert server.state.camera_json("cam-a")["watch"] == {"state": "rejoined", "progress": 0.0,
                                                              "message": "rejoined message", "time_s": 5.0}
        assert server.state.camera_json("cam-b") is None
    finally:
        server.close()
