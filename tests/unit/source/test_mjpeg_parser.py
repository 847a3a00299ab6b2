"""The MJPEG part parser on crafted byte streams: the firmware's exact part layout (contracts §1),
every way a part can be broken, and arbitrary splits of the stream into reads."""

from __future__ import annotations

import itertools

import cv2
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from cubecam import mjpeg
from cubecam.testdata import synthetic_jpeg
from cubetrack.source.mjpeg import MjpegParser, boundary_from_content_type

B = mjpeg.BOUNDARY
DELIM = mjpeg.PART_DELIMITER  # b"\r\n--<B>\r\n"
JPEGS = [synthetic_jpeg(i, 96, 64) for i in range(4)]


def part(jpeg: bytes, seq: int, stamp_us: int, length: int | None = None, extra: bytes = b"") -> bytes:
    """One part exactly as the node writes it (headers, blank line, JPEG, next delimiter)."""
    n = len(jpeg) if length is None else length
    return mjpeg.part_header(n, seq, stamp_us)[:-2] + extra + b"\r\n" + jpeg + DELIM


def headers_part(header_lines: list[bytes], jpeg: bytes) -> bytes:
    return b"".join(h + b"\r\n" for h in header_lines) + b"\r\n" + jpeg + DELIM


def good_stream(n: int = 3) -> bytes:
    return DELIM + b"".join(part(JPEGS[i % 4], 10 + i, 5_000_000 + 125_000 * i) for i in range(n))


def feed_all(parser: MjpegParser, data: bytes, step: int | None = None):
    if step is None:
        return parser.feed(data)
    out = []
    for i in range(0, len(data), step):
        out += parser.feed(data[i:i + step])
    return out


@pytest.mark.parametrize("step", [None, 1, 7, 1000])
def test_the_nodes_stream_gives_every_part_whatever_the_read_sizes(step):
    parser = MjpegParser(B)
    parts = feed_all(parser, good_stream(3), step)
    assert [p.seq for p in parts] == [10, 11, 12]
    assert [p.device_time_s for p in parts] == [5.0, 5.125, 5.25]
    assert [p.jpeg for p in parts] == JPEGS[:3]
    assert not parser.bad and parser.parts == 3
    image = cv2.imdecode(np.frombuffer(parts[0].jpeg, np.uint8), cv2.IMREAD_GRAYSCALE)
    assert image.shape == (64, 96)


def test_a_part_is_complete_when_its_last_byte_arrives_not_when_the_next_part_starts():
    parser = MjpegParser(B)
    data = DELIM + mjpeg.part_header(len(JPEGS[0]), 1, 1_000_000) + JPEGS[0]
    assert parser.feed(data[:-1]) == []
    done = parser.feed(data[-1:])
    assert [p.seq for p in done] == [1]


def test_without_content_length_the_part_ends_at_the_next_delimiter():
    parser = MjpegParser(B)
    data = DELIM + headers_part([b"Content-Type: image/jpeg", b"X-Timestamp: 2.000001", b"X-Frame: 4"], JPEGS[1])
    parts = parser.feed(data[:-len(DELIM)])
    assert parts == []  # cannot know where it ends yet
    parts = parser.feed(data[-len(DELIM):])
    assert len(parts) == 1 and parts[0].jpeg == JPEGS[1] and parts[0].device_time_s == 2.000001
    assert not parser.bad


def test_a_part_shorter_than_its_content_length_is_skipped_and_the_next_one_kept():
    parser = MjpegParser(B)
    truncated = part(JPEGS[1][:200], 2, 2_000_000, length=len(JPEGS[1]))
    data = DELIM + part(JPEGS[0], 1, 1_000_000) + truncated + part(JPEGS[2], 3, 3_000_000)
    parts = parser.feed(data)
    assert [p.seq for p in parts] == [1, 3]
    assert parser.bad == {"part shorter than its Content-Length": 1}


def test_garbage_jpeg_data_with_intact_framing_is_skipped():
    garbage = JPEGS[1][:100] + bytes(range(256)) * 4  # SOI but no EOI: not a whole JPEG
    parser = MjpegParser(B)
    parts = parser.feed(DELIM + part(garbage, 2, 2_000_000) + part(JPEGS[2], 3, 3_000_000))
    assert [p.seq for p in parts] == [3]
    assert parser.bad == {"not a whole JPEG": 1}


@pytest.mark.parametrize("bad_headers,reason", [
    ([b"Content-Type image/jpeg", b"X-Timestamp: 1.000000"], "malformed part header"),
    ([b"Content-Length: abc", b"X-Timestamp: 1.000000"], "bad Content-Length"),
    ([b"Content-Length: -5", b"X-Timestamp: 1.000000"], "bad Content-Length"),
    ([b"Content-Length: 99999999999", b"X-Timestamp: 1.000000"], "bad Content-Length"),
    ([b"Content-Length: 0", b"X-Timestamp: 1.000000"], "bad Content-Length"),
    ([b"Content-Type: image/jpeg", b"X-Frame: 2"], "no X-Timestamp"),
    ([b"X-Timestamp: soon", b"X-Frame: 2"], "bad X-Timestamp"),
    ([b"X-Timestamp: nan", b"X-Frame: 2"], "bad X-Timestamp"),
    ([b"X-Timestamp: -1.5", b"X-Frame: 2"], "bad X-Timestamp"),
    ([b"X-Timestamp: 1.000000", b"X-Frame: two"], "bad X-Frame"),
    ([b"X-Timestamp: 1.000000", b"X-Pad: " + b"a" * 3000], "part headers too long"),
])
def test_a_part_with_broken_headers_is_skipped_and_counted(bad_headers, reason):
    parser = MjpegParser(B, max_header_bytes=2048)
    data = DELIM + headers_part(bad_headers, JPEGS[1]) + part(JPEGS[2], 3, 3_000_000) + part(JPEGS[3], 4, 4_000_000)
    parts = parser.feed(data)
    assert [p.seq for p in parts] == [3, 4]
    assert parser.bad == {reason: 1}


def test_a_part_without_x_frame_is_kept_without_a_number():
    parser = MjpegParser(B)
    parts = parser.feed(DELIM + headers_part([b"Content-Length: %d" % len(JPEGS[0]), b"X-Timestamp: 7.5"], JPEGS[0]))
    assert len(parts) == 1 and parts[0].seq is None and parts[0].device_time_s == 7.5


def test_an_oversized_part_without_content_length_is_dropped_without_growing_the_buffer():
    parser = MjpegParser(B, max_part_bytes=10_000)
    head = DELIM + b"Content-Type: image/jpeg\r\nX-Timestamp: 1.0\r\n\r\n" + b"\xff\xd8"
    parser.feed(head)
    for _ in range(50):
        parser.feed(b"\x00" * 1000)
    assert parser.bad["part too large"] >= 1
    assert len(parser._buf) < 20_000
    assert [p.seq for p in parser.feed(DELIM + part(JPEGS[0], 9, 9_000_000))] == [9]


@pytest.mark.parametrize("content_type,boundary", [
    (mjpeg.STREAM_CONTENT_TYPE, B),
    ('multipart/x-mixed-replace; boundary="frame"', "frame"),
    ("multipart/x-mixed-replace;boundary=--myboundary", "myboundary"),
    ("multipart/x-mixed-replace ; Boundary = 123456789000000000000987654321", "123456789000000000000987654321"),
    ("multipart/x-mixed-replace", None),
])
def test_boundary_from_content_type(content_type, boundary):
    assert boundary_from_content_type(content_type) == boundary


def test_servers_that_repeat_dashes_or_omit_the_first_crlf_are_read():
    # mjpg-streamer style: header says boundary=--myboundary, body uses "--myboundary" lines
    body = b"--myboundary\r\n" + headers_part(
        [b"Content-Type: image/jpeg", b"Content-Length: %d" % len(JPEGS[0]), b"X-Timestamp: 1.5"],
        JPEGS[0])[:-len(DELIM)]
    body += b"\r\n--myboundary\r\n" + headers_part([b"Content-Length: %d" % len(JPEGS[1]), b"X-Timestamp: 1.6"],
                                                  JPEGS[1])
    parser = MjpegParser(boundary_from_content_type("multipart/x-mixed-replace;boundary=--myboundary"))
    assert [p.device_time_s for p in parser.feed(body)] == [1.5, 1.6]


def test_a_missing_boundary_is_learnt_from_the_first_delimiter_line():
    parser = MjpegParser(None)
    assert [p.seq for p in parser.feed(good_stream(2))] == [10, 11]


def test_junk_before_the_first_delimiter_and_a_close_delimiter_are_ignored():
    parser = MjpegParser(B)
    close = f"\r\n--{B}--\r\n".encode()
    data = b"preamble text\r\n" + good_stream(1)[:-len(DELIM)] + close + DELIM + part(JPEGS[3], 20, 1)
    assert [p.seq for p in parser.feed(data)] == [10, 20]
    assert not parser.bad


def test_an_empty_part_is_passed_over_and_a_part_without_headers_counted():
    parser = MjpegParser(B)
    assert [p.seq for p in parser.feed(good_stream(1) + good_stream(1))] == [10, 10]
    assert not parser.bad
    parser.feed(b"\r\n" + JPEGS[0] + DELIM)
    assert parser.bad == {"part without headers": 1}
    assert [p.seq for p in parser.feed(part(JPEGS[1], 11, 1))] == [11]


def test_a_stream_ending_inside_a_part_counts_one_truncated_part_and_between_parts_none():
    whole = good_stream(2)
    between = MjpegParser(B)
    between.feed(whole)
    between.close()
    assert not between.bad
    inside = MjpegParser(B)
    inside.feed(whole + mjpeg.part_header(len(JPEGS[0]), 12, 1) + JPEGS[0][:50])
    inside.close()
    assert inside.bad == {"part cut off by the end of the stream": 1}


@settings(max_examples=60, deadline=None)
@given(cuts=st.lists(st.integers(min_value=0, max_value=len(good_stream(4))), max_size=30))
def test_any_split_into_reads_gives_the_same_parts(cuts):
    data = good_stream(4)
    bounds = sorted(set([0, len(data), *cuts]))
    parser = MjpegParser(B)
    parts = []
    for a, b in itertools.pairwise(bounds):
        parts += parser.feed(data[a:b])
    assert [p.seq for p in parts] == [10, 11, 12, 13] and not parser.bad


@settings(max_examples=100, deadline=None)
@given(noise=st.binary(max_size=3000), at=st.integers(min_value=0, max_value=2000))
def test_noise_spliced_into_the_stream_never_raises_and_yields_only_whole_jpegs(noise, at):
    data = good_stream(3)
    at = min(at, len(data))
    parser = MjpegParser(B, max_header_bytes=512, max_part_bytes=50_000)
    parts = parser.feed(data[:at] + noise + data[at:] + good_stream(2))  # an empty part between the two
    for p in parts:
        assert p.jpeg in JPEGS
    assert [p.seq for p in parts][-2:] == [10, 11]  # the stream recovers
