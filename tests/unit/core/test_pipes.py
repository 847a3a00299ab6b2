"""PipePoll: multiprocessing.connection.wait over kept pipes, without a selector per call."""

from __future__ import annotations

import multiprocessing
import time

from cubetrack.core.pipes import LatestBytes, PipePoll


def test_ready_is_what_wait_says_in_the_order_added():
    (a, a_far), (b, b_far), (c, c_far) = (multiprocessing.Pipe() for _ in range(3))
    pipes = PipePoll({a: 0, b: 1})
    pipes[c] = 2
    assert pipes.ready() == [] and dict(pipes) == {a: 0, b: 1, c: 2}
    c_far.send("x")
    a_far.send("y")
    assert pipes.ready() == [a, c]  # the order added, not the order written
    assert a.recv() == "y"
    assert pipes.ready() == [c]
    del pipes[c]  # no longer polled, though it holds a message
    assert pipes.ready() == [] and list(pipes) == [a, b]
    b_far.close()  # the other end gone: readable (recv raises EOFError), as Connection.poll() says
    assert pipes.ready() == [b] and b.poll()
    del pipes[b]
    a.close()  # a connection closed before it leaves still leaves
    del pipes[a]
    assert len(pipes) == 0 and pipes.ready(None) == []  # nothing to wait for: no wait


def test_ready_waits_up_to_the_timeout():
    a, a_far = multiprocessing.Pipe()
    pipes = PipePoll({a: "lane"})
    t0 = time.monotonic()
    assert pipes.ready(0.05) == []
    assert time.monotonic() - t0 >= 0.05
    a_far.send(1)
    t0 = time.monotonic()
    assert pipes.ready(5.0) == [a]
    assert time.monotonic() - t0 < 1.0


def _read_latest(board: LatestBytes, seen: int, out) -> None:
    out.send(board.newer(seen))


def test_latest_bytes_hands_another_process_the_newest_message():
    context = multiprocessing.get_context("spawn")
    board = LatestBytes(context, capacity=64)
    here, there = context.Pipe()
    assert board.newer(0) == (0, None)  # nothing posted yet
    assert board.post(b"first") and board.post(b"second")
    assert not board.post(b"x" * 65)  # over its capacity: refused, the last one stays
    child = context.Process(target=_read_latest, args=(board, 0, there))
    child.start()
    assert here.recv() == (2, b"second")  # the newest, read in another process; one version per post
    child.join(10.0)
    assert board.newer(2) == (2, None)  # already seen: nothing
    assert board.post(b"") and board.newer(2) == (3, b"")
