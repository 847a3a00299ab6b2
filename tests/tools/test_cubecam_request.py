"""The emulator's request reading: incremental (any split), bounded at 2 KiB, routed as the
firmware routes (unknown path 404 before method 405)."""

from __future__ import annotations

import pytest

from cubecam.request import ParseStatus, RequestParser, Route, parse_fps, route


def decide(data: bytes, step: int = 0):
    p = RequestParser()
    if step:
        for i in range(0, len(data), step):
            p.feed(data[i:i + step])
    else:
        p.feed(data)
    return route(p)


@pytest.mark.parametrize("step", [0, 1, 3, 7])
def test_any_split_gives_the_same_route(step):
    d = decide(b"\r\nGET /stream?x=1&fps=7.5 HTTP/1.0\r\nHost: a\r\nUser-Agent: t\r\n\r\n", step)
    assert (d.route, d.status, d.fps_cap) == (Route.STREAM, 200, 7.5)


def test_head_size_limit_is_2048_bytes():
    line = b"GET / HTTP/1.1\r\n"
    pad = 2048 - len(line) - len(b"X: \r\n\r\n")
    exact = line + b"X: " + b"a" * pad + b"\r\n\r\n"
    assert len(exact) == 2048 and decide(exact).status == 200
    over = line + b"X: " + b"a" * (pad + 1) + b"\r\n\r\n"
    assert decide(over).status == 431


def test_bare_lf_line_ends_are_accepted():
    assert decide(b"GET /time HTTP/1.1\nHost: a\n\n").route is Route.TIME


def test_incomplete_head_stays_incomplete():
    p = RequestParser()
    assert p.feed(b"GET / HTTP/1.1\r\nHost: a\r\n") is ParseStatus.INCOMPLETE


def test_unknown_path_wins_over_method():
    assert decide(b"POST /nope HTTP/1.1\r\n\r\n").status == 404
    assert decide(b"POST / HTTP/1.1\r\n\r\n").status == 405


@pytest.mark.parametrize("text, fps", [("30", 30.0), ("7.5", 7.5), ("0.5", 0.5), ("0", None), ("30.1", None),
                                       (".5", None), ("5.", None), ("-1", None), ("1e1", None)])
def test_fps_values(text, fps):
    assert parse_fps(text) == fps
