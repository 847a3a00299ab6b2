"""Property-based tests (hypothesis) of every parser that faces the network, the serial port or a
file: what the project writes reads back unchanged however it is cut into reads, and arbitrary or
hostile input ends in the project's own error (files) or in skipped, counted input (streams) with
bounded buffers -- never in another exception. benchmarks/fuzz_campaign.py runs the same parsers
coverage-guided for millions of inputs; tests/reliability/test_fuzz_corpora.py replays what it found."""

from __future__ import annotations

import itertools
import json
import math
import os
import shutil
import tempfile
from pathlib import Path

import numpy as np
import pytest
import tomli_w
import yaml
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from cubecam import improv, mjpeg
from cubetrack.core.cameras import CameraExtrinsics, CameraIntrinsics, ClockSample, WorldConfig
from cubetrack.core.errors import CameraInfoError, ConfigError, RecordingError
from cubetrack.core.geometry import T_from_position_quat
from cubetrack.core.layout import layout_to_table, paper_cube_layout
from cubetrack.io.camera_info import read_camera_info, write_camera_info
from cubetrack.io.config import (
    CameraConfig,
    read_extrinsics,
    read_tracker_config,
    tracker_config_to_table,
    write_extrinsics,
    write_toml,
)
from cubetrack.io.recording import CameraEntry, Recording, RecordingWriter
from cubetrack.source.mjpeg import MjpegParser
from cubetrack.source.time_poll import parse_time_answer

# CUBETRACK_PROPERTY_EXAMPLES=2000 runs a longer search (docs/reliability.md); times are written with 6 decimals (1 us)
FAST = settings(max_examples=int(os.environ.get("CUBETRACK_PROPERTY_EXAMPLES", "40")), deadline=None,
                suppress_health_check=[HealthCheck.too_slow])
SOI, EOI = b"\xff\xd8", b"\xff\xd9"
B = mjpeg.BOUNDARY


_SCRATCH: list[Path] = []


def scratch() -> Path:
    # hypothesis runs each test many times in one function-scoped fixture: a folder per example,
    # all removed when the module is done
    _SCRATCH.append(Path(tempfile.mkdtemp(prefix="cubetrack-prop-")))
    return _SCRATCH[-1]


@pytest.fixture(autouse=True, scope="module")
def _remove_scratch():
    yield
    while _SCRATCH:
        shutil.rmtree(_SCRATCH.pop(), ignore_errors=True)


def split(data: bytes, cuts: list[int]) -> list[bytes]:
    bounds = sorted({0, len(data), *(c % (len(data) + 1) for c in cuts)})
    return [data[a:b] for a, b in itertools.pairwise(bounds)]


# --- MJPEG parts ---------------------------------------------------------------------------------

jpeg_bodies = st.binary(max_size=300).map(lambda b: SOI + b + EOI).filter(lambda j: b"\n--" + B.encode() not in j)
header_names = st.text("abcdefghijklmnopqrstuvwxyz-", min_size=1, max_size=12).filter(
    lambda n: n.strip("-") == n and n not in ("content-length", "x-timestamp", "x-frame"))
header_values = st.text(st.characters(min_codepoint=0x21, max_codepoint=0x7E), max_size=20)


@st.composite
def mjpeg_parts(draw):
    return {
        "seq": draw(st.none() | st.integers(0, 2**40)),
        "micros": draw(st.integers(0, 10**15)),
        "jpeg": draw(jpeg_bodies),
        "length": draw(st.booleans()),
        "extra": draw(st.dictionaries(header_names, header_values, max_size=3)),
    }


def encode_part(p: dict) -> bytes:
    lines = ["Content-Type: image/jpeg"]
    if p["length"]:
        lines.append(f"Content-Length: {len(p['jpeg'])}")
    lines.append(f"X-Timestamp: {mjpeg.format_timestamp(p['micros'])}")
    if p["seq"] is not None:
        lines.append(f"X-Frame: {p['seq']}")
    lines += [f"{k.title()}: {v}" for k, v in p["extra"].items()]
    return ("\r\n".join(lines) + "\r\n\r\n").encode() + p["jpeg"] + mjpeg.PART_DELIMITER


@FAST
@given(parts=st.lists(mjpeg_parts(), max_size=5), cuts=st.lists(st.integers(0, 10**6), max_size=12),
       learn_boundary=st.booleans())
def test_any_stream_of_parts_reads_back_exactly_however_it_is_cut(parts, cuts, learn_boundary):
    data = mjpeg.PART_DELIMITER + b"".join(encode_part(p) for p in parts)
    parser = MjpegParser(None if learn_boundary else B)
    got = [part for piece in split(data, cuts) for part in parser.feed(piece)]
    assert [(g.seq, g.device_time_s, g.jpeg) for g in got] == [
        (p["seq"], float(mjpeg.format_timestamp(p["micros"])), p["jpeg"]) for p in parts]
    for g, p in zip(got, parts, strict=True):
        assert {k: g.headers[k] for k in p["extra"]} == {k: v.strip() for k, v in p["extra"].items()}
    parser.close()
    assert not parser.bad


# Hostile building blocks: delimiters, lying and huge lengths, endless headers, bare JPEG markers.
hostile_pieces = st.sampled_from([
    mjpeg.PART_DELIMITER, b"\r\n--" + B.encode(), b"--" + B.encode() + b"--\r\n", b"\r\n\r\n", b"\n",
    b"Content-Length: 99999999999\r\n", b"Content-Length: 40\r\n", b"Content-Length: 0\r\n",
    b"Content-Length: -1\r\n", b"X-Timestamp: 1.5\r\n", b"X-Timestamp: nan\r\n", b"X-Frame: 7\r\n",
    b"X-Pad: " + b"a" * 300, SOI, EOI, b"\x00" * 700, b"Content-Type image/jpeg\r\n",
]) | st.binary(max_size=64)


@FAST
@given(pieces=st.lists(hostile_pieces, max_size=60), reads=st.lists(st.integers(1, 400), min_size=1, max_size=8),
       learn_boundary=st.booleans())
def test_hostile_streams_never_raise_keep_the_buffer_bounded_and_yield_only_whole_jpegs(pieces, reads, learn_boundary):
    data = b"".join(pieces)
    parser = MjpegParser(None if learn_boundary else B, max_header_bytes=256, max_part_bytes=1024)
    pos, i = 0, 0
    while pos < len(data):
        step = reads[i % len(reads)]
        for part in parser.feed(data[pos:pos + step]):
            assert part.jpeg.startswith(SOI) and part.jpeg.rstrip(b"\r\n").endswith(EOI)
            assert len(part.jpeg) <= 1024 and part.jpeg in data
            assert math.isfinite(part.device_time_s) and part.device_time_s >= 0
        assert len(parser._buf) <= 1024 + 256 + step + 256
        pos, i = pos + step, i + 1
    parser.close()
    if learn_boundary:
        return  # a boundary learnt from a hostile first line stays wrong until the next connection
    # and a good part after all that is still read
    good = {"seq": 5, "micros": 1, "jpeg": SOI + b"ok" + EOI, "length": True, "extra": {}}
    assert [p.seq for p in parser.feed(mjpeg.PART_DELIMITER + encode_part(good) + mjpeg.PART_DELIMITER)] == [5]


# --- /time answers -------------------------------------------------------------------------------


@FAST
@given(micros=st.integers(0, 10**18 - 1), pad=st.sampled_from(["", "\n", "\r\n", " "]))
def test_time_answers_the_node_writes_read_back(micros, pad):
    assert parse_time_answer((mjpeg.format_timestamp(micros) + pad).encode()) == pytest.approx(micros / 1e6, rel=1e-15)


@FAST
@given(body=st.binary(max_size=40) | st.text(max_size=40).map(str.encode))
def test_any_time_answer_is_a_finite_time_or_a_value_error(body):
    try:
        value = parse_time_answer(body)
    except ValueError:
        return
    assert math.isfinite(value) and 0 <= value < 1e13


# --- Improv serial -------------------------------------------------------------------------------

frames = st.builds(lambda t, d: ("frame", t, d), st.integers(0, 255), st.binary(max_size=255))
lines = st.text(st.characters(blacklist_categories=("Cs",), blacklist_characters="\r\n"), max_size=80).filter(
    lambda t: "IMPROV" not in t).map(lambda t: ("line", t))


@FAST
@given(events=st.lists(frames | lines, max_size=8), cuts=st.lists(st.integers(0, 10**5), max_size=10))
def test_improv_frames_and_lines_read_back_however_the_bytes_are_cut(events, cuts):
    data = b"".join(improv.encode_frame(e[1], e[2]) + b"\n" if e[0] == "frame" else e[1].encode() + b"\n"
                    for e in events)
    parser = improv.Parser()
    got = [ev for piece in split(data, cuts) for ev in parser.feed(piece)]
    expected = [improv.Frame(e[1], e[2]) if e[0] == "frame" else improv.Line(e[1]) for e in events]
    assert got == expected


utf8_strings = st.text(max_size=60).filter(lambda s: len(s.encode()) <= 60)


@FAST
@given(command=st.sampled_from(list(improv.Command)), strings=st.lists(utf8_strings, max_size=4))
def test_rpc_and_rpc_results_round_trip(command, strings):
    for encode, decode in ((improv.encode_rpc, improv.decode_rpc),
                           (improv.encode_rpc_result, improv.decode_rpc_result)):
        frame = improv.Parser().feed(encode(command, strings) + b"\n")[0]
        assert decode(frame) == (command, strings)


@FAST
@given(data=st.binary(max_size=2000), timeouts=st.lists(st.integers(0, 2000), max_size=5))
def test_improv_parser_never_raises_on_noise_and_stays_bounded(data, timeouts):
    parser = improv.Parser()
    pos = 0
    for cut in sorted(timeouts) + [len(data)]:
        for ev in parser.feed(data[pos:cut]) + parser.timeout():
            if isinstance(ev, improv.Frame):
                for decode in (improv.decode_state, improv.decode_error, improv.decode_rpc, improv.decode_rpc_result):
                    try:
                        decode(ev)
                    except improv.ImprovError:
                        pass
        pos = max(pos, cut)
        assert len(parser._line) < improv.MAX_LINE and len(parser._frame) <= improv.HEADER_LEN + improv.MAX_DATA + 1


# --- the recording folder ------------------------------------------------------------------------

finite_times = st.floats(0, 2e9, allow_nan=False, allow_infinity=False)


@FAST
@given(rows=st.lists(st.tuples(st.integers(0, 10**8), finite_times, finite_times), min_size=1, max_size=12,
                    unique_by=lambda r: r[0]),
       samples=st.lists(st.tuples(finite_times, finite_times, finite_times), max_size=5))
def test_a_recording_reads_back_what_was_written(rows, samples):
    folder = scratch() / "rec"
    with RecordingWriter(folder, [CameraEntry("cam", "http://x/stream")]) as w:
        for seq, device, host in rows:
            w.add_frame("cam", seq, device, host, SOI + bytes([seq % 256]) + EOI)
        for s in samples:
            w.add_clock_sample("cam", ClockSample(*s))
    rec = Recording.open(folder)
    got = list(rec.frames("cam"))
    assert [f.seq for f in got] == [r[0] for r in rows]
    assert all(abs(f.device_time_s - r[1]) <= 1e-6 and abs(f.host_time_s - r[2]) <= 1e-6
               for f, r in zip(got, rows, strict=True))
    assert [f.jpeg for f in got] == [SOI + bytes([r[0] % 256]) + EOI for r in rows]
    back = rec.clock_samples("cam")
    assert len(back) == len(samples) and all(
        abs(a - b) <= 1e-6 for s, t in zip(back, samples, strict=True)
        for a, b in zip((s.host_send_s, s.device_time_s, s.host_recv_s), t, strict=True))
    assert not rec.skipped


junk_rows = st.one_of(
    st.text(max_size=40).filter(lambda t: "\n" not in t and "\r" not in t),
    st.sampled_from(["1,nan,1,a.jpg", "1,1,inf,a.jpg", "1,1,1,../escape.jpg", "1,1,1,", "x,1,1,a.jpg", "1,1,1,a/b.jpg",
                     "1,1,1", "1,1,1,a.jpg,extra", '"1,1,1,a.jpg'.replace('"', "")]),
)


@FAST
@given(junk=st.lists(junk_rows, max_size=10), good=st.integers(1, 5))
def test_broken_index_rows_are_skipped_and_never_escape_the_camera_folder(junk, good):
    folder = scratch() / "rec"
    with RecordingWriter(folder, [CameraEntry("cam")]) as w:
        for seq in range(1, good + 1):
            w.add_frame("cam", seq, seq * 0.1, 1e9 + seq, SOI + EOI)
    with (folder / "cam" / "index.csv").open("a", encoding="utf-8") as f:
        f.write("".join(j + "\n" for j in junk))
    rec = Recording.open(folder)
    rows = rec.index("cam")
    assert [r.seq for r in rows][:good] == list(range(1, good + 1))
    for r in rows:
        assert math.isfinite(r.device_time_s) and math.isfinite(r.host_time_s)
        assert (folder / "cam" / r.file).resolve().parent == (folder / "cam").resolve()
    # every line is a row or counted (a quote may join lines into one record)
    assert good <= len(rows) + rec.skipped["bad index row"] <= good + len(junk)


@FAST
@given(meta=st.binary(max_size=200), index=st.binary(max_size=200), clock=st.binary(max_size=200))
def test_arbitrary_recording_files_give_a_recording_error_or_valid_rows(meta, index, clock):
    folder = scratch()
    (folder / "cam").mkdir()
    good_meta = json.dumps({"format": "cubetrack.recording", "version": 1, "cameras": [{"name": "cam"}]}).encode()
    for m in (meta, good_meta):
        (folder / "recording.json").write_bytes(m)
        (folder / "cam" / "index.csv").write_bytes(b"seq,device_time,host_time,file\n" + index)
        (folder / "cam" / "clock.csv").write_bytes(b"host_send,device_time,host_recv\n" + clock)
        try:
            rec = Recording.open(folder)
            rec.index("cam")
            samples = rec.clock_samples("cam")
        except RecordingError:
            continue
        assert all(math.isfinite(v) for s in samples for v in (s.host_send_s, s.device_time_s, s.host_recv_s))


# --- tracker config, cube layout, extrinsics -----------------------------------------------------

names = st.from_regex(r"[A-Za-z0-9_][A-Za-z0-9_.-]{0,10}", fullmatch=True).filter(lambda n: n not in (".", ".."))


@FAST
@given(cams=st.lists(names, unique=True, max_size=4), marker_id=st.integers(0, 40),
       size=st.floats(0.01, 2.0), source_timeout=st.floats(0.1, 30.0))
def test_a_written_tracker_config_reads_back(cams, marker_id, size, source_timeout):
    folder = scratch()
    (folder / "cube.toml").write_text(tomli_w.dumps(layout_to_table(paper_cube_layout(marker_id=41))))
    cameras = [CameraConfig(c, f"http://10.0.0.{i + 2}/stream", folder / f"{c}.yaml") for i, c in enumerate(cams)]
    doc = tracker_config_to_table(WorldConfig(marker_id=marker_id, marker_size_m=size), cameras, [("bot", "cube.toml")],
                                  {"source": {"read_timeout_s": source_timeout}}, relative_to=folder)
    write_toml(doc, folder / "tracker.toml")
    cfg = read_tracker_config(folder / "tracker.toml")
    assert cfg.world == WorldConfig(marker_id=marker_id, marker_size_m=size)
    assert cfg.cameras == tuple(cameras)
    assert [r.name for r in cfg.robots] == ["bot"] and cfg.robots[0].layout.ids == {41}
    assert cfg.section("source") == {"read_timeout_s": source_timeout}


toml_scalars = st.one_of(st.integers(-2**63, 2**63 - 1), st.floats(), st.booleans(), st.text(max_size=8))
toml_values = st.recursive(toml_scalars, lambda inner: st.lists(inner, max_size=3)
                           | st.dictionaries(st.text(max_size=6), inner, max_size=3), max_leaves=12)
config_keys = st.sampled_from(["world", "cameras", "robots", "source", "detector", "name", "layout", "url",
                               "camera_info", "marker_size", "marker_id", "dictionary", "markers"])


@FAST
@given(doc=st.dictionaries(config_keys | st.text(max_size=6), toml_values, max_size=5),
       camera=st.dictionaries(config_keys, toml_values, max_size=4),
       robot=st.dictionaries(config_keys, toml_values, max_size=4))
def test_arbitrary_config_documents_give_only_config_errors(doc, camera, robot):
    folder = scratch()
    good_layout = layout_to_table(paper_cube_layout(marker_id=3))
    good_robot = {"name": "bot", "layout": "cube.toml"}
    cases = [  # (tracker config, cube layout)
        (doc, good_layout),
        ({**doc, "cameras": [camera], "robots": [good_robot]}, good_layout),
        ({"robots": [robot]}, good_layout),
        ({"robots": [good_robot], "world": camera}, good_layout),
        ({"robots": [good_robot]}, {**doc, "markers": [robot, camera]}),
    ]
    for config, layout in cases:
        try:
            (folder / "tracker.toml").write_text(tomli_w.dumps(config))
            (folder / "cube.toml").write_text(tomli_w.dumps(layout))
        except (TypeError, ValueError):  # not representable in TOML
            continue
        for read in (read_tracker_config, read_extrinsics):
            try:
                read(folder / "tracker.toml")
            except ConfigError:
                pass


unit_quats = st.lists(st.floats(-1, 1), min_size=4, max_size=4).filter(lambda q: np.linalg.norm(q) > 0.1)


@FAST
@given(cams=st.dictionaries(names, st.tuples(st.lists(st.floats(-50, 50), min_size=3, max_size=3), unit_quats,
                                               st.integers(0, 10**6)), min_size=1, max_size=3))
def test_extrinsics_read_back(cams):
    folder = scratch()
    written = {n: CameraExtrinsics(T_from_position_quat(np.array(p), np.array(q)), s, 0.001, 0.2, "world marker")
               for n, (p, q, s) in cams.items()}
    write_extrinsics(written, folder / "e.toml")
    back = read_extrinsics(folder / "e.toml")
    assert set(back) == set(written)
    for n, e in written.items():
        assert np.allclose(back[n].T_world_cam, e.T_world_cam, atol=1e-9) and back[n].samples == e.samples


# --- camera_info ---------------------------------------------------------------------------------


@FAST
@given(size=st.tuples(st.integers(1, 8000), st.integers(1, 8000)), f=st.tuples(st.floats(1, 1e4), st.floats(1, 1e4)),
       c=st.tuples(st.floats(-1e4, 1e4), st.floats(-1e4, 1e4)),
       dist=st.lists(st.floats(-10, 10), min_size=5, max_size=5))
def test_camera_info_reads_back_what_was_written(size, f, c, dist):
    K = np.array([[f[0], 0.0, c[0]], [0.0, f[1], c[1]], [0.0, 0.0, 1.0]])
    intr = CameraIntrinsics(size[0], size[1], K, np.array(dist), "cam")
    path = scratch() / "cam.yaml"
    write_camera_info(intr, path)
    back = read_camera_info(path)
    assert (back.width, back.height, back.camera_name) == (*size, "cam")
    assert np.array_equal(back.K, K) and np.array_equal(back.dist, np.array(dist))


yaml_values = st.recursive(st.one_of(st.integers(), st.floats(), st.text(max_size=6), st.booleans(), st.none()),
                           lambda inner: st.lists(inner, max_size=10)
                           | st.dictionaries(st.text(max_size=5), inner, max_size=3),
                           max_leaves=20)
info_keys = st.sampled_from(["image_width", "image_height", "camera_matrix", "distortion_coefficients",
                             "distortion_model", "camera_name", "data"])


@FAST
@given(doc=st.dictionaries(info_keys, yaml_values, max_size=6),
       matrix=st.dictionaries(info_keys, yaml_values, max_size=2),
       opencv=st.booleans())
def test_arbitrary_camera_info_documents_give_only_camera_info_errors(doc, matrix, opencv):
    path = scratch() / "cam.yaml"
    for variant in (doc, {**doc, "camera_matrix": matrix}):
        text = yaml.safe_dump(variant)
        path.write_text(("%YAML:1.0\n---\n" if opencv else "") + text)
        try:
            intr = read_camera_info(path)
        except CameraInfoError:
            continue
        assert intr.width > 0 and intr.height > 0 and np.all(np.isfinite(intr.K))
