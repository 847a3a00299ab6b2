"""The offline smoother over FilterFusion's tracks (cubetrack.fuse.smoother): closer to the truth
than the causal filter, split where the filter did not go on from the state before, and the
causal poses unchanged by keeping what it needs."""

import dataclasses
import re

import numpy as np
import pytest
from scipy.spatial.transform import Rotation
from test_filter_fusion import run, same_pose
from test_joint_and_filter import CAMS, INTR, LAYOUT, detections

from cubetrack.core.errors import ParamsError
from cubetrack.core.geometry import R_from_quat_xyzw, make_T, rotation_angle
from cubetrack.core.records import CubeSighting
from cubetrack.estimate.pose import estimate_cube
from cubetrack.fuse.corner_filter import FilterParams
from cubetrack.fuse.fusion import FilterFusion, FusionParams
from cubetrack.fuse.smoother import Gains, TrailStep, segments, smoothed_poses


def weaving(t):
    """A cube driving at 0.3 m/s along x while it weaves (yaw 25° at 0.5 Hz, sideways 5 cm)."""
    yaw = 0.45 * np.sin(np.pi * t)
    return make_T(Rotation.from_euler("z", yaw).as_matrix(), [-0.4 + 0.3 * t, 0.1 + 0.05 * np.sin(np.pi * t), 0.305])


def sightings(truth, t_end, rng, noise_px=0.8, t_start=0.0):
    """Three unsynchronised 7.5 fps cameras seeing ``truth`` with noisy corners, in capture order."""
    out = []
    for k, cam in enumerate(CAMS):
        for n, t in enumerate(np.arange(t_start + k * 0.044, t_end, 1 / 7.5)):
            dets = detections(truth(t), CAMS[cam], rng, noise_px=noise_px)
            est = estimate_cube(dets, LAYOUT, INTR, CAMS[cam], camera=cam, robot="bot", seq=n,
                                capture_time_s=t, arrival_time_s=t + 0.05)
            out.append(CubeSighting(cam, "bot", n, t, t + 0.05, dets, est, CAMS[cam], INTR))
    return sorted(out, key=lambda s: (s.capture_time_s, s.camera))


def errors(poses, truth):
    """Position (m) and rotation (deg) errors of each pose against ``truth`` at its time."""
    pos = np.array([np.linalg.norm(p.position_m - truth(p.time_s)[:3, 3]) for p in poses])
    rot = np.array([rotation_angle(R_from_quat_xyzw(p.quaternion_xyzw), truth(p.time_s)[:3, :3], "deg")
                    for p in poses])
    return pos, rot


def rms(a):
    return float(np.sqrt(np.mean(np.square(a))))


def tracked(items, params=FusionParams()):
    """(causal poses, smoothed poses, fusion) of the sightings fed on time."""
    fusion = FilterFusion({"bot": LAYOUT}, params)
    fusion.keep_trail()
    causal = run(fusion, items)
    return causal, smoothed(fusion, items[-1].arrival_time_s), fusion


def smoothed(fusion, now_s):
    return smoothed_poses(fusion.trail("bot", now_s), now_s)


@pytest.mark.parametrize("seed", [0, 1])
def test_smoothed_poses_are_closer_to_the_truth_than_the_filters(seed):
    items = sightings(weaving, 4.0, np.random.default_rng(seed))
    causal, smoothed, fusion = tracked(items)
    assert fusion.stats["accepted sighting"] > 0.9 * len(items)
    assert [p.time_s for p in smoothed] == [p.time_s for p in causal]  # one pose per sighting, as the filter's
    assert all(p.smoothed and p.smooth_lag_s is None for p in smoothed) and not any(p.smoothed for p in causal)
    assert all(p.latency_s >= items[-1].arrival_time_s - p.time_s - 1e-9 for p in smoothed)  # out at the end
    (pos_f, rot_f), (pos_s, rot_s) = errors(causal, weaving), errors(smoothed, weaving)
    assert rms(pos_s) < 0.75 * rms(pos_f)
    assert rms(rot_s) < 0.75 * rms(rot_f)
    for p, q in zip(smoothed, causal, strict=True):  # the rest of the record is the sighting's
        assert p.cameras == q.cameras and p.markers == q.markers and p.covariance.shape == (6, 6)
    # the smoother's covariance is no larger than the filter's (it has more sightings)
    ratios = [np.trace(p.covariance) / np.trace(q.covariance) for p, q in zip(smoothed, causal, strict=True)]
    assert np.median(ratios) < 0.8
    assert smoothed[-1].position_m.tolist() == causal[-1].position_m.tolist()  # the last state: nothing after it


def test_keeping_the_trail_changes_no_causal_pose():
    items = sightings(weaving, 2.0, np.random.default_rng(2))
    jittered = sorted(items, key=lambda s: s.capture_time_s + np.random.default_rng(s.seq).exponential(0.08))
    plain = run(FilterFusion({"bot": LAYOUT}), jittered)
    kept = FilterFusion({"bot": LAYOUT})
    kept.keep_trail()
    with_trail = run(kept, jittered)
    assert kept.stats["late sighting"] > 5
    assert len(plain) == len(with_trail)
    for a, b in zip(plain, with_trail, strict=True):
        same_pose(a, b)


def test_gains_kept_from_pass_to_pass_change_no_smoothed_pose():
    """A fixed lag smooths nearly the same states at every pose: the gains kept from the last pass
    give the same poses as computing them afresh, also once a state is replaced (re-applied)."""
    items = sightings(weaving, 1.5, np.random.default_rng(12))
    _, _, fusion = tracked(items)
    trail = fusion.trail("bot", 2.0)
    gains = Gains()
    for n in range(10, len(trail), 3):
        part = trail[n - 10: n]
        if n == 19:  # a state replaced, as a late sighting's re-application does
            f = part[5].filter
            part[5] = dataclasses.replace(part[5], filter=f.moved(np.full(12, 1e-3), f.P))
        for kept, fresh in zip(smoothed_poses(part, 2.0, 4, 0.1, gains), smoothed_poses(part, 2.0, 4, 0.1),
                               strict=True):
            assert kept.position_m.tolist() == fresh.position_m.tolist()
            assert kept.covariance.tolist() == fresh.covariance.tolist()
            assert (kept.smoothed, kept.smooth_lag_s) == (fresh.smoothed, fresh.smooth_lag_s)


def test_late_sightings_are_smoothed_as_in_capture_order():
    """The trail is what capture-order processing finally made of every sighting, whatever the
    arrival order: the smoothed poses equal those of the sightings fed in capture order."""
    items = sightings(weaving, 2.5, np.random.default_rng(3))
    arrived = sorted(items, key=lambda s: s.capture_time_s + np.random.default_rng(s.seq + 7).exponential(0.08))
    late = FilterFusion({"bot": LAYOUT})
    late.keep_trail()
    run(late, arrived)
    assert late.stats["late sighting"] > 5
    _, expected, _ = tracked(items)
    got = smoothed(late, items[-1].arrival_time_s)
    assert len(got) == len(expected)
    for a, b in zip(got, expected, strict=True):
        np.testing.assert_allclose(a.position_m, b.position_m, atol=1e-12)
        np.testing.assert_allclose(a.quaternion_xyzw, b.quaternion_xyzw, atol=1e-12)


def turn_in_place(t):
    """Weaving, then from 1.5 s the cube is suddenly 70° further round (a flip no motion model
    predicts: the filter re-acquires from the camera's own pose)."""
    T = weaving(t)
    if t >= 1.5:
        T = make_T(Rotation.from_euler("z", 70, degrees=True).as_matrix() @ T[:3, :3], T[:3, 3])
    return T


def test_segments_break_at_a_re_acquisition():
    items = sightings(turn_in_place, 3.0, np.random.default_rng(4), noise_px=0.4)
    causal, smoothed, fusion = tracked(items)
    trail = fusion.trail("bot", 3.0)
    assert fusion.stats["re-acquired sighting"] >= 1
    parts = [[trail[i] for i in part] for part in segments(trail)]
    assert len(parts) >= 2
    for part in parts[1:]:
        assert part[0].outcome in ("re-acquired sighting", "track start")
    first = [p for p in parts[0] if p.pose is not None]
    last_before = first[-1].filter
    smoothed_before = next(p for p in smoothed if p.time_s == last_before.time_s)
    # a segment's last state has nothing after it in its segment: smoothing leaves it as filtered
    np.testing.assert_array_equal(smoothed_before.position_m, last_before.position_m)
    # and the poses before the flip are not dragged towards it
    before = [p for p in smoothed if p.time_s < 1.5]
    assert max(errors(before, turn_in_place)[1]) < 3.0
    pos_f, _ = errors([p for p in causal if p.time_s < 1.5], turn_in_place)
    assert rms(errors(before, turn_in_place)[0]) < rms(pos_f)


def test_segments_break_at_a_lost_track():
    rng = np.random.default_rng(5)
    items = sightings(weaving, 1.5, rng) + sightings(weaving, 3.5, rng, t_start=2.5)  # unseen 1.5-2.5 s
    items.sort(key=lambda s: (s.capture_time_s, s.camera))
    causal, smoothed, fusion = tracked(items)
    trail = fusion.trail("bot", 3.5)
    parts = [[trail[i] for i in part] for part in segments(trail)]
    assert len(parts) == 2 and parts[1][0].outcome == "track start"
    assert max(s.filter.time_s for s in parts[0]) < 1.5 < 2.5 <= parts[1][0].filter.time_s
    times = np.array([p.time_s for p in smoothed])
    assert not np.any((times > 1.5) & (times < 2.5))  # nothing invented while unseen


def test_segments_follow_the_outcomes():
    state, lost = object(), None  # segments only look at whether a step has a filter
    outcomes = [("sighting before track start", lost), ("track start", state), ("accepted sighting", state),
                ("rejected sighting", state), ("accepted sighting", state), ("re-acquired sighting", state),
                ("accepted sighting", state), ("rejected sighting", lost), ("accepted sighting", state),
                ("track start", state)]
    trail = [TrailStep(outcome, f, None, 0.0, 0.0) for outcome, f in outcomes]
    assert segments(trail) == [[1, 2, 3, 4], [5, 6], [8], [9]]


def test_a_fusion_without_a_trail_refuses_to_give_one():
    fusion = FilterFusion({"bot": LAYOUT})
    with pytest.raises(ParamsError, match="keep_trail"):
        fusion.trail("bot", 0.0)



def lagged_run(items, lag_s, arrived=None):
    """(poses, [(the newest capture time applied when each left, pose)]) with ``smooth_lag_s``."""
    fusion = FilterFusion({"bot": LAYOUT}, filter_params=FilterParams(smooth_lag_s=lag_s))
    left, newest = [], -np.inf
    for s in arrived or items:
        newest = max(newest, s.capture_time_s)
        left += [(newest, p) for p in fusion.add(s, s.arrival_time_s)]
    left += [(np.inf, p) for p in fusion.flush(items[-1].arrival_time_s)]
    return [p for _, p in left], left


@pytest.mark.parametrize("seed", [6, 7])
def test_a_fixed_lag_gives_each_pose_that_late_and_closer_to_the_truth(seed):
    items = sightings(weaving, 4.0, np.random.default_rng(seed))
    causal = run(FilterFusion({"bot": LAYOUT}), items)
    poses, left = lagged_run(items, 0.15)
    assert [p.time_s for p in poses] == [p.time_s for p in causal]  # the same poses, each once, in capture order
    assert all(p.time_s < newest - 0.15 for newest, p in left if newest < np.inf)  # none before 0.15 s of newer
    assert sum(newest == np.inf for newest, _ in left) <= 8  # the session's last 0.15 s leave at its end
    # each says its lag: the setting, or at the session's end what there was after it
    assert all(p.smoothed and p.smooth_lag_s == 0.15 for newest, p in left if newest < np.inf)
    assert all(p.smooth_lag_s == round(items[-1].capture_time_s - p.time_s, 4) < 0.15
               for newest, p in left if newest == np.inf)
    assert all(p.latency_s > 0.15 + 0.05 for newest, p in left if newest < np.inf)  # arrival 50 ms after capture
    (pos_f, rot_f), (pos_l, rot_l) = errors(causal, weaving), errors(poses, weaving)
    _, whole, _ = tracked(items)
    pos_s, rot_s = errors(whole, weaving)
    assert rms(pos_l) < 0.8 * rms(pos_f) and rms(rot_l) < 0.85 * rms(rot_f)
    assert rms(pos_s) <= rms(pos_l) * 1.05  # the whole recording knows at least as much


def test_a_fixed_lag_with_late_sightings_still_gives_each_pose_once_in_capture_order():
    items = sightings(weaving, 3.0, np.random.default_rng(8))
    arrived = sorted(items, key=lambda s: s.capture_time_s + np.random.default_rng(s.seq + 11).exponential(0.08))
    poses, left = lagged_run(items, 0.1, arrived)
    times = [p.time_s for p in poses]
    assert times == sorted(times) and len(set(times)) == len(times) > 0.8 * len(items)
    assert all(p.time_s < newest - 0.1 for newest, p in left if newest < np.inf)


@pytest.mark.parametrize("lag_s,margin_s,history_s,needle", [
    (-0.1, 0.2, 0.5, "smooth_lag_s must be a non-negative number of seconds"),
    (0.6, 0.2, 0.5, "must not exceed [fusion] history_s"),
    (0.05, -0.01, 0.5, "smooth_margin_s must be a non-negative number of seconds"),
    (0.05, float("inf"), 0.5, "smooth_margin_s must be a non-negative number of seconds"),
    (0.05, float("nan"), 0.5, "smooth_margin_s must be a non-negative number of seconds")])
def test_a_fixed_lag_out_of_range_is_refused(lag_s, margin_s, history_s, needle):
    with pytest.raises(ParamsError, match=re.escape(needle)):
        FilterFusion({"bot": LAYOUT}, FusionParams(history_s=history_s),
                     FilterParams(smooth_lag_s=lag_s, smooth_margin_s=margin_s))


def clocked_run(fusion, items, end_s, arrived=None, tick_s=0.01):
    """[(now, pose)]: the sightings added as they arrive (``arrived``: (arrival, sighting) pairs,
    default each at its own arrival time) and :meth:`FilterFusion.release` every ``tick_s`` of
    host time up to ``end_s``, as the live loop does."""
    queue = sorted(arrived or [(s.arrival_time_s, s) for s in items], key=lambda a: a[0])
    out = []
    for now in np.arange(0.0, end_s, tick_s):
        while queue and queue[0][0] <= now:
            out += [(now, p) for p in fusion.add(queue.pop(0)[1], now)]
        out += [(now, p) for p in fusion.release(now)]
    return out


def test_a_robot_seen_no_more_gets_its_held_poses_within_lag_and_margin():
    """Three cameras see the robot until 2 s, then none does: its last poses leave by the host
    clock once ``smooth_lag_s + smooth_margin_s`` have passed since their capture (not at the
    session's end), each once, smoothed over what came after them; a sighting that arrives after
    its pose left is folded in as a late one and gives no second pose."""
    lag_s, margin_s, tick_s = 0.1, 0.15, 0.01
    items = sightings(weaving, 2.0, np.random.default_rng(9))
    withheld = items[-2]  # captured just before the last one, but it arrives at 2.5 s
    fusion = FilterFusion({"bot": LAYOUT}, filter_params=FilterParams(smooth_lag_s=lag_s, smooth_margin_s=margin_s))
    out = clocked_run(fusion, items, 3.0, [(s.arrival_time_s, s) for s in items if s is not withheld]
                      + [(2.5, withheld)], tick_s)
    assert fusion.flush(3.0) == []  # nothing was left for the session's end
    assert fusion.stats["late sighting"] == 1
    causal = run(FilterFusion({"bot": LAYOUT}), [s for s in items if s is not withheld])
    assert [p.time_s for _, p in out] == [p.time_s for p in causal]  # each pose once, in capture order
    assert all(now <= p.time_s + lag_s + margin_s + tick_s + 1e-9 for now, p in out)  # on time
    early = [(now, p) for now, p in out if p.smooth_lag_s < lag_s]
    last_s = max(s.capture_time_s for s in items if s is not withheld)
    assert len(early) >= 2 and fusion.stats["pose released before its lag"] == len(early)
    for now, p in early:  # the last lag's poses, when their time was up, smoothed over what came after them
        assert p.time_s > last_s - lag_s and now >= p.time_s + lag_s + margin_s - 1e-9
        assert p.smooth_lag_s == round(last_s - p.time_s, 4)
        assert p.latency_s == pytest.approx(now - p.time_s)
    assert early[-1][1].time_s == last_s


def test_release_gives_nothing_before_its_time_nor_without_a_lag():
    items = sightings(weaving, 1.0, np.random.default_rng(10))
    for lag_s in (0.0, 0.1):
        fusion = FilterFusion({"bot": LAYOUT}, filter_params=FilterParams(smooth_lag_s=lag_s, smooth_margin_s=0.2))
        poses = [p for s in items for p in fusion.add(s, s.arrival_time_s)]
        last_s = items[-1].capture_time_s
        causal = run(FilterFusion({"bot": LAYOUT}), items)
        held = causal[len(poses):]  # the last lag's
        assert len(held) == sum(p.time_s >= last_s - lag_s for p in causal) if lag_s else held == []
        first_s = held[0].time_s if held else last_s
        assert fusion.release(first_s + lag_s + 0.2 - 0.001) == []  # not before its time
        first = fusion.release(first_s + lag_s + 0.2 + 0.001)
        assert len(first) == (1 if held else 0)  # the oldest, whose time is up; the others' is not
        out = first + fusion.release(last_s + lag_s + 0.2 + 0.001)
        assert [p.time_s for p in out] == [p.time_s for p in held] and (len(out) >= 2 or lag_s == 0)
        assert fusion.release(last_s + 10.0) == [] and fusion.flush(last_s + 10.0) == []  # none twice
