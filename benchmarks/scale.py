"""Issue 13's benchmark: what one fusion process can take from many workers over Zenoh.

1. A simulated recording (``cubetrack simulate``, its true extrinsics) is run through the
   workers' per-frame work in this process (:meth:`Tracker.admit`, :meth:`FrameProcessor.work`,
   :func:`cubetrack.app.worker.sighting_message`): the sighting messages a worker would publish.
   Reported: bytes per message (frames with and without the cube), and the per-frame work's CPU.
2. The fusion's CPU per message, in this process: decode + rebuild + :meth:`Tracker.fuse`
   (:func:`cubetrack.app.fusion_service.frame_result`), every message of the recording, the
   best of --repeat rounds. This is the fusion's ceiling: 1 / (CPU per message) messages/s per core.
3. Over real loopback Zenoh: --workers publisher processes, each --cameras cameras at --fps,
   publish those messages (no detection: only the transport is measured) to one subscriber in
   this process that decodes each; reported: messages/s offered and received, lost, and the
   subscriber's CPU per message (Zenoh receive + decode), against the in-process decode alone
   (the baseline measured in the same run).

Then the arithmetic for --target-cameras cameras at --fps (docs/scaling.md): messages/s,
bytes/s, and the cores one fusion process needs. The machine's core count is printed.

    .venv/bin/python benchmarks/scale.py [--workers 2] [--cameras 8] [--fps 30] [--duration 10]
    .venv/bin/python benchmarks/scale.py --quick       # 2 workers x 2 cameras x 10 fps for 3 s
"""

from __future__ import annotations

import argparse
import dataclasses
import multiprocessing
import os
import socket
import statistics
import sys
import tempfile
import threading
import time
from pathlib import Path


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def make_messages(rec_dir: Path) -> tuple[list[bytes], float, object, object]:
    """The recording's sighting messages (frames in arrival order), the per-frame work's CPU per
    frame, and the config and extrinsics."""
    from cubetrack.app.config import load_config
    from cubetrack.app.tracker import Tracker
    from cubetrack.app.worker import sighting_message
    from cubetrack.io.config import read_extrinsics
    from cubetrack.io.recording import Recording
    from cubetrack.io.sighting_wire import encode_sighting
    from cubetrack.source.streams import CameraStats

    config, settings = load_config(rec_dir / "config.toml")
    extrinsics = read_extrinsics(rec_dir / "true_extrinsics.toml")
    rec = Recording.open(rec_dir)
    from cubetrack.io.camera_info import read_camera_info

    intrinsics = {c: read_camera_info(rec.camera_info_path(c)) for c in rec.camera_names}
    tracker = Tracker(intrinsics, config.world, config.robots, extrinsics, settings.stages)
    frames = sorted((f for c in rec.camera_names for f in rec.frames(c)), key=lambda f: f.host_time_s)
    messages = []
    cpu = time.process_time()
    for frame in frames:
        job = tracker.admit(frame)
        if job is None:
            continue
        job = dataclasses.replace(job, regions=None, estimate_robots=frozenset())
        result = tracker.processor.work(job)
        messages.append(encode_sighting(sighting_message(result, tracker.clocks[frame.camera], CameraStats(), False)))
    return messages, (time.process_time() - cpu) / max(1, len(frames)), config, extrinsics


def fusion_cpu(messages: list[bytes], config, extrinsics, repeat: int) -> tuple[float, float, int]:
    """Best-of-``repeat`` CPU seconds per message: (decode only, decode + rebuild + fuse), poses."""
    from cubetrack.app.config import config_params
    from cubetrack.app.fusion_service import frame_result
    from cubetrack.app.live import live_intrinsics
    from cubetrack.app.tracker import Tracker
    from cubetrack.io.sighting_wire import decode_sighting

    intrinsics = live_intrinsics(config)
    decode_s, fuse_s, poses = [], [], 0
    for _ in range(repeat):
        start = time.process_time()
        decoded = [decode_sighting(m) for m in messages]
        decode_s.append((time.process_time() - start) / len(messages))
        tracker = Tracker(intrinsics, config.world, config.robots, extrinsics, config_params(config).stages)
        start = time.process_time()
        poses = 0
        for message in sorted((decode_sighting(m) for m in messages), key=lambda m: m.capture_time_s):
            poses += len(tracker.fuse(frame_result(tracker, message), message.arrival_time_s))
        fuse_s.append((time.process_time() - start) / len(messages))
        del decoded
    return min(decode_s), min(fuse_s), poses


def empty_cpu(messages: list[bytes], config, extrinsics) -> float:
    """CPU per message of frames in which no robot is seen (decode + rebuild + fuse): most of a
    large site's cameras, for any one robot."""
    from cubetrack.app.config import config_params
    from cubetrack.app.fusion_service import frame_result
    from cubetrack.app.live import live_intrinsics
    from cubetrack.app.tracker import Tracker
    from cubetrack.io.sighting_wire import decode_sighting, encode_sighting

    empty = [encode_sighting(dataclasses.replace(decode_sighting(m), detections=())) for m in messages] * 10
    tracker = Tracker(live_intrinsics(config), config.world, config.robots, extrinsics, config_params(config).stages)
    start = time.process_time()
    for data in empty:
        message = decode_sighting(data)
        tracker.fuse(frame_result(tracker, message), message.arrival_time_s)
    return (time.process_time() - start) / len(empty)


def publish(port: int, worker: int, cameras: int, fps: float, duration_s: float, messages: list[bytes]) -> None:
    """One publisher process: ``cameras`` keys at ``fps`` each for ``duration_s``."""
    from cubetrack.app.worker import worker_endpoints
    from cubetrack.io.worker_bus import sighting_key
    from cubetrack.sink.zenoh_session import open_session

    session = open_session(worker_endpoints(connect=(f"tcp/127.0.0.1:{port}",)), "benchmark worker")
    publishers = [session.declare_publisher(sighting_key(f"w{worker}c{c}")) for c in range(cameras)]
    period_s = 1.0 / fps
    start = time.monotonic() + 0.5
    n = 0
    while (now := time.monotonic()) < start + duration_s:
        due = int((now - start) / period_s) + 1 if now >= start else 0
        while n < due:
            for c, publisher in enumerate(publishers):
                publisher.put(messages[(n * cameras + c) % len(messages)])
            n += 1
        time.sleep(max(0.0, start + n * period_s - time.monotonic()))
    time.sleep(0.5)
    session.close()


def transport(messages: list[bytes], workers: int, cameras: int, fps: float, duration_s: float) -> dict:
    """Publisher processes -> one subscriber here over loopback Zenoh."""
    from cubetrack.app.worker import fuse_endpoints
    from cubetrack.io.sighting_wire import decode_sighting
    from cubetrack.io.worker_bus import SIGHTINGS_KEY
    from cubetrack.sink.zenoh_session import open_session

    port = free_port()
    session = open_session(fuse_endpoints(listen=(f"tcp/127.0.0.1:{port}",)), "benchmark fusion")
    received, size = [0], [0]
    lock = threading.Lock()

    def receive(sample) -> None:
        data = bytes(sample.payload)
        decode_sighting(data)
        with lock:
            received[0] += 1
            size[0] += len(data)

    subscriber = session.declare_subscriber(f"{SIGHTINGS_KEY}/*", receive)
    context = multiprocessing.get_context("spawn")
    procs = [context.Process(target=publish, args=(port, w, cameras, fps, duration_s, messages))
             for w in range(workers)]
    for p in procs:
        p.start()
    cpu0, wall0 = time.process_time(), time.monotonic()
    for p in procs:
        p.join()
    cpu, wall = time.process_time() - cpu0, time.monotonic() - wall0
    subscriber.undeclare()
    session.close()
    offered = workers * cameras * fps * duration_s
    return {"offered": offered, "received": received[0], "received_per_s": received[0] / duration_s,
            "bytes": size[0], "cpu_per_message_s": cpu / max(1, received[0]), "wall_s": wall}


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--workers", type=int, default=2, help="publisher processes (default 2)")
    p.add_argument("--cameras", type=int, default=8, help="cameras per publisher (default 8)")
    p.add_argument("--fps", type=float, default=30.0, help="frames/s per camera (default 30)")
    p.add_argument("--duration", type=float, default=10.0, metavar="S", help="publishing time (default 10)")
    p.add_argument("--repeat", type=int, default=3, help="rounds of the in-process fusion timing (default 3)")
    p.add_argument("--target-cameras", type=int, default=200, help="cameras for the arithmetic (default 200)")
    p.add_argument("--out", type=Path, help="keep the simulated recording here (reused when present)")
    p.add_argument("--quick", action="store_true", help="2 workers x 2 cameras x 10 fps for 3 s, 1 round")
    args = p.parse_args(argv)
    if args.quick:
        args.workers, args.cameras, args.fps, args.duration, args.repeat = 2, 2, 10.0, 3.0, 1
    from cubetrack.cli.main import main as cubetrack

    tmp = tempfile.TemporaryDirectory(prefix="cubetrack-scale-")
    rec = (args.out or Path(tmp.name)) / "rec"
    if not (rec / "config.toml").exists():
        code = cubetrack(["simulate", "--out", str(rec), "--duration", "3" if args.quick else "6", "--seed", "3",
                          "--calibration-frames", "0"])
        if code != 0:
            return code
    cores = os.cpu_count()
    messages, work_s, config, extrinsics = make_messages(rec)
    from cubetrack.io.sighting_wire import decode_sighting

    with_cube = [len(m) for m in messages if decode_sighting(m).detections]
    print(f"cores: {cores}; {len(messages)} sighting messages from {rec}")
    print(f"bytes per message: mean {statistics.mean(len(m) for m in messages):.0f}, with "
          f"markers {statistics.mean(with_cube) if with_cube else 0:.0f} (max {max(len(m) for m in messages)}), "
          f"{len(messages) - len(with_cube)} without; a JPEG of the same frames is ~{_jpeg_bytes(rec):.0f}")
    print(f"worker: per-frame work {work_s * 1000:.2f} ms CPU per frame")
    decode_s, fuse_s, poses = fusion_cpu(messages, config, extrinsics, args.repeat)
    print(f"fusion in process: decode {decode_s * 1e6:.1f} us, decode + rebuild + fuse {fuse_s * 1e6:.1f} us CPU "
          f"per message ({poses} poses), ceiling {1 / fuse_s:.0f} messages/s per core")
    idle_s = empty_cpu(messages, config, extrinsics)
    print(f"fusion in process, frames without markers: {idle_s * 1e6:.1f} us CPU per message")
    t = transport(messages, args.workers, args.cameras, args.fps, args.duration)
    lost = max(0.0, 1 - t["received"] / t["offered"])
    print(f"Zenoh loopback: {args.workers} publisher processes x {args.cameras} cameras x {args.fps:g} fps: offered "
          f"{t['offered'] / args.duration:.0f}/s, received {t['received_per_s']:.0f}/s ({lost * 100:.1f} % lost), "
          f"{t['bytes'] / args.duration / 1e3:.0f} kB/s; subscriber CPU {t['cpu_per_message_s'] * 1e6:.1f} us per "
          f"message (receive + decode) = {t['cpu_per_message_s'] / decode_s:.1f}x the in-process decode")
    rate = args.target_cameras * args.fps
    per_message_s = fuse_s + t["cpu_per_message_s"] - decode_s
    mean_bytes = statistics.mean(len(m) for m in messages)
    print(f"{args.target_cameras} cameras x {args.fps:g} fps: {rate:.0f} messages/s, "
          f"{rate * mean_bytes / 1e6:.2f} MB/s of sightings; one fusion process needs {rate * per_message_s:.2f} cores "
          f"(ceiling {1 / per_message_s:.0f} messages/s = {1 / per_message_s / args.fps:.0f} cameras at "
          f"{args.fps:g} fps)")
    tmp.cleanup()
    return 0


def _jpeg_bytes(rec: Path) -> float:
    sizes = [f.stat().st_size for f in rec.rglob("*.jpg")][:200]
    return statistics.mean(sizes) if sizes else 0.0


if __name__ == "__main__":
    sys.exit(main())
