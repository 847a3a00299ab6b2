"""The sighting message (cubetrack.io.sighting_wire): bit-exact round trips, compactness, and
one-line refusals of anything that is not a version-1 sighting."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from cubetrack.core.records import Detection, FrameOutcome
from cubetrack.io.sighting_wire import (
    _HEAD,
    CLOCK_METHOD_CODES,
    OUTCOME_CODES,
    SightingMessage,
    SightingWireError,
    WireClock,
    WireHealth,
    decode_sighting,
    encode_sighting,
    restamped,
)
from cubetrack.source.clock import ClockFitMethod


def message(pose: bool = False, detections: int = 3) -> SightingMessage:
    rng = np.random.default_rng(3)
    dets = tuple(Detection(7 + i, rng.uniform(0, 640, (4, 2)), float(rng.uniform(100, 900)),
                           "DICT_4X4_50" if i % 2 else "DICT_6X6_250") for i in range(detections))
    T = np.eye(4)
    T[:3, :3] = np.array([[0.0, -1, 0], [1, 0, 0], [0, 0, 1]])
    T[:3, 3] = [1.0 / 3, -2.5, 0.1]
    return SightingMessage("cäm-1", 2**40 + 5, 1234.000001, 1.7e9 + 1 / 7, 1.7e9 + 0.05 + 1 / 7, "full frame", dets,
                           WireClock("round-trip", 1.7e9 - 1234.0, 3.1e-5, 1000.0),
                           WireHealth(False, 812, 3, 1, 2), T if pose else None)


@pytest.mark.parametrize("pose", [False, True])
def test_round_trip_is_bit_exact(pose):
    sent = message(pose)
    got = decode_sighting(encode_sighting(sent))
    for name in ("camera", "seq", "device_time_s", "capture_time_s", "arrival_time_s", "outcome", "clock", "health"):
        assert getattr(got, name) == getattr(sent, name), name
    assert len(got.detections) == len(sent.detections)
    for a, b in zip(got.detections, sent.detections, strict=True):
        assert (a.marker_id, a.area_px2, a.dictionary) == (b.marker_id, b.area_px2, b.dictionary)
        assert np.array_equal(a.corners_px, b.corners_px) and a.corners_px.shape == (4, 2)
    if pose:
        assert np.array_equal(got.T_world_cam, sent.T_world_cam)
    else:
        assert got.T_world_cam is None


def test_every_outcome_and_an_empty_frame_travel():
    for outcome in FrameOutcome:
        sent = SightingMessage("c", 0, 0.0, 1.0, 2.0, outcome.value, ())
        assert decode_sighting(encode_sighting(sent)).outcome == outcome.value


def test_the_wire_codes_are_written_out_and_cover_every_enum_value():
    """The outcome and clock-method bytes are the codes written in io/sighting_wire.py, not the
    enums' order (reordering FrameOutcome or ClockFitMethod must not change a byte on the wire)."""
    assert set(OUTCOME_CODES) == {o.value for o in FrameOutcome}
    assert set(CLOCK_METHOD_CODES) == {m.value for m in ClockFitMethod}
    for codes in (OUTCOME_CODES, CLOCK_METHOD_CODES):
        assert sorted(codes.values()) == list(range(len(codes)))
    assert OUTCOME_CODES == {"regions": 0, "full frame": 1, "corrupt": 2, "no camera pose": 3}  # version 1's bytes
    assert CLOCK_METHOD_CODES == {"none": 0, "arrival": 1, "round-trip": 2}
    data = encode_sighting(SightingMessage("c", 0, 0.0, 1.0, 2.0, "corrupt", (), WireClock("arrival")))
    flags, method = data[5], data[5 + 1 + 8 + 24]  # after magic and version: flags, seq i64, three f64 times
    assert (flags >> 1, method) == (2, 1)


def test_compact_corners_not_images():
    size = len(encode_sighting(message(detections=3)))
    assert size == len(encode_sighting(message(detections=2))) + 77  # id, dictionary, 8 corners, area
    assert size < 400


@pytest.mark.parametrize("data, needle", [
    (b"", "not a cubetrack sighting"),
    (b"GET / HTTP/1.1\r\n", "not a cubetrack sighting"),
    (b"CTSG\x02" + bytes(90), "version 2, this cubetrack reads version 1"),
])
def test_foreign_or_newer_data_is_refused_in_one_line(data, needle):
    with pytest.raises(SightingWireError, match=needle) as info:
        decode_sighting(data)
    assert "\n" not in str(info.value)


def test_every_truncation_and_trailing_bytes_are_refused():
    data = encode_sighting(message(pose=True))
    for n in range(len(data)):
        with pytest.raises(SightingWireError) as info:
            decode_sighting(data[:n])
        assert "\n" not in str(info.value)
    with pytest.raises(SightingWireError, match="1 bytes after its end"):
        decode_sighting(data + b"\0")


def test_a_bad_dictionary_index_or_name_is_refused():
    data = bytearray(encode_sighting(message(detections=1)))
    data[-73] = 9  # the only detection's dictionary index (after its 4-byte id)
    with pytest.raises(SightingWireError, match="names dictionary 9 of 1"):
        decode_sighting(bytes(data))
    with pytest.raises(SightingWireError, match="unknown outcome"):
        encode_sighting(SightingMessage("c", 0, 0.0, 0.0, 0.0, "lost", ()))
    with pytest.raises(SightingWireError, match="longer than 255 bytes"):
        encode_sighting(SightingMessage("c" * 300, 0, 0.0, 0.0, 0.0, "regions", ()))


DROPS = {"edge refinement failed": 3, "not a convex quad": 1}


def test_drop_counts_travel_and_a_frame_without_drops_keeps_the_version_1_bytes():
    """The markers a worker's detector found and dropped reach ``cubetrack fuse``'s summary (issue 25)."""
    import dataclasses

    sent = dataclasses.replace(message(pose=True), dropped=DROPS)
    assert decode_sighting(encode_sighting(sent)).dropped == DROPS
    plain = encode_sighting(message(pose=True))
    assert decode_sighting(plain).dropped == {} and not plain[5] & 8  # flags bit 3 clear: as before
    data = encode_sighting(sent)
    for n in range(len(plain), len(data)):  # cut inside the drop counts
        with pytest.raises(SightingWireError):
            decode_sighting(data[:n])


def test_a_workers_message_carries_its_frames_drop_counts_to_the_fusions_frame_result():
    from cubetrack.app.worker import sighting_message
    from cubetrack.core.records import Frame, FrameJob, FrameResult
    from cubetrack.source.clock import ClockSync
    from cubetrack.source.streams import CameraStats

    job = FrameJob(Frame("cam1", 4, 10.0, 10.05, b""), 10.0, None, frozenset())
    result = FrameResult(job, FrameOutcome.FULL_FRAME, (), dropped=DROPS)
    got = decode_sighting(encode_sighting(sighting_message(result, ClockSync(), CameraStats(), with_pose=False)))
    assert got.dropped == DROPS


def test_a_bodys_share_of_a_frame_names_the_body_and_a_whole_frame_is_byte_for_byte_as_before():
    """A worker publishes a frame per robot it holds markers of (flags bit 4, the robot's name after
    the camera's); a message without a body is the version-1 message as it was (bit 4 clear, no
    byte more), so the bytes of workers from before shards still decode."""
    whole = message(pose=True)
    share = dataclasses.replace(whole, body="robot-7", detections=whole.detections[:1])
    old, new = encode_sighting(whole), encode_sighting(share)
    assert not old[5] & 16 and new[5] & 16
    got = decode_sighting(new)
    assert got.body == "robot-7" and decode_sighting(old).body is None
    assert len(got.detections) == 1 and np.array_equal(got.detections[0].corners_px, whole.detections[0].corners_px)
    assert np.array_equal(got.T_world_cam, whole.T_world_cam) and got.camera == whole.camera
    with pytest.raises(SightingWireError, match="truncated in its body name"):
        decode_sighting(new[:_HEAD.size + 1 + len(whole.camera.encode()) + 3])
    with pytest.raises(SightingWireError, match="unknown flags"):
        decode_sighting(old[:5] + bytes([old[5] | 32]) + old[6:])


@pytest.mark.parametrize("pose", [False, True])
def test_a_restamped_message_is_the_same_message_at_its_new_times(pose):
    sent = dataclasses.replace(message(pose), body="r1")
    data = restamped(encode_sighting(sent), 55.25, 1.8e9 + 1 / 3, 1.8e9 + 0.04, 54.0)
    clock = dataclasses.replace(sent.clock, device_ref_s=54.0)
    expected = dataclasses.replace(sent, device_time_s=55.25, capture_time_s=1.8e9 + 1 / 3,
                                   arrival_time_s=1.8e9 + 0.04, clock=clock)
    assert data == encode_sighting(expected)
    with pytest.raises(SightingWireError, match="not a sighting"):
        restamped(b"CTXX" + data[4:], 0.0, 0.0, 0.0, 0.0)


def test_a_fused_state_round_trips_bit_exactly_and_anything_else_is_refused():
    from cubetrack.io.sighting_wire import FusedState, decode_state, encode_state

    rng = np.random.default_rng(5)
    T = np.eye(4)
    T[:3] = rng.normal(size=(3, 4))
    state = FusedState("r1", 1700000000.123456, T, rng.normal(size=3), rng.normal(size=3), rng.normal(size=(12, 12)))
    back = decode_state(encode_state(state))
    assert back.robot == "r1" and back.time_s == state.time_s
    for a, b in zip(back[2:], state[2:], strict=True):
        assert np.array_equal(a, b)
    data = encode_state(state)
    for bad in (data[:-1], b"CTSG" + data[4:], data[:4] + bytes([9]) + data[5:]):
        with pytest.raises(SightingWireError):
            decode_state(bad)


def test_a_batch_holds_its_messages_bit_exact_and_a_lone_message_still_reads():
    from cubetrack.io.sighting_wire import decode_messages, encode_batch

    one, two = encode_sighting(message(pose=True)), encode_sighting(dataclasses.replace(message(), body="r1"))
    got = decode_messages(encode_batch([one, two]))
    assert [encode_sighting(m) for m in got] == [one, two] and got[1].body == "r1"
    assert [encode_sighting(m) for m in decode_messages(one)] == [one]   # what workers sent before batches


def test_a_bad_batch_is_refused_in_one_line():
    from cubetrack.io.sighting_wire import decode_messages, encode_batch

    data = encode_batch([encode_sighting(message()), encode_sighting(message(detections=1))])
    for n in (5, 7, 12, len(data) - 1):
        with pytest.raises(SightingWireError, match="truncated"):
            decode_messages(data[:n])
    with pytest.raises(SightingWireError, match="after its end"):
        decode_messages(data + b"\0")
    with pytest.raises(SightingWireError, match="batch version 2, this cubetrack reads version 1"):
        decode_messages(data[:4] + b"\x02" + data[5:])
    with pytest.raises(SightingWireError, match="not a cubetrack sighting"):
        decode_messages(data[:11] + b"XXXX" + data[15:])   # a batch of something else
    with pytest.raises(SightingWireError, match="1 to 65535"):
        encode_batch([])


def test_a_shards_states_travel_in_one_message_bit_exactly_and_another_version_is_refused():
    from cubetrack.io.sighting_wire import (
        FusedState,
        decode_states,
        encode_state,
        encode_states,
        states_error,
    )

    rng = np.random.default_rng(6)
    states = [FusedState(f"r{k}", 1.7e9 + k, np.eye(4), rng.normal(size=3), rng.normal(size=3),
                         rng.normal(size=(12, 12))) for k in (1, 2, 3)]
    data = encode_states(states)
    assert states_error(data) is None
    for got, sent in zip(decode_states(data), states, strict=True):
        assert encode_state(got) == encode_state(sent)
    newer = data[:4] + bytes([2]) + data[5:]
    assert states_error(newer) == "fused states version 2, this reads 1"
    for bad, why in ((newer, "version 2"), (encode_state(states[0]), "not a fused states"),
                     (data[:-1], "truncated"), (data + b"x", "after its end")):
        with pytest.raises(SightingWireError, match=why):
            decode_states(bad)
