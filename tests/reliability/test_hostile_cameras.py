"""Hostile camera nodes next to a well-behaved one (issue 12, item 4): the live source
(cubetrack.source.streams.LiveCameras) reads one emulated camera and, at the same time, eleven
peers that send endless headers, multi-GB parts, lying Content-Lengths, one byte a second, or
nothing (tests/reliability/hostile_peers.py, in a process of its own). The good camera's frames
and clock samples keep flowing, no hostile byte becomes a frame, every misbehaviour is counted,
the reader's memory stays bounded while gigabytes arrive, and stop() still returns in time."""

from __future__ import annotations

import itertools
import subprocess
import sys
import time
import tracemalloc
from pathlib import Path

import pytest

from cubecam.emulator import Emulator
from cubecam.testdata import write_images
from cubetrack.core.records import Frame
from cubetrack.source.streams import LiveCameras, SourceParams

HERE = Path(__file__).resolve().parent
KINDS = ("endless_header", "many_headers", "endless_part_header", "huge_part", "huge_part_no_length",
         "short_length", "long_length", "trickle_body", "trickle_head", "trickle_fast", "silent")
FPS = 10.0
WINDOW_S = 6.0
PARAMS = SourceParams(connect_timeout_s=1.0, read_timeout_s=2.0, backoff_initial_s=0.1, backoff_max_s=0.5,
                      clock_period_s=0.5, clock_timeout_s=0.5, max_part_bytes=1 << 20)
# What each peer must be seen as: a reason counted among the bad parts, or a lost connection.
EXPECTED_BAD = {
    "endless_part_header": "part headers too long",
    "huge_part": "bad Content-Length",
    "huge_part_no_length": "part too large",
    "short_length": "not a whole JPEG",
    "long_length": "part shorter than its Content-Length",
}
EXPECTED_RECONNECTS = ("endless_header", "many_headers", "silent")


@pytest.fixture(scope="module")
def peers():
    proc = subprocess.Popen([sys.executable, str(HERE / "hostile_peers.py"), *KINDS], stdout=subprocess.PIPE, text=True)
    ports = {}
    for line in proc.stdout:
        if line.strip() == "ready":
            break
        kind, port = line.split()
        ports[kind] = int(port)
    yield proc, ports
    if proc.poll() is None:
        proc.kill()
        proc.wait()


def test_hostile_cameras_never_stall_the_good_one_or_exhaust_memory(peers, tmp_path):
    proc, ports = peers
    images = write_images(tmp_path / "img", 8, 160, 120)
    with Emulator(images=images, fps=FPS, name="good", loop=True) as emu:
        urls = {"good": emu.urls["good"], **{k: f"http://127.0.0.1:{p}/stream" for k, p in ports.items()}}
        tracemalloc.start()
        try:
            baseline = tracemalloc.get_traced_memory()[0]
            live = LiveCameras(urls, PARAMS).start()
            good_arrivals, good_clock, frames_from = [], 0, {}
            deadline = time.monotonic() + WINDOW_S
            while time.monotonic() < deadline:
                event = live.get(0.1)
                if isinstance(event, Frame):
                    frames_from[event.camera] = frames_from.get(event.camera, 0) + 1
                    if event.camera == "good":
                        good_arrivals.append(time.monotonic())
                elif event is not None and event.camera == "good":
                    good_clock += 1
            peak = tracemalloc.get_traced_memory()[1] - baseline
            stats = live.stats()
            t0 = time.monotonic()
            live.stop()
            stop_s = time.monotonic() - t0
        finally:
            tracemalloc.stop()
    proc.terminate()
    out, _ = proc.communicate(timeout=10)
    sent = {line.split()[1]: int(line.split()[2]) for line in out.splitlines() if line.startswith("sent ")}

    print(f"\nhostile peers: {sum(sent.values()) / 1e9:.2f} GB sent in {WINDOW_S:.0f} s; good camera "
          f"{len(good_arrivals)} frames, longest gap "
          f"{max(b - a for a, b in itertools.pairwise(good_arrivals)):.2f} s; reader peak {peak / 1e6:.1f} MB traced; "
          f"stop() {stop_s:.2f} s")
    # the good camera never stalled
    assert len(good_arrivals) >= 0.5 * FPS * WINDOW_S, (len(good_arrivals), stats["good"])
    gaps = [b - a for a, b in itertools.pairwise(good_arrivals)]
    assert max(gaps) < 1.5, max(gaps)
    assert good_clock >= 4
    # no hostile byte became a frame; every misbehaviour was seen for what it is
    assert set(frames_from) == {"good"}, frames_from
    for kind, reason in EXPECTED_BAD.items():
        assert stats[kind].bad_parts[reason] >= 1, (kind, stats[kind])
    for kind in EXPECTED_RECONNECTS:
        assert stats[kind].reconnects >= 1 and stats[kind].last_error, (kind, stats[kind])
    # one byte a second is below the read timeout: the connection stays, holding only its own thread
    assert stats["trickle_body"].connects == 1 and stats["trickle_body"].reconnects == 0
    for kind in ("trickle_head", "trickle_fast"):
        assert stats[kind].connects == 0  # the response head never completes
    assert stats["trickle_head"].clock_failures["no answer"] >= 2  # 1 s per byte > the /time timeout
    # gigabytes arrived, memory did not follow
    flood = sum(sent[k] for k in ("endless_header", "many_headers", "endless_part_header", "huge_part",
                                  "huge_part_no_length"))
    assert flood > 100e6, sent
    assert peak < 40e6, f"peak traced memory {peak / 1e6:.1f} MB while {flood / 1e6:.0f} MB arrived"
    # trickling peers do not hold stop() hostage beyond one read timeout
    assert stop_s < PARAMS.read_timeout_s + 2.0
