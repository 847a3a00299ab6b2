"""The Improv serial v1 codec: wire bytes of each frame type, and the incremental parser on
streams mixed with log lines, split anywhere, with garbage and bad checksums."""

from __future__ import annotations

import random

import pytest

from cubecam import improv
from cubecam.errors import ImprovError


def test_frame_layout_and_checksum_by_hand():
    frame = improv.encode_current_state(improv.State.READY)
    body = b"IMPROV" + bytes([1, 0x01, 1, 0x02])
    assert frame == body + bytes([sum(body) % 256])


def test_wifi_settings_rpc_bytes():
    frame = improv.encode_wifi_settings("lab", "password1")
    data = bytes([0x01, 1 + 3 + 1 + 9, 3]) + b"lab" + bytes([9]) + b"password1"
    body = b"IMPROV" + bytes([1, 0x03, len(data)]) + data
    assert frame == body + bytes([sum(body) % 256])


@pytest.mark.parametrize("encode, frame_type", [
    (lambda: improv.encode_current_state(improv.State.PROVISIONED), improv.FrameType.CURRENT_STATE),
    (lambda: improv.encode_error_state(improv.Error.UNABLE_TO_CONNECT), improv.FrameType.ERROR_STATE),
    (lambda: improv.encode_rpc(improv.Command.GET_DEVICE_INFO), improv.FrameType.RPC),
    (lambda: improv.encode_rpc_result(improv.Command.GET_DEVICE_INFO, ["cubecam", "1.0", "Spresense", "cam1"]),
     improv.FrameType.RPC_RESULT),
])
def test_every_frame_type_round_trips(encode, frame_type):
    frame = encode()
    events = improv.Parser().feed(frame + b"\n")
    assert events == [improv.Frame(int(frame_type), frame[9:-1])]


def test_decoders_give_back_what_was_encoded():
    p = improv.Parser()
    state, err, rpc, result = (p.feed(f + b"\n")[0] for f in (
        improv.encode_current_state(improv.State.PROVISIONING),
        improv.encode_error_state(improv.Error.BAD_HOSTNAME),
        improv.encode_wifi_settings("my net", "pässword!"),
        improv.encode_rpc_result(improv.Command.WIFI_SETTINGS, ["http://10.0.0.2/"])))
    assert improv.decode_state(state) == improv.State.PROVISIONING
    assert improv.decode_error(err) == improv.Error.BAD_HOSTNAME
    assert improv.decode_rpc(rpc) == (improv.Command.WIFI_SETTINGS, ["my net", "pässword!"])
    assert improv.decode_rpc_result(result) == (improv.Command.WIFI_SETTINGS, ["http://10.0.0.2/"])


def test_too_long_data_is_refused():
    with pytest.raises(ImprovError):
        improv.encode_rpc_result(improv.Command.GET_DEVICE_INFO, ["x" * 200, "y" * 100])
    with pytest.raises(ImprovError):
        improv.encode_frame(improv.FrameType.RPC, bytes(256))


def test_inconsistent_rpc_result_is_an_error():
    bad = improv.Frame(improv.FrameType.RPC_RESULT, bytes([0x03, 5, 9]) + b"abcd")
    with pytest.raises(ImprovError):
        improv.decode_rpc_result(bad)


def stream_of_everything() -> tuple[bytes, list]:
    frames = [improv.encode_current_state(improv.State.READY),
              improv.encode_rpc_result(improv.Command.GET_DEVICE_INFO, ["cubecam", "1.0", "Spresense", "cam\n1"]),
              improv.encode_error_state(improv.Error.NONE)]
    data = (b"[I] boot: cubecam 1.0\r\n" + frames[0] + b"\n" + b"[I] link: joining 'lab'\n" + frames[1] + b"\n"
            + b"OK\n" + frames[2] + b"\n")
    expected = [improv.Line("[I] boot: cubecam 1.0"), improv.Frame(1, frames[0][9:-1]),
                improv.Line("[I] link: joining 'lab'"), improv.Frame(4, frames[1][9:-1]), improv.Line("OK"),
                improv.Frame(2, frames[2][9:-1])]
    return data, expected


@pytest.mark.parametrize("seed", range(20))
def test_parser_gives_the_same_events_however_the_bytes_are_split(seed):
    data, expected = stream_of_everything()
    rng = random.Random(seed)
    p = improv.Parser()
    events = []
    i = 0
    while i < len(data):
        n = rng.randint(1, 9)
        events += p.feed(data[i:i + n])
        i += n
    assert events == expected


def test_bad_checksum_is_reported_and_parsing_resumes():
    good = improv.encode_current_state(improv.State.READY)
    bad = good[:-1] + bytes([(good[-1] + 1) % 256])
    events = improv.Parser().feed(bad + b"\n" + good + b"\n")
    assert isinstance(events[0], improv.BadFrame) and "checksum" in events[0].reason
    assert events[1:] == [improv.Frame(1, b"\x02")]


def test_wrong_version_is_a_bad_frame():
    events = improv.Parser().feed(b"IMPROV\x02\x01\x01\x02\x00\n")
    assert isinstance(events[0], improv.BadFrame) and "version" in events[0].reason


def test_garbage_without_newlines_does_not_hide_a_following_frame():
    good = improv.encode_current_state(improv.State.READY)
    junk = bytes(random.Random(1).randrange(256) for _ in range(3000)).replace(b"\n", b"").replace(b"IMPROV", b"")
    events = improv.Parser().feed(junk + good + b"\n")
    assert events[-1] == improv.Frame(1, b"\x02")


def test_partial_frame_is_dropped_after_a_timeout():
    p = improv.Parser()
    good = improv.encode_current_state(improv.State.READY)
    assert p.feed(good[:5 + 3]) == []
    assert isinstance(p.timeout()[0], improv.BadFrame)
    assert p.feed(good + b"\n") == [improv.Frame(1, b"\x02")]
