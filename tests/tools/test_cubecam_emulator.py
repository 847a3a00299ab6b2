"""The emulator as a replayer of recordings: recorded frame numbers, timestamps, timing and
drift, looping, several cameras, skipped files; and each fault mode seen by a real client."""

from __future__ import annotations

import json
import socket
import sys
import time
import urllib.request
from pathlib import Path

import cv2
import numpy as np
import pytest

from cubecam import mjpeg
from cubecam.emulator import Emulator, Faults
from cubecam.errors import EmulatorError
from cubecam.replay import Timeline, load_recording
from cubecam.testdata import CameraSpec, write_images, write_recording

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "contract"))
import itertools

from contract_http import StreamClient, get  # noqa: E402


def host_port(url: str) -> tuple[str, int]:
    rest = url.split("//", 1)[1].split("/", 1)[0]
    host, port = rest.rsplit(":", 1)
    return host, int(port)


def time_of(base_url: str) -> float:
    with urllib.request.urlopen(base_url + "time", timeout=5) as r:
        return mjpeg.parse_timestamp(r.read().decode())


@pytest.fixture
def rec(tmp_path) -> Path:
    return write_recording(tmp_path / "rec", [CameraSpec("cam1", 100.0, drop=(3, 4)), CameraSpec("cam2", 7.5)],
                           frames=20, fps=10.0)


def first_parts(url: str, n: int) -> list[mjpeg.Part]:
    with StreamClient(*host_port(url)) as c:
        return [c.next_part() for _ in range(n)]


def test_replays_recorded_frame_numbers_timestamps_and_drops(rec):
    with Emulator(rec) as emu:
        parts = first_parts(emu.urls["cam1"], 8)
    recorded = {i + 1: f"{100.0 + i * 0.1:.6f}" for i in range(20) if i not in (3, 4)}
    frames = [p.frame for p in parts]
    assert frames == sorted(recorded)[:8]  # 1, 2, 3, 6, 7, ...: the drops stay gaps
    assert [p.headers["x-timestamp"] for p in parts] == [recorded[f] for f in frames]


def test_frames_are_released_at_the_recorded_rate(rec):
    with Emulator(rec) as emu:
        with StreamClient(*host_port(emu.urls["cam2"])) as c:
            c.next_part()
            t0 = time.monotonic()
            for _ in range(10):
                c.next_part()
            elapsed = time.monotonic() - t0
    assert elapsed == pytest.approx(1.0, abs=0.15)


def test_cameras_get_consecutive_ports(rec):
    probe = socket.create_server(("127.0.0.1", 0))
    port = probe.getsockname()[1]
    probe.close()
    with Emulator(rec, port=port) as emu:
        assert emu.urls == {"cam1": f"http://127.0.0.1:{port}/stream", "cam2": f"http://127.0.0.1:{port + 1}/stream"}
        names = {json.loads(get("127.0.0.1", p, "/status").body)["name"] for p in (port, port + 1)}
    assert names == {"cam1", "cam2"}


def test_cameras_get_their_own_loopback_addresses(rec):
    with Emulator(rec, host="127.0.0.21", addresses="auto", port=0) as emu:
        hosts = {name: host_port(url)[0] for name, url in emu.urls.items()}
        assert hosts == {"cam1": "127.0.0.21", "cam2": "127.0.0.22"}
        for name, url in emu.base_urls.items():
            with urllib.request.urlopen(url + "status", timeout=5) as r:
                doc = json.loads(r.read())
            assert doc["name"] == name and doc["ip"] == hosts[name]


def test_cameras_stay_aligned_as_recorded(tmp_path):
    path = write_recording(tmp_path / "r", [CameraSpec("a", 500.0), CameraSpec("b", 3.0, rate=1.0 + 50e-6)])
    tracks, _ = load_recording(path)
    timeline = Timeline(tracks, loop=False)
    release_a = [r.at_s for r in timeline.releases(0)]
    release_b = [r.at_s for r in timeline.releases(1)]
    assert release_a == pytest.approx(release_b, abs=1e-4)
    assert release_a[0] == pytest.approx(0.0, abs=1e-6) and release_a[-1] == pytest.approx(1.9, abs=1e-4)


@pytest.mark.parametrize("clock_csv", [True, False], ids=["clock.csv", "index.csv"])
def test_time_runs_on_the_recorded_device_clock_with_its_drift(tmp_path, clock_csv):
    # an exaggerated 5 % drift so that one second shows it: the device clock runs slow
    rate = 1.05
    path = write_recording(tmp_path / "r", [CameraSpec("cam1", 40.0, rate=rate, clock_csv=clock_csv)], frames=30)
    tracks, _ = load_recording(path)
    assert tracks[0].clock.rate == pytest.approx(rate, rel=1e-4)
    with Emulator(path) as emu:
        base = emu.base_urls["cam1"]

        def sample() -> tuple[float, float]:
            # the quickest of a few round trips, as a clock sync does: a request that waited for the
            # CPU (a loaded CI machine) would put the device reading anywhere inside a long round trip
            trips = []
            for _ in range(5):
                before = time.monotonic()
                device = time_of(base)
                after = time.monotonic()
                trips.append((after - before, (before + after) / 2, device))
            return min(trips)[1:]

        t0, d0 = sample()
        time.sleep(1.5)
        t1, d1 = sample()
        parts = first_parts(emu.urls["cam1"], 3)
        now = time_of(base)
    assert (d1 - d0) / (t1 - t0) == pytest.approx(1 / rate, abs=0.015)  # 0.952, not 1
    # /time is the clock of X-Timestamp: the newest part is from just before now
    assert parts[-1].timestamp_s <= now < parts[-1].timestamp_s + 0.25


def test_loop_keeps_clocks_and_frame_numbers_counting(tmp_path):
    path = write_recording(tmp_path / "r", [CameraSpec("cam1", 10.0)], frames=6, fps=10.0)
    with Emulator(path, loop=True) as emu:
        parts = first_parts(emu.urls["cam1"], 14)
    frames = [p.frame for p in parts]
    stamps = [p.timestamp_s for p in parts]
    assert frames == list(range(1, 15))
    assert all(b > a for a, b in itertools.pairwise(stamps))
    assert stamps[6] - stamps[5] == pytest.approx(0.1, abs=1e-6)  # the loop seam keeps the frame period


def test_without_loop_the_replay_finishes_and_the_last_frame_stays(tmp_path):
    path = write_recording(tmp_path / "r", [CameraSpec("cam1", 10.0)], frames=5, fps=20.0)
    with Emulator(path) as emu:
        assert emu.wait_finished(3.0)
        host, port = host_port(emu.urls["cam1"])
        a = get(host, port, "/capture")
        assert a.status == 200 and a.headers["x-frame"] == "5"


def test_corrupt_and_missing_frames_are_skipped_and_counted(tmp_path):
    path = write_recording(tmp_path / "r", [CameraSpec("cam1", 10.0, corrupt_files=2, missing_files=1)], frames=12)
    with (path / "cam1" / "index.csv").open("a") as f:
        f.write("oops,1,2\n")
    with Emulator(path) as emu:
        assert emu.skipped == {"corrupt frame file": 2, "missing frame file": 1, "bad index row": 1}
        frames = [p.frame for p in first_parts(emu.urls["cam1"], 9)]
    assert frames == [1, 2, 3, 4, 5, 6, 7, 8, 12]


def test_images_folder_is_one_camera_at_the_given_rate(tmp_path):
    folder = write_images(tmp_path / "shots", 6)
    (folder / "frame_0003.jpg").write_bytes(b"not a jpeg")
    with Emulator(images=folder, fps=5.0, name="bench") as emu:
        assert emu.cameras == ("bench",) and emu.skipped == {"corrupt frame file": 1}
        parts = first_parts(emu.urls["bench"], 4)
    assert [p.frame for p in parts] == [1, 2, 3, 4]
    assert [p.headers["x-timestamp"] for p in parts] == ["1.000000", "1.200000", "1.400000", "1.600000"]


def test_missing_recording_and_port_in_use_are_emulator_errors(tmp_path, rec):
    with pytest.raises(EmulatorError, match="not found"):
        Emulator(tmp_path / "nothing")
    with socket.create_server(("127.0.0.1", 0)) as busy:
        port = busy.getsockname()[1]
        with pytest.raises(EmulatorError, match=f"127.0.0.1:{port} is in use"):
            Emulator(rec, port=port).start()


# --- faults, each observed by a client ---------------------------------------------------


@pytest.fixture
def images(tmp_path) -> Path:
    return write_images(tmp_path / "img", 20)


def test_latency_delays_every_answer(images):
    with Emulator(images=images, fps=10, faults=Faults(latency_s=0.3)) as emu:
        t0 = time.monotonic()
        time_of(emu.base_urls["img"])
        assert time.monotonic() - t0 >= 0.3
        with StreamClient(*host_port(emu.urls["img"])) as c:
            part = c.next_part()
            arrived = time_of(emu.base_urls["img"])  # device clock now (this answer is late too)
    assert arrived - part.timestamp_s >= 0.3


def test_jitter_spreads_the_delay(images):
    with Emulator(images=images, fps=10, faults=Faults(jitter_s=0.2, seed=3)) as emu:
        delays = []
        for _ in range(6):
            t0 = time.monotonic()
            time_of(emu.base_urls["img"])
            delays.append(time.monotonic() - t0)
    assert max(delays) <= 0.3 and max(delays) - min(delays) > 0.05, delays


def test_drop_rate_leaves_gaps_in_x_frame(images):
    with Emulator(images=images, fps=25, loop=True, faults=Faults(drop_rate=0.5, seed=1)) as emu:
        frames = [p.frame for p in first_parts(emu.urls["img"], 15)]
    span = frames[-1] - frames[0] + 1
    assert 0.3 < len(frames) / span < 0.75, frames


def test_bandwidth_cap_limits_bytes_per_second_and_skips_frames(tmp_path):
    folder = write_images(tmp_path / "big", 20, 640, 480)
    size = (folder / "frame_0000.jpg").stat().st_size
    cap = 3 * size  # three frames a second of a 10 fps camera
    with Emulator(images=folder, fps=10, loop=True, faults=Faults(bandwidth_bytes_per_s=cap)) as emu:
        with StreamClient(*host_port(emu.urls["big"]), rcvbuf=8192) as c:
            c.next_part()
            t0 = time.monotonic()
            parts = [c.next_part() for _ in range(5)]
            elapsed = time.monotonic() - t0
    received = sum(len(p.jpeg) + len(p.raw_header) for p in parts)
    assert received / elapsed == pytest.approx(cap, rel=0.3)
    frames = [p.frame for p in parts]
    assert all(b - a >= 2 for a, b in itertools.pairwise(frames)), frames  # newest only: ~3 of 10 frames


def test_disconnect_every_cuts_the_stream(images):
    with Emulator(images=images, fps=10, loop=True, faults=Faults(disconnect_every_s=0.5)) as emu:
        t0 = time.monotonic()
        with StreamClient(*host_port(emu.urls["img"])) as c:
            n = sum(1 for _ in c.parts())  # until the node hangs up
        elapsed = time.monotonic() - t0
        assert 0.4 < elapsed < 1.2 and 2 <= n <= 7
        assert get(*host_port(emu.urls["img"]), "/time").status == 200  # the node itself is fine


def test_stall_keeps_the_connection_open_but_silent(images):
    with Emulator(images=images, fps=10, loop=True, faults=Faults(stall_after_s=0.3)) as emu:
        with StreamClient(*host_port(emu.urls["img"])) as c:
            c.next_part()
            c.sock.settimeout(1.0)
            with pytest.raises(socket.timeout):
                for _ in range(50):
                    c.next_part()


def test_stall_for_a_while_then_resumes_with_the_newest_frame(images):
    with Emulator(images=images, fps=10, loop=True, faults=Faults(stall_after_s=0.3, stall_for_s=0.6)) as emu:
        with StreamClient(*host_port(emu.urls["img"])) as c:
            parts = [c.next_part() for _ in range(8)]
    gaps = [b.timestamp_s - a.timestamp_s for a, b in itertools.pairwise(parts)]
    assert max(gaps) >= 0.5, gaps  # the silence shows as a jump in capture time


def test_corrupt_jpeg_parts_keep_the_framing(images):
    with Emulator(images=images, fps=20, loop=True, faults=Faults(corrupt_every=3, seed=2)) as emu:
        parts = first_parts(emu.urls["img"], 9)
    decoded = [cv2.imdecode(np.frombuffer(p.jpeg, np.uint8), cv2.IMREAD_COLOR) for p in parts]
    broken = [i for i, (p, img) in enumerate(zip(parts, decoded, strict=True))
              if img is None or p.jpeg[-2:] != b"\xff\xd9"]
    assert broken == [2, 5, 8]


def test_truncated_parts_break_the_content_length(images):
    with Emulator(images=images, fps=20, loop=True, faults=Faults(corrupt_every=2, corrupt_kind="truncate")) as emu:
        with StreamClient(*host_port(emu.urls["img"])) as c:
            c.next_part()
            with pytest.raises(mjpeg.StreamFormatError):  # a strict reader loses the framing
                for _ in range(3):
                    c.next_part()


def test_faults_are_checked():
    with pytest.raises(EmulatorError):
        Faults(drop_rate=1.5).check()
    with pytest.raises(EmulatorError):
        Faults(corrupt_kind="melt").check()


def test_drift_from_arrival_times_ignores_arrival_jitter():
    import random

    from cubecam.replay import fit_clock

    rng = random.Random(5)
    device = [10.0 + i / 15 for i in range(900)]  # one minute at 15 fps
    rate = 1 + 40e-6
    host = [1000.0 + rate * (d - 10.0) + 0.02 + rng.expovariate(1 / 0.03) for d in device]
    clock = fit_clock(device, host, True, "test")
    assert abs(clock.rate - rate) < 20e-6
    assert clock.host(10.0) == pytest.approx(1000.02, abs=0.005)
